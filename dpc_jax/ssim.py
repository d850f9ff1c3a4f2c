"""Structural similarity (SSIM) per pixel, as used by the photometric losses (DESIGN §2).

Pure ``jnp``, batched over leading axes, dtype-preserving, differentiable.

Local statistics are 3×3 means (box filter, every neighbour weighted 1/9). At the image border
the window is completed by **reflect padding** (mirror without repeating the edge pixel, numpy's
``mode="reflect"``, PyTorch's ``ReflectionPad2d``), as in monodepth; the map therefore has the
size of the input and every border pixel gets a full 3×3 window.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

C1 = 0.01**2
C2 = 0.03**2


def _float(x: Array) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _box3(x: Array) -> Array:
    """3×3 mean over the spatial axes (-3, -2) of ``[..., H, W, C]`` with reflect padding."""
    pad = [(0, 0)] * (x.ndim - 3) + [(1, 1), (1, 1), (0, 0)]
    p = jnp.pad(x, pad, mode="reflect")
    height, width = x.shape[-3], x.shape[-2]
    rows = p[..., 0:height, :, :] + p[..., 1 : height + 1, :, :] + p[..., 2 : height + 2, :, :]
    cols = rows[..., 0:width, :] + rows[..., 1 : width + 1, :] + rows[..., 2 : width + 2, :]
    return cols / 9.0


def ssim(x: Array, y: Array, c1: float = C1, c2: float = C2) -> Array:
    """Per-pixel, per-channel SSIM of two images in [0, 1].

    ``SSIM = (2 μx μy + c1)(2 σxy + c2) / ((μx² + μy² + c1)(σx² + σy² + c2))`` with 3×3 local
    means, variances and covariance (population statistics, divisor 9).

    ``x``, ``y``: ``[..., H, W, C]`` with the same shape, ``H, W ≥ 2`` -> ``[..., H, W, C]``
    in [-1, 1].
    """
    x, y = _float(x), _float(y)
    if x.shape != y.shape or x.ndim < 3:
        raise ValueError(
            f"x and y must both be [..., H, W, C] with the same shape, got {x.shape} and {y.shape}"
        )
    if x.shape[-3] < 2 or x.shape[-2] < 2:
        raise ValueError(f"SSIM needs images of at least 2×2 pixels, got {x.shape}")
    dtype = jnp.result_type(x.dtype, y.dtype)
    x, y = x.astype(dtype), y.astype(dtype)
    mu_x, mu_y = _box3(x), _box3(y)
    var_x = _box3(x * x) - mu_x * mu_x
    var_y = _box3(y * y) - mu_y * mu_y
    cov = _box3(x * y) - mu_x * mu_y
    numerator = (2.0 * mu_x * mu_y + c1) * (2.0 * cov + c2)
    denominator = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    return numerator / denominator


def ssim_loss(x: Array, y: Array, c1: float = C1, c2: float = C2) -> Array:
    """Per-pixel, per-channel SSIM dissimilarity ``clip((1 − SSIM) / 2, 0, 1)`` (Zhang eq. 6).

    ``[..., H, W, C]`` -> ``[..., H, W, C]`` in [0, 1]; 0 where the images agree.
    """
    return jnp.clip((1.0 - ssim(x, y, c1, c2)) * 0.5, 0.0, 1.0)
