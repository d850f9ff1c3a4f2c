"""Warping against OpenCV, known geometry, and an analytic scene ray-cast in float64.

The scene (a textured ground plane and a textured wall, seen by a rectified stereo rig from two
poses) is rendered with numpy and scipy only (``support.render_scene``, shared with ``test_losses.py``).
"""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from support import K_SCENE, SCENE_BASELINE, camera_pose, render_scene, right_of

from dpc_jax.geometry.lie import se3_exp
from dpc_jax.geometry.warp import bilinear_sample, disparity_consistency, inverse_warp, stereo_warp


@pytest.fixture(scope="module")
def scene() -> dict[str, np.ndarray]:
    T_w_0 = camera_pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    T_w_1 = camera_pose((0.12, -0.05, 0.6), (0.01, 0.03, -0.005))
    out = {"T_w_0": T_w_0, "T_w_1": T_w_1}
    cameras = {"left0": T_w_0, "left1": T_w_1, "right0": right_of(T_w_0), "right1": right_of(T_w_1)}
    for name, T in cameras.items():
        out[name], out[name + "_depth"] = render_scene(T)
    return out


def masked_mae(a: jax.Array, b: np.ndarray, valid: jax.Array) -> float:
    error = np.abs(np.asarray(a) - b).mean(-1)
    return float(error[np.asarray(valid)].mean())


# --- bilinear sampling -------------------------------------------------------------------------


