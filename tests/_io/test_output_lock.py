"""One writer per output (``dpc_jax._io.output_lock``), and what the commands that write caches and
runs, and read caches and priors, refuse before JAX starts: a locked output, a cache whose bytes
changed or of a newer format, a prior of other frames, an upsampling size, a judge smaller than its
cache. The command lines run in one fresh interpreter, which must not import JAX."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from support import dead_pid, in_one_process, train_config, write_odometry

from dpc_jax._io import LockError, lock_path, output_lock
from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.kitti import open_odometry
from dpc_jax.data.poses_io import write_kitti_poses

SIZE = (10, 16)
ROOT = Path(__file__).resolve().parents[2]

# A process that takes the lock of argv[1] (or is refused) and says which on one line; a holder keeps
# it until its standard input closes.
_HOLDER = textwrap.dedent("""
    import sys
    from dpc_jax._io import LockError, output_lock
    try:
        with output_lock(sys.argv[1], "--out " + sys.argv[1]):
            print("held", flush=True)
            sys.stdin.read()
    except LockError as error:
        print(f"refused {error}", flush=True)
""")


def _holder(path: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", _HOLDER, str(path)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)


@pytest.fixture
def held(tmp_path: Path) -> Iterator[tuple[Path, int]]:
    """``tmp_path/out``, locked by another live process (its pid)."""
    path = tmp_path / "out"
    process = _holder(path)
    assert process.stdout is not None and process.stdout.readline().strip() == "held"
    yield path, process.pid
    process.communicate("")


def test_of_processes_racing_for_one_output_exactly_one_writes(tmp_path: Path) -> None:
    path = tmp_path / "cache" / "01"
    processes = [_holder(path) for _ in range(4)]
    answers = [p.stdout.readline().strip() for p in processes if p.stdout is not None]
    winner = [p.pid for p, answer in zip(processes, answers, strict=True) if answer == "held"]
    assert len(winner) == 1, answers
    refusals = [answer for answer in answers if answer != "held"]
    assert all(f"being written by process {winner[0]} " in answer for answer in refusals), refusals
    assert json.loads(lock_path(path).read_text())["pid"] == winner[0]
    for process in processes:
        process.communicate("")
    assert not lock_path(path).exists() and sorted(os.listdir(tmp_path / "cache")) == []


def test_a_stale_lock_is_reported_with_its_pid_and_never_taken(tmp_path: Path) -> None:
    path = tmp_path / "run"
    lock = lock_path(path)
    dead = dead_pid()
    lock.write_text(json.dumps({"pid": dead, "host": socket.gethostname(), "command": "dpc-jax train"}))
    before = lock.read_bytes()
    with pytest.raises(LockError) as refused, output_lock(path, f"--workdir {path}"):
        pass
    assert str(refused.value) == (
        f"--workdir {path}: {path} is locked by process {dead}, which is no longer running (dpc-jax train); "
        f"the lock {lock} was left by a run that was killed: remove it if no other process writes there")
    assert lock.read_bytes() == before
    lock.write_text("")  # a lock that names nobody is not taken either
    with pytest.raises(LockError, match="which names no process; remove it"), output_lock(path, "x"):
        pass


def test_the_lock_lies_beside_its_output_is_held_again_by_its_holder_and_removed(tmp_path: Path) -> None:
    target = tmp_path / "real"
    target.mkdir()
    (tmp_path / "link").symlink_to(target)
    lock = tmp_path / ".real.lock"
    assert lock_path(tmp_path / "link") == lock_path(tmp_path / "sub" / ".." / "real") == lock
    with output_lock(tmp_path / "link", "--out link") as held:
        assert held == lock and json.loads(lock.read_text())["pid"] == os.getpid()
        with output_lock(target, "--out real"):  # the command line, then the library it calls
            pass
        assert lock.exists()
    assert not lock.exists() and sorted(os.listdir(tmp_path)) == ["link", "real"]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two 6-frame sequences at 40×64 with KITTI priors, their caches at 10×16 and at 20×32 (00), a
    prior of frames 0:4 of 00 with `vo`'s record, and a run folder as `correct` reads it first."""
    root = tmp_path_factory.mktemp("inputs")
    poses = {}
    for seed, name in enumerate(("00", "05")):
        poses[name] = write_odometry(root / "kitti", name=name, n=6, size=(40, 64), seed=seed)["poses"]
        write_kitti_poses(root / f"prior_{name}.txt", poses[name])
        sequence = open_odometry(root / "kitti", name)
        prepare_sequence(sequence, root / f"prior_{name}.txt", root / "cache", size=SIZE, progress=False,
                         workers=1)
    prepare_sequence(open_odometry(root / "kitti", "00"), root / "prior_00.txt", root / "large",
                     size=(20, 32), progress=False, workers=1)
    write_kitti_poses(root / "first4.txt", poses["00"][:4])
    (root / "first4.json").write_text(json.dumps({"sequence": "00", "source_frames": [0, 4], "frames": 4}))
    (root / "run" / "checkpoints").mkdir(parents=True)
    config = {"method": "stereo_dpc", "validation_sequences": ["05"], "image_size": [20, 32]}
    (root / "run" / "checkpoints" / "config.json").write_text(json.dumps(config) + "\n")
    train_config(root / "train.py", root / "cache")
    return {"root": root, "kitti": root / "kitti", "cache": root / "cache", "large": root / "large"}


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_writers_and_readers_refuse_before_jax(
    inputs: dict[str, Path], held: tuple[Path, int], tmp_path: Path
) -> None:
    """Each command line: its exit status, one line on stderr that holds the expected words, no JAX,
    and every input byte-identical afterwards."""
    root, out = inputs["root"], tmp_path / "new"
    workdir, pid = held
    changed = tmp_path / "changed"
    shutil.copytree(inputs["large"], changed)
    right = np.load(changed / "00" / "right.npy", mmap_mode="r+")
    right[2, 5, 7, 1] ^= 1
    right.flush()
    del right
    newer = tmp_path / "newer"
    shutil.copytree(inputs["large"], newer)
    manifest = json.loads((newer / "00" / "manifest.json").read_text())
    (newer / "00" / "manifest.json").write_text(json.dumps({**manifest, "version": 99}))
    # The held workdir holds a run: a second train without --resume names the writer, not only the run.
    (workdir / "checkpoints").mkdir(parents=True)
    shutil.copy(root / "run" / "checkpoints" / "config.json", workdir / "checkpoints" / "config.json")
    before = {folder: _tree(folder) for folder in (root, changed, newer)}
    cache_root = tmp_path / "root"
    prepare = ["prepare", "--kitti-odometry", inputs["kitti"], "--sequence", "00", "--prior",
               root / "prior_00.txt", "--no-progress"]
    correct = ["correct", "--checkpoint", root / "run", "--out", out / "c.txt", "--no-progress"]
    holder = _holder(cache_root / "00")  # another prepare building cache_root/00
    assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
    cases = [
        (f"--out {cache_root}: {cache_root / '00'} is being written by process {holder.pid} ", 2,
         [*prepare, "--size", "10x16", "--out", cache_root]),
        (f"--workdir {workdir}: {workdir} is being written by process {pid} ", 2,
         ["train", "--config", root / "train.py", "--workdir", workdir, "--no-progress"]),
        (f"{changed / '00' / 'right.npy'}: its bytes differ from those `dpc-jax prepare` wrote", 2,
         [*correct, "--data", changed / "00"]),
        (f"{newer / '00' / 'manifest.json'}: this cache was written by a newer dpc_jax (cache format "
         "version 99; this one reads version 3 and does not replace it)", 2,
         [*correct, "--data", newer / "00"]),
        (f"--out {newer}: {newer / '00' / 'manifest.json'}: this cache was written by a newer dpc_jax", 2,
         [*prepare, "--size", "20x32", "--out", newer]),
        (f"00: {root / 'first4.txt'}: holds the VO of frames 0:4 (recorded in {root / 'first4.json'}), "
         "not of frames 2:6 (--frames 2:6)", 1,
         [*prepare, "--size", "10x16", "--prior", root / "first4.txt", "--frames", "2:6", "--out", out]),
        ("--size 80x64: larger than the source images of 00 (40x64); a cache is never upsampled", 2,
         [*prepare, "--size", "80x64", "--out", out]),
        (f"--judge {inputs['cache'] / '00'}: images are 10x16, smaller than those of --data "
         f"{inputs['large'] / '00'} (20x32)", 2,
         [*correct, "--data", inputs["large"] / "00", "--judge", inputs["cache"] / "00"]),
    ]
    try:
        status, imported, done = in_one_process([argv for _, _, argv in cases])
    finally:
        holder.communicate("")
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == len(cases) and "Traceback" not in done.stderr, done.stderr
    for (needle, _, _), line in zip(cases, lines, strict=True):
        assert needle in line, (needle, line)
    assert status == [code for _, code, _ in cases] and imported == [], (status, imported)
    assert {folder: _tree(folder) for folder in (root, changed, newer)} == before
    assert not out.exists() and sorted(os.listdir(cache_root)) == []
    assert sorted(str(p.relative_to(workdir)) for p in workdir.rglob("*")) == ["checkpoints",
                                                                             "checkpoints/config.json"]
