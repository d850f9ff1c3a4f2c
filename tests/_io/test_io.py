"""dpc_jax._io: installing a finished folder over an older one; outputs that are links, FIFOs or devices."""

import errno
import io
import os
import re
import socket
import stat
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest

from dpc_jax import _io
from dpc_jax._io import STAGING_PREFIX, OutputSet, atomic_write, install_folder, output_problem, output_target
from dpc_jax.data.poses_io import write_kitti_poses
from dpc_jax.runtime.compilation_cache import OPT_OUT


def _folder(path: Path, name: str) -> Path:
    path.mkdir()
    (path / name).write_text(name)
    return path


def test_install_folder_replaces_the_older_one_and_leaves_nothing_behind(tmp_path: Path) -> None:
    target = tmp_path / "seq"
    install_folder(_folder(tmp_path / ".seq.tmp-1", "first"), target)
    assert [p.name for p in target.iterdir()] == ["first"]
    install_folder(_folder(tmp_path / ".seq.tmp-2", "second"), target)
    assert [p.name for p in target.iterdir()] == ["second"]
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]


# ----------------------------------------------------------------------------- output targets


def test_output_target_follows_links_and_tells_streams_from_files(tmp_path: Path) -> None:
    real = tmp_path / "real.json"
    real.write_text("{}")
    (tmp_path / "link.json").symlink_to("real.json")
    (tmp_path / "dangling.json").symlink_to("sub/new.json")
    (tmp_path / "sub").mkdir()
    (tmp_path / "chain.json").symlink_to(tmp_path / "link.json")
    os.mkfifo(tmp_path / "fifo")
    assert output_target(real) == ("file", real)
    assert output_target(tmp_path / "new.json") == ("file", tmp_path / "new.json")
    assert output_target(tmp_path / "link.json") == ("file", real)
    assert output_target(tmp_path / "chain.json") == ("file", real)
    assert output_target(tmp_path / "dangling.json") == ("file", tmp_path / "sub" / "new.json")
    assert output_target(tmp_path / "sub") == ("folder", tmp_path / "sub")
    assert output_target(tmp_path / "fifo")[0] == "stream"
    assert output_target("/dev/null") == ("stream", Path("/dev/null"))
    # /dev/stdout leads into /proc whatever descriptor 1 is (here pytest's temporary file): written
    # through, never replaced.
    assert output_target("/dev/stdout")[0] == "stream"
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(tmp_path / "sock"))
        assert output_target(tmp_path / "sock")[0] == "socket"
        assert output_problem(tmp_path / "sock", "--json") == (
            f"--json {tmp_path / 'sock'}: is a socket; expected a regular file, a character device or a FIFO")


def test_a_symlinked_output_replaces_its_target_atomically_and_keeps_the_link(tmp_path: Path) -> None:
    real = tmp_path / "results" / "real.json"
    real.parent.mkdir()
    real.write_text("old")
    before = real.stat().st_ino
    link = tmp_path / "link.json"
    link.symlink_to(real)
    atomic_write(link, "new")
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert real.read_text() == "new" and real.stat().st_ino != before  # a new file renamed over it
    with OutputSet() as outputs:
        atomic_write(outputs.file(link), "set")
        atomic_write(outputs.file(tmp_path / "other.txt"), "other")
        outputs.commit()
    assert link.is_symlink() and real.read_text() == "set"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "other.txt", "results"]
    assert [p.name for p in real.parent.iterdir()] == ["real.json"]  # no staging folder left


def _read_fifo(path: Path, into: list[bytes]) -> threading.Thread:
    def read() -> None:
        with open(path, "rb") as handle:
            into.append(handle.read())

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread


