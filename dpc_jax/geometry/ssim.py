"""Structural similarity (SSIM) per pixel, as used by the photometric losses (docs/method.md §2).

Pure ``jnp``, batched over leading axes, dtype-preserving, differentiable.

Local statistics are 3×3 means (box filter, every neighbour weighted 1/9). At the image border
the window is completed by **reflect padding** (mirror without repeating the edge pixel, numpy's
``mode="reflect"``, PyTorch's ``ReflectionPad2d``), as in monodepth; the map therefore has the
size of the input and every border pixel gets a full 3×3 window.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import Array, lax

C1 = 0.01**2
C2 = 0.03**2


def _float(x: Array) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _window_sum(x: Array, axes: tuple[int, int]) -> Array:
    """Sums over 3×3 windows, VALID: ``[..., H+2, W+2, ...]`` -> ``[..., H, W, ...]`` on ``axes``.

    Two separable 1-D ``reduce_window`` ops: XLA CPU never fuses a reduce-window into its
    consumers, so its operand is computed once, whereas sums of shifted slices of an
    elementwise chain are re-evaluated at every shift (9× for a 3×3 window) and, in the
    backward pass, nested into each other.
    """
    for axis in axes:
        window = tuple(3 if i == axis else 1 for i in range(x.ndim))
        x = lax.reduce_window(x, 0.0, lax.add, window, (1,) * x.ndim, "VALID")
    return x


def _spatial_pad(x: Array, width: int, mode: str) -> Array:
    """Pad the spatial axes (-3, -2) of ``[..., H, W, C]`` by ``width`` on both sides."""
    return jnp.pad(x, [(0, 0)] * (x.ndim - 3) + [(width, width), (width, width), (0, 0)], mode=mode)


def _unreflect(g: Array, axis: int) -> Array:
    """Adjoint of 1-pixel reflect padding along ``axis``: ``[.., n+2, ..]`` -> ``[.., n, ..]``.

    Padded entry 0 is a copy of entry 1 and padded entry n+1 a copy of entry n−2, so their
    cotangents are added there.
    """
    n = g.shape[axis] - 2
    zero = jnp.zeros((), g.dtype)

    def spread(start: int, low: int, high: int) -> Array:
        config = [(low, high, 0) if i == axis else (0, 0, 0) for i in range(g.ndim)]
        return lax.pad(lax.slice_in_dim(g, start, start + 1, axis=axis), zero, config)

    return lax.slice_in_dim(g, 1, n + 1, axis=axis) + spread(0, 1, n - 2) + spread(n + 1, n - 2, 1)


def _moments(x: Array, y: Array) -> Array:
    """3×3 reflect-padded means of ``x, y, x², y², xy``: ``[5, ..., H, W, C]``."""
    # Pad the two images, not the five products: one pass less over five maps.
    xp, yp = _spatial_pad(x, 1, "reflect"), _spatial_pad(y, 1, "reflect")
    stacked = jnp.stack([xp, yp, xp * xp, yp * yp, xp * yp])
    return _window_sum(stacked, (stacked.ndim - 3, stacked.ndim - 2)) / 9.0


def _terms(moments: Array, c1: float, c2: float) -> tuple[Array, Array, Array, Array]:
    """Luminance and contrast-structure numerator and denominator factors ``(a1, a2, b1, b2)``."""
    mu_x, mu_y, xx, yy, xy = moments
    a1 = 2.0 * mu_x * mu_y + c1
    a2 = 2.0 * (xy - mu_x * mu_y) + c2
    b1 = mu_x * mu_x + mu_y * mu_y + c1
    b2 = (xx - mu_x * mu_x) + (yy - mu_y * mu_y) + c2
    return a1, a2, b1, b2


@partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4))
def _ssim(x: Array, y: Array, c1: float, c2: float, grad_x: bool) -> Array:
    a1, a2, b1, b2 = _terms(_moments(x, y), c1, c2)
    return (a1 * a2) / (b1 * b2)


def _ssim_fwd(
    x: Array, y: Array, c1: float, c2: float, grad_x: bool
) -> tuple[Array, tuple[Array, Array, Array]]:
    moments = _moments(x, y)
    a1, a2, b1, b2 = _terms(moments, c1, c2)
    return (a1 * a2) / (b1 * b2), (x, y, moments)


def _ssim_bwd(
    c1: float, c2: float, grad_x: bool, residuals: tuple[Array, Array, Array], g: Array
) -> tuple[Array, Array]:
    """Hand-written backward pass (XLA fuses JAX's own into a many-fold recomputation).

    With ``S = a1 a2 / (b1 b2)``: cotangents of the five local means, then the adjoint of the
    reflect-padded box filter (zero-padded box filter, then :func:`_unreflect`), then the chain
    rule through ``x², y², xy``. Without ``grad_x`` the cotangent of ``x`` is zero and its
    local-mean cotangent is not filtered (a quarter less work).
    """
    x, y, moments = residuals
    mu_x, mu_y = moments[0], moments[1]
    a1, a2, b1, b2 = _terms(moments, c1, c2)
    inv = 1.0 / (b1 * b2)
    s = a1 * a2 * inv
    g_a1, g_a2 = g * a2 * inv, g * a1 * inv
    g_b1, g_b2 = -g * s / b1, -g * s / b2
    d_a, d_b = g_a1 - g_a2, g_b1 - g_b2
    # Cotangents of (μy, E[x²] = E[y²], E[xy](, μx)); E[x²] and E[y²] share theirs.
    parts = [2.0 * (mu_x * d_a + mu_y * d_b), g_b2, 2.0 * g_a2]
    if grad_x:
        parts.append(2.0 * (mu_y * d_a + mu_x * d_b))
    cotangents = jnp.stack(parts)
    h_axis, w_axis = cotangents.ndim - 3, cotangents.ndim - 2
    summed = _window_sum(_spatial_pad(cotangents / 9.0, 2, "constant"), (w_axis, h_axis))
    g_mu_y, g_sq, g_xy, *g_mu_x = _unreflect(_unreflect(summed, w_axis), h_axis)
    g_y = g_mu_y + 2.0 * y * g_sq + x * g_xy
    if not grad_x:
        return jnp.zeros_like(x), g_y
    return g_mu_x[0] + 2.0 * x * g_sq + y * g_xy, g_y


_ssim.defvjp(_ssim_fwd, _ssim_bwd)


def ssim(x: Array, y: Array, c1: float = C1, c2: float = C2, *, grad_x: bool = True) -> Array:
    """Per-pixel, per-channel SSIM of two images in [0, 1].

    ``SSIM = (2 μx μy + c1)(2 σxy + c2) / ((μx² + μy² + c1)(σx² + σy² + c2))`` with 3×3 local
    means, variances and covariance (population statistics, divisor 9).

    ``x``, ``y``: ``[..., H, W, C]`` with the same shape, ``H, W ≥ 2`` -> ``[..., H, W, C]``
    in [-1, 1]. Reverse-mode differentiable (custom VJP; forward mode is not supported);
    ``c1``, ``c2`` are Python floats, not differentiated. ``grad_x=False`` treats ``x`` as a
    constant (its gradient is zero), which saves a quarter of the backward pass when ``x`` is
    data, e.g. the target image of a photometric loss.
    """
    x, y = _float(x), _float(y)
    if x.shape != y.shape or x.ndim < 3:
        raise ValueError(
            f"x and y must both be [..., H, W, C] with the same shape, got {x.shape} and {y.shape}"
        )
    if x.shape[-3] < 2 or x.shape[-2] < 2:
        raise ValueError(f"SSIM needs images of at least 2×2 pixels, got {x.shape}")
    dtype = jnp.result_type(x.dtype, y.dtype)
    return _ssim(x.astype(dtype), y.astype(dtype), float(c1), float(c2), grad_x)


def ssim_loss(x: Array, y: Array, c1: float = C1, c2: float = C2, *, grad_x: bool = True) -> Array:
    """Per-pixel, per-channel SSIM dissimilarity ``clip((1 − SSIM) / 2, 0, 1)`` (Zhang eq. 6).

    ``[..., H, W, C]`` -> ``[..., H, W, C]`` in [0, 1]; 0 where the images agree. ``grad_x``
    as in :func:`ssim`.
    """
    return jnp.clip((1.0 - ssim(x, y, c1, c2, grad_x=grad_x)) * 0.5, 0.0, 1.0)
