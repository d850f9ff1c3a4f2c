"""Metrics against the plain float64 loops of ``reference_metrics`` (1e-9), known geometry, and real data."""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import DATA
from scipy.spatial.transform import Rotation

from dpc_jax.data.poses_io import read_mat
from dpc_jax.eval import metrics
from dpc_jax.eval import reference_metrics as ref
from dpc_jax.geometry.poses import compose

LIBVISO2 = DATA / "kitti-libviso2"
TOL = {"rtol": 1e-9, "atol": 1e-12}


def drive(n: int, seed: int, step: float = 3.5, yaw_bias: float = 0.0, noise: float = 0.0) -> np.ndarray:
    """A car-like trajectory (KITTI camera frame: y down, z forward), optionally with drift."""
    rng = np.random.default_rng(seed)
    rotvec = np.zeros((n - 1, 3))
    rotvec[:, 1] = 0.04 * np.sin(np.arange(n - 1) / 15.0) + yaw_bias
    rotvec += noise * rng.normal(size=(n - 1, 3))
    rel = np.tile(np.eye(4), (n - 1, 1, 1))
    rel[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    rel[:, :3, 3] = [0.0, 0.0, -step] + noise * 10 * rng.normal(size=(n - 1, 3))
    return compose(rel, np.eye(4))


def random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=5.0, size=(n, 3))
    return poses


@pytest.fixture(scope="module")
def synthetic() -> tuple[np.ndarray, np.ndarray]:
    gt = drive(N, seed=0)
    est = drive(N, seed=0, yaw_bias=0.002, noise=0.003)
    est = gt[0] @ np.linalg.inv(est[0]) @ est
    return gt, est


@pytest.fixture(scope="module")
def seq07() -> tuple[np.ndarray, np.ndarray]:
    return read_mat(LIBVISO2 / "stereo_07.mat")


@pytest.fixture(scope="module")
def seq00() -> tuple[np.ndarray, np.ndarray]:
    return read_mat(LIBVISO2 / "stereo_00.mat")


N = 300  # every synthetic test uses this length so each jitted function compiles once
OPTIONS = {"align": "sim3", "rpe_delta": 3}


def check_combined(gt: np.ndarray, est: np.ndarray, lengths: tuple[float, ...] = ref.LENGTHS) -> None:
    """``trajectory_metrics`` (one compiled call) equals every reference loop."""
    out = {k: np.asarray(v) for k, v in metrics.trajectory_metrics(gt, est, **OPTIONS).items()}
    np.testing.assert_allclose([out["m_ate_trans_m"], out["m_ate_rot_deg"]], ref.m_ate(gt, est), **TOL)
    c_trans, c_rot = ref.c_ate(gt, est)
    np.testing.assert_allclose(out["c_ate_trans_m"], c_trans, **TOL)
    np.testing.assert_allclose(out["c_ate_rot_deg"], c_rot, **TOL)
    seg_t, seg_r, per_t, per_r, counts = ref.segment_errors(gt, est, lengths)
    columns = [ref.LENGTHS.index(length) for length in lengths]
    np.testing.assert_array_equal(out["seg_counts"][columns], counts)
    np.testing.assert_allclose(out["seg_per_length_trans_pct"][columns], per_t, **TOL)
    np.testing.assert_allclose(out["seg_per_length_rot_deg_per_100m"][columns], per_r, **TOL)
    if lengths == ref.LENGTHS:
        np.testing.assert_allclose([out["seg_trans_pct"], out["seg_rot_deg_per_100m"]], [seg_t, seg_r], **TOL)
    kt, kr, _ = ref.kitti_devkit_errors(gt, est)
    np.testing.assert_allclose([out["kitti_trans_pct"], out["kitti_rot_deg_per_100m"]], [kt, kr], **TOL)
    np.testing.assert_allclose(out["ate_m"], ref.ate(gt, est, "sim3"), **TOL)
    np.testing.assert_allclose([out["rpe_trans_m"], out["rpe_rot_deg"]], ref.rpe(gt, est, 3), **TOL)
    assert int(out["loop_closures"]) == ref.count_loop_closures(est)


