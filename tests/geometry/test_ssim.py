"""SSIM against an independent float64 numpy loop with reflect-padded 3×3 windows."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dpc_jax.geometry.ssim import ssim, ssim_loss


def reflect(i: int, n: int) -> int:
    """Mirror index without repeating the edge: -1 -> 1, n -> n-2."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * (n - 1) - i
    return i


def ssim_reference(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    height, width, channels = x.shape
    out = np.empty_like(x)
    c1, c2 = 0.01**2, 0.03**2
    for v in range(height):
        for u in range(width):
            rows = [reflect(v + dv, height) for dv in (-1, 0, 1)]
            cols = [reflect(u + du, width) for du in (-1, 0, 1)]
            for c in range(channels):
                wx = np.array([x[r, q, c] for r in rows for q in cols])
                wy = np.array([y[r, q, c] for r in rows for q in cols])
                mx, my = wx.mean(), wy.mean()
                vx, vy = ((wx - mx) ** 2).mean(), ((wy - my) ** 2).mean()
                cov = ((wx - mx) * (wy - my)).mean()
                out[v, u, c] = (2 * mx * my + c1) * (2 * cov + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return out


def test_ssim_matches_numpy_reference() -> None:
    rng = np.random.default_rng(0)
    x = rng.random((6, 7, 2))
    y = np.clip(x + 0.2 * rng.standard_normal(x.shape), 0, 1)
    np.testing.assert_allclose(np.asarray(ssim(x, y)), ssim_reference(x, y), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ssim_loss(x, y)),
                               np.clip((1 - ssim_reference(x, y)) / 2, 0, 1), rtol=1e-10, atol=1e-12)


def test_ssim_batched_float32() -> None:
    rng = np.random.default_rng(1)
    x = rng.random((2, 3, 5, 4, 3)).astype(np.float32)
    y = rng.random((2, 3, 5, 4, 3)).astype(np.float32)
    out = jax.jit(ssim)(x, y)
    assert out.dtype == jnp.float32 and out.shape == x.shape
    np.testing.assert_allclose(np.asarray(out[1, 2]), ssim_reference(x[1, 2].astype(np.float64),
                                                                    y[1, 2].astype(np.float64)), atol=1e-5)


def test_ssim_identity_and_ranges() -> None:
    rng = np.random.default_rng(2)
    x = rng.random((8, 9, 3))
    np.testing.assert_allclose(np.asarray(ssim(x, x)), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ssim_loss(x, x)), 0.0, atol=1e-12)
    # Anti-correlated images give negative SSIM; the loss stays within [0, 1].
    for y in (1.0 - x, rng.random(x.shape), np.zeros_like(x), np.ones_like(x)):
        s = np.asarray(ssim(x, y))
        assert (s >= -1 - 1e-12).all() and (s <= 1 + 1e-12).all()
        loss = np.asarray(ssim_loss(x, y))
        assert (loss >= 0).all() and (loss <= 1).all()
    assert float(jnp.min(ssim(x, 1.0 - x))) < 0


@pytest.mark.parametrize("shape", [(2, 2, 1), (3, 5, 2), (5, 4, 1)])
def test_ssim_gradient_matches_finite_differences(shape: tuple[int, int, int]) -> None:
    # The backward pass is hand-written (custom VJP): check it, border pixels included, against
    # central differences of the numpy reference for both arguments.
    rng = np.random.default_rng(3)
    x, y, weights = rng.random(shape), rng.random(shape), rng.random(shape)
    grad_x, grad_y = jax.grad(lambda a, b: jnp.sum(ssim(a, b) * weights), argnums=(0, 1))(x, y)
    step = 1e-6
    for image, grad, which in ((x, grad_x, 0), (y, grad_y, 1)):
        numeric = np.empty(shape)
        for index in np.ndindex(shape):
            plus, minus = image.copy(), image.copy()
            plus[index] += step
            minus[index] -= step
            args_plus = (plus, y) if which == 0 else (x, plus)
            args_minus = (minus, y) if which == 0 else (x, minus)
            numeric[index] = np.sum((ssim_reference(*args_plus) - ssim_reference(*args_minus)) * weights) / (
                2 * step
            )
        np.testing.assert_allclose(np.asarray(grad), numeric, rtol=1e-6, atol=1e-6)


def test_ssim_constant_x_keeps_the_gradient_of_y() -> None:
    # grad_x=False (a data target) drops x's cotangent only: y's equals the full backward pass.
    rng = np.random.default_rng(4)
    x, y, weights = rng.random((6, 7, 3)), rng.random((6, 7, 3)), rng.random((6, 7, 3))

    def grads(grad_x: bool) -> tuple[jax.Array, jax.Array]:
        loss = lambda a, b: jnp.sum(ssim(a, b, grad_x=grad_x) * weights)
        return jax.jit(jax.grad(loss, argnums=(0, 1)))(x, y)

    full_x, full_y = grads(True)
    zero_x, only_y = grads(False)
    np.testing.assert_allclose(np.asarray(only_y), np.asarray(full_y), rtol=1e-12, atol=1e-14)
    assert not np.any(np.asarray(zero_x)) and np.any(np.asarray(full_x))
    np.testing.assert_array_equal(np.asarray(ssim(x, y, grad_x=False)), np.asarray(ssim(x, y)))


def test_ssim_gradient_finite_on_constant_images() -> None:
    x = jnp.full((4, 5, 3), 0.5)
    grad = jax.grad(lambda y: ssim_loss(x, y).sum())(jnp.full((4, 5, 3), 0.25))
    assert bool(jnp.isfinite(grad).all())


def test_ssim_shape_errors() -> None:
    with pytest.raises(ValueError, match="same shape"):
        ssim(np.ones((4, 5, 3)), np.ones((4, 6, 3)))
    with pytest.raises(ValueError, match="at least 2×2"):
        ssim(np.ones((1, 5, 3)), np.ones((1, 5, 3)))
