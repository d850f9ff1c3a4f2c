"""Pinhole camera: intrinsics scaling, pixel grids, back-projection and projection.

Pure ``jnp`` functions, batched over leading axes and dtype-preserving. Conventions (docs/method.md §1):
``K = [[fu, 0, cu], [0, fv, cv], [0, 0, 1]]`` in pixels; pixel coordinates are ``(x, y) =
(column, row)`` with pixel centres at integers; camera frame x right, y down, z forward (metres).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from dpc_jax.geometry.projective import perspective_divide


def _float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _check_intrinsics(K: Array) -> None:
    if K.ndim < 2 or K.shape[-2:] != (3, 3):
        raise ValueError(f"K must have shape [..., 3, 3], got {K.shape}")


def scale_intrinsics(
    K: ArrayLike, sx: float | Array, sy: float | Array, half_pixel: bool = True
) -> Array:
    """Intrinsics of an image resized by ``(sx, sy)`` (new width = sx · old width).

    ``fu, fv`` (and the skew) are multiplied by ``sx``/``sy``. With pixel centres at integers, as
    here and in OpenCV's ``resize``, new pixel ``u'`` covers old ``(u' + ½)/s − ½``, so
    ``cu' = (cu + ½) sx − ½`` and ``cv' = (cv + ½) sy − ½`` (``half_pixel``). Without it the
    principal point is scaled like the focal length (the reference code's rule): 0.37 px off after
    376 → 96 columns, a rotation of the camera frame by 7 mrad about its y axis, which forward
    motion turns into 6 mm of sideways motion per metre.

    ``K``: ``[..., 3, 3]`` -> ``[..., 3, 3]``; ``sx``, ``sy`` scalars or arrays broadcasting
    against the leading axes.
    """
    K = _float(K)
    _check_intrinsics(K)
    sx = jnp.asarray(sx, dtype=K.dtype)
    sy = jnp.asarray(sy, dtype=K.dtype)
    one = jnp.ones_like(sx * sy)
    scale = jnp.stack([sx * one, sy * one, one], axis=-1)
    scaled = K * scale[..., :, None]
    if not half_pixel:
        return scaled
    shift = jnp.stack([0.5 * (sx - 1) * one, 0.5 * (sy - 1) * one, 0 * one], axis=-1)
    return scaled.at[..., :, 2].add(shift)


def pixel_grid(height: int, width: int, dtype: jnp.dtype = jnp.float32) -> Array:
    """Pixel coordinates ``[H, W, 2]``: ``grid[v, u] = (u, v)`` (x = column, y = row)."""
    xs = jnp.arange(width, dtype=dtype)
    ys = jnp.arange(height, dtype=dtype)
    return jnp.stack(jnp.meshgrid(xs, ys, indexing="xy"), axis=-1)


def backproject(depth: Array, K: Array) -> Array:
    """3-D points ``depth(u, v) · K⁻¹ [u, v, 1]ᵀ`` of every pixel.

    ``depth``: ``[..., H, W]`` z-depth in metres; ``K``: ``[..., 3, 3]`` whose leading axes
    broadcast against those of ``depth`` -> points ``[..., H, W, 3]`` in the camera frame.
    """
    depth, K = _float(depth), _float(K)
    _check_intrinsics(K)
    if depth.ndim < 2:
        raise ValueError(f"depth must have shape [..., H, W], got {depth.shape}")
    dtype = jnp.result_type(depth.dtype, K.dtype)
    height, width = depth.shape[-2:]
    grid = pixel_grid(height, width, dtype)
    homogeneous = jnp.concatenate([grid, jnp.ones((height, width, 1), dtype)], axis=-1)
    rays = jnp.einsum("...ij,hwj->...hwi", jnp.linalg.inv(K.astype(dtype)), homogeneous)
    return rays * depth[..., None]


def project(points: Array, K: Array, eps: float = 1e-3) -> tuple[Array, Array]:
    """Pixel coordinates of 3-D points and a mask of points in front of the camera.

    ``points``: ``[..., H, W, 3]`` (camera frame, metres; any two spatial axes);
    ``K``: ``[..., 3, 3]`` broadcasting against the leading axes of ``points``.
    Returns ``uv``: ``[..., H, W, 2]`` (x = column, y = row) and ``valid``: bool ``[..., H, W]``,
    true where ``z > eps``. Where ``z ≤ eps`` the division uses 1 instead of ``z``, so ``uv``
    and its gradient stay finite there; such pixels must be discarded through ``valid``
    (:func:`dpc_jax.geometry.projective.perspective_divide`).
    """
    points, K = _float(points), _float(K)
    _check_intrinsics(K)
    if points.ndim < 3 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape [..., H, W, 3], got {points.shape}")
    dtype = jnp.result_type(points.dtype, K.dtype)
    pixels = jnp.einsum("...ij,...hwj->...hwi", K.astype(dtype), points.astype(dtype))
    u, v, valid = perspective_divide(pixels[..., 0], pixels[..., 1], pixels[..., 2], eps, jnp)
    return jnp.stack([u, v], axis=-1), valid
