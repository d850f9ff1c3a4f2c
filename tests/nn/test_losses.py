"""dpc_jax.nn.losses: the self-supervised loss assemblies on exact and analytic scenes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from support import K_SCENE, SCENE_BASELINE, camera_pose, render_scene, right_of

from dpc_jax.geometry.lie import se3_log
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.losses import gradient_loss, ss_dpc_loss, stereo_dpc_loss
from dpc_jax.nn.model_config import SSDPCLossConfig, StereoDPCLossConfig
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs

# --- scenes -------------------------------------------------------------------------------------


def static_mono_batch(rng: np.random.Generator, batch: int = 2) -> tuple[DPCOutputs, Batch]:
    """Identical frames, identity prior, exact reconstruction everywhere."""
    height, width = 8, 10
    left = rng.integers(0, 256, (batch, 2, height, width, 3), dtype=np.uint8)
    left[:, 1] = left[:, 0]
    K = np.broadcast_to(K_SCENE, (batch, 3, 3))
    b = Batch(left=left, right=left.copy(), xi_vo=np.zeros((batch, 6)), intrinsics=K,
              baseline=np.full(batch, SCENE_BASELINE), weight=np.ones(batch))
    inv_depth = rng.uniform(0.1, 1.0, (batch, 1, height, width))
    outputs = DPCOutputs(xi_corr=np.zeros((batch, 6)), left=BranchOutputs(inv_depth, np.ones_like(inv_depth)))
    return outputs, b


@pytest.fixture(scope="module")
def analytic() -> tuple[DPCOutputs, Batch]:
    """The two-pose scene of ``support.render_scene`` with exact depth: a near-perfect reconstruction."""
    T_w_0 = camera_pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    T_w_1 = camera_pose((0.12, -0.05, 0.6), (0.01, 0.03, -0.005))
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
                  baseline=np.array([SCENE_BASELINE]), weight=np.ones(1))
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
    xi_vo = np.array([[-SCENE_BASELINE, 0, 0, 0, 0, 0]])  # T_{k+1,k}: world points move by −B in the camera
    batch = Batch(left=left, right=right, xi_vo=xi_vo, intrinsics=K[None],
                  baseline=np.array([SCENE_BASELINE]), weight=np.ones(1))
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
