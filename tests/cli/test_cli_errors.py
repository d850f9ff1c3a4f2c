"""What a new user runs into (issue 16): every bad input or output ends in one line on stderr naming
the file and what was expected, a non-zero exit status, no traceback and nothing half-written.

The commands run in-process through ``dpc_jax.cli.main`` on tiny inputs (a 6-frame odometry
sequence of random 40×64 images, a 10×16 cache, a 30-pose trajectory); Ctrl-C runs in a subprocess.
Nothing here trains or renders a world: the checks under test all happen before that work.
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from support import CACHE_SIZE, ROOT, dead_pid, fixture_poses, in_one_process, train_config, write_odometry

from dpc_jax import _io
from dpc_jax._io import OutputSet, atomic_write, remove_stale
from dpc_jax.cli import build_parser, main
from dpc_jax.cli._common import Formatter, restore_problem
from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.kitti import open_odometry
from dpc_jax.data.poses_io import read_trajectory, write_kitti_poses, write_tum
from dpc_jax.data.sequence_cache import CacheError, load_cache

N_POSES = 30


def _one_line(err: str, needle: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in err, err
    return lines[0]


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 6-frame odometry sequence, its poses as a KITTI prior, a 10×16 cache, a trajectory pair and
    a fake run folder (a config.json is all ``correct`` looks at before it restores the network)."""
    root = tmp_path_factory.mktemp("inputs")
    written = write_odometry(root / "kitti", n=6, size=(40, 64))
    prior = root / "prior.txt"
    write_kitti_poses(prior, written["poses"])
    prepare_sequence(open_odometry(root / "kitti", "00"), prior, root / "cache", size=CACHE_SIZE,
                     progress=False, workers=1)
    gt = fixture_poses(N_POSES, seed=1, step=2.0)
    est = gt.copy()
    est[:, 0, 3] += np.linspace(0.0, 1.5, N_POSES)
    write_kitti_poses(root / "gt.txt", gt)
    write_kitti_poses(root / "est.txt", est)
    scipy.io.savemat(root / "pair.mat",
                     {"poses_gt": np.moveaxis(gt, 0, -1), "poses_est": np.moveaxis(est, 0, -1),
                      "convention": "Twv"})
    (root / "run" / "checkpoints").mkdir(parents=True)
    # A config that fits the cache: correct checks the run's image size, method and flow first.
    run_config = {"validation_sequences": ["00"], "image_size": list(CACHE_SIZE)}
    (root / "run" / "checkpoints" / "config.json").write_text(json.dumps(run_config) + "\n")
    return {"root": root, "kitti": root / "kitti", "prior": prior, "cache": root / "cache" / "00",
            "gt": root / "gt.txt", "est": root / "est.txt", "mat": root / "pair.mat", "run": root / "run"}


