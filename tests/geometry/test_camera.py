"""Camera model against float64 numpy loops and known geometry."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dpc_jax.geometry.camera import backproject, pixel_grid, project, scale_intrinsics

K_NP = np.array([[40.0, 0.0, 31.5], [0.0, 38.0, 23.5], [0.0, 0.0, 1.0]])


def test_scale_intrinsics_rows_reference_rule() -> None:
    scaled = np.asarray(scale_intrinsics(K_NP, 0.5, 0.25, half_pixel=False))
    expected = K_NP.copy()
    expected[0] *= 0.5
    expected[1] *= 0.25
    np.testing.assert_array_equal(scaled, expected)


SIZES = [((48, 64), (12, 16)), ((375, 1242), (64, 96)), ((40, 60), (50, 99))]


@pytest.mark.parametrize(("old", "new"), SIZES, ids=["shrink", "kitti", "grow"])
def test_scale_intrinsics_follows_opencv_resize(old: tuple[int, int], new: tuple[int, int]) -> None:
    """A ray's pixel in the resized image is where cv2.resize puts that image content.

    The old image holds its own column coordinate u (and row v), a linear ramp that bilinear
    resizing reproduces exactly: resized[v', u'] is the old coordinate that new pixel (u', v')
    shows. Projecting that old pixel's ray with the scaled K must land on (u', v')."""
    (h0, w0), (h1, w1) = old, new
    K = np.array([[0.9 * w0, 0.0, 0.47 * w0], [0.0, 0.9 * w0, 0.52 * h0], [0.0, 0.0, 1.0]])
    v0, u0 = np.mgrid[0:h0, 0:w0].astype(np.float32)
    shown_u = cv2.resize(u0, (w1, h1), interpolation=cv2.INTER_LINEAR)[1:-1, 1:-1]
    shown_v = cv2.resize(v0, (w1, h1), interpolation=cv2.INTER_LINEAR)[1:-1, 1:-1]
    Ks = np.asarray(scale_intrinsics(K, w1 / w0, h1 / h0))
    ray_x, ray_y = (shown_u - K[0, 2]) / K[0, 0], (shown_v - K[1, 2]) / K[1, 1]
    v1, u1 = np.mgrid[1:h1 - 1, 1:w1 - 1]
    np.testing.assert_allclose(Ks[0, 0] * ray_x + Ks[0, 2], u1, atol=2e-3)
    np.testing.assert_allclose(Ks[1, 1] * ray_y + Ks[1, 2], v1, atol=2e-3)
    wrong = np.asarray(scale_intrinsics(K, w1 / w0, h1 / h0, half_pixel=False))
    assert np.abs(wrong[0, 0] * ray_x + wrong[0, 2] - u1).max() > 0.1


def test_scale_intrinsics_batched_and_dtype() -> None:
    K = np.stack([K_NP, 2 * K_NP]).astype(np.float32)
    K[:, 2, 2] = 1.0
    scaled = scale_intrinsics(K, jnp.array([1.0, 2.0]), 3.0)
    assert scaled.dtype == jnp.float32 and scaled.shape == (2, 3, 3)
    np.testing.assert_allclose(np.asarray(scaled[1, 0, :2]), 2.0 * K[1, 0, :2], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(scaled[1, 1, :2]), 3.0 * K[1, 1, :2], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(scaled[:, 2]), K[:, 2])
    np.testing.assert_allclose(np.asarray(scaled[1, :2, 2]), [2.0 * K[1, 0, 2] + 0.5, 3.0 * K[1, 1, 2] + 1.0],
                               rtol=1e-6)


def test_pixel_grid_is_column_row() -> None:
    grid = np.asarray(pixel_grid(3, 4, jnp.float64))
    assert grid.shape == (3, 4, 2) and grid.dtype == np.float64
    for v in range(3):
        for u in range(4):
            assert tuple(grid[v, u]) == (u, v)