def test_bilinear_matches_cv2_remap_inside() -> None:
    rng = np.random.default_rng(0)
    image = rng.random((20, 30, 3)).astype(np.float32)
    uv = np.stack([rng.uniform(0, 29, (16, 24)), rng.uniform(0, 19, (16, 24))], -1).astype(np.float32)
    sampled, valid = bilinear_sample(image, uv)
    expected = cv2.remap(image, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    assert sampled.dtype == jnp.float32 and bool(valid.all())
    np.testing.assert_allclose(np.asarray(sampled), expected, atol=1e-5)


def test_bilinear_border_blend_and_outside_match_cv2() -> None:
    # Regression: samples between −2 and −1 once picked up pixel 0 with weight x − floor(x).
    rng = np.random.default_rng(1)
    image = rng.random((20, 30, 3)).astype(np.float32)
    uv = np.stack([rng.uniform(-3, 33, (40, 50)), rng.uniform(-3, 23, (40, 50))], -1).astype(np.float32)
    sampled, valid = bilinear_sample(image, uv)
    expected = cv2.remap(image, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    np.testing.assert_allclose(np.asarray(sampled), expected, atol=1e-5)
    inside = (uv[..., 0] >= 0) & (uv[..., 0] <= 29) & (uv[..., 1] >= 0) & (uv[..., 1] <= 19)
    np.testing.assert_array_equal(np.asarray(valid), inside)
    assert 0.1 < inside.mean() < 0.9


def test_bilinear_validity_edges_and_non_finite() -> None:
    image = np.ones((4, 5, 1))
    uv = np.array([[[0.0, 0.0], [4.0, 3.0], [4.0 + 1e-9, 1.0], [-1e-9, 1.0], [np.nan, 1.0], [np.inf, 0.0]]])
    sampled, valid = bilinear_sample(image, uv)
    assert valid.tolist() == [[True, True, False, False, False, False]]
    np.testing.assert_allclose(np.asarray(sampled[0, :2, 0]), [1.0, 1.0])
    np.testing.assert_array_equal(np.asarray(sampled[0, 4:, 0]), [0.0, 0.0])


def test_bilinear_batch_broadcast_equals_loop() -> None:
    rng = np.random.default_rng(2)
    images = rng.random((2, 3, 6, 7, 2))
    uv = np.stack([rng.uniform(-1, 7, (3, 4, 5)), rng.uniform(-1, 6, (3, 4, 5))], -1)  # broadcasts over 2
    sampled, valid = bilinear_sample(images, uv)
    assert sampled.shape == (2, 3, 4, 5, 2) and valid.shape == (2, 3, 4, 5)
    for i in range(2):
        for j in range(3):
            one, one_valid = bilinear_sample(images[i, j], uv[j])
            np.testing.assert_allclose(np.asarray(sampled[i, j]), np.asarray(one), rtol=1e-14)
            np.testing.assert_array_equal(np.asarray(valid[i, j]), np.asarray(one_valid))


def test_bilinear_gradients_match_finite_differences() -> None:
    rng = np.random.default_rng(3)
    image = jnp.asarray(rng.random((6, 7, 2)))
    # Away from integers, where the interpolation is smooth in uv.
    uv = jnp.asarray(np.stack([rng.uniform(0.1, 0.9, (3, 4)) + rng.integers(0, 5, (3, 4)),
                               rng.uniform(0.1, 0.9, (3, 4)) + rng.integers(0, 4, (3, 4))], -1))
    weights = jnp.asarray(rng.random((3, 4, 2)))

    def f(img: jax.Array, coords: jax.Array) -> jax.Array:
        return jnp.sum(bilinear_sample(img, coords)[0] * weights)

    check_grads(f, (image, uv), order=1, modes=["rev"], eps=1e-6)


def test_bilinear_shape_errors() -> None:
    with pytest.raises(ValueError, match="uv must have shape"):
        bilinear_sample(np.ones((4, 5, 3)), np.ones((4, 5, 3)))
    with pytest.raises(ValueError, match="image must have shape"):
        bilinear_sample(np.ones((4, 5)), np.ones((4, 5, 2)))
    with pytest.raises(ValueError, match=r"do not broadcast"):
        bilinear_sample(np.ones((2, 4, 5, 3)), np.ones((3, 4, 5, 2)))


# --- temporal warp -------------------------------------------------------------------------------


def test_inverse_warp_identity_reproduces_image(scene: dict[str, np.ndarray]) -> None:
    image = scene["left0"].astype(np.float32)
    recon, valid = inverse_warp(image, scene["left0_depth"].astype(np.float32), np.eye(4, dtype=np.float32),
                                K_SCENE.astype(np.float32))
    # float32 rounding of K⁻¹ can put a border pixel a hair outside [0, W−1]; the interior is exact.
    assert recon.dtype == jnp.float32 and bool(valid[1:-1, 1:-1].all())
    np.testing.assert_allclose(np.asarray(recon)[np.asarray(valid)], image[np.asarray(valid)], atol=1e-4)


def test_inverse_warp_reconstructs_analytic_scene(scene: dict[str, np.ndarray]) -> None:
    # Rebuild frame 1 from frame 0: T_{0,1} maps frame-1 points into frame 0.
    T_0_1 = np.linalg.inv(scene["T_w_0"]) @ scene["T_w_1"]
    recon, valid = inverse_warp(scene["left0"], scene["left1_depth"], T_0_1, K_SCENE)
    assert recon.dtype == jnp.float64
    assert float(np.mean(valid)) > 0.7
    assert masked_mae(recon, scene["left1"], valid) < 1e-3
    # The other direction, with the exact inverse.
    recon, valid = inverse_warp(scene["left1"], scene["left0_depth"], np.linalg.inv(T_0_1), K_SCENE)
    assert float(np.mean(valid)) > 0.5
    assert masked_mae(recon, scene["left0"], valid) < 1e-3
    # A wrong pose is visibly wrong, so the threshold above means something.
    recon, valid = inverse_warp(scene["left0"], scene["left1_depth"], np.eye(4), K_SCENE)
    assert masked_mae(recon, scene["left1"], valid) > 1e-2


def test_inverse_warp_batched_equals_loop(scene: dict[str, np.ndarray]) -> None:
    T_0_1 = np.linalg.inv(scene["T_w_0"]) @ scene["T_w_1"]
    sources = np.stack([scene["left0"], scene["right0"]])
    depths = np.stack([scene["left1_depth"], scene["right1_depth"]])
    poses = np.stack([T_0_1, np.eye(4)])
    recon, valid = jax.jit(inverse_warp)(sources, depths, poses, K_SCENE)
    for i in range(2):
        one, one_valid = inverse_warp(sources[i], depths[i], poses[i], K_SCENE)
        np.testing.assert_allclose(np.asarray(recon[i]), np.asarray(one), atol=1e-12)
        np.testing.assert_array_equal(np.asarray(valid[i]), np.asarray(one_valid))


def test_inverse_warp_points_behind_are_invalid() -> None:
    T = np.eye(4)
    T[2, 3] = -5.0  # moves every point of depth 2 m to z = −3 m
    _, valid = inverse_warp(np.ones((4, 5, 1)), np.full((4, 5), 2.0), T, K_SCENE)
    assert not bool(valid.any())


def test_inverse_warp_shape_errors() -> None:
    with pytest.raises(ValueError, match="target_depth"):
        inverse_warp(np.ones((4, 5, 3)), np.ones((4, 6)), np.eye(4), K_SCENE)
    with pytest.raises(ValueError, match="T_source_target"):
        inverse_warp(np.ones((4, 5, 3)), np.ones((4, 5)), np.eye(3), K_SCENE)


def test_pose_recovers_from_perturbation_by_gradient_descent(scene: dict[str, np.ndarray]) -> None:
    T_0_1 = jnp.asarray(np.linalg.inv(scene["T_w_0"]) @ scene["T_w_1"])
    target = jnp.asarray(scene["left1"])

    @jax.jit
    def loss_and_grad(delta: jax.Array) -> tuple[jax.Array, jax.Array]:
        def loss(d: jax.Array) -> jax.Array:
            recon, valid = inverse_warp(scene["left0"], scene["left1_depth"], se3_exp(d) @ T_0_1, K_SCENE)
            error = jnp.abs(recon - target).mean(-1)
            return jnp.sum(error * valid) / jnp.sum(valid)

        return jax.value_and_grad(loss)(delta)

    delta = jnp.array([0.03, -0.02, 0.04, 0.004, -0.006, 0.003])
    start_loss, grad = loss_and_grad(delta)
    assert bool(jnp.isfinite(grad).all()) and float(jnp.abs(grad).max()) > 0
    # Per-block step sizes: the loss is far more sensitive to rotation than to translation.
    step = jnp.array([0.1, 0.1, 0.1, 0.002, 0.002, 0.002])
    for _ in range(15):
        _, grad = loss_and_grad(delta)
        delta = delta - step * grad
    end_loss, _ = loss_and_grad(delta)
    assert float(end_loss) < 0.3 * float(start_loss)
    # x-translation and yaw are nearly ambiguous in this scene, so the pose error shrinks
    # more slowly than the photometric error.
    start = np.array([0.03, -0.02, 0.04, 0.004, -0.006, 0.003])
    assert float(jnp.linalg.norm(delta)) < 0.8 * np.linalg.norm(start)


# --- stereo warp ---------------------------------------------------------------------------------


def test_stereo_warp_reconstructs_both_views(scene: dict[str, np.ndarray]) -> None:
    fu = K_SCENE[0, 0]
    for frame in ("0", "1"):
        left, right = scene["left" + frame], scene["right" + frame]
        d_left = fu * SCENE_BASELINE / scene["left" + frame + "_depth"]
        d_right = fu * SCENE_BASELINE / scene["right" + frame + "_depth"]
        recon, valid = stereo_warp(right, d_left, "right_to_left")
        assert float(np.mean(valid)) > 0.6
        assert masked_mae(recon, left, valid) < 1e-3
        recon, valid = stereo_warp(left, d_right, "left_to_right")
        assert float(np.mean(valid)) > 0.6
        assert masked_mae(recon, right, valid) < 1e-3
        # Swapping the direction is wrong by a clear margin.
        recon, valid = stereo_warp(right, d_left, "left_to_right")
        assert masked_mae(recon, left, valid) > 1e-2


def test_stereo_warp_direction_convention() -> None:
    # A bright column at u = 5 in the right image appears at u = 5 + d in the left image.
    right = np.zeros((3, 12, 1))
    right[:, 5] = 1.0
    recon, valid = stereo_warp(right, np.full((3, 12), 2.0), "right_to_left")
    assert np.asarray(recon[0, :, 0]).tolist() == [0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0]
    assert np.asarray(valid[0]).tolist() == [False, False] + [True] * 10
    recon, valid = stereo_warp(right, np.full((3, 12), 2.0), "left_to_right")
    assert np.asarray(recon[0, :, 0]).tolist() == [0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0]
    assert np.asarray(valid[0]).tolist() == [True] * 10 + [False, False]
    with pytest.raises(ValueError, match="direction"):
        stereo_warp(right, np.ones((3, 12)), "up")


def test_disparity_consistency_zero_for_true_disparities(scene: dict[str, np.ndarray]) -> None:
    fu = K_SCENE[0, 0]
    d_left = fu * SCENE_BASELINE / scene["left0_depth"]
    d_right = fu * SCENE_BASELINE / scene["right0_depth"]
    err_l, valid_l, err_r, valid_r = disparity_consistency(d_left, d_right)
    assert float(np.mean(valid_l)) > 0.6 and float(np.mean(valid_r)) > 0.6
    # Disparity is linear in image position on both planes except at the crease.
    assert float(np.median(np.asarray(err_l)[np.asarray(valid_l)])) < 1e-9
    assert float(np.mean(np.asarray(err_l)[np.asarray(valid_l)])) < 1e-4
    assert float(np.mean(np.asarray(err_r)[np.asarray(valid_r)])) < 1e-4


def test_disparity_consistency_against_numpy_loop() -> None:
    rng = np.random.default_rng(4)
    d_left = rng.uniform(0.0, 4.0, (5, 9))
    d_right = rng.uniform(0.0, 4.0, (5, 9))
    err_l, valid_l, err_r, valid_r = disparity_consistency(d_left, d_right)

    def sample_row(row: np.ndarray, x: float) -> float:
        x0 = int(np.floor(x))
        a = x - x0
        value = lambda i: row[i] if 0 <= i < row.size else 0.0
        return (1 - a) * value(x0) + a * value(x0 + 1)

    for v in range(5):
        for u in range(9):
            x = u - d_left[v, u]
            assert bool(valid_l[v, u]) == (0 <= x <= 8)
            if valid_l[v, u]:
                expected = abs(d_left[v, u] - sample_row(d_right[v], x)) / 9
                assert abs(float(err_l[v, u]) - expected) < 1e-12
            x = u + d_right[v, u]
            assert bool(valid_r[v, u]) == (0 <= x <= 8)
            if valid_r[v, u]:
                expected = abs(d_right[v, u] - sample_row(d_left[v], x)) / 9
                assert abs(float(err_r[v, u]) - expected) < 1e-12
    with pytest.raises(ValueError, match="same shape"):
        disparity_consistency(d_left, d_right[:, :5])
