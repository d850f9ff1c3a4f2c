"""The supervised linear baseline (dpc_jax.eval.linear_baseline): numpy least squares, planted biases."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from dpc_jax.eval import reference_metrics as ref
from dpc_jax.eval.linear_baseline import (
    apply_linear_correction,
    fit_linear_correction,
    fit_weights,
    predict,
    sequence_steps,
)
from dpc_jax.eval.metrics import step_corrections


def _pair(seed: int, n: int, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth with varied 6-DoF steps, and a prior whose every step needs exactly ``bias``:
    ``T_vo_{t+1,t} = Exp(−bias) · G_{t+1,t}`` (scipy's expm as the reference exponential)."""
    rng = np.random.default_rng(seed)
    gt, prior = [np.eye(4)], [np.eye(4)]
    for _ in range(n - 1):
        step_xi = np.concatenate([[0.0, 0.0, -1.0] + 0.2 * rng.normal(size=3), 0.02 * rng.normal(size=3)])
        g_step = ref.se3_exp(step_xi)
        gt.append(gt[-1] @ np.linalg.inv(g_step))
        prior.append(prior[-1] @ np.linalg.inv(ref.se3_exp(-bias) @ g_step))
    return np.stack(gt), np.stack(prior)


def test_fit_recovers_a_planted_linear_model_exactly() -> None:
    rng = np.random.default_rng(0)
    xi_vo = np.concatenate([0.3 * rng.normal(size=(500, 3)), 0.02 * rng.normal(size=(500, 3))], axis=1)
    weights = rng.normal(size=(6, 7)) * 1e-2
    xi_gt = np.concatenate([xi_vo, np.ones((500, 1))], axis=1) @ weights.T
    with jax.enable_x64(True):
        full = np.asarray(fit_weights(xi_vo, xi_gt, rotation_only=False))
        rotation = np.asarray(fit_weights(xi_vo, xi_gt, rotation_only=True))
        predicted = np.asarray(predict(full, xi_vo))
    np.testing.assert_allclose(full, weights, atol=1e-12)
    np.testing.assert_allclose(rotation[3:], weights[3:], atol=1e-12)
    np.testing.assert_array_equal(rotation[:3], 0.0)
    np.testing.assert_allclose(predicted, xi_gt, atol=1e-12)


def test_fit_is_numpy_least_squares_on_noisy_data() -> None:
    rng = np.random.default_rng(1)
    xi_vo = np.concatenate([0.3 * rng.normal(size=(300, 3)), 0.02 * rng.normal(size=(300, 3))], axis=1)
    xi_gt = 1e-3 * rng.normal(size=(300, 6)) + 2e-4
    x = np.concatenate([xi_vo, np.ones((300, 1))], axis=1)
    expected, *_ = np.linalg.lstsq(x, xi_gt, rcond=None)
    with jax.enable_x64(True):
        got = np.asarray(fit_weights(xi_vo, xi_gt, rotation_only=False))
    np.testing.assert_allclose(got, expected.T, rtol=1e-8, atol=1e-14)


def test_constant_only_fit_is_the_mean_correction_and_ignores_the_step() -> None:
    rng = np.random.default_rng(2)
    xi_vo = np.concatenate([0.3 * rng.normal(size=(200, 3)), 0.02 * rng.normal(size=(200, 3))], axis=1)
    xi_gt = 1e-3 * rng.normal(size=(200, 6)) + 0.5 * xi_vo  # a gain the constant model must not take
    with jax.enable_x64(True):
        got = np.asarray(fit_weights(xi_vo, xi_gt, rotation_only=True, constant_only=True))
    np.testing.assert_array_equal(got[:, :6], 0.0)
    np.testing.assert_array_equal(got[:3], 0.0)
    np.testing.assert_allclose(got[3:, 6], xi_gt[:, 3:].sum(axis=0) / 200, rtol=1e-12)


def test_planted_constant_bias_is_learned_and_removed_on_another_sequence() -> None:
    bias = np.array([0.0, 0.0, 0.0, 1e-4, -3e-4, 2.5e-4])  # rad per step, rotation only
    train = [_pair(2, 400, bias), _pair(3, 300, bias)]
    gt, prior = _pair(4, 350, bias)
    xi_vo, xi_gt = sequence_steps(gt, prior)
    assert xi_vo.shape == (349, 6)
    with jax.enable_x64(True):
        np.testing.assert_allclose(xi_gt, np.asarray(step_corrections(gt, prior)), atol=1e-12)
    np.testing.assert_allclose(xi_gt, np.tile(bias, (349, 1)), atol=1e-10)
    model = fit_linear_correction(train, rotation_only=True)
    assert model.steps == 399 + 299 and model.rotation_only
    np.testing.assert_allclose(model.weights[3:, 6], bias[3:], atol=1e-10)  # the constant
    np.testing.assert_allclose(model.weights[:, :6], 0.0, atol=1e-8)  # no gain
    corrected = apply_linear_correction(model, prior)
    assert np.abs(prior[-1, :3, 3] - gt[-1, :3, 3]).max() > 0.5  # the prior drifts …
    np.testing.assert_allclose(corrected, gt, atol=1e-6)  # … the corrected trajectory does not


def test_bad_input() -> None:
    with pytest.raises(ValueError, match=r"\[M, 6\]"):
        fit_weights(np.zeros((10, 5)), np.zeros((10, 6)))
    with pytest.raises(ValueError, match="at least 7 steps"):
        fit_weights(np.zeros((3, 6)), np.zeros((3, 6)))
    with pytest.raises(ValueError, match="no training sequence"):
        fit_linear_correction([])
    with pytest.raises(ValueError, match="shape"):
        sequence_steps(np.tile(np.eye(4), (5, 1, 1)), np.tile(np.eye(4), (4, 1, 1)))


def test_script_reports_a_missing_folder_in_one_line(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "experiments" / "studies" / "linear_baseline.py"
    spec = importlib.util.spec_from_file_location("linear_baseline_script", path)
    assert spec is not None and spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main(["--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "stereo_00.mat not found" in err
