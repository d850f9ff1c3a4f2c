"""Differentiable image warping: bilinear sampling, temporal (rigid) and stereo warps.

Pure ``jnp`` functions, batched over leading axes, dtype-preserving, jit/vmap/grad-safe
(DESIGN §2). Images are ``[..., H, W, C]``; pixel coordinates are ``(x, y) = (column, row)``
with pixel centres at integers. Every warp returns the reconstruction and a bool validity mask;
reconstructed values at invalid pixels are meaningless (zero or a partial border blend) and must
be excluded by the caller.
"""

from __future__ import annotations

from typing import Literal

import jax.numpy as jnp
from jax import Array

from dpc_jax.camera import backproject, pixel_grid, project
from dpc_jax.lie import transform_points


def _float(x: Array) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _check_image(image: Array, name: str) -> None:
    if image.ndim < 3:
        raise ValueError(f"{name} must have shape [..., H, W, C], got {image.shape}")


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
    image, uv = image.astype(dtype), uv.astype(dtype)
    height, width, channels = image.shape[-3:]
    out_h, out_w = uv.shape[-3:-1]
    try:
        lead = jnp.broadcast_shapes(image.shape[:-3], uv.shape[:-3])
    except ValueError as error:
        raise ValueError(
            f"leading axes of image {image.shape} and uv {uv.shape} do not broadcast"
        ) from error

    finite = jnp.all(jnp.isfinite(uv), axis=-1)
    # Far outside the image, so every neighbour is outside and the sample is zero.
    uv = jnp.where(finite[..., None], uv, jnp.asarray(-2.0, dtype))
    x, y = uv[..., 0], uv[..., 1]
    valid = finite & (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)

    x0f, y0f = jnp.floor(x), jnp.floor(y)
    wx1, wy1 = x - x0f, y - y0f
    wx0, wy0 = 1.0 - wx1, 1.0 - wy1
    # Clamp before the integer cast so huge coordinates cannot overflow int32.
    x0 = jnp.clip(x0f, -2, width).astype(jnp.int32)
    y0 = jnp.clip(y0f, -2, height).astype(jnp.int32)

    flat = jnp.broadcast_to(image, (*lead, height, width, channels)).reshape(-1, height * width, channels)
    n = flat.shape[0]

    def corner(xi: Array, yi: Array, weight: Array) -> Array:
        inside = (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
        index = jnp.clip(yi, 0, height - 1) * width + jnp.clip(xi, 0, width - 1)
        index = jnp.broadcast_to(index, (*lead, out_h, out_w)).reshape(n, out_h * out_w)
        values = jnp.take_along_axis(flat, index[..., None], axis=1).reshape(*lead, out_h, out_w, channels)
        return values * jnp.where(inside, weight, jnp.zeros_like(weight))[..., None]

    sampled = (
        corner(x0, y0, wx0 * wy0)
        + corner(x0 + 1, y0, wx1 * wy0)
        + corner(x0, y0 + 1, wx0 * wy1)
        + corner(x0 + 1, y0 + 1, wx1 * wy1)
    )
    return sampled, jnp.broadcast_to(valid, (*lead, out_h, out_w))


def inverse_warp(
    source: Array, target_depth: Array, T_source_target: Array, K: Array, eps: float = 1e-3
) -> tuple[Array, Array]:
    """Reconstruct the target image from the source image (inverse compositional warp).

    Every target pixel is back-projected with the target depth, moved into the source frame
    with ``T_source_target`` (the exact 4×4 transform mapping target-frame points to
    source-frame points, e.g. ``inv(T*_{t+1,t})`` to rebuild frame t+1 from frame t), projected
    with ``K`` and looked up in ``source`` (DESIGN §2).

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
    height, width = target_depth.shape[-2:]
    points = backproject(target_depth, K)
    lead = points.shape[:-3]
    moved = transform_points(T_source_target, points.reshape(*lead, height * width, 3))
    uv, in_front = project(moved.reshape(*moved.shape[:-2], height, width, 3), K, eps)
    sampled, inside = bilinear_sample(source, uv)
    return sampled, inside & in_front


StereoDirection = Literal["right_to_left", "left_to_right"]


def stereo_warp(source: Array, disparity_px: Array, direction: StereoDirection) -> tuple[Array, Array]:
    """Reconstruct one image of a rectified stereo pair from the other (DESIGN §1–2).

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
    height, width = disparity_px.shape[-2:]
    grid = pixel_grid(height, width, dtype)
    shift = jnp.stack([sign * disparity_px, jnp.zeros_like(disparity_px)], axis=-1).astype(dtype)
    return bilinear_sample(source, grid + shift)


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
