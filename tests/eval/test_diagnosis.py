"""The error diagnosis (dpc_jax.eval.diagnosis): planted bias and noise, float64 numpy/scipy reference."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dpc_jax.cli import main
from dpc_jax.data.poses_io import write_kitti_poses
from dpc_jax.eval import reference_metrics as ref
from dpc_jax.eval.diagnosis import diagnose
from dpc_jax.eval.evaluation import evaluate
from dpc_jax.report.evaluation_report import format_diagnosis, write_report

M = 1500  # steps
BIAS = np.array([4e-3, -2e-3, 1e-3, -1e-4, 3e-4, 2.5e-4])  # [ρ m, φ rad] per step
NOISE = np.array([2e-2, 1e-2, 4e-2, 8e-4, 1.8e-3, 8e-4])  # about libviso2-s's per-step spread



def _ground_truth(rng: np.random.Generator) -> np.ndarray:
    """Car-like ground truth ``[M+1, 4, 4]``: 1 m forward steps (−z in T_{t+1,t}) with gentle turns."""
    poses = [np.eye(4)]
    for k in range(M):
        step = np.eye(4)
        yaw = 0.02 * np.sin(k / 40.0) + 1e-3 * rng.normal()
        step[:3, :3] = Rotation.from_rotvec([0.0, yaw, 0.0]).as_matrix()
        step[2, 3] = -1.0
        poses.append(poses[-1] @ np.linalg.inv(step))  # T_w_{t+1} = T_w_t · inv(T_{t+1,t})
    return np.stack(poses)


def _estimate(gt: np.ndarray, corrections: np.ndarray) -> np.ndarray:
    """Estimate whose steps need exactly ``corrections`` ``[M, 6]``: ``E_{t+1,t} = Exp(−ξ_t) · G_{t+1,t}``."""
    poses = [gt[0]]
    for k in range(M):
        g_step = np.linalg.inv(gt[k + 1]) @ gt[k]
        e_step = ref.se3_exp(-corrections[k]) @ g_step
        poses.append(poses[-1] @ np.linalg.inv(e_step))
    return np.stack(poses)


@pytest.fixture(scope="module")
def planted() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    gt = _ground_truth(rng)
    corrections = BIAS + NOISE * rng.normal(size=(M, 6))
    return gt, _estimate(gt, corrections), corrections


def test_recovers_planted_bias_within_its_standard_error(
    planted: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    gt, est, corrections = planted
    d = diagnose(gt, est)
    assert d.steps == M
    mean, spread, sem = (np.array(v) * 1e-3 for v in (d.mean, d.spread, d.standard_error))
    # The statistics of the planted per-step corrections, computed independently.
    np.testing.assert_allclose(mean, corrections.mean(axis=0), rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(spread, corrections.std(axis=0, ddof=1), rtol=1e-7)
    np.testing.assert_allclose(sem, corrections.std(axis=0, ddof=1) / np.sqrt(M), rtol=1e-7)
    # The bias is recovered within three standard errors on every axis, and the standard error is
    # the planted noise's (σ/√M).
    assert np.all(np.abs(mean - BIAS) < 3.0 * sem), (mean - BIAS) / sem
    np.testing.assert_allclose(sem, NOISE / np.sqrt(M), rtol=0.1)


def test_pure_bias_is_the_whole_drift_and_pixels_scale_with_focal() -> None:
    rng = np.random.default_rng(3)
    gt = _ground_truth(rng)
    est = _estimate(gt, np.tile(BIAS, (M, 1)))
    d = diagnose(gt, est, focal_px=700.0)
    np.testing.assert_allclose(np.array(d.mean) * 1e-3, BIAS, rtol=1e-7)
    assert max(d.spread) < 1e-6
    # The bias-only trajectory is the estimate itself: all of the drift is explained.
    assert d.drift_trans_m > 1.0 and d.drift_rot_deg > 1.0
    assert d.bias_drift_trans_m == pytest.approx(d.drift_trans_m, rel=1e-6)
    assert d.bias_drift_rot_deg == pytest.approx(d.drift_rot_deg, rel=1e-6)
    assert d.drift_trans_explained == pytest.approx(1.0, abs=1e-6)
    assert d.drift_rot_explained == pytest.approx(1.0, abs=1e-6)
    # End-point drift of the estimate, measured independently.
    heading = np.degrees(Rotation.from_matrix(est[-1, :3, :3].T @ gt[-1, :3, :3]).magnitude())
    assert d.drift_trans_m == pytest.approx(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]), rel=1e-9)
    assert d.drift_rot_deg == pytest.approx(heading, rel=1e-9)
    # Small-angle image shift: f · φ per axis, f · ‖(φx, φy)‖ at the principal point.
    assert d.mean_rot_px is not None and d.mean_rot_px_norm is not None
    np.testing.assert_allclose(d.mean_rot_px, 700.0 * BIAS[3:], rtol=1e-7)
    assert d.mean_rot_px_norm == pytest.approx(700.0 * np.hypot(BIAS[3], BIAS[4]), rel=1e-7)


def test_noise_only_shows_no_bias(planted: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    gt, _, corrections = planted
    noise = corrections - BIAS  # the same noise, no bias
    d = diagnose(gt, _estimate(gt, noise))
    np.testing.assert_allclose(np.array(d.mean) * 1e-3, noise.mean(axis=0), rtol=1e-7, atol=1e-12)
    assert np.all(np.abs(np.array(d.mean)) < 4.0 * np.array(d.standard_error))
    # The share is the projection of the bias-only drift on the estimate's drift (reference: numpy).
    drift = _estimate(gt, noise)[-1, :3, 3] - gt[-1, :3, 3]
    bias_only = _estimate(gt, np.tile(noise.mean(axis=0), (M, 1)))[-1, :3, 3] - gt[-1, :3, 3]
    assert d.drift_trans_explained == pytest.approx(bias_only @ drift / (drift @ drift), rel=1e-6)


def test_bad_input() -> None:
    gt = np.tile(np.eye(4), (5, 1, 1))
    with pytest.raises(ValueError, match="shape"):
        diagnose(gt, gt[:4])
    with pytest.raises(ValueError, match="focal"):
        diagnose(gt, gt, focal_px=0.0)


def test_evaluate_api_report_and_cli(
    planted: tuple[np.ndarray, np.ndarray, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    gt, est, _ = planted
    result = evaluate(gt, {"prior": est}, diagnose=True, focal_px=718.856)
    expected = diagnose(gt, est, 718.856)
    assert result.diagnoses["prior"] == expected
    summary = json.loads(result.to_json())
    assert summary["diagnosis"]["prior"]["mean"] == pytest.approx(list(expected.mean))
    assert "diagnosis" not in evaluate(gt, {"prior": est})  # only when asked
    text = format_diagnosis(result.diagnoses)
    assert "| prior | 1500 |" in text and "share explained" in text
    write_report(tmp_path / "report", result)
    assert "What the error is made of" in (tmp_path / "report" / "report.md").read_text()

    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "prior.txt", est)
    args = ["evaluate", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "prior.txt")]
    assert main([*args, "--diagnose", "--focal", "718.856"]) == 0
    out = capsys.readouterr().out
    assert "Per-step error" in out and "f = 718.856" in out
    assert main([*args, "--diagnose", "--json", "-"]) == 0
    assert json.loads(capsys.readouterr().out)["diagnosis"]["prior"]["steps"] == M
    assert main([*args, "--focal", "700"]) == 2
    assert "--focal is used only with --diagnose" in capsys.readouterr().err
    assert main([*args, "--diagnose", "--focal", "-3"]) == 2