def test_backproject_matches_numpy_loop() -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 10.0, (2, 5, 6))
    points = np.asarray(backproject(depth, K_NP))
    K_inv = np.linalg.inv(K_NP)
    for b in range(2):
        for v in range(5):
            for u in range(6):
                expected = depth[b, v, u] * K_inv @ np.array([u, v, 1.0])
                np.testing.assert_allclose(points[b, v, u], expected, rtol=1e-13)


def test_project_inverts_backproject_and_flags_points_behind() -> None:
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 20.0, (3, 4, 5)).astype(np.float32)
    K = np.broadcast_to(K_NP.astype(np.float32), (3, 3, 3))
    uv, valid = project(backproject(depth, K), K)
    assert uv.dtype == jnp.float32 and uv.shape == (3, 4, 5, 2)
    assert bool(valid.all())
    np.testing.assert_allclose(np.asarray(uv), np.broadcast_to(np.asarray(pixel_grid(4, 5)), uv.shape),
                               atol=1e-4)

    points = np.array([[[[1.0, 2.0, 0.0005], [1.0, 2.0, -3.0], [1.0, 2.0, 2.0]]]])
    uv, valid = project(points, K_NP, eps=1e-3)
    assert valid.tolist() == [[[False, False, True]]]
    assert bool(jnp.isfinite(uv).all())
    np.testing.assert_allclose(np.asarray(uv[0, 0, 2]), [40 * 0.5 + 31.5, 38 * 1.0 + 23.5])


def test_project_gradient_finite_at_zero_depth() -> None:
    points = jnp.zeros((1, 2, 3))
    grad = jax.grad(lambda p: project(p, K_NP)[0].sum())(points)
    assert bool(jnp.isfinite(grad).all())


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: backproject(np.ones((4, 5)), np.eye(4)), "K must have shape"),
        (lambda: backproject(np.ones(4), K_NP), "depth must have shape"),
        (lambda: project(np.ones((4, 5, 2)), K_NP), "points must have shape"),
        (lambda: scale_intrinsics(np.eye(2), 1.0, 1.0), "K must have shape"),
    ],
)
def test_shape_errors(call, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call()


# The fast inline projections elsewhere (the warp's per-coordinate form, the VO's numpy form) are
# the same pinhole model as this module: checked here so the one camera model stays one.


def test_inverse_warp_projects_like_the_camera_model() -> None:
    from dpc_jax.geometry.lie import se3_exp, transform_points
    from dpc_jax.geometry.warp import inverse_warp

    height, width = 24, 32
    with jax.enable_x64(True):
        K = jnp.array([[30.0, 0.0, 15.5], [0.0, 29.0, 11.5], [0.0, 0.0, 1.0]])
        T = se3_exp(jnp.array([0.05, -0.02, 0.1, 0.01, -0.02, 0.005]))
        depth = 4.0 + jnp.linspace(0.0, 2.0, height * width).reshape(height, width)
        # Bilinear sampling of an image that is its own pixel coordinates returns the sampled point.
        sampled, valid = inverse_warp(pixel_grid(height, width, jnp.float64), depth, T, K)
        points = transform_points(T, backproject(depth, K).reshape(-1, 3)).reshape(height, width, 3)
        uv, _ = project(points, K)
    mask = np.asarray(valid)
    assert mask.mean() > 0.5
    np.testing.assert_allclose(np.asarray(sampled)[mask], np.asarray(uv)[mask], atol=1e-9)


def test_vo_projection_is_the_camera_model() -> None:
    from dpc_jax.vo.motion import camera_pixels as vo_project

    rng = np.random.default_rng(0)
    points = rng.uniform([-5.0, -2.0, 3.0], [5.0, 2.0, 30.0], size=(50, 3))
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.05, 0.3]
    uv, in_front = vo_project(T, points, K_NP, offset_x=0.54)
    moved = points @ T[:3, :3].T + T[:3, 3] - np.array([0.54, 0.0, 0.0])
    expected, valid = project(jnp.asarray(moved[None]), jnp.asarray(K_NP))
    np.testing.assert_array_equal(in_front, np.asarray(valid)[0])
    np.testing.assert_allclose(uv, np.asarray(expected)[0], rtol=1e-12, atol=1e-9)
