"""``dpc-jax synth --format mcap|rosbag1|rosbag2``: the synthetic world written as a recording gives `vo` and
`prepare` what the same sequence in the KITTI layout gives (the trajectory and the cache byte for byte,
the ground truth from its topic to rounding); a recording is never replaced. The size and frame count are
tests/synth/test_synth.py's, so that the renderer compiles once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dpc_jax.cli import main

H, W = 64, 160
SYNTH = ["synth", "--sequences", "1", "--frames", "3", "--size", f"{H}x{W}", "--seed", "7", "--no-progress"]
NAMES = {"mcap": "00.mcap", "rosbag1": "00.bag", "rosbag2": "00"}


@pytest.fixture(scope="module")
def layout(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The sequence in the KITTI layout, with `vo`'s trajectory and `prepare`'s cache of it."""
    tmp = tmp_path_factory.mktemp("synth_layout")
    assert main([*SYNTH, "--out", str(tmp / "kitti")]) == 0
    source = ["--kitti-odometry", str(tmp / "kitti"), "--sequence", "00"]
    assert main(["vo", *source, "--out", str(tmp / "vo.txt"), "--no-progress"]) == 0
    assert main(["prepare", *source, "--prior", str(tmp / "kitti" / "poses" / "00.txt"), "--out",
                 str(tmp / "cache"), "--size", "32x80", "--no-progress"]) == 0
    return {"tmp": tmp, "vo": (tmp / "vo.txt").read_bytes(), "cache": tmp / "cache" / "00",
            "poses": tmp / "kitti" / "poses" / "00.txt"}


@pytest.mark.parametrize("form", list(NAMES))
def test_a_synthetic_recording_gives_what_the_kitti_layout_gives(
    layout: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str], form: str
) -> None:
    from dpc_jax.data.kitti import read_ground_truth
    from dpc_jax.data.sequence_cache import load_cache

    assert main([*SYNTH, "--out", str(tmp_path), "--format", form]) == 0
    rec = tmp_path / NAMES[form]
    assert capsys.readouterr().out.splitlines() == [str(rec)]
    assert sorted(p.name for p in tmp_path.iterdir()) == [NAMES[form]]  # nothing else left in OUT
    assert main(["vo", "--bag", str(rec), "--out", str(tmp_path / "vo.txt"), "--no-progress"]) == 0
    assert (tmp_path / "vo.txt").read_bytes() == layout["vo"]
    assert main(["prepare", "--bag", str(rec), "--prior", str(layout["poses"]), "--gt-topic", "/ground_truth",
                 "--out", str(tmp_path / "cache"), "--size", "32x80", "--no-progress"]) == 0
    ours, theirs = tmp_path / "cache" / rec.stem, layout["cache"]
    arrays = sorted(p.name for p in theirs.glob("*.npy"))
    assert {"left.npy", "right.npy", "K.npy", "baseline.npy", "times.npy", "gt.npy"} <= set(arrays)
    assert arrays == sorted(p.name for p in ours.glob("*.npy"))
    for array in set(arrays) - {"gt.npy"}:
        assert (ours / array).read_bytes() == (theirs / array).read_bytes(), array
    # The ground truth through nav_msgs/Odometry's quaternions: the layout's poses to rounding.
    np.testing.assert_allclose(load_cache(ours).gt, read_ground_truth(layout["poses"]), atol=1e-12)
    capsys.readouterr()
    # A recording is never replaced; nothing is rendered.
    assert main([*SYNTH, "--out", str(tmp_path), "--format", form]) == 2
    assert f"{rec} exists" in capsys.readouterr().err
    assert main([*SYNTH, "--out", str(tmp_path / "other"), "--format", form, "--overwrite"]) == 2
    assert "a recording is never replaced" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()