def test_a_fifo_output_is_streamed_once_the_set_is_complete(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    received: list[bytes] = []
    reader = _read_fifo(fifo, received)
    with OutputSet() as outputs:
        atomic_write(outputs.file(fifo), "through the pipe\n")
        atomic_write(outputs.file(tmp_path / "beside.txt"), "beside")
        assert received == []  # nothing reaches the reader before the commit
        assert outputs.commit() == [tmp_path / "beside.txt", fifo]
    reader.join(timeout=10)
    assert received == [b"through the pipe\n"]
    assert stat.S_ISFIFO(fifo.lstat().st_mode)  # still a FIFO, not replaced by a file
    assert sorted(p.name for p in tmp_path.iterdir()) == ["beside.txt", "fifo"]
    assert not list(Path(tempfile.gettempdir()).glob(f"{STAGING_PREFIX}{os.getpid()}-*"))


def test_a_character_device_output_is_written_not_replaced() -> None:
    atomic_write("/dev/null", "discarded")
    with OutputSet() as outputs:
        atomic_write(outputs.file("/dev/null"), "discarded")
        outputs.commit()
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.slow
def test_evaluate_json_to_a_fifo_a_link_and_redirected_stdout(tmp_path: Path,
                                                            tmp_path_factory: pytest.TempPathFactory) -> None:
    """The command line end to end: the same JSON reaches a regular file, a FIFO's reader, a symlink's
    target and a file the shell redirected standard output to (and there nothing else: no table after
    the JSON, which would make it unreadable as JSON)."""
    poses = np.tile(np.eye(4), (12, 1, 1))
    poses[:, 0, 3] = np.arange(12.0)
    est = poses.copy()
    est[:, 1, 3] = 0.05 * np.arange(12.0)
    write_kitti_poses(tmp_path / "gt.txt", poses)
    write_kitti_poses(tmp_path / "est.txt", est)
    fifo, real, link = tmp_path / "fifo", tmp_path / "real.json", tmp_path / "link.json"
    os.mkfifo(fifo)
    real.write_text("old")
    link.symlink_to(real.name)
    base = [sys.executable, "-m", "dpc_jax", "evaluate", "--gt", "gt.txt", "--est", "est.txt", "--json"]
    # One compilation cache for the four runs (outside tmp_path, whose files are checked below): the later
    # three load the metrics' program the first compiled.
    env = {**os.environ, "DPC_JAX_HUGE_PAGES": "0", OPT_OUT: str(tmp_path_factory.mktemp("compiled"))}
    subprocess.run([*base, "plain.json"], cwd=tmp_path, check=True, capture_output=True, env=env)
    expected = (tmp_path / "plain.json").read_bytes()
    received: list[bytes] = []
    reader = _read_fifo(fifo, received)
    subprocess.run([*base, "fifo"], cwd=tmp_path, check=True, capture_output=True, env=env)
    reader.join(timeout=10)
    subprocess.run([*base, "link.json"], cwd=tmp_path, check=True, capture_output=True, env=env)
    with open(tmp_path / "stdout.txt", "wb") as stdout:
        subprocess.run([*base, "/dev/stdout"], cwd=tmp_path, check=True, stdout=stdout, env=env)
    assert received == [expected] and stat.S_ISFIFO(fifo.lstat().st_mode)
    assert link.is_symlink() and real.read_bytes() == expected
    assert (tmp_path / "stdout.txt").read_bytes() == expected
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "est.txt", "fifo", "gt.txt", "link.json", "plain.json", "real.json", "stdout.txt"]


def test_a_full_disk_names_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The write that fails on a full disk names no file; the error the command prints must."""
    with pytest.raises(OSError, match=r"No space left on device: '/dev/full'"):
        atomic_write("/dev/full", "x")

    class Full(io.BytesIO):
        def write(self, data: object) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

    def full_disk(fd: int, mode: str) -> Full:
        os.close(fd)
        return Full()

    monkeypatch.setattr(_io.os, "fdopen", full_disk)
    target = tmp_path / "m.json"
    with pytest.raises(OSError, match=re.escape(f"No space left on device: '{target}'")):
        atomic_write(target, "x")
    assert list(tmp_path.iterdir()) == []  # the temporary file is gone too