def test_single_functions_against_reference(synthetic: tuple[np.ndarray, np.ndarray]) -> None:
    gt, est = synthetic
    assert ref.cumulative_distance(gt)[-1] > 1000.0  # every length has segments
    np.testing.assert_allclose(metrics.m_ate(gt, est), ref.m_ate(gt, est), **TOL)
    np.testing.assert_allclose(metrics.c_ate(gt, est), ref.c_ate(gt, est), **TOL)
    np.testing.assert_allclose(metrics.path_length(gt), ref.cumulative_distance(gt), **TOL)
    seg_t, seg_r, per_t, per_r, counts = ref.segment_errors(gt, est)
    seg = metrics.segment_errors(gt, est)
    np.testing.assert_array_equal(seg.counts, counts)
    np.testing.assert_allclose(seg.per_length_trans_pct, per_t, **TOL)
    np.testing.assert_allclose(seg.per_length_rot_deg_per_100m, per_r, **TOL)
    np.testing.assert_allclose([seg.trans_pct, seg.rot_deg_per_100m], [seg_t, seg_r], **TOL)
    np.testing.assert_allclose(seg.lengths, ref.LENGTHS)
    kt, kr, kcount = ref.kitti_devkit_errors(gt, est)
    dev = metrics.kitti_devkit_errors(gt, est)
    assert int(dev.count) == kcount
    np.testing.assert_allclose([dev.trans_pct, dev.rot_deg_per_100m], [kt, kr], **TOL)
    for align in metrics.ALIGNMENTS:
        np.testing.assert_allclose(metrics.ate(gt, est, align), ref.ate(gt, est, align), **TOL)
    np.testing.assert_allclose(metrics.rpe(gt, est), ref.rpe(gt, est, 1), **TOL)
    assert int(metrics.count_loop_closures(est)) == ref.count_loop_closures(est)


def test_combined_against_reference(synthetic: tuple[np.ndarray, np.ndarray]) -> None:
    check_combined(*synthetic)


def test_random_rotations_against_reference() -> None:
    gt, est = random_poses(N, 1), random_poses(N, 2)
    np.testing.assert_allclose(metrics.m_ate(gt, est), ref.m_ate(gt, est), **TOL)
    np.testing.assert_allclose(metrics.rpe(gt, est), ref.rpe(gt, est), **TOL)
    for align in metrics.ALIGNMENTS:
        np.testing.assert_allclose(metrics.ate(gt, est, align), ref.ate(gt, est, align), **TOL)


def test_real_sequence_07_against_reference(seq07: tuple[np.ndarray, np.ndarray]) -> None:
    check_combined(*seq07)


def test_real_sequence_00_against_reference(seq00: tuple[np.ndarray, np.ndarray]) -> None:
    """The longest sequence (4541 poses); the slow segment loop runs for the 800 m length only."""
    gt, est = seq00
    check_combined(gt, est, lengths=(800.0,))
    assert int(metrics.trajectory_metrics(gt, gt, **OPTIONS)["loop_closures"]) == ref.count_loop_closures(gt)
    assert ref.count_loop_closures(gt) > 1000  # sequence 00 revisits many places


def test_segment_end_is_first_frame_beyond_length() -> None:
    # 10 m steps: cumulative 0, 10, …; a 100 m segment from frame 0 ends at the first c > 100 (frame 11).
    gt = drive(N, seed=0, step=10.0)
    _, _, end, valid = metrics.segment_error_matrix(gt, gt)
    np.testing.assert_allclose(ref.cumulative_distance(gt)[:3], [0.0, 10.0, 20.0], atol=1e-9)
    assert int(end[0, 0]) == 11 and int(end[0, 7]) == 81
    assert int(end[N - 12, 0]) == N - 1 and not bool(valid[N - 11, 0])


def test_short_trajectory_has_nan_lengths() -> None:
    gt = drive(N, seed=3, step=0.9)  # 269 m: lengths 100 and 200 only
    est = drive(N, seed=3, step=0.9, yaw_bias=0.001)
    seg = metrics.segment_errors(gt, est)
    assert np.isfinite(seg.per_length_trans_pct[:2]).all() and np.isnan(seg.per_length_trans_pct[2:]).all()
    np.testing.assert_allclose(seg.trans_pct, np.mean(seg.per_length_trans_pct[:2]), **TOL)
    _, _, per_t, _, counts = ref.segment_errors(gt, est)
    np.testing.assert_array_equal(seg.counts, counts)
    np.testing.assert_allclose(seg.per_length_trans_pct, per_t, **TOL)


def test_perfect_estimate_has_zero_error(synthetic: tuple[np.ndarray, np.ndarray]) -> None:
    gt, _ = synthetic
    out = metrics.trajectory_metrics(gt, gt, **OPTIONS)
    for key in ("m_ate_trans_m", "seg_trans_pct", "kitti_trans_pct", "ate_m", "rpe_trans_m", "rpe_rot_deg"):
        assert abs(float(out[key])) < 1e-9, key


