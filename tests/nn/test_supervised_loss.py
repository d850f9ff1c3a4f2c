"""dpc_jax.nn.supervised_loss: DPC-Net's loss and precision against float64 scipy references, and
the training loop feeding ground truth to the supervised loss only."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dpc_jax.geometry.lie import se3_log
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.outputs import DPCOutputs


def _se3_vee_log(matrix: np.ndarray) -> np.ndarray:
    """``[ρ, φ]`` of a rigid transform by scipy's matrix logarithm (the float64 reference)."""
    import scipy.linalg

    log = np.real(scipy.linalg.logm(matrix))
    return np.array([log[0, 3], log[1, 3], log[2, 3], log[2, 1], log[0, 2], log[1, 0]])


def _se3_expm(xi: np.ndarray) -> np.ndarray:
    import scipy.linalg

    rho, phi = xi[:3], xi[3:]
    twist = np.array([[0.0, -phi[2], phi[1], rho[0]], [phi[2], 0.0, -phi[0], rho[1]],
                      [-phi[1], phi[0], 0.0, rho[2]], [0.0, 0.0, 0.0, 0.0]])
    return scipy.linalg.expm(twist)


def _supervised_case(seed: int, b: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rho = [0.0, 0.0, -1.0] + 0.1 * rng.normal(size=(b, 3))
    xi_vo = np.concatenate([rho, 0.02 * rng.normal(size=(b, 3))], 1)
    xi_gt = xi_vo + np.concatenate([0.02 * rng.normal(size=(b, 3)), 2e-3 * rng.normal(size=(b, 3))], 1)
    xi_corr = np.concatenate([0.01 * rng.normal(size=(b, 3)), 1e-3 * rng.normal(size=(b, 3))], 1)
    weight = np.ones(b)
    weight[-1] = 0.0  # a padding sample counts for nothing
    return xi_vo, xi_gt, xi_corr, weight


def _supervised_batch(xi_vo: np.ndarray, xi_gt: np.ndarray | None, weight: np.ndarray) -> Batch:
    b = xi_vo.shape[0]
    return Batch(left=np.zeros((b, 2, 1, 1, 3), np.uint8), right=np.zeros((b, 2, 1, 1, 3), np.uint8),
                 xi_vo=xi_vo, intrinsics=np.tile(np.eye(3), (b, 1, 1)), baseline=np.ones(b), weight=weight,
                 xi_gt=xi_gt)


@pytest.mark.parametrize("rotation_only", [False, True])
def test_supervised_loss_matches_a_float64_reference(rotation_only: bool) -> None:
    from dpc_jax.nn.model_config import SupervisedLossConfig
    from dpc_jax.nn.supervised_loss import supervised_dpc_loss

    xi_vo, xi_gt, xi_corr, weight = _supervised_case(0)
    rng = np.random.default_rng(1)
    a = rng.normal(size=(6, 6))
    precision = a @ a.T + 6 * np.eye(6)
    config = SupervisedLossConfig(precision=tuple(precision.ravel()), rotation_only=rotation_only)
    with jax.enable_x64(True):
        loss, metrics = supervised_dpc_loss(
            DPCOutputs(xi_corr=jnp.asarray(xi_corr), left=None),  # type: ignore[arg-type]
            _supervised_batch(xi_vo, xi_gt, weight), config,
        )
    corrected, uncorrected = [], []
    for k in range(xi_vo.shape[0]):
        target = _se3_expm(xi_gt[k]) @ np.linalg.inv(_se3_expm(xi_vo[k]))
        correction = _se3_expm(xi_corr[k])
        if rotation_only:
            correction = np.eye(4)
            correction[:3, :3] = _se3_expm(np.concatenate([[0, 0, 0], xi_corr[k, 3:]]))[:3, :3]
            target = target.copy()
            target[:3, 3] = 0.0
            p = precision[3:, 3:]
            g = _se3_vee_log(correction @ np.linalg.inv(target))[3:]
            g0 = _se3_vee_log(np.linalg.inv(target))[3:]
        else:
            p = precision
            g = _se3_vee_log(correction @ np.linalg.inv(target))
            g0 = _se3_vee_log(np.linalg.inv(target))
        corrected.append(0.5 * g @ p @ g)
        uncorrected.append(0.5 * g0 @ p @ g0)
    expected_c = np.sum(weight * np.array(corrected)) / weight.sum()
    expected_u = np.sum(weight * np.array(uncorrected)) / weight.sum()
    np.testing.assert_allclose(float(metrics["supervised_error"]), expected_c, rtol=1e-9)
    np.testing.assert_allclose(float(metrics["no_correction"]), expected_u, rtol=1e-9)
    np.testing.assert_allclose(float(loss), expected_c - expected_u, rtol=1e-8, atol=1e-15)


def test_supervised_loss_is_minimal_at_the_ground_truth_correction() -> None:
    from dpc_jax.nn.model_config import SupervisedLossConfig
    from dpc_jax.nn.supervised_loss import supervised_dpc_loss, target_corrections

    xi_vo, xi_gt, _, weight = _supervised_case(2)
    batch = _supervised_batch(xi_vo, xi_gt, weight)
    config = SupervisedLossConfig(precision=(1.0, 1.0, 1.0, 100.0, 100.0, 100.0))
    with jax.enable_x64(True):
        perfect = se3_log(target_corrections(xi_vo, xi_gt))

        def loss_of(xi: jax.Array) -> jax.Array:
            return supervised_dpc_loss(DPCOutputs(xi_corr=xi, left=None), batch, config)[0]  # type: ignore[arg-type]

        at_truth, metrics = supervised_dpc_loss(
            DPCOutputs(xi_corr=perfect, left=None), batch, config  # type: ignore[arg-type]
        )
        gradient = np.asarray(jax.grad(loss_of)(perfect))
        at_zero = loss_of(jnp.zeros_like(perfect))
    # The corrected pose equals the ground truth: T* = Exp(ξ) · T_vo = T_gt.
    corrected = _se3_expm(np.asarray(perfect)[0]) @ _se3_expm(xi_vo[0])
    np.testing.assert_allclose(corrected, _se3_expm(xi_gt[0]), atol=1e-12)
    assert float(metrics["supervised_error"]) < 1e-20
    assert float(at_truth) == pytest.approx(-float(metrics["no_correction"]))
    assert float(at_zero) == pytest.approx(0.0, abs=1e-15)  # no correction: no improvement
    np.testing.assert_allclose(gradient, 0.0, atol=1e-12)


def test_supervised_loss_needs_ground_truth_and_dpc_loss_dispatches() -> None:
    from dpc_jax.nn.losses import dpc_loss
    from dpc_jax.nn.model_config import SupervisedLossConfig
    from dpc_jax.nn.supervised_loss import target_precision

    xi_vo, xi_gt, xi_corr, weight = _supervised_case(3)
    outputs = DPCOutputs(xi_corr=jnp.asarray(xi_corr), left=None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs ground truth"):
        dpc_loss(outputs, _supervised_batch(xi_vo, None, weight), SupervisedLossConfig())
    loss, metrics = dpc_loss(outputs, _supervised_batch(xi_vo, xi_gt, weight), SupervisedLossConfig())
    assert set(metrics) == {"loss", "supervised_error", "no_correction"} and np.isfinite(float(loss))
    with pytest.raises(ValueError, match="precision"):
        SupervisedLossConfig(precision=(1.0, 2.0))
    rng = np.random.default_rng(4)
    targets = rng.normal(size=(200, 6)) * [0.02, 0.01, 0.04, 1e-3, 2e-3, 1e-3]
    with jax.enable_x64(True):
        np.testing.assert_allclose(np.asarray(target_precision(targets)), np.linalg.inv(np.cov(targets.T)),
                                   rtol=1e-9)
        rotation = np.asarray(target_precision(targets, rotation_only=True))
    np.testing.assert_allclose(rotation[3:, 3:], np.linalg.inv(np.cov(targets[:, 3:].T)), rtol=1e-9)
    assert np.all(rotation[:3] == 0.0) and np.all(rotation[:, :3] == 0.0)


@pytest.mark.slow
def test_only_supervised_training_reads_ground_truth(tmp_path) -> None:
    """Self-supervised training: no training batch carries ground truth; ``supervision: supervised``:
    every batch does (the ground truth of its pairs) and the step minimises DPC-Net's loss."""
    from support import cheap_loss, make_caches, se3_logs, tiny_config, train_loss

    from dpc_jax.config import ConfigError
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.nn.model_config import SupervisedLossConfig
    from dpc_jax.training import steps as steps_lib
    from dpc_jax.training.loop import train
    from dpc_jax.training.train_data import open_data

    root = make_caches(tmp_path / "data", ["00", "01", "02"])
    seen: list[tuple[str, bool]] = []
    supervised = steps_lib.dpc_loss

    def recording(outputs: DPCOutputs, batch: Batch, config: object) -> tuple[jax.Array, dict]:
        seen.append((type(config).__name__, batch.xi_gt is not None))  # at trace time
        if isinstance(config, SupervisedLossConfig):
            return supervised(outputs, batch, config)
        return cheap_loss(outputs, batch, config)

    with train_loss(recording):
        self_data = open_data(tiny_config(root), workers=0)
        assert self_data.loader.table.xi_gt is None
        assert all(b.xi_gt is None for b in self_data.loader.epoch(0))
        train(tiny_config(root, epochs=1), tmp_path / "self", progress=False, workers=0)
        assert seen and all(name == "StereoDPCLossConfig" and not has_gt for name, has_gt in seen)

        seen.clear()
        config = tiny_config(root, epochs=1, supervision="supervised", precision=[1, 1, 1, 100, 100, 100])
        assert config.train_loss_config() == SupervisedLossConfig(
            precision=(1.0, 1.0, 1.0, 100.0, 100.0, 100.0), method="stereo_dpc"
        )
        data = open_data(config, workers=0)
        table = data.loader.table
        assert table.xi_gt is not None
        forward = (table.cache == 0) & (table.kind == 0)
        gt = load_cache(root / "00").gt
        pairs = table.xi_gt[forward][np.argsort(table.source[forward])]
        np.testing.assert_allclose(pairs, se3_logs(gt, 1), atol=1e-6)
        summary = train(config, tmp_path / "supervised", progress=False, workers=0)
        assert seen and all(name == "SupervisedLossConfig" and has_gt for name, has_gt in seen)
        assert summary["epochs"] == 1
        # Without a precision the loop takes DPC-Net's from the training pairs; these tiny sequences'
        # priors err in one direction only, so it does not exist, and training says so before a step.
        with pytest.raises(ValueError, match="no spread"):
            train(tiny_config(root, epochs=1, supervision="supervised"), tmp_path / "default", progress=False,
                  workers=0)

        with pytest.raises(ConfigError, match="precision is used only"):
            tiny_config(root, precision=[1, 1, 1, 1, 1, 1])


def test_training_precision_is_the_inverse_covariance_of_the_targets() -> None:
    from dpc_jax.nn.model_config import StereoDPCLossConfig, SupervisedLossConfig
    from dpc_jax.nn.supervised_loss import with_target_precision

    xi_vo, xi_gt, _, _ = _supervised_case(6, b=300)
    targets = np.stack([
        _se3_vee_log(_se3_expm(g) @ np.linalg.inv(_se3_expm(v))) for v, g in zip(xi_vo, xi_gt, strict=True)
    ])
    with jax.enable_x64(True):
        config = with_target_precision(SupervisedLossConfig(), xi_vo, xi_gt)
        rotation = with_target_precision(SupervisedLossConfig(rotation_only=True), xi_vo, xi_gt)
        given = SupervisedLossConfig(precision=(1.0,) * 6)
        assert with_target_precision(given, xi_vo, xi_gt) is given
        assert with_target_precision(StereoDPCLossConfig(), xi_vo, None) == StereoDPCLossConfig()
        with pytest.raises(ValueError, match="ground truth"):
            with_target_precision(SupervisedLossConfig(), xi_vo, None)
        flat = xi_gt.copy()
        flat[:, 3:] = xi_vo[:, 3:]  # no rotation error at all
        with pytest.raises(ValueError, match="no spread"):
            with_target_precision(SupervisedLossConfig(), xi_vo, flat)
    assert isinstance(config, SupervisedLossConfig) and isinstance(rotation, SupervisedLossConfig)
    np.testing.assert_allclose(np.array(config.precision).reshape(6, 6), np.linalg.inv(np.cov(targets.T)),
                               rtol=1e-7)
    expected = np.zeros((6, 6))
    expected[3:, 3:] = np.linalg.inv(np.cov(targets[:, 3:].T))
    np.testing.assert_allclose(np.array(rotation.precision).reshape(6, 6), expected, rtol=1e-7, atol=1e-9)
