"""One progress policy for every command: with stderr not a terminal (a log file), the long stages write
plain progress lines to it, not tqdm's carriage returns (``dpc_jax.runtime.progress``)."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys
from pathlib import Path

import pytest

from dpc_jax.pipelines import protocol as dpc_protocol
from dpc_jax.runtime.progress import LineProgress, progress_bar, progress_mode

FRAMES = 8


def _command(args: list[str], log: Path) -> str:
    with log.open("w") as stderr:
        subprocess.run([sys.executable, "-m", "dpc_jax", *args], stdout=subprocess.DEVNULL, stderr=stderr,
                       check=True, timeout=600)
    return log.read_text()


def test_vo_and_correct_write_progress_lines_into_a_log(tmp_path: Path, capsys) -> None:
    """``vo`` as a process with its stderr in a file; ``correct`` in this process, whose stderr is not a
    terminal either (pytest captures it)."""
    from support import write_fake_odometry, write_stored_run

    from dpc_jax.cli import main
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.training.train_config import REFERENCE, TrainConfig

    kitti = write_fake_odometry(tmp_path / "kitti", ["05"], frames=FRAMES,
                                              prior_dir=tmp_path / "p")
    vo = _command(["vo", "--kitti-odometry", str(kitti), "--sequence", "05", "--out",
                   str(tmp_path / "vo.txt")], tmp_path / "vo.log")
    assert f"vo: {FRAMES}/{FRAMES} frames" in vo and "\r" not in vo
    cache = prepare_sequence(open_odometry(kitti, "05"), tmp_path / "p" / "stereo_05.mat", tmp_path / "cache",
                             size=dpc_protocol.SMOKE["image_size"], progress=False, workers=1)
    config = TrainConfig(method="stereo_dpc", **{**dpc_protocol.SMOKE, **REFERENCE},
                         cache_root=str(tmp_path / "cache"), train_sequences=("00",),
                         validation_sequences=("05",))
    write_stored_run(tmp_path / "run", config, {1: (7, 0.5, 0, -1e-4)})
    capsys.readouterr()
    assert main(["correct", "--checkpoint", str(tmp_path / "run"), "--data", str(cache), "--out",
                 str(tmp_path / "c.txt")]) == 0
    correct = capsys.readouterr().err
    assert f"{FRAMES - 1}/{FRAMES - 1} pairs (" in correct and "\r" not in correct


def test_the_policy() -> None:
    """--no-progress: nothing; a log (stderr not a terminal, as under pytest): lines; the demo's stages take
    the same mode (``dpc-jax demo`` passes it, ``run_demo`` hands it to each stage's bar)."""
    assert progress_mode(no_progress=True) is False
    assert not sys.stderr.isatty() and progress_mode() == "lines"
    with progress_bar(3, "render test", "lines") as bar:
        assert isinstance(bar, LineProgress)
        buffer = io.StringIO()
        with contextlib.redirect_stderr(buffer):
            bar.update(3)
            bar.close()
    assert buffer.getvalue() == "render test: 3/3 frames (" + buffer.getvalue().split("(", 1)[1]


def test_lines_off_a_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    assert progress_mode(True) is False and progress_mode(False) == "lines"  # pytest's stderr is no terminal
    with LineProgress(total=4, desc="work", unit="frame", interval=0.0) as bar:
        for _ in range(4):
            bar.update(1)
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(" (")[0] for line in lines] == [f"work: {k}/4 frames" for k in range(1, 5)]
    with pytest.raises(KeyboardInterrupt), LineProgress(4, "work", "frame", interval=60.0) as bar:
        bar.update(1)
        raise KeyboardInterrupt
    assert capsys.readouterr().err == ""  # an interrupted loop adds no line to the one Ctrl-C prints
