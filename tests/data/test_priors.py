"""VO priors: loading with frame-count checks, ξ_vo against a matrix-logarithm reference, mono rescaling."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from conftest import DATA

from dpc_jax.data.poses_io import validate_poses
from dpc_jax.data.priors import load_prior, relative_xi, rescale_monocular
from dpc_jax.eval import reference_metrics as ref

LIBVISO = DATA / "kitti-raw" / "libviso2"
STEREO = LIBVISO / "stereo_2011_09_26_drive_0001.mat"
MONO = LIBVISO / "mono_2011_09_26_drive_0001.mat"


def mat_poses(path: Path, key: str) -> np.ndarray:
    return np.moveaxis(scipy.io.loadmat(str(path))[key], -1, 0)


def xi_reference(poses: np.ndarray) -> np.ndarray:
    """ξ of inv(T_{t+1}) T_t via the general matrix logarithm."""
    return np.array([ref.se3_logm(np.linalg.inv(b) @ a) for a, b in itertools.pairwise(poses)])


def test_load_mat_prior_is_the_estimate() -> None:
    prior = load_prior(STEREO, 108)
    np.testing.assert_allclose(prior, mat_poses(STEREO, "poses_est"), atol=1e-9)


def test_prior_count_must_match_frames() -> None:
    expected = r"stereo_2011_09_26_drive_0001\.mat: 108 prior poses for 100 frames"
    with pytest.raises(ValueError, match=expected):
        load_prior(STEREO, 100)


def test_kitti_text_and_array_priors(tmp_path: Path) -> None:
    est = mat_poses(STEREO, "poses_est")[:20]
    path = tmp_path / "prior.txt"
    np.savetxt(path, est[:, :3, :].reshape(20, 12), fmt="%.15e")
    np.testing.assert_allclose(load_prior(path, 20, "kitti"), est, atol=1e-9)
    np.testing.assert_allclose(load_prior(est, 20), est, atol=1e-9)
    with pytest.raises(ValueError, match="unknown prior format 'csv'"):
        load_prior(path, 20, "csv")


def test_non_rigid_prior_array() -> None:
    est = mat_poses(STEREO, "poses_est")[:5].copy()
    est[3, :3, :3] *= 2.0
    with pytest.raises(ValueError, match="prior array: pose 3 is not rigid"):
        load_prior(est, 5)


def test_relative_xi_matches_matrix_logarithm() -> None:
    prior = load_prior(STEREO, 108)
    xi = relative_xi(prior)
    assert xi.shape == (107, 6)
    np.testing.assert_allclose(xi[:30], xi_reference(prior[:31]), atol=1e-9)
    # The car drives forward (+z), so a point in frame t is closer in frame t+1: ρ_z from −1.4 to −0.5 m.
    assert np.all(xi[:, 2] < -0.4)


def test_monocular_rescaling_matches_ground_truth_step_lengths() -> None:
    gt = validate_poses(mat_poses(MONO, "poses_gt"))  # stored in single precision: make rotations exact
    mono = load_prior(MONO, 108)
    rescaled = rescale_monocular(mono, gt)
    np.testing.assert_allclose(rescaled[0], gt[0], atol=1e-12)
    rel = lambda t: np.linalg.inv(t[1:]) @ t[:-1]
    gt_steps = np.linalg.norm(rel(gt)[:, :3, 3], axis=1)
    np.testing.assert_allclose(np.linalg.norm(rel(rescaled)[:, :3, 3], axis=1), gt_steps, rtol=1e-9)
    # Rotations and translation directions are the monocular estimate's.
    np.testing.assert_allclose(rel(rescaled)[:, :3, :3], rel(mono)[:, :3, :3], atol=1e-9)
    unit = lambda t: t / np.linalg.norm(t, axis=1, keepdims=True)
    np.testing.assert_allclose(unit(rel(rescaled)[:, :3, 3]), unit(rel(mono)[:, :3, 3]), atol=1e-9)
    # The README's per-frame distances agree with the ground truth used here.
    rel_dists = scipy.io.loadmat(str(MONO))["rel_dists"].ravel()[1:]
    np.testing.assert_allclose(gt_steps, rel_dists, atol=1e-6)


def test_monocular_rescaling_shape_mismatch() -> None:
    gt = mat_poses(MONO, "poses_gt")
    with pytest.raises(ValueError, match="same shape"):
        rescale_monocular(gt[:5], gt)


def _recorded_prior(folder: Path, poses: np.ndarray, frames: tuple[int, int] | None) -> Path:
    """A KITTI prior of ``poses`` with (``frames``) or without (None) the record `dpc-jax vo` writes."""
    from dpc_jax.data.poses_io import write_kitti_poses

    path = folder / "prior.txt"
    write_kitti_poses(path, poses)
    if frames is not None:
        record = {"sequence": "00", "source_frames": list(frames), "frames": len(poses)}
        path.with_suffix(".json").write_text(json.dumps(record))
    return path


def test_a_prior_is_taken_for_the_frames_its_record_holds(tmp_path: Path) -> None:
    """With a record, the frames decide (not the count): frames 0:20 of a 30-frame sequence are not
    frames 10:30, though both are 20; frames inside the recorded range are cut from it."""
    est = mat_poses(STEREO, "poses_est")[:30]
    first = _recorded_prior(tmp_path, est[:20], (0, 20))
    with pytest.raises(ValueError, match=re.escape(
            f"{first}: holds the VO of frames 0:20 (recorded in {tmp_path / 'prior.json'}), not of frames "
            "10:30 (--frames 10:30); write the prior of frames 10:30 with `dpc-jax vo --frames 10:30`")):
        load_prior(first, 30, frames=(10, 30))
    with pytest.raises(ValueError, match=r"not of the 30 frames 0:30 of the sequence; pass --frames 0:20"):
        load_prior(first, 30)
    np.testing.assert_allclose(load_prior(first, 30, frames=(5, 15)), est[5:15], atol=1e-9)
    later = _recorded_prior(tmp_path, est[10:30], (10, 30))
    np.testing.assert_allclose(load_prior(later, 30, frames=(10, 30)), est[10:30], atol=1e-9)
    whole = _recorded_prior(tmp_path, est, (0, 30))
    np.testing.assert_allclose(load_prior(whole, 30, frames=(10, 30)), est[10:30], atol=1e-9)
    with pytest.raises(ValueError, match=r"the sequence has 25 frames, so the prior is another sequence's"):
        load_prior(whole, 25)
    # Without a record the count decides, as before: 20 poses are taken as the range 10:30's.
    (tmp_path / "bare").mkdir()
    bare = _recorded_prior(tmp_path / "bare", est[:20], None)
    np.testing.assert_allclose(load_prior(bare, 30, frames=(10, 30)), est[:20], atol=1e-9)


def test_a_record_of_another_trajectory_is_refused(tmp_path: Path) -> None:
    est = mat_poses(STEREO, "poses_est")[:12]
    path = _recorded_prior(tmp_path, est, (0, 20))
    with pytest.raises(ValueError, match=r"prior\.json: records frames 0:20 for .*prior\.txt, which holds 12 "
                                         r"poses; the record is another trajectory's"):
        load_prior(path, 20)
    path.with_suffix(".json").write_text(json.dumps({"source_frames": [5, 2]}))
    with pytest.raises(ValueError, match=r"prior\.json: field 'source_frames' is \[5, 2\]"):
        load_prior(path, 12)
    path.with_suffix(".json").write_text(json.dumps({"summary": {}}))  # a record without frames
    assert load_prior(path, 12).shape == (12, 4, 4)


def test_a_replacement_prior_for_a_cache_must_hold_its_frames(tmp_path: Path) -> None:
    """`correct --data CACHE --prior FILE`: a recorded prior is indexed by the cache's source frame
    numbers, and refused when it does not hold them."""
    from dpc_jax.data.priors import prior_for_cache

    class Cache:  # what prior_for_cache reads of a cache of source frames 10:30
        def __init__(self) -> None:
            self.path, self.indices = tmp_path / "cache", np.arange(10, 30)
            self.manifest = {"n_source_frames": 20, "parameters": {"frames": [10, 30]}}

        def __len__(self) -> int:
            return 20

    est = mat_poses(STEREO, "poses_est")[:30]
    cache = Cache()
    np.testing.assert_allclose(prior_for_cache(cache, _recorded_prior(tmp_path, est, (0, 30))), est[10:30],
                               atol=1e-9)
    with pytest.raises(ValueError, match=r"holds the VO of frames 0:20 .* not of the frames 10:30 of the "):
        prior_for_cache(cache, _recorded_prior(tmp_path, est[:20], (0, 20)))
    # Without the record, 20 poses are one per cached frame.
    (tmp_path / "prior.json").unlink()
    np.testing.assert_allclose(prior_for_cache(cache, tmp_path / "prior.txt"), est[:20], atol=1e-9)


def test_vo_records_its_frames_and_prepare_takes_the_prior_for_them_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`vo --frames 1:5` writes source_frames [1, 5] beside the trajectory and numbers the CSV's rows by
    source frame; `prepare` takes that prior for frames 1:5 (or inside them), not for 0:4, of the same
    length, nor without --frames."""
    from support import write_odometry

    from dpc_jax.cli import main
    from dpc_jax.data.poses_io import read_kitti_poses
    from dpc_jax.data.sequence_cache import load_cache

    write_odometry(tmp_path / "kitti", n=6, size=(40, 64))
    vo = tmp_path / "vo" / "v15.txt"
    assert main(["vo", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00", "--frames", "1:5",
                 "--out", str(vo), "--no-progress"]) == 0
    assert json.loads(vo.with_suffix(".json").read_text())["source_frames"] == [1, 5]
    rows = vo.with_suffix(".csv").read_text().splitlines()[1:]
    assert [int(row.split(",")[0]) for row in rows] == [2, 3, 4]  # the pairs (1, 2), (2, 3), (3, 4)
    capsys.readouterr()
    prepare = ["prepare", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00", "--prior", str(vo),
               "--size", "10x16", "--no-progress"]
    for frames in (["--frames", "0:4"], []):
        assert main([*prepare, *frames, "--out", str(tmp_path / "refused")]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"dpc-jax prepare: error: 00: {vo}: holds the VO of frames 1:5 (recorded in "
                              f"{vo.with_suffix('.json')}), not of ") and "\n" not in err, err
    assert not (tmp_path / "refused").exists()
    assert main([*prepare, "--frames", "2:5", "--out", str(tmp_path / "cache")]) == 0
    cache = load_cache(tmp_path / "cache" / "00")
    np.testing.assert_array_equal(cache.indices, [2, 3, 4])
    np.testing.assert_allclose(cache.prior, read_kitti_poses(vo)[1:4], atol=1e-12)  # its poses of 2, 3, 4