def test_umeyama_recovers_a_known_similarity(synthetic: tuple[np.ndarray, np.ndarray]) -> None:
    gt, _ = synthetic
    rotation = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    translation, scale = np.array([5.0, -3.0, 40.0]), 0.37
    moved = gt.copy()
    moved[:, :3, 3] = scale * gt[:, :3, 3] @ rotation.T + translation
    moved[:, :3, :3] = rotation @ gt[:, :3, :3]
    r, t, s = metrics.umeyama_alignment(moved[:, :3, 3], gt[:, :3, 3], with_scale=True)
    np.testing.assert_allclose(r, rotation.T, atol=1e-12)
    np.testing.assert_allclose(s, 1.0 / scale, rtol=1e-12)
    np.testing.assert_allclose(t, -(rotation.T @ translation) / scale, atol=1e-9)
    assert float(metrics.ate(gt, moved, "sim3")) < 1e-9
    assert float(metrics.ate(gt, moved, "se3")) > 1.0  # a rigid alignment cannot undo the scale
    rigid = moved.copy()
    rigid[:, :3, 3] = gt[:, :3, 3] @ rotation.T + translation
    assert float(metrics.ate(gt, rigid, "se3")) < 1e-9
    assert float(metrics.ate(gt, rigid, "none")) > 1.0
    with pytest.raises(ValueError, match="align must be one of"):
        metrics.ate(gt, rigid, "affine")


def test_rpe_of_a_constant_yaw_bias() -> None:
    gt = drive(N, seed=0)
    est = drive(N, seed=0, yaw_bias=np.radians(0.1))
    np.testing.assert_allclose(metrics.rpe(gt, est)[1], 0.1, rtol=1e-9)
    np.testing.assert_allclose(metrics.rpe(gt, est, 4)[1], 0.4, rtol=1e-9)


def test_step_corrections_recover_a_known_perturbation() -> None:
    """E's steps are G's steps with a known left perturbation: step_corrections gives it back."""
    from scipy.linalg import expm

    gt = drive(40, seed=1)
    rng = np.random.default_rng(2)
    xi = np.concatenate([rng.normal(0, 0.02, (39, 3)), rng.normal(0, 0.003, (39, 3))], axis=1)
    hat = np.zeros((39, 4, 4))
    hat[:, :3, 3] = xi[:, :3]
    hat[:, [2, 0, 1], [1, 2, 0]] = xi[:, 3:]
    hat[:, [1, 2, 0], [2, 0, 1]] = -xi[:, 3:]
    steps = np.linalg.inv(gt[1:]) @ gt[:-1]
    est_steps = np.stack([np.linalg.inv(expm(h)) @ s for h, s in zip(hat, steps, strict=True)])
    est = compose(est_steps, gt[0])
    np.testing.assert_allclose(np.asarray(metrics.step_corrections(gt, est)), xi, atol=1e-10)


def circle(n: int, radius: float, laps: float, drift: float = 0.0) -> np.ndarray:
    """Camera driving a circle in the x–z plane; ``drift`` (m per lap) shifts it sideways as it goes."""
    angle = np.linspace(0.0, 2 * np.pi * laps, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(-angle, [0.0, 1.0, 0.0])).as_matrix()
    poses[:, 0, 3] = radius * (1.0 - np.cos(angle)) + drift * angle / (2 * np.pi)
    poses[:, 2, 3] = radius * np.sin(angle)
    return poses


def test_loop_closures_count_pairs_and_decrease_with_drift() -> None:
    closed = circle(N, radius=30.0, laps=2.0)
    count = int(metrics.count_loop_closures(closed))
    assert count == ref.count_loop_closures(closed)
    # Lap 2 re-traverses lap 1: every start in lap 1 sees the frames near its own place in lap 2.
    assert count > 100
    drifts = (0.0, 2.0, 4.0, 8.0, 12.0)
    counts = [int(metrics.count_loop_closures(circle(N, 30.0, 2.0, drift))) for drift in drifts]
    assert counts[0] == count >= counts[1]
    assert all(a > b for a, b in itertools.pairwise(counts[1:]))
    assert counts[-1] == 0
    almost = circle(N, 30.0, 1.0 - 1e-3)
    assert int(metrics.count_loop_closures(almost)) == ref.count_loop_closures(almost)
    # No travel, no closure: a car standing still.
    assert int(metrics.count_loop_closures(np.tile(np.eye(4), (N, 1, 1)))) == 0


def test_float32_is_preserved(synthetic: tuple[np.ndarray, np.ndarray]) -> None:
    gt, est = synthetic
    out32 = metrics.trajectory_metrics(jnp.asarray(gt, jnp.float32), jnp.asarray(est, jnp.float32), **OPTIONS)
    out64 = metrics.trajectory_metrics(gt, est, **OPTIONS)
    assert out32["seg_trans_pct"].dtype == jnp.float32
    assert out64["seg_trans_pct"].dtype == jnp.float64
    for key in ("m_ate_trans_m", "seg_trans_pct", "seg_rot_deg_per_100m", "ate_m"):
        np.testing.assert_allclose(float(out32[key]), float(out64[key]), rtol=1e-3)


def test_bad_shapes() -> None:
    with pytest.raises(ValueError, match="both have shape"):
        metrics.m_ate(np.tile(np.eye(4), (5, 1, 1)), np.tile(np.eye(4), (4, 1, 1)))
    with pytest.raises(ValueError, match="delta must be"):
        metrics.rpe(np.tile(np.eye(4), (5, 1, 1)), np.tile(np.eye(4), (5, 1, 1)), 5)