@pytest.fixture
def readonly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder this process may not write into.

    root ignores permission bits, so under root the check's view of the folder is emulated; a
    command that skipped the check would then write into it, which the tests catch.
    """
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    if os.access(folder, os.W_OK):
        real = _io.writable
        monkeypatch.setattr(_io, "writable", lambda path: Path(path) != folder and real(path))
    yield folder
    folder.chmod(0o755)


# ----------------------------------------------------------------------------- output paths


def _outputs_cases(d: dict[str, Path], ro: Path, ok: Path) -> dict[str, list[object]]:
    evaluate = ["evaluate", "--gt", d["gt"], "--est", d["est"]]
    vo = ["vo", "--kitti-odometry", d["kitti"], "--sequence", "00", "--no-progress"]
    correct = ["correct", "--checkpoint", d["run"], "--data", d["cache"], "--no-progress"]
    return {
        "evaluate --json": [*evaluate, "--json", ro / "m.json"],
        "evaluate --report": [*evaluate, "--json", ok, "--report", ro / "r"],
        "evaluate --export": [*evaluate, "--export", ro / "e"],
        "vo --out": [*vo, "--out", ro / "t.txt"],
        "vo --csv": [*vo, "--out", ok, "--csv", ro / "t.csv"],
        "correct --out": [*correct, "--out", ro / "c.txt"],
        "correct --report": [*correct, "--out", ok, "--report", ro / "r"],
        "correct --cache": ["correct", "--checkpoint", d["run"], "--kitti-odometry", d["kitti"],
                            "--sequence", "00", "--prior", d["prior"], "--cache", ro / "cache", "--out", ok],
        "synth --out": ["synth", "--out", ro / "s", "--sequences", "1", "--frames", "2", "--size", "16x24"],
        "prepare --out": ["prepare", "--kitti-odometry", d["kitti"], "--sequence", "00",
                          "--prior", d["prior"], "--out", ro / "cache", "--size", "10x16"],
        # A missing config: were the workdir checked after loading it, the error would be another.
        "train --workdir": ["train", "--config", d["root"] / "missing.py", "--workdir", ro / "run"],
        "demo --out": ["demo", "--out", ro / "demo", "--config", d["root"] / "missing.py"],
    }


CASES = ["evaluate --json", "evaluate --report", "evaluate --export", "vo --out", "vo --csv", "correct --out",
         "correct --report", "correct --cache", "synth --out", "prepare --out", "train --workdir",
         "demo --out"]


@pytest.mark.parametrize("case", CASES)
def test_unwritable_output_is_refused_before_any_work(
    case: str, data: dict[str, Path], readonly: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ok = tmp_path / "ok.txt"
    args = _outputs_cases(data, readonly, ok)[case]
    assert main([str(a) for a in args]) == 2
    _one_line(capsys.readouterr().err, f"folder {readonly} is not writable")
    assert _files(readonly) == [] and not ok.exists()


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
def test_output_in_a_folder_nobody_can_write_is_refused_even_as_root(
    data: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    # Permission bits say yes to root in /proc (and read-only mounts); the check tries for real.
    target = Path("/proc/dpc-jax-test/m.json")
    assert main(["evaluate", "--gt", str(data["gt"]), "--est", str(data["est"]), "--json", str(target)]) == 2
    _one_line(capsys.readouterr().err, "folder /proc is not writable")


def test_a_disk_failing_after_the_checks_is_one_line(
    data: dict[str, Path], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import dpc_jax.cli.evaluate as evaluate_cli

    def full_disk(args: object) -> int:
        raise OSError(errno.ENOSPC, "No space left on device", "m.json")

    monkeypatch.setattr(evaluate_cli, "run", full_disk)
    assert main(["evaluate", "--gt", str(data["gt"]), "--est", str(data["est"])]) == 1
    _one_line(capsys.readouterr().err, "evaluate: error: [Errno 28] No space left on device: 'm.json'")


@pytest.mark.parametrize("case, existing, needle", [
    ("vo --out", "folder", "is a folder; expected a file name"),
    ("correct --out", "folder", "is a folder; expected a file name"),
    ("evaluate --json", "folder", "is a folder; expected a file name"),
    ("evaluate --report", "file", "exists and is not a folder"),
    ("correct --report", "file", "exists and is not a folder"),
    ("synth --out", "file", "exists and is not a folder"),
    ("prepare --out", "file", "exists and is not a folder"),
])
def test_output_of_the_wrong_kind_is_refused(
    case: str, existing: str, needle: str, data: dict[str, Path], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    target = tmp_path / f"a_{existing}"
    if existing == "folder":
        target.mkdir()
    else:
        target.write_text("keep me")
    ok = tmp_path / "ok.txt"
    args = _outputs_cases(data, tmp_path / "unused", ok)[case]
    option = case.split()[1]
    args[args.index(option) + 1] = target
    assert main([str(a) for a in args]) == 2
    _one_line(capsys.readouterr().err, f"{option} {target}: {needle}")
    assert _files(tmp_path) == [target.name] and (existing == "folder" or target.read_text() == "keep me")


def test_missing_parent_folders_are_created_only_when_writing(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "new" / "deeper"
    assert main(["evaluate", "--gt", str(data["gt"]), "--est", str(tmp_path / "missing.txt"),
                 "--json", str(out / "m.json")]) == 2
    assert "missing.txt" in capsys.readouterr().err and _files(tmp_path) == []

    assert main(["evaluate", "--gt", str(data["gt"]), "--est", str(data["est"]),
                 "--json", str(out / "m.json"), "--export", str(tmp_path / "new" / "export")]) == 0
    assert json.loads((out / "m.json").read_text())["num_poses"] == N_POSES
    assert (tmp_path / "new" / "export" / "gt.kitti.txt").is_file()
    assert main(["vo", "--kitti-odometry", str(data["kitti"]), "--sequence", "00", "--no-progress",
                 "--out", str(tmp_path / "vo" / "a" / "t.txt")]) == 0
    assert _files(tmp_path / "vo") == ["a", "a/.dpc-jax-files", "a/t.csv", "a/t.json", "a/t.txt"]


def test_vo_writes_trajectory_and_csv_all_or_nothing(
    data: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import dpc_jax.vo.odometry

    out = tmp_path / "t.txt"
    out.write_text("previous trajectory\n")

    def broken_table(result: object, first_frame: int = 0) -> str:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(dpc_jax.vo.odometry, "per_frame_table", broken_table)
    assert main(["vo", "--kitti-odometry", str(data["kitti"]), "--sequence", "00", "--no-progress",
                 "--out", str(out)]) == 1
    _one_line(capsys.readouterr().err, "vo: error: [Errno 28] No space left on device; nothing half-written")
    assert out.read_text() == "previous trajectory\n" and _files(tmp_path) == ["t.txt"]


def test_output_set_commit_is_undone_when_a_move_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    first, second = tmp_path / "a.txt", tmp_path / "sub" / "b.txt"
    first.write_text("old a")
    real_replace = os.replace

    def replace(src: object, dst: object) -> None:
        if Path(dst) == second:
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(_io.os, "replace", replace)
    with pytest.raises(OSError, match="No space left"), OutputSet() as outputs:
        atomic_write(outputs.file(first), "new a")
        atomic_write(outputs.file(second), "new b")
        outputs.commit()
    assert first.read_text() == "old a" and _files(tmp_path) == ["a.txt"]

    monkeypatch.setattr(_io.os, "replace", real_replace)
    with OutputSet() as outputs:
        atomic_write(outputs.file(first), "new a")
        atomic_write(outputs.folder(tmp_path / "sub") / "b.txt", "new b")
        assert outputs.commit() == [first, second]
    assert (first.read_text(), second.read_text()) == ("new a", "new b")
    assert _files(tmp_path) == ["a.txt", "sub", "sub/b.txt"]


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600)])
def test_written_files_get_the_mode_the_umask_allows(
    umask: int, mode: int, data: dict[str, Path], tmp_path: Path
) -> None:
    old = os.umask(umask)
    try:
        atomic_write(tmp_path / "plain.txt", "x")
        with OutputSet() as outputs:
            write_kitti_poses(outputs.file(tmp_path / "set" / "poses.txt"), np.eye(4)[None])
            outputs.commit()
        if umask == 0o022:
            assert main(["evaluate", "--gt", str(data["gt"]), "--est", str(data["est"]),
                         "--export", str(tmp_path / "export")]) == 0
    finally:
        os.umask(old)
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert len(files) >= 2 and {stat.S_IMODE(p.stat().st_mode) for p in files} == {mode}


# ----------------------------------------------------------------------------- inputs


def test_mat_given_to_gt_and_est_reads_poses_gt_and_poses_est(
    data: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    def m_ate(args: list[str]) -> float:
        assert main(["evaluate", *args, "--json", "-"]) == 0
        return next(iter(json.loads(capsys.readouterr().out)["estimates"].values()))["m_ate_trans_m"]

    mat, gt, est = str(data["mat"]), str(data["gt"]), str(data["est"])
    reference = m_ate(["--gt", gt, "--est", est])
    # est drifts sideways linearly up to 1.5 m: the mean position error is 0.75 m.
    assert reference == pytest.approx(0.75, rel=1e-6)
    assert m_ate(["--gt", mat, "--est", mat]) == pytest.approx(reference, rel=1e-9)
    assert m_ate(["--gt", mat, "--est", est]) == pytest.approx(reference, rel=1e-9)
    assert m_ate(["--gt", gt, "--est", mat]) == pytest.approx(reference, rel=1e-9)
    assert m_ate(["--mat", mat]) == pytest.approx(reference, rel=1e-9)
    np.testing.assert_allclose(read_trajectory(mat, mat_key="poses_gt"), read_trajectory(gt), atol=1e-12)


@pytest.mark.parametrize("command", ["evaluate --mat", "evaluate --gt", "evaluate --est", "prepare --prior"])
def test_random_bytes_named_mat_are_refused_in_one_line(
    command: str, data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "random.mat"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 100, dtype=np.uint8).tobytes())
    args = {
        "evaluate --mat": ["evaluate", "--mat", bad],
        "evaluate --gt": ["evaluate", "--gt", bad, "--est", data["est"]],
        "evaluate --est": ["evaluate", "--gt", data["gt"], "--est", bad],
        "prepare --prior": ["prepare", "--kitti-odometry", data["kitti"], "--sequence", "00", "--prior", bad,
                            "--out", tmp_path / "cache", "--size", "10x16", "--no-progress"],
    }[command]
    assert main([str(a) for a in args]) != 0
    _one_line(capsys.readouterr().err, f"{bad}: not a readable MATLAB .mat file")
    assert _files(tmp_path) == ["random.mat"]


def test_bad_inputs_fail_before_jax_is_imported(data: dict[str, Path], tmp_path: Path) -> None:
    """Every command checks its inputs (and options and outputs) before it imports JAX, so a mistake
    costs a fraction of a second: run in a fresh interpreter, JAX is still not imported afterwards."""
    (tmp_path / "empty").mkdir()
    (tmp_path / "taken" / "sequences" / "00").mkdir(parents=True)
    (tmp_path / "random.mat").write_bytes(bytes(range(256)))
    (tmp_path / "no_config.py").write_text("X = 1\n")
    (tmp_path / "bad_demo.py").write_text('CONFIG = {"select": "best"}\n')
    missing, out = tmp_path / "missing", tmp_path / "out"
    shutil.copytree(data["cache"], tmp_path / "damaged")
    _damage(tmp_path / "damaged", "broken manifest")
    for name in ("00", "05", "07"):
        shutil.copytree(data["cache"], tmp_path / "caches" / name)
    # train_sequences is empty: 07 is a training sequence (every cached one but the validation one).
    _damage(tmp_path / "caches" / "07", "manifest without n_frames")
    train_config(tmp_path / "no_cache.py", missing / "cache")
    train_config(tmp_path / "damaged_cache.py", tmp_path / "caches")
    correct = ["correct", "--checkpoint", data["run"], "--out", out / "c.txt"]
    cases = {
        "--mat {m}/a.mat: no such file": ["evaluate", "--mat", missing / "a.mat"],
        "--rpe-delta must be in [1, 29] for 30 poses, got 30": [
            "evaluate", "--gt", data["gt"], "--est", data["gt"], "--label", "same", "--rpe-delta", "30"],
        "random.mat: not a readable MATLAB .mat file": ["evaluate", "--gt", data["gt"], "--est",
                                                        tmp_path / "random.mat"],
        "--data {m}: not a folder": [*correct, "--data", missing],
        "not a prepared cache (no manifest.json)": [*correct, "--data", tmp_path / "empty"],
        "damaged/manifest.json: not valid JSON": [*correct, "--data", tmp_path / "damaged"],
        "--checkpoint {m}: not a training run": ["correct", "--checkpoint", missing, "--data", data["cache"],
                                                 "--out", out / "c.txt"],
        "--prior {m}/p.txt: no such file": [*correct, "--kitti-odometry", data["kitti"], "--sequence", "00",
                                            "--prior", missing / "p.txt"],
        "--kitti-raw {m}: no such folder": [*correct, "--kitti-raw", missing, "--date", "2011_09_26",
                                            "--drive", "1", "--prior", data["prior"]],
        "07: {k}/sequences/07: odometry sequence folder not found": [
            "prepare", "--kitti-odometry", data["kitti"], "--sequence", "07", "--prior", data["prior"],
            "--out", out / "cache"],
        "00: --gt {m}/gt.txt: no such file": [
            "prepare", "--kitti-odometry", data["kitti"], "--sequence", "00", "--prior", data["prior"],
            "--gt", missing / "gt.txt", "--out", out / "cache"],
        "--kitti-odometry {m}: no such folder": ["vo", "--kitti-odometry", missing, "--sequence", "00",
                                                 "--out", out / "t.txt"],
        "frames must be at least 2": ["synth", "--out", out / "synth", "--frames", "1"],
        "taken/sequences already holds sequence(s) 00; pass --overwrite": [
            "synth", "--out", tmp_path / "taken", "--frames", "2", "--sequences", "1"],
        "missing/c.py: config file not found": ["train", "--config", missing / "c.py", "--workdir",
                                                out / "run"],
        "no_config.py: defines no CONFIG": ["train", "--config", tmp_path / "no_config.py", "--workdir",
                                            out / "run"],
        "cache_root '{m}/cache' is not a directory": ["train", "--config", tmp_path / "no_cache.py",
                                                       "--workdir", out / "run"],
        "caches/07/manifest.json: field 'n_frames' is missing": [
            "train", "--config", tmp_path / "damaged_cache.py", "--workdir", out / "run"],
        "--config {m}/c.py: no such file": ["demo", "--config", missing / "c.py", "--out", out / "demo"],
        "select must be one of": ["demo", "--config", tmp_path / "bad_demo.py", "--out", out / "demo"],
    }
    status, imported, done = in_one_process(list(cases.values()))
    assert imported == [] and all(s != 0 for s in status), (status, imported)
    lines = done.stderr.splitlines()
    assert len(lines) == len(cases) and "Traceback" not in done.stderr, done.stderr
    for needle, line in zip(cases, lines, strict=True):
        assert needle.format(m=missing, k=data["kitti"]) in line, (needle, line)
    assert not out.exists()


def test_silent_and_late_mistakes_are_one_line_and_exit_2_before_jax(
    data: dict[str, Path], tmp_path: Path
) -> None:
    """Issue 33: what was accepted silently (a CSV overwritten by the summary, one prior for several
    sequences, a NaN offset), failed late (a hold-out that keeps nothing out) or with a traceback (a
    config file that is not valid Python or raises, demo fields checked by the renderer), and the
    misleading messages, each end in one line and exit status 2, before JAX is imported."""
    out = tmp_path / "out"
    for name in ("00", "05"):
        shutil.copytree(data["cache"], tmp_path / "caches" / name)
    (tmp_path / "syntax.py").write_text('CONFIG = {"method": "stereo_dpc",\n    "preset": "small"\n')
    (tmp_path / "raises.py").write_text("import json\nCONFIG = json.loads('{')\n")
    train_config(tmp_path / "ss_dpc.py", tmp_path / "caches", method="ss_dpc")
    for name, field in (("size", '"render_size": (0, 0)'), ("noise", '"noise": -1'),
                        ("cars", '"moving_objects": -3')):
        (tmp_path / f"demo_{name}.py").write_text(f"CONFIG = {{{field}}}\n")
    one_pose = tmp_path / "one.txt"
    one_pose.write_text(data["gt"].read_text().splitlines()[0] + "\n")
    odd_name = tmp_path / "my estimate (v2) é.txt"
    shutil.copy(data["est"], odd_name)
    vo = ["vo", "--kitti-odometry", data["kitti"], "--sequence", "00"]
    prepare = ["prepare", "--kitti-odometry", data["kitti"], "--prior", data["prior"], "--out", out / "cache"]
    cases = {
        "--csv {o}/a.json: the same file as the run summary {o}/a.json": [
            *vo, "--out", out / "a.txt", "--csv", out / "a.json"],
        "--out {o}/a.json: the run summary goes to OUT with suffix .json, the same file": [
            *vo, "--out", out / "a.json"],
        "--disparity-offset nan: expected a finite number": [*vo, "--out", out / "a.txt",
                                                             "--disparity-offset", "nan"],
        "--frames 2:9: 00 has 6 frames (0 to 5); STOP must be at most 6": [
            *vo, "--out", out / "a.txt", "--frames", "2:9"],
        "--prior {p}: 2 sequences would share this one file; put {{seq}} in the path": [
            *prepare, "--sequence", "00", "05"],
        "--frames 0:7: 00 has 6 frames (0 to 5)": [*prepare, "--sequence", "00", "--frames", "0:7"],
        "--noise nan: expected a finite number": ["synth", "--out", out / "s", "--noise", "nan"],
        "--judge CACHE goes with --data": [
            "correct", "--checkpoint", data["run"], "--kitti-odometry", data["kitti"], "--sequence", "00",
            "--prior", data["prior"], "--judge", data["cache"], "--out", out / "c.txt"],
        "--holdout-every 1000: keeps 0 of the 5 frame pairs of": [
            "correct", "--checkpoint", data["run"], "--data", data["cache"], "--out", out / "c.txt",
            "--adapt", "5", "--holdout-every", "1000"],
        "syntax.py, line 1: not valid Python": ["train", "--config", tmp_path / "syntax.py",
                                               "--workdir", out / "run"],
        "raises.py, line 2: running it raised JSONDecodeError": [
            "train", "--config", tmp_path / "raises.py", "--workdir", out / "run"],
        "no forward or skip flow in the cache, which method 'ss_dpc' reads": [
            "train", "--config", tmp_path / "ss_dpc.py", "--workdir", out / "run"],
        "demo_size.py: image size must be at least 8": ["demo", "--config", tmp_path / "demo_size.py",
                                                       "--out", out / "demo"],
        "demo_noise.py: noise must be >= 0": ["demo", "--config", tmp_path / "demo_noise.py",
                                             "--out", out / "demo"],
        "demo_cars.py: moving_objects must be >= 0, got -3": [
            "demo", "--config", tmp_path / "demo_cars.py", "--out", out / "demo"],
        "one.txt: holds 1 pose; a trajectory to evaluate needs at least 2": [
            "evaluate", "--gt", one_pose, "--est", one_pose],
        "the label comes from the file name, so give one with --label NAME": [
            "evaluate", "--gt", data["gt"], "--est", odd_name],
    }
    status, imported, done = in_one_process(list(cases.values()))
    lines = done.stderr.splitlines()
    assert len(lines) == len(cases) and "Traceback" not in done.stderr, done.stderr
    for needle, line in zip(cases, lines, strict=True):
        assert needle.format(o=out, p=data["prior"]) in line, (needle, line)
    assert imported == [] and status == [2] * len(cases), (status, imported)
    assert not out.exists()


def test_slow_and_unclear_failures_are_one_line_before_jax(data: dict[str, Path], tmp_path: Path) -> None:
    """``correct`` from raw inputs checks --frames and the prior's length before JAX (it did after JAX
    loaded); a sequence given as a path, the root of several caches as --data and --no-judge with --data
    (no judge to turn off) are named in one line, exit status 2, nothing written."""
    out = tmp_path / "out"
    short = tmp_path / "short.txt"
    short.write_text("".join(data["prior"].read_text().splitlines(keepends=True)[:3]))
    shutil.copytree(data["cache"], tmp_path / "caches" / "00")
    raw = ["correct", "--checkpoint", data["run"], "--kitti-odometry", data["kitti"], "--out", out / "c.txt"]
    cached = ["correct", "--checkpoint", data["run"], "--out", out / "c.txt"]
    cases = {
        "--frames 2:9: 00 has 6 frames (0 to 5); STOP must be at most 6": [
            *raw, "--sequence", "00", "--prior", data["prior"], "--frames", "2:9"],
        f"--prior {short}: 3 prior poses for 6 frames": [*raw, "--sequence", "00", "--prior", short],
        "sequence '../sequences/00': expected the name of a folder in": [
            *raw, "--sequence", "../sequences/00", "--prior", data["prior"]],
        f"--data {tmp_path / 'caches'}: a folder of caches (00), not one; give one of them, e.g. --data "
        f"{tmp_path / 'caches' / '00'}": [*cached, "--data", tmp_path / "caches"],
        "--no-judge goes with raw inputs": [*cached, "--data", data["cache"], "--no-judge"],
    }
    status, imported, done = in_one_process(list(cases.values()))
    lines = done.stderr.splitlines()
    assert len(lines) == len(cases) and "Traceback" not in done.stderr, done.stderr
    for needle, line in zip(cases, lines, strict=True):
        assert needle in line, (needle, line)
    assert imported == [] and status == [2] * len(cases), (status, imported)
    assert not out.exists()


def test_a_file_output_spelled_as_a_folder_is_refused(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``vo --out vo/newdir/`` (no such folder) wrote a file named vo/newdir; the slash now means a folder."""
    folder = f"{tmp_path}/new/"
    for argv in (["vo", "--kitti-odometry", data["kitti"], "--sequence", "00", "--out", folder],
                 ["evaluate", "--gt", data["gt"], "--est", data["est"], "--json", folder],
                 ["correct", "--checkpoint", data["run"], "--data", data["cache"], "--out", folder]):
        with pytest.raises(SystemExit) as exited:
            main([str(a) for a in argv])
        assert exited.value.code == 2
        assert f"'{tmp_path}/new/' ends in '/', the spelling of a folder" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_standard_output_into_an_input_is_refused(data: dict[str, Path], tmp_path: Path) -> None:
    """``dpc-jax evaluate ... >> est.txt`` appended the table (or the JSON of --json /dev/stdout) to its
    own input; the command tells by the inode that its standard output is a file it reads."""
    est = tmp_path / "est.txt"
    shutil.copy(data["est"], est)
    before = est.read_bytes()
    code = "import sys; from dpc_jax.cli import main; sys.exit(main(sys.argv[1:]))"
    for extra in ([], ["--json", "/dev/stdout"]):
        with est.open("ab") as stdout:
            argv = [sys.executable, "-c", code, "evaluate", "--gt", str(data["gt"]), "--est", str(est),
                    *extra]
            done = subprocess.run(argv, stdout=stdout, stderr=subprocess.PIPE, text=True, cwd=ROOT)
        assert done.returncode == 2
        _one_line(done.stderr, f"standard output is the input --est {est} (redirected there with > or >>)")
    assert est.read_bytes() == before


