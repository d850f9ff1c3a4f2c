"""Differentiable image warping: bilinear sampling, temporal (rigid) and stereo warps.

Pure ``jnp`` functions, batched over leading axes, dtype-preserving, jit/vmap/grad-safe
(docs/method.md §2). Images are ``[..., H, W, C]``; pixel coordinates are ``(x, y) = (column, row)``
with pixel centres at integers. Every warp returns the reconstruction and a bool validity mask;
reconstructed values at invalid pixels are meaningless (zero or a partial border blend) and must
be excluded by the caller.
"""

from __future__ import annotations

from typing import Literal, cast

import jax
import jax.numpy as jnp
from jax import Array, lax

from dpc_jax.geometry.projective import perspective_divide


def _float(x: Array) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _check_image(image: Array, name: str) -> None:
    if image.ndim < 3:
        raise ValueError(f"{name} must have shape [..., H, W, C], got {image.shape}")


def _patches(image: Array, row: Array, col: Array, rows: int) -> Array:
    """``rows × 2`` neighbourhoods of ``image`` ``[N, H, W, C]`` at integer top-left corners.

    ``row``, ``col``: int32 ``[N, P]`` (any values). The image is zero-padded by one pixel and
    the corners clamped into the padded image, so a neighbour outside the image reads zero as
    long as the corner lies within one pixel of it; farther corners read clamped pixels, which
    the caller weights by zero. One gather of ``rows·2·C`` contiguous-row values per point: XLA
    CPU spends its time per gathered index, so one patch beats four single-pixel gathers.
    Returns ``[N, P, rows, 2, C]``.
    """
    height, width, channels = image.shape[-3:]
    padded = jnp.pad(image, ((0, 0), (1, 1), (1, 1), (0, 0)))
    row = jnp.clip(row + 1, 0, height + 2 - rows)
    col = jnp.clip(col + 1, 0, width)

    def one(img: Array, r: Array, c: Array) -> Array:
        return lax.dynamic_slice(img, (r, c, jnp.zeros_like(r)), (rows, 2, channels))

    return jax.vmap(jax.vmap(one, in_axes=(None, 0, 0)))(padded, row, col)


def _flatten(image: Array, coords: list[Array]) -> tuple[Array, list[Array], tuple[int, ...]]:
    """Broadcast the leading axes of ``image`` ``[..., H, W, C]`` and ``coords`` ``[..., H', W']``
    against each other and flatten them: ``[N, H, W, C]``, ``[N, H'·W']`` each, leading shape."""
    try:
        lead = jnp.broadcast_shapes(image.shape[:-3], *(c.shape[:-2] for c in coords))
    except ValueError as error:
        raise ValueError(
            f"leading axes of image {image.shape} and coordinates {coords[0].shape[:-2]} do not broadcast"
        ) from error
    out_h, out_w = coords[0].shape[-2:]
    flat = jnp.broadcast_to(image, (*lead, *image.shape[-3:])).reshape(-1, *image.shape[-3:])
    return flat, [jnp.broadcast_to(c, (*lead, out_h, out_w)).reshape(-1, out_h * out_w) for c in coords], lead


