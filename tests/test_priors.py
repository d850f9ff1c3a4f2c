"""VO priors: loading with frame-count checks, ξ_vo against a matrix-logarithm reference, mono rescaling."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import reference_metrics as ref
import scipy.io
from conftest import DATA

from dpc_jax.data.poses_io import validate_poses
from dpc_jax.data.priors import load_prior, relative_xi, rescale_monocular

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