def _damage(cache: Path, how: str) -> str:
    """Damage a copy of a cache; return the file the error must name."""
    def rewrite(file: str, change) -> None:
        np.save(cache / file, change(np.load(cache / file)))

    if how == "NaN prior":
        rewrite("prior.npy", lambda a: np.where(np.arange(a.shape[0])[:, None, None] == 2, np.nan, a))
        return "prior.npy: pose 2 is not finite"
    if how == "prior 3 poses short":
        rewrite("prior.npy", lambda a: a[:-3])
        return "prior.npy: float64 (3, 4, 4), but"
    if how == "non-rigid ground truth":
        rewrite("gt.npy", lambda a: np.concatenate([a[:, :, :3] * 1.5, a[:, :, 3:]], axis=2))
        return "gt.npy: pose 0 is not rigid"
    if how == "NaN in K":
        rewrite("K.npy", lambda a: np.full_like(a, np.nan))
        return "K.npy: holds a value that is not finite"
    if how == "broken manifest":
        text = (cache / "manifest.json").read_text()
        (cache / "manifest.json").write_text(text[:40])
        return "manifest.json: not valid JSON"
    if how == "manifest without n_frames":
        manifest = json.loads((cache / "manifest.json").read_text())
        del manifest["n_frames"]
        (cache / "manifest.json").write_text(json.dumps(manifest))
        return "manifest.json: field 'n_frames' is missing"
    if how == "truncated left.npy":
        raw = (cache / "left.npy").read_bytes()
        (cache / "left.npy").write_bytes(raw[: len(raw) // 2])
        return "left.npy: unreadable or truncated .npy file"
    if how == "missing right.npy":
        (cache / "right.npy").unlink()
        return "right.npy: missing from the cache"
    raise AssertionError(how)


DAMAGES = ["NaN prior", "prior 3 poses short", "non-rigid ground truth", "NaN in K", "broken manifest",
           "manifest without n_frames", "truncated left.npy", "missing right.npy"]


@pytest.mark.parametrize("how", DAMAGES)
def test_damaged_cache_is_named_before_the_network_runs(
    how: str, data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cache = tmp_path / "cache"
    shutil.copytree(data["cache"], cache)
    needle = _damage(cache, how)
    with pytest.raises(CacheError, match=re.escape(needle)):
        load_cache(cache)
    out = tmp_path / "c.txt"
    # The run folder holds no network: the cache must be refused before one is restored.
    assert main(["correct", "--checkpoint", str(data["run"]), "--data", str(cache), "--out", str(out),
                 "--no-progress"]) == 2
    _one_line(capsys.readouterr().err, f"{cache}/{needle}")
    assert not out.exists()


def test_train_on_a_truncated_cache_is_one_line(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "cache"
    for name in ("00", "05"):
        shutil.copytree(data["cache"], root / name)
    _damage(root / "00", "truncated left.npy")
    config = tmp_path / "config.py"
    config.write_text(
        f"CONFIG = {{'method': 'stereo_dpc', 'preset': 'small', 'image_size': (32, 48), 'batch_size': 2, "
        f"'epochs': 1, 'pose_warmup_epochs': 0, 'cache_root': {str(root)!r}, 'train_sequences': ('00',), "
        f"'validation_sequences': ('05',)}}\n"
    )
    assert main(["train", "--config", str(config), "--workdir", str(tmp_path / "run"), "--no-progress"]) == 2
    _one_line(capsys.readouterr().err, f"{root / '00' / 'left.npy'}: unreadable or truncated .npy file")
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_train_checks_the_caches_it_reads_and_only_those(data: dict[str, Path], tmp_path: Path) -> None:
    from dpc_jax.cli.train import _cache_problem
    from dpc_jax.config import load_file
    from dpc_jax.training.train_config import TrainConfig

    root = tmp_path / "cache"
    for name in ("00", "05", "07", "09"):
        shutil.copytree(data["cache"], root / name)
    _damage(root / "09", "broken manifest")  # the test sequence: training never reads it
    train_config(tmp_path / "all.py", root, test_sequences=("09",))
    train_config(tmp_path / "only_00.py", root, train_sequences=("00",), test_sequences=("09",))
    every, only_00 = (load_file(tmp_path / f, TrainConfig) for f in ("all.py", "only_00.py"))
    assert _cache_problem(every, "all.py") is None and _cache_problem(only_00, "only_00.py") is None
    # train_sequences empty: every cached sequence but the validation and test ones is read.
    needle = _damage(root / "07", "truncated left.npy")
    assert f"{root / '07'}/{needle}" in str(_cache_problem(every, "all.py"))
    assert _cache_problem(only_00, "only_00.py") is None
    needle = _damage(root / "05", "NaN in K")  # the validation sequence
    assert f"{root / '05'}/{needle}" in str(_cache_problem(only_00, "only_00.py"))


def test_damaged_checkpoint_is_one_line_naming_its_folder(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "config.json").write_bytes(b"\x00\x01 not a config")
    out = tmp_path / "c.txt"
    assert main(["correct", "--checkpoint", str(run), "--data", str(data["cache"]), "--out", str(out),
                 "--no-progress"]) == 2
    _one_line(capsys.readouterr().err, f"{run / 'checkpoints' / 'config.json'}: not valid JSON")
    assert not out.exists()


def test_restore_failure_silences_the_event_loop_noise(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
    monkeypatch.setattr(logging.getLogger("asyncio"), "level", logging.getLogger("asyncio").level)
    cause = ValueError('OUT_OF_RANGE: Error reading "w/0" in OCDBT database at local file "/run/state/"')
    try:
        raise Exception("Encountered error while reading array index. See TensorStore details") from cause
    except Exception as error:  # the shape of orbax's error: a bare Exception around tensorstore's
        message = restore_problem(Path("/run/checkpoints"), error)
    assert message.startswith("/run/checkpoints: cannot restore the checkpoint (ValueError: OUT_OF_RANGE")

    class Closed:
        def __del__(self) -> None:
            raise RuntimeError("Event loop is closed")

    Closed()  # an exception in __del__ goes to sys.unraisablehook
    logging.getLogger("asyncio").error("Task exception was never retrieved")
    captured = capsys.readouterr()
    assert "Event loop is closed" not in captured.err and "never retrieved" not in captured.err


def test_calibration_nan_says_not_finite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    written = write_odometry(tmp_path / "kitti", n=3, size=(16, 24))
    calib = tmp_path / "kitti" / "sequences" / "00" / "calib.txt"
    rows = calib.read_text().splitlines()
    fields = rows[2].split()
    rows[2] = " ".join([fields[0], fields[1], "nan", *fields[3:]])
    calib.write_text("\n".join(rows) + "\n")
    prior = tmp_path / "prior.txt"
    write_kitti_poses(prior, written["poses"])
    assert main(["prepare", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00", "--prior",
                 str(prior), "--out", str(tmp_path / "cache"), "--size", "8x8", "--no-progress"]) == 1
    _one_line(capsys.readouterr().err,
              f"{calib}, line 3: P2 holds a value that is not finite (nan at entry 2")
    assert main(["vo", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00", "--no-progress",
                 "--out", str(tmp_path / "vo.txt")]) == 1
    _one_line(capsys.readouterr().err,
              f"dpc-jax vo: error: {calib}, line 3: P2 holds a value that is not finite (nan at entry 2")
    assert not (tmp_path / "vo.txt").exists()


@pytest.mark.parametrize("command", ["synth", "prepare"])
def test_oversized_images_need_allow_large(
    command: str, data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    args = {
        # --frames 1 is refused by the synthesiser: reaching that error proves the size was accepted.
        "synth": ["synth", "--out", out, "--sequences", "1", "--frames", "1"],
        "prepare": ["prepare", "--kitti-odometry", data["kitti"], "--sequence", "00", "--prior",
                    tmp_path / "missing.txt", "--out", out, "--no-progress"],
    }[command]
    args = [str(a) for a in args]
    assert main([*args, "--size", "5000x8000"]) == 2
    _one_line(capsys.readouterr().err,
              "--size 5000x8000: 40.0 megapixels per image, more than 4; pass --allow-large")
    assert main([*args, "--size", "2000x2000"]) != 0  # 4.0 MP: allowed, fails on the input
    assert "megapixels" not in capsys.readouterr().err
    assert main([*args, "--size", "5000x8000", "--allow-large"]) != 0
    err = capsys.readouterr().err
    assert "megapixels" not in err and ("frames must be" in err or "missing.txt" in err)
    assert not out.exists()


def test_tum_timestamps_going_back_are_refused_and_a_jump_warns(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    poses = read_trajectory(data["gt"])
    stamps = np.arange(N_POSES) * 0.1
    gap = stamps.copy()
    gap[10:] += 3.0
    # write_tum refuses times that go back (test_api_validation), so the file is edited after writing.
    write_tum(tmp_path / "back.tum", poses, stamps)
    lines = (tmp_path / "back.tum").read_text().splitlines()
    lines[5] = " ".join(["0.05", *lines[5].split()[1:]])
    (tmp_path / "back.tum").write_text("\n".join(lines) + "\n")
    write_tum(tmp_path / "gap.tum", poses, gap)
    assert main(["evaluate", "--gt", str(data["gt"]), "--est", str(tmp_path / "back.tum")]) == 2
    _one_line(capsys.readouterr().err, f"{tmp_path / 'back.tum'}, line 6: timestamp 0.05")
    assert main(["evaluate", "--gt", str(data["gt"]), "--est", str(tmp_path / "gap.tum"), "--json", "-"]) == 0
    captured = capsys.readouterr()
    _one_line(captured.err,
              f"dpc-jax evaluate: warning: {tmp_path / 'gap.tum'}, line 11: timestamps jump by 3.1 s")
    assert json.loads(captured.out)["estimates"]["gap"]["m_ate_trans_m"] == pytest.approx(0.0, abs=1e-9)


def test_rerunning_synth_suggests_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "sequences" / "00").mkdir(parents=True)
    args = ["synth", "--out", str(tmp_path), "--sequences", "1", "--frames", "2", "--size", "16x24"]
    assert main(args) == 2
    _one_line(capsys.readouterr().err, "already holds sequence(s) 00; pass --overwrite to replace them")


# ----------------------------------------------------------------------------- interruption, temporaries


def _stale_and_live(folder: Path, prefix: str) -> tuple[Path, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    stale = folder / f"{prefix}{dead_pid()}-dead"
    live = folder / f"{prefix}{os.getpid()}-live"
    for path in (stale, live):
        path.mkdir()
        (path / "left.npy").write_bytes(b"x" * 1000)
    return stale, live


def test_remove_stale_keeps_live_runs_and_drops_dead_or_reused_pids(tmp_path: Path) -> None:
    stale, live = _stale_and_live(tmp_path, ".x.tmp-")
    reused = tmp_path / f".x.tmp-{os.getpid()}-old"
    reused.mkdir()
    other = tmp_path / "x.tmp-1-unrelated"
    other.mkdir()
    if Path("/proc/self/stat").exists():
        # Last written long before this process started: the pid was reused, the owner is gone.
        os.utime(reused, (time.time() - 10 * 86400,) * 2)
    removed = remove_stale(tmp_path, ".x.tmp-")
    expected = {stale, reused} if Path("/proc/self/stat").exists() else {stale}
    assert set(removed) == expected and live.is_dir() and other.is_dir()
    assert all(not p.exists() for p in expected)


def test_prepare_removes_the_temporaries_of_killed_runs_and_reports_rebuild_or_reuse(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cache"
    stale, live = _stale_and_live(out, ".00.tmp-")
    old_stale, _ = _stale_and_live(out, ".00.old-")
    args = ["prepare", "--kitti-odometry", str(data["kitti"]), "--sequence", "00",
            "--prior", str(data["prior"]), "--out", str(out), "--size", "10x16"]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert captured.out.strip() == str(out / "00")
    assert re.search(r"^00 prepare: 6/6 frames \(", captured.err, re.M)  # progress lines off a terminal
    assert re.search(rf"^00: built {re.escape(str(out / '00'))} in [0-9.]+ s$", captured.err, re.M)
    assert not stale.exists() and not old_stale.exists() and live.is_dir()
    assert main([*args, "--no-progress"]) == 0
    _one_line(capsys.readouterr().err, f"00: up to date, reused {out / '00'}")


def test_ctrl_c_in_prepare_is_one_line_and_leaves_no_temporary(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import dpc_jax.data.frames as frames_module

    real = frames_module.load_image  # each image of a frame is decoded through it
    calls: list[Path] = []

    def interrupted(path: Path, *args: object) -> np.ndarray:
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(path, *args)

    monkeypatch.setattr(frames_module, "load_image", interrupted)
    out = tmp_path / "cache"
    assert main(["prepare", "--kitti-odometry", str(data["kitti"]), "--sequence", "00", "--prior",
                 str(data["prior"]), "--out", str(out), "--size", "10x16"]) == 130
    assert capsys.readouterr().err == "dpc-jax prepare: interrupted; nothing half-written\n"
    assert not out.exists()  # made for the cache, removed with it


def test_prepare_failing_on_a_sequence_leaves_no_folder_it_made(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    short = tmp_path / "short.txt"
    short.write_text("".join(data["prior"].read_text().splitlines(keepends=True)[:3]))
    out = tmp_path / "new" / "cache"
    assert main(["prepare", "--kitti-odometry", str(data["kitti"]), "--sequence", "00", "--prior", str(short),
                 "--out", str(out), "--size", "10x16", "--no-progress"]) == 1
    _one_line(capsys.readouterr().err, "short.txt")
    assert _files(tmp_path) == ["short.txt"]


def test_ctrl_c_in_synth_subprocess(tmp_path: Path) -> None:
    """A real SIGINT: exit status 130, one line, no sequence and no temporary folder left behind
    (and the temporary folder of an earlier killed run is gone too)."""
    out = tmp_path / "synth"
    _stale_and_live(out / "sequences", ".00.tmp-")
    shutil.rmtree(out / "sequences" / f".00.tmp-{os.getpid()}-live")
    argv = ["dpc-jax", "synth", "--out", str(out), "--sequences", "1", "--frames", "500", "--size", "48x72"]
    # As from a terminal: a suite started in the background (`cmd &` in a script) has SIGINT
    # ignored, its children inherit that, and Python then never raises KeyboardInterrupt.
    start = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
             f"sys.argv = {argv!r}; runpy.run_module('dpc_jax', run_name='__main__')")
    process = subprocess.Popen(
        [sys.executable, "-c", start], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "DPC_JAX_HUGE_PAGES": "0"}, cwd=ROOT,
    )
    deadline = time.monotonic() + 120
    while process.poll() is None and time.monotonic() < deadline:
        if list((out / "sequences").glob(".00.tmp-*/image_2/000001.png")):  # rendering
            break
        time.sleep(0.01)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert err.splitlines()[-1] == "dpc-jax synth: interrupted; nothing half-written"
    assert "Traceback" not in err
    # sequences/ held the dead run's folder, so it stays; poses/ was made by this run, so it goes.
    assert _files(out) == ["sequences"]


# Ctrl-C while XLA compiles: the signal is sent from a timer the first compilation starts, so it
# lands while jaxlib's thread pool is still compiling (the compilation cache is off: conftest).
_INTERRUPT_COMPILE = """
import os, runpy, signal, sys, threading
from jax._src import compiler
signal.signal(signal.SIGINT, signal.default_int_handler)
compile_and_load, started = compiler.backend_compile_and_load, []
def interrupted(*args, **kwargs):
    if not started:
        started.append(threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)))
        started[0].start()
    return compile_and_load(*args, **kwargs)
compiler.backend_compile_and_load = interrupted
sys.argv = ["dpc-jax", *sys.argv[1:]]
runpy.run_module("dpc_jax", run_name="__main__")
"""


@pytest.mark.parametrize("attempt", range(3))
def test_ctrl_c_during_compilation_exits_130_without_a_crash(
    attempt: int, data: dict[str, Path], tmp_path: Path
) -> None:
    """Before the fix the interpreter's teardown freed XLA's client under the running compilation:
    exit status 139 (a segmentation fault) after the one line, every time."""
    argv = ["evaluate", "--gt", str(data["gt"]), "--est", str(data["est"]),
            "--json", str(tmp_path / "m.json")]
    done = subprocess.run([sys.executable, "-c", _INTERRUPT_COMPILE, *argv], capture_output=True, text=True,
                          env={**os.environ, "DPC_JAX_COMPILATION_CACHE": "0"}, cwd=ROOT, timeout=300)
    assert done.returncode == 130, done.stderr
    _one_line(done.stderr, "dpc-jax evaluate: interrupted; nothing half-written")
    assert _files(tmp_path) == []


def test_ctrl_c_during_synth_compilation_exits_130_and_leaves_nothing(tmp_path: Path) -> None:
    out = tmp_path / "synth"
    argv = ["synth", "--out", str(out), "--sequences", "1", "--frames", "50", "--size", "48x72"]
    done = subprocess.run([sys.executable, "-c", _INTERRUPT_COMPILE, *argv], capture_output=True, text=True,
                          env={**os.environ, "DPC_JAX_COMPILATION_CACHE": "0", "DPC_JAX_HUGE_PAGES": "0"},
                          cwd=ROOT, timeout=300)
    assert done.returncode == 130, done.stderr
    assert done.stderr.splitlines()[-1] == "dpc-jax synth: interrupted; nothing half-written"
    assert "Traceback" not in done.stderr and not out.exists()


# ----------------------------------------------------------------------------- help, progress, config


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_help_has_no_noise_and_examples() -> None:
    for name, parser in _subparsers().items():
        text = parser.format_help()
        assert "(default: None)" not in text and "(default: False)" not in text, name
        assert "examples:" in text and f"dpc-jax {name} " in text.split("examples:")[1], name
        formatter = parser._get_formatter()
        assert isinstance(formatter, Formatter), name
        for action in parser._actions:
            if action.help:
                assert formatter._expand_help(action).lower().count("default") <= 1, (name, action.dest)
            if action.option_strings and action.nargs != 0 and "_" in action.dest:
                default = formatter._get_default_metavar_for_optional(action)
                assert formatter._metavar_formatter(action, default)(1)[0] != action.dest.upper(), name


def test_help_states_defaults_of_zero() -> None:
    """0 equals False, and the formatter once took a default of 0 for "no default"."""
    parsers = _subparsers()
    cases = [("synth", "--seed", "0"), ("synth", "--moving-objects", "0"), ("synth", "--noise", "0.0"),
             ("synth", "--illumination-drift", "0.0"), ("synth", "--disparity-offset", "0.0"),
             ("vo", "--disparity-offset", "0.0")]
    for command, option, default in cases:
        parser = parsers[command]
        action = next(a for a in parser._actions if option in a.option_strings)
        text = parser._get_formatter()._expand_help(action)
        assert text.endswith(f"(default: {default})"), (command, option, text)


def test_train_help_cites_configs_that_exist() -> None:
    text = _subparsers()["train"].format_help()
    cited = set(re.findall(r"experiments/\w+/configs/[a-z0-9_]+\.py", text))  # not the NAME.py placeholder
    assert "experiments/protocols/configs/own_data.py" in cited
    assert all((ROOT / path).is_file() for path in cited), cited


def test_own_data_config_is_a_train_config_and_states_its_command() -> None:
    from dpc_jax import TrainConfig
    from dpc_jax.config import load_file

    path = ROOT / "experiments" / "protocols" / "configs" / "own_data.py"
    config = load_file(path, TrainConfig)
    doc = path.read_text().split('"""')[1]
    assert "dpc-jax prepare" in doc
    assert "dpc-jax train --config experiments/protocols/configs/own_data.py" in doc
    assert config.cache_root and config.validation_sequences
