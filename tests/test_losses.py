"""Loss building blocks against numpy references; assemblies on exact and analytic scenes."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_warp import BASELINE, K_SCENE, render_scene, right_of
from test_warp import pose as make_pose

from dpc_jax.geometry.lie import se3_log
from dpc_jax.geometry.ssim import ssim_loss
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.config import SSDPCLossConfig, StereoDPCLossConfig
from dpc_jax.nn.losses import (
    explainability_loss,
    gradient_loss,
    gradient_mask,
    masked_mean,
    photometric_error,
    rotation_weights,
    ss_dpc_loss,
    stereo_dpc_loss,
)
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs

# --- building blocks ----------------------------------------------------------------------------


def test_photometric_error_reference_and_learned_weight() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.random((2, 5, 6, 3)), rng.random((2, 5, 6, 3))
    l1 = np.abs(a - b).mean(-1)
    structural = np.asarray(ssim_loss(a, b)).mean(-1)
    np.testing.assert_allclose(np.asarray(photometric_error(a, b, 0.0)), l1, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(photometric_error(a, b)), 0.85 * structural + 0.15 * l1, rtol=1e-12)
    learned = photometric_error(a, b, jnp.asarray(0.3))
    np.testing.assert_allclose(np.asarray(learned), 0.3 * structural + 0.7 * l1, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(photometric_error(a, a)), 0.0, atol=1e-12)


def test_photometric_error_ignores_invalid_neighbours_in_ssim() -> None:
    rng = np.random.default_rng(1)
    target = rng.random((6, 8, 3))
    recon = target.copy()
    recon[:, :2] = 0.0  # what the sampler returns outside the source
    valid = np.ones((6, 8), bool)
    valid[:, :2] = False
    error = np.asarray(photometric_error(target, recon, 0.85, valid))
    np.testing.assert_allclose(error[valid], 0.0, atol=1e-12)
    assert np.asarray(photometric_error(target, recon, 0.85))[:, 2].min() > 1e-3


def test_masked_mean_reference_invalid_and_padding() -> None:
    rng = np.random.default_rng(2)
    values = rng.random((3, 4, 5))
    valid = rng.random((3, 4, 5)) > 0.3
    weight = np.array([1.0, 0.5, 0.0])
    scale = np.array([5.0, 1.0, 7.0])
    w = weight[:, None, None] * valid
    expected = (w * scale[:, None, None] * values).sum() / w.sum()
    np.testing.assert_allclose(float(masked_mean(values, valid, weight, scale)), expected, rtol=1e-13)
    # Invalid pixels and padding samples neither count nor dilute, whatever they hold.
    changed = values.copy()
    changed[~valid] = np.inf
    changed[2] = np.nan
    np.testing.assert_allclose(float(masked_mean(changed, valid, weight, scale)), expected, rtol=1e-13)
    assert float(masked_mean(values, np.zeros_like(valid), weight)) == 0.0


def test_explainability_loss_and_clamp() -> None:
    mask = np.array([[[0.5, 1.0]], [[0.25, 0.25]]])
    weight = np.array([1.0, 0.0])
    np.testing.assert_allclose(float(explainability_loss(mask, weight)), np.log(2) / 2, rtol=1e-13)
    clamped = explainability_loss(np.zeros((1, 2, 2)), np.ones(1), floor=1e-3)
    assert float(clamped) == pytest.approx(-np.log(1e-3))
    grad = jax.grad(lambda m: explainability_loss(m, jnp.ones(1)))(jnp.zeros((1, 2, 2)))
    assert bool(jnp.isfinite(grad).all())


def test_rotation_weights_switch_at_gamma() -> None:
    gamma = 0.005
    xi = np.zeros((4, 6))
    xi[:, 3] = [0.0, gamma * (1 - 1e-9), gamma, gamma * 1.5]
    xi[:, 0] = 5.0  # translation is irrelevant
    np.testing.assert_array_equal(np.asarray(rotation_weights(xi, gamma, 4.0)), [1.0, 1.0, 5.0, 5.0])


def test_gradient_mask_against_cv2_grey_and_numpy() -> None:
    rng = np.random.default_rng(3)
    image = rng.random((2, 7, 9, 3)).astype(np.float32) * 0.2
    mask = np.asarray(gradient_mask(image, 0.03))
    for b in range(2):
        grey = cv2.cvtColor(image[b], cv2.COLOR_RGB2GRAY).astype(np.float64)
        dx = np.zeros_like(grey)
        dy = np.zeros_like(grey)
        dx[:, :-1] = np.abs(grey[:, 1:] - grey[:, :-1])
        dy[:-1, :] = np.abs(grey[1:, :] - grey[:-1, :])
        expected = (dx + dy) / 2 > 0.03
        # Ignore pixels within float32 rounding of the threshold.
        close = np.abs((dx + dy) / 2 - 0.03) < 1e-5
        np.testing.assert_array_equal(mask[b][~close], expected[~close])
        assert 0.05 < expected.mean() < 0.95


# --- scenes -------------------------------------------------------------------------------------


def static_mono_batch(rng: np.random.Generator, batch: int = 2) -> tuple[DPCOutputs, Batch]:
    """Identical frames, identity prior, exact reconstruction everywhere."""
    height, width = 8, 10
    left = rng.integers(0, 256, (batch, 2, height, width, 3), dtype=np.uint8)
    left[:, 1] = left[:, 0]
    K = np.broadcast_to(K_SCENE, (batch, 3, 3))
    b = Batch(left=left, right=left.copy(), xi_vo=np.zeros((batch, 6)), intrinsics=K,
              baseline=np.full(batch, BASELINE), weight=np.ones(batch))
    inv_depth = rng.uniform(0.1, 1.0, (batch, 1, height, width))
    outputs = DPCOutputs(xi_corr=np.zeros((batch, 6)), left=BranchOutputs(inv_depth, np.ones_like(inv_depth)))
    return outputs, b


@pytest.fixture(scope="module")
def analytic() -> tuple[DPCOutputs, Batch]:
    """The two-pose stereo scene of test_warp with exact depth: a near-perfect reconstruction."""
    T_w_0 = make_pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    T_w_1 = make_pose((0.12, -0.05, 0.6), (0.01, 0.03, -0.005))
    frames = {}
    for name, T in (("l0", T_w_0), ("l1", T_w_1), ("r0", right_of(T_w_0)), ("r1", right_of(T_w_1))):
        frames[name] = render_scene(T)
    left = np.stack([frames["l0"][0], frames["l1"][0]])[None]
    right = np.stack([frames["r0"][0], frames["r1"][0]])[None]
    inv_l = 1.0 / np.stack([frames["l0"][1], frames["l1"][1]])[None]
    inv_r = 1.0 / np.stack([frames["r0"][1], frames["r1"][1]])[None]
    T_1_0 = np.linalg.inv(T_w_1) @ T_w_0
    xi_vo = np.asarray(se3_log(T_1_0))[None]
    # Float images in [0, 1] (not uint8) so quantisation does not hide the geometry.
    batch = Batch(left=left, right=right, xi_vo=xi_vo, intrinsics=K_SCENE[None],
                  baseline=np.array([BASELINE]), weight=np.ones(1))
    outputs = DPCOutputs(xi_corr=np.zeros((1, 6)), left=BranchOutputs(inv_l, np.ones_like(inv_l)),
                         right=BranchOutputs(inv_r, np.ones_like(inv_r)))
    return outputs, batch


def mono_view(outputs: DPCOutputs) -> DPCOutputs:
    """ss-DPC-Net outputs: the target (frame t+1) slice of the left branch."""
    left = BranchOutputs(outputs.left.inv_depth[:, 1:], outputs.left.mask[:, 1:])
    return DPCOutputs(xi_corr=outputs.xi_corr, left=left)


def perturbed(outputs: DPCOutputs, delta: np.ndarray) -> DPCOutputs:
    return outputs._replace(xi_corr=outputs.xi_corr + delta)


DELTA = np.array([[0.05, -0.03, 0.08, 0.01, -0.015, 0.01]])


# --- ss-DPC-Net ---------------------------------------------------------------------------------


def test_ss_dpc_zero_for_exact_reconstruction() -> None:
    outputs, batch = static_mono_batch(np.random.default_rng(4))
    loss, metrics = ss_dpc_loss(outputs, batch, SSDPCLossConfig())
    assert abs(float(loss)) < 1e-10
    # Rounding of K⁻¹ can push border pixels a hair outside [0, W−1]; the interior is valid.
    assert float(metrics["valid_fraction"]) >= 48 / 80
    assert set(metrics) >= {"loss", "photometric", "explainability", "valid_fraction", "ssim_weight"}


def test_ss_dpc_analytic_scene(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    mono = mono_view(outputs)
    config = SSDPCLossConfig(rot_weight=0.0)
    loss, metrics = ss_dpc_loss(mono, batch, config)
    assert float(metrics["explainability"]) == 0.0
    assert float(loss) < 1e-3
    wrong, _ = ss_dpc_loss(perturbed(mono, DELTA), batch, config)
    assert float(wrong) > 10 * float(loss)


def test_ss_dpc_assembly_and_rotation_switch(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    mono = perturbed(mono_view(outputs), DELTA)
    mask = np.full(mono.left.mask.shape, 0.5)
    mono = mono._replace(left=mono.left._replace(mask=mask))
    angle = float(np.linalg.norm(batch.xi_vo[0, 3:]))
    base = SSDPCLossConfig(rot_weight=0.0)
    _, plain = ss_dpc_loss(mono, batch, base)
    assert float(plain["explainability"]) == pytest.approx(np.log(2))
    for threshold, factor in ((angle * 1.001, 1.0), (angle * 0.999, 5.0)):
        config = SSDPCLossConfig(rot_weight=4.0, rot_threshold=threshold, exp_weight=0.23)
        loss, metrics = ss_dpc_loss(mono, batch, config)
        np.testing.assert_allclose(float(metrics["photometric"]), factor * float(plain["photometric"]),
                                   rtol=1e-12)
        np.testing.assert_allclose(float(loss), float(metrics["photometric"]) + 0.23 * np.log(2), rtol=1e-12)


def test_ss_dpc_learned_ssim_weight_overrides(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    mono = perturbed(mono_view(outputs), DELTA)
    fixed, _ = ss_dpc_loss(mono, batch, SSDPCLossConfig(ssim_weight=0.4))
    learned, metrics = ss_dpc_loss(mono._replace(ssim_weight=jnp.asarray(0.4)), batch, SSDPCLossConfig())
    np.testing.assert_allclose(float(learned), float(fixed), rtol=1e-12)
    assert float(metrics["ssim_weight"]) == pytest.approx(0.4)


def test_ss_dpc_gradients_reach_depth_mask_and_pose(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    mono = perturbed(mono_view(outputs), DELTA)

    def loss_of(inv_depth: jax.Array, mask: jax.Array, xi: jax.Array) -> jax.Array:
        out = DPCOutputs(xi_corr=xi, left=BranchOutputs(inv_depth, mask))
        return ss_dpc_loss(out, batch, SSDPCLossConfig())[0]

    grads = jax.grad(loss_of, argnums=(0, 1, 2))(mono.left.inv_depth, mono.left.mask * 0.9, mono.xi_corr)
    for g in grads:
        assert bool(jnp.isfinite(g).all()) and float(jnp.abs(g).max()) > 0


def test_ss_dpc_padding_samples_do_not_change_loss(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    mono = perturbed(mono_view(outputs), DELTA)
    loss, metrics = ss_dpc_loss(mono, batch, SSDPCLossConfig())
    rng = np.random.default_rng(5)

    def pad(x: np.ndarray, garbage: np.ndarray) -> np.ndarray:
        return np.concatenate([np.asarray(x), garbage.astype(np.asarray(x).dtype)])

    padded_batch = batch._replace(
        left=pad(batch.left, rng.random(batch.left.shape)),
        right=pad(batch.right, rng.random(batch.right.shape)),
        xi_vo=pad(batch.xi_vo, rng.normal(size=(1, 6))), intrinsics=pad(batch.intrinsics, K_SCENE[None] * 2),
        baseline=pad(batch.baseline, np.ones(1)), weight=np.array([1.0, 0.0]),
    )
    padded = DPCOutputs(
        xi_corr=pad(mono.xi_corr, rng.normal(size=(1, 6))),
        left=BranchOutputs(pad(mono.left.inv_depth, rng.random(mono.left.inv_depth.shape)),
                           pad(mono.left.mask, rng.random(mono.left.mask.shape) * 1e-3)),
    )
    padded_loss, padded_metrics = ss_dpc_loss(padded, padded_batch, SSDPCLossConfig())
    np.testing.assert_allclose(float(padded_loss), float(loss), rtol=1e-12)
    for key in metrics:
        np.testing.assert_allclose(float(padded_metrics[key]), float(metrics[key]), rtol=1e-12)


def test_ss_dpc_jit_float32_uint8() -> None:
    outputs, batch = static_mono_batch(np.random.default_rng(6))
    outputs = jax.tree.map(lambda x: np.asarray(x, np.float32), outputs)
    batch = jax.tree.map(lambda x: x if x.dtype == np.uint8 else np.asarray(x, np.float32), batch)
    outputs = perturbed(outputs, DELTA.astype(np.float32))
    config = SSDPCLossConfig(ssim_weight=0.85)
    loss, _ = jax.jit(ss_dpc_loss, static_argnums=2)(outputs, batch, config)
    assert loss.dtype == jnp.float32 and bool(jnp.isfinite(loss)) and float(loss) > 0
    eager, _ = ss_dpc_loss(outputs, batch, config)
    np.testing.assert_allclose(float(loss), float(eager), rtol=1e-5)


def test_ss_dpc_gradient_loss(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    mono = mono_view(outputs)
    # The analytic texture is smooth: a low threshold keeps about half of the pixels.
    config = SSDPCLossConfig(grad_threshold=0.006)
    exact = float(gradient_loss(mono, batch, config))
    wrong = float(gradient_loss(perturbed(mono, DELTA), batch, config))
    assert exact < 1e-3 < wrong
    # Unaffected by the explainability mask.
    masked = mono._replace(left=mono.left._replace(mask=np.full(mono.left.mask.shape, 0.01)))
    assert float(gradient_loss(perturbed(masked, DELTA), batch, config)) == pytest.approx(wrong, rel=1e-12)


# --- Stereo DPC ---------------------------------------------------------------------------------


def shifted_stereo_scene(rng: np.random.Generator) -> tuple[DPCOutputs, Batch]:
    """A fronto-parallel plane at 10 m, rig moving by one baseline along x: every warp is an
    exact whole-pixel shift (disparity fu·B/Z = 2 px), so a perfect model has zero loss."""
    height, width, shift = 8, 12, 2
    strip = rng.integers(0, 256, (height, width + 2 * shift, 3), dtype=np.uint8)
    view = lambda camera: strip[:, camera * shift : camera * shift + width]  # camera at x = camera·B
    left = np.stack([view(0), view(1)])[None]
    right = np.stack([view(1), view(2)])[None]
    inv_depth = np.full((1, 2, height, width), 0.1)
    K = np.array([[40.0, 0.0, 5.5], [0.0, 40.0, 3.5], [0.0, 0.0, 1.0]])
    xi_vo = np.array([[-BASELINE, 0, 0, 0, 0, 0]])  # T_{k+1,k}: world points move by −B in the camera
    batch = Batch(left=left, right=right, xi_vo=xi_vo, intrinsics=K[None], baseline=np.array([BASELINE]),
                  weight=np.ones(1))
    branch = BranchOutputs(inv_depth, np.ones_like(inv_depth))
    return DPCOutputs(xi_corr=np.zeros((1, 6)), left=branch, right=branch), batch


def test_stereo_zero_for_exact_reconstruction() -> None:
    outputs, batch = shifted_stereo_scene(np.random.default_rng(7))
    _, metrics = stereo_dpc_loss(outputs, batch, StereoDPCLossConfig())
    expected_keys = {"spatial_left", "spatial_right", "disparity_left", "disparity_right", "explainability",
                     "temporal_left_k_to_k1", "temporal_left_k1_to_k", "temporal_right_k_to_k1",
                     "temporal_right_k1_to_k", "loss", "ssim_weight"}
    assert set(metrics) == expected_keys
    for key in expected_keys - {"ssim_weight"}:
        assert abs(float(metrics[key])) < 1e-10, key
    assert float(gradient_loss(outputs, batch, StereoDPCLossConfig())) < 1e-10
    wrong, _ = stereo_dpc_loss(perturbed(outputs, np.array([[0.2, 0, 0, 0, 0, 0]])), batch,
                               StereoDPCLossConfig())
    assert float(wrong) > 1e-2


def test_stereo_analytic_scene_all_terms_small(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    _, metrics = stereo_dpc_loss(outputs, batch, StereoDPCLossConfig())
    for key, value in metrics.items():
        if key != "ssim_weight":
            assert float(value) < 2e-3, (key, float(value))
    _, wrong = stereo_dpc_loss(perturbed(outputs, DELTA), batch, StereoDPCLossConfig())
    # The right camera's temporal terms use C T* C⁻¹; they are as small as the left ones.
    for key in ("temporal_right_k_to_k1", "temporal_right_k1_to_k"):
        assert float(wrong[key]) > 5 * float(metrics[key])
    assert float(gradient_loss(outputs, batch, StereoDPCLossConfig())) < 2e-3


def test_stereo_assembly_weights(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    outputs = perturbed(outputs, DELTA)
    mask = np.full(outputs.left.mask.shape, 0.5)
    outputs = outputs._replace(left=outputs.left._replace(mask=mask), right=outputs.right._replace(mask=mask))
    alpha = (1.5, 2.0, 0.5, 0.1)
    loss, m = stereo_dpc_loss(outputs, batch, StereoDPCLossConfig(alpha=alpha))
    temporal = sum(m[k] for k in m if k.startswith("temporal"))
    expected = (alpha[0] * (m["spatial_left"] + m["spatial_right"])
                + alpha[1] * (m["disparity_left"] + m["disparity_right"]) + alpha[2] * temporal
                + alpha[3] * m["explainability"])
    np.testing.assert_allclose(float(loss), float(expected), rtol=1e-12)
    np.testing.assert_allclose(float(m["explainability"]), 4 * np.log(2), rtol=1e-12)


def test_stereo_gradients_and_jit_float32(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    outputs = jax.tree.map(lambda x: np.asarray(x, np.float32), perturbed(outputs, DELTA))
    batch = jax.tree.map(lambda x: np.asarray(x, np.float32), batch)
    config = StereoDPCLossConfig()

    @jax.jit
    def grads(out: DPCOutputs) -> tuple[jax.Array, DPCOutputs]:
        return jax.value_and_grad(lambda o: stereo_dpc_loss(o, batch, config)[0])(out)

    loss, g = grads(outputs._replace(left=outputs.left._replace(mask=outputs.left.mask * 0.9)))
    assert loss.dtype == jnp.float32 and bool(jnp.isfinite(loss))
    for leaf in (g.xi_corr, g.left.inv_depth, g.left.mask, g.right.inv_depth, g.right.mask):
        assert bool(jnp.isfinite(leaf).all()) and float(jnp.abs(leaf).max()) > 0


def test_stereo_needs_right_branch(analytic: tuple[DPCOutputs, Batch]) -> None:
    outputs, batch = analytic
    with pytest.raises(ValueError, match=r"outputs\.right"):
        stereo_dpc_loss(outputs._replace(right=None), batch, StereoDPCLossConfig())
    with pytest.raises(ValueError, match=r"outputs\.left\.inv_depth has shape"):
        ss_dpc_loss(outputs, batch, SSDPCLossConfig())


# --- DPC-Net's supervised loss ---------------------------------------------------------------------


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
    from dpc_jax.nn.config import SupervisedLossConfig
    from dpc_jax.nn.losses import supervised_dpc_loss

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
    from dpc_jax.nn.config import SupervisedLossConfig
    from dpc_jax.nn.losses import supervised_dpc_loss, target_corrections

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
    from dpc_jax.nn.config import SupervisedLossConfig
    from dpc_jax.nn.losses import dpc_loss, target_precision

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


def test_only_supervised_training_reads_ground_truth(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Self-supervised training: no training batch carries ground truth; ``supervision: supervised``:
    every batch does (the ground truth of its pairs) and the step minimises DPC-Net's loss."""
    from test_train import _cheap_loss, _logs, make_caches, tiny_config

    from dpc_jax.config import ConfigError
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.nn.config import SupervisedLossConfig
    from dpc_jax.training import steps as steps_lib
    from dpc_jax.training.loop import open_data, train

    root = make_caches(tmp_path / "data", ["00", "01", "02"])
    seen: list[tuple[str, bool]] = []
    supervised = steps_lib.dpc_loss

    def recording(outputs: DPCOutputs, batch: Batch, config: object) -> tuple[jax.Array, dict]:
        seen.append((type(config).__name__, batch.xi_gt is not None))  # at trace time
        if isinstance(config, SupervisedLossConfig):
            return supervised(outputs, batch, config)
        return _cheap_loss(outputs, batch, config)

    monkeypatch.setattr(steps_lib, "dpc_loss", recording)
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
    np.testing.assert_allclose(pairs, _logs(gt, 1), atol=1e-6)
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
    from dpc_jax.nn.config import StereoDPCLossConfig, SupervisedLossConfig
    from dpc_jax.nn.losses import with_target_precision

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
