"""The Python API refuses what the command line refuses (issue 40): poses that are not finite, not rigid,
with a bottom row other than ``[0, 0, 0, 1]`` or transposed, in ``evaluate``, ``corrected_trajectory`` and
the trajectory writers; arguments that cannot take effect. One ``ValueError`` line naming the argument.

The reference for "what the command line refuses" is the file reader: every matrix refused here is
also refused by :func:`~dpc_jax.data.poses_io.read_kitti_poses` when written as KITTI text."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from support import fixture_poses

from dpc_jax.data.poses_io import read_kitti_poses, read_tum, write_kitti_poses, write_tum
from dpc_jax.eval.evaluation import evaluate

N = 12


def _bad(kind: str) -> np.ndarray:
    """A rigid trajectory with pose 3 made bad in the way ``kind`` names (the issue's four cases)."""
    poses = fixture_poses(N, seed=2, step=1.0)
    if kind == "NaN":
        poses[3, 1, 2] = np.nan
    elif kind == "rotation scaled by 1.5":
        poses[3, :3, :3] *= 1.5
    elif kind == "bottom row [1, 2, 3, 4]":
        poses[3, 3] = [1.0, 2.0, 3.0, 4.0]
    elif kind == "transposed":
        poses = np.swapaxes(poses, 1, 2)  # every pose; pose 0 is the identity, pose 1 the first moved
    return poses


CASES = {
    "NaN": "pose 3 contains a non-finite value",
    "rotation scaled by 1.5": "pose 3 is not rigid",
    "bottom row [1, 2, 3, 4]": "pose 3 has bottom row [1.0, 2.0, 3.0, 4.0]",
    "transposed": "pose 1 has bottom row",  # pose 1 is the first to move: its translation is the row
}


def _needle(kind: str) -> str:
    return re.escape(CASES[kind])


@pytest.mark.parametrize("kind", ["NaN", "rotation scaled by 1.5"])
def test_the_reader_refuses_each_case(kind: str, tmp_path: Path) -> None:
    """The reference: the same poses as a KITTI file are refused by the reader (a KITTI file holds the
    3×4 rows only, so the bottom-row cases have no file to compare with)."""
    poses = _bad(kind)
    path = tmp_path / "poses.txt"
    rows = poses[:, :3, :].reshape(N, 12)
    path.write_text("".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in rows))
    with pytest.raises(ValueError):
        read_kitti_poses(path)


@pytest.mark.parametrize("kind", CASES)
def test_evaluate_refuses_bad_estimates_and_ground_truth(kind: str) -> None:
    gt = fixture_poses(N, seed=2, step=1.0)
    with pytest.raises(ValueError, match=rf"^estimates\['p'\]: {_needle(kind)}") as error:
        evaluate(gt, {"p": _bad(kind)})
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match=rf"^gt: {_needle(kind)}"):
        evaluate(_bad(kind), {"p": gt})
    with pytest.raises(ValueError, match=r"^estimates\['est'\]: "):  # one array, labelled est
        evaluate(gt, _bad(kind))


def test_evaluate_refuses_arguments_that_cannot_take_effect() -> None:
    gt = fixture_poses(N, seed=2, step=1.0)
    with pytest.raises(ValueError, match=r"^rpe_delta must be a whole number of frames, got 2\.5$"):
        evaluate(gt, {"p": gt}, rpe_delta=2.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^rpe_delta must be a whole number of frames, got True$"):
        evaluate(gt, {"p": gt}, rpe_delta=True)
    with pytest.raises(ValueError, match=r"^focal_px=700\.0 is used only with diagnose=True"):
        evaluate(gt, {"p": gt}, focal_px=700.0)


def test_corrected_trajectory_refuses_nan_corrections_and_bad_priors() -> None:
    from dpc_jax.geometry.pose_correction import corrected_trajectory

    prior = fixture_poses(N, seed=3, step=1.0)
    xi = np.zeros((N - 1, 6))
    np.testing.assert_allclose(corrected_trajectory(xi, prior, prior[0]), prior, atol=1e-12)
    xi[4, 2] = np.nan
    with pytest.raises(ValueError, match=r"^xi_corr: the correction of pair 4 is not finite \(NaN or inf\); "
                                         r"1 of 11 pairs are$"):
        corrected_trajectory(xi, prior, prior[0])
    for kind, needle in CASES.items():
        with pytest.raises(ValueError, match=rf"^prior: {re.escape(needle)}"):
            corrected_trajectory(np.zeros((N - 1, 6)), _bad(kind), prior[0])
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(ValueError, match=r"^first_pose: pose 0 is not rigid"):
        corrected_trajectory(np.zeros((N - 1, 6)), prior, scaled)


@pytest.mark.parametrize("kind", CASES)
def test_writers_refuse_what_the_readers_would_refuse(kind: str, tmp_path: Path) -> None:
    for write, name in ((write_kitti_poses, "t.txt"), (write_tum, "t.tum")):
        with pytest.raises(ValueError, match=rf"^poses: {_needle(kind)}"):
            write(tmp_path / name, _bad(kind))
    assert list(tmp_path.iterdir()) == []


def test_tum_writer_refuses_times_its_reader_refuses(tmp_path: Path) -> None:
    poses = fixture_poses(N, seed=4, step=1.0)
    stamps = np.arange(N) * 0.1
    for k, value in ((5, 0.05), (5, stamps[4])):  # going back; repeated
        bad = stamps.copy()
        bad[k] = value
        with pytest.raises(ValueError, match=rf"^timestamps: {value:.15g} \(pose 5\) does not increase after "
                                             rf"{stamps[4]:.15g} \(pose 4\); read_tum refuses"):
            write_tum(tmp_path / "t.tum", poses, bad)
    assert not (tmp_path / "t.tum").exists()
    write_tum(tmp_path / "t.tum", poses, stamps)  # increasing: written and read back
    times, read = read_tum(tmp_path / "t.tum")
    np.testing.assert_array_equal(times, stamps)
    np.testing.assert_allclose(read, poses, atol=1e-12)