def _sample(image: Array, x: Array, y: Array | None) -> tuple[Array, Array]:
    """Bilinear sampling at columns ``x`` and rows ``y`` (``None``: ``y`` = the output row, the
    exact 1-D interpolation along rows of a rectified stereo warp).

    ``image``: ``[..., H, W, C]``; ``x``, ``y``: ``[..., H', W']`` (``H' = H`` when ``y`` is None).
    Returns ``([..., H', W', C], valid [..., H', W'])``; see :func:`bilinear_sample`.
    """
    height, width, channels = image.shape[-3:]
    out_h, out_w = x.shape[-2:]
    dtype = image.dtype
    if y is None:
        finite = jnp.isfinite(x)
        x = jnp.where(finite, x, jnp.asarray(-2.0, dtype))
        valid = finite & (x >= 0) & (x <= width - 1)
        y = jnp.broadcast_to(jnp.arange(out_h, dtype=dtype)[:, None], x.shape)
        rows = 1
    else:
        finite = jnp.isfinite(x) & jnp.isfinite(y)
        # Far outside the image, so every neighbour is outside and the sample is zero.
        x = jnp.where(finite, x, jnp.asarray(-2.0, dtype))
        y = jnp.where(finite, y, jnp.asarray(-2.0, dtype))
        valid = finite & (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
        rows = 2
    x0f, y0f = jnp.floor(x), jnp.floor(y)
    wx1, wy1 = x - x0f, y - y0f
    # Clamp before the integer cast so huge coordinates cannot overflow int32.
    x0 = jnp.clip(x0f, -2, width).astype(jnp.int32)
    y0 = jnp.clip(y0f, -2, height).astype(jnp.int32)
    zero = jnp.zeros_like(wx1)

    def inside(index: Array, size: int) -> Array:
        return (index >= 0) & (index < size)

    wx = [jnp.where(inside(x0, width), 1.0 - wx1, zero), jnp.where(inside(x0 + 1, width), wx1, zero)]
    if rows == 1:
        weights = [[w] for w in wx]
    else:
        wy = [jnp.where(inside(y0, height), 1.0 - wy1, zero), jnp.where(inside(y0 + 1, height), wy1, zero)]
        weights = [[wx[j] * wy[i] for i in range(2)] for j in range(2)]

    flat, (row, col), lead = _flatten(image, [y0, x0])
    patches = _patches(flat, row, col, rows).reshape(*lead, out_h, out_w, rows, 2, channels)
    # sum() starts from the int 0, which the type checker keeps in the result's type; the generator
    # is never empty (rows >= 1), so the sum is an Array.
    sampled = cast(Array, sum(
        patches[..., i, j, :] * jnp.broadcast_to(weights[j][i], (*lead, out_h, out_w))[..., None]
        for i in range(rows)
        for j in range(2)
    ))
    return sampled, jnp.broadcast_to(valid, (*lead, out_h, out_w))


def bilinear_sample(image: Array, uv: Array) -> tuple[Array, Array]:
    """Sample ``image`` at real-valued pixel coordinates with bilinear interpolation.

    ``image``: ``[..., H, W, C]``; ``uv``: ``[..., H', W', 2]`` (x = column, y = row), leading
    axes broadcasting against those of ``image``. Returns ``sampled``: ``[..., H', W', C]`` and
    ``valid``: bool ``[..., H', W']``, true where ``0 ≤ x ≤ W−1`` and ``0 ≤ y ≤ H−1``.

    Neighbours outside the image count as zero, which is what
    ``cv2.remap(..., INTER_LINEAR, BORDER_CONSTANT, 0)`` does. Non-finite coordinates sample
    zero and are invalid. Differentiable with respect to ``image`` and ``uv`` (the gradient
    with respect to ``uv`` is that of the interpolation weights; it is piecewise constant and
    jumps at integer coordinates).
    """
    image, uv = _float(image), _float(uv)
    _check_image(image, "image")
    if uv.ndim < 3 or uv.shape[-1] != 2:
        raise ValueError(f"uv must have shape [..., H', W', 2], got {uv.shape}")
    dtype = jnp.result_type(image.dtype, uv.dtype)
    return _sample(image.astype(dtype), uv[..., 0].astype(dtype), uv[..., 1].astype(dtype))


def inverse_warp(
    source: Array, target_depth: Array, T_source_target: Array, K: Array, eps: float = 1e-3
) -> tuple[Array, Array]:
    """Reconstruct the target image from the source image (inverse compositional warp).

    Every target pixel is back-projected with the target depth, moved into the source frame
    with ``T_source_target`` (the exact 4×4 transform mapping target-frame points to
    source-frame points, e.g. ``inv(T*_{t+1,t})`` to rebuild frame t+1 from frame t), projected
    with ``K`` and looked up in ``source`` (docs/method.md §2).

    ``source``: ``[..., H, W, C]``; ``target_depth``: ``[..., H, W]`` (m);
    ``T_source_target``: ``[..., 4, 4]``; ``K``: ``[..., 3, 3]``, all leading axes broadcasting.
    Returns ``(reconstruction [..., H, W, C], valid bool [..., H, W])``; a pixel is invalid
    when its source-frame depth is ``≤ eps`` or it projects outside the source image.
    """
    source, target_depth = _float(source), _float(target_depth)
    T_source_target, K = _float(T_source_target), _float(K)
    _check_image(source, "source")
    if target_depth.ndim < 2 or target_depth.shape[-2:] != source.shape[-3:-1]:
        raise ValueError(
            f"target_depth {target_depth.shape} must be [..., H, W] matching source {source.shape}"
        )
    if T_source_target.ndim < 2 or T_source_target.shape[-2:] != (4, 4):
        raise ValueError(f"T_source_target must have shape [..., 4, 4], got {T_source_target.shape}")
    if K.ndim < 2 or K.shape[-2:] != (3, 3):
        raise ValueError(f"K must have shape [..., 3, 3], got {K.shape}")
    dtype = jnp.result_type(source.dtype, target_depth.dtype, T_source_target.dtype, K.dtype)
    height, width = target_depth.shape[-2:]
    # K R K⁻¹ and K t, per leading index: the projection of the moved point of pixel (u, v) with
    # depth d is d·(M [u, v, 1]ᵀ) + K t. Written out per coordinate: XLA CPU handles [..., 3]
    # minor axes (einsums, reductions over 3) many times slower than elementwise arithmetic.
    K = K.astype(dtype)
    M = K @ T_source_target[..., :3, :3].astype(dtype) @ jnp.linalg.inv(K)
    Kt = jnp.einsum("...ij,...j->...i", K, T_source_target[..., :3, 3].astype(dtype))
    u = jnp.arange(width, dtype=dtype)
    v = jnp.arange(height, dtype=dtype)[:, None]
    depth = target_depth.astype(dtype)

    def coordinate(i: int) -> Array:
        m = M[..., i, :, None, None]
        return depth * (m[..., 0, :, :] * u + m[..., 1, :, :] * v + m[..., 2, :, :]) + Kt[..., i, None, None]

    x, y, in_front = perspective_divide(coordinate(0), coordinate(1), coordinate(2), eps, jnp)
    sampled, inside = _sample(source.astype(dtype), x, y)
    return sampled, inside & in_front


StereoDirection = Literal["right_to_left", "left_to_right"]


def stereo_warp(source: Array, disparity_px: Array, direction: StereoDirection) -> tuple[Array, Array]:
    """Reconstruct one image of a rectified stereo pair from the other (docs/method.md §1–2).

    ``right_to_left``: ``source`` is the right image and ``disparity_px`` the left disparity,
    ``I_l*(u, v) = I_r(u − d_l(u, v), v)``. ``left_to_right``: ``source`` is the left image and
    ``disparity_px`` the right disparity, ``I_r*(u, v) = I_l(u + d_r(u, v), v)``.

    ``source``: ``[..., H, W, C]``; ``disparity_px``: ``[..., H, W]`` (pixels, ``fu · B / Z``).
    Returns ``(reconstruction [..., H, W, C], valid bool [..., H, W])``.
    """
    source, disparity_px = _float(source), _float(disparity_px)
    _check_image(source, "source")
    if disparity_px.ndim < 2 or disparity_px.shape[-2:] != source.shape[-3:-1]:
        raise ValueError(
            f"disparity_px {disparity_px.shape} must be [..., H, W] matching source {source.shape}"
        )
    if direction == "right_to_left":
        sign = -1.0
    elif direction == "left_to_right":
        sign = 1.0
    else:
        raise ValueError(f"direction must be 'right_to_left' or 'left_to_right', got {direction!r}")
    dtype = jnp.result_type(source.dtype, disparity_px.dtype)
    width = disparity_px.shape[-1]
    x = jnp.arange(width, dtype=dtype) + sign * disparity_px.astype(dtype)
    # Rows are integral, so this is exact 1-D linear interpolation along each row.
    return _sample(source.astype(dtype), x, None)


def disparity_consistency(
    disparity_left: Array, disparity_right: Array
) -> tuple[Array, Array, Array, Array]:
    """Left–right disparity consistency per pixel (Zhang et al. 2021, eq. 7–8).

    The right disparity is warped into the left view with the left disparity,
    ``d_r(u − d_l(u, v), v)``, and compared with ``d_l`` in L1; symmetrically the left
    disparity is warped into the right view with ``d_r``, ``d_l(u + d_r(u, v), v)``.

    Normalisation: the errors are divided by the image width ``W`` (disparity as a fraction of
    the width, as in Godard et al. 2017). A raw-pixel error would be tens of times larger than
    the photometric terms, which live in [0, 1], and would dominate the loss; with this choice
    an error of one pixel costs ``1/W``.

    ``disparity_left``, ``disparity_right``: ``[..., H, W]`` (pixels). Returns
    ``(error_left, valid_left, error_right, valid_right)``, each ``[..., H, W]``; errors are
    non-negative floats, validity masks are bool (the warped sample lies inside the image).
    Gradients flow through both disparity maps and the sampling positions.
    """
    disparity_left, disparity_right = _float(disparity_left), _float(disparity_right)
    if disparity_left.ndim < 2 or disparity_left.shape != disparity_right.shape:
        raise ValueError(
            f"disparity maps must both be [..., H, W] with the same shape, got "
            f"{disparity_left.shape} and {disparity_right.shape}"
        )
    width = disparity_left.shape[-1]
    right_in_left, valid_left = stereo_warp(disparity_right[..., None], disparity_left, "right_to_left")
    left_in_right, valid_right = stereo_warp(disparity_left[..., None], disparity_right, "left_to_right")
    error_left = jnp.abs(disparity_left - right_in_left[..., 0]) / width
    error_right = jnp.abs(disparity_right - left_in_right[..., 0]) / width
    return error_left, valid_left, error_right, valid_right
