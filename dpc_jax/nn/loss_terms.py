"""Building blocks of the self-supervised losses (docs/method.md §2 and §4): the photometric error,
masked and per-sample means, the explainability regulariser, ss-DPC-Net's rotation weights and
gradient mask, Stereo DPC's disparity-consistency terms.

Pure ``jnp`` functions of arrays, dtype-preserving, usable under ``jax.jit``; they are assembled
into the losses by :mod:`dpc_jax.nn.losses`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from dpc_jax.geometry.ssim import ssim_loss
from dpc_jax.geometry.warp import disparity_consistency

# ITU-R BT.601 luma weights, as in cv2.cvtColor(..., COLOR_RGB2GRAY).
_GREY_WEIGHTS = (0.299, 0.587, 0.114)


def to_unit_images(images: ArrayLike, dtype: jnp.dtype) -> Array:
    """uint8 images in [0, 255] -> ``dtype`` in [0, 1]; float images are only cast."""
    images = jnp.asarray(images)
    if jnp.issubdtype(images.dtype, jnp.integer):
        return images.astype(dtype) / 255.0
    return images.astype(dtype)


def photometric_error(
    target: Array, reconstruction: Array, ssim_weight: float | Array = 0.85, valid: Array | None = None
) -> Array:
    """Per-pixel photometric error ``λ_s · L_SSIM + (1 − λ_s) · |I − I*|``, channels averaged.

    ``target``, ``reconstruction``: ``[..., H, W, C]`` in [0, 1] -> ``[..., H, W]``.
    ``ssim_weight`` (λ_s) is a Python float (0 skips the SSIM computation) or a scalar array
    (a learned value, e.g. the sigmoid of a parameter). ``valid`` (bool ``[..., H, W]``): where
    given, invalid reconstructed pixels are replaced by the target before SSIM, so the zeros
    that the sampler puts outside the source image do not corrupt the 3×3 statistics of their
    valid neighbours (invalid pixels themselves are dropped later by :func:`masked_mean`).
    The target is data: no gradient flows into it through the SSIM term.
    """
    l1 = jnp.mean(jnp.abs(target - reconstruction), axis=-1)
    if isinstance(ssim_weight, (int, float)) and ssim_weight == 0:
        return l1
    if valid is not None:
        reconstruction = jnp.where(valid[..., None], reconstruction, target)
    structural = jnp.mean(ssim_loss(target, reconstruction, grad_x=False), axis=-1)
    return ssim_weight * structural + (1.0 - ssim_weight) * l1


def masked_mean(values: Array, valid: Array, weight: Array, scale: Array | None = None) -> Array:
    """``Σ w_b s_b v e / Σ w_b v`` over the batch and all pixels; 0 when nothing is valid.

    ``values`` (e), ``valid`` (v, bool or {0, 1}): ``[B, ...]``; ``weight`` (w): ``[B]`` sample
    weights (0 = padding); ``scale`` (s): optional ``[B]`` factors that multiply the numerator
    only (up-weighting without renormalising). Non-finite values at excluded pixels cannot leak
    into the result.
    """
    extra = (1,) * (values.ndim - 1)
    keep = (valid > 0) & (weight.reshape(-1, *extra) > 0)
    w = jnp.broadcast_to(weight.reshape(-1, *extra).astype(values.dtype), values.shape)
    if scale is not None:
        w_num = w * scale.reshape(-1, *extra).astype(values.dtype)
    else:
        w_num = w
    numerator = jnp.sum(jnp.where(keep, w_num * values, 0.0))
    denominator = jnp.sum(jnp.where(keep, w, 0.0))
    return jnp.where(denominator > 0, numerator / jnp.where(denominator > 0, denominator, 1.0), 0.0)


def explainability_loss(mask: Array, weight: Array, floor: float = 1e-6) -> Array:
    """``mean(−log W)`` over all pixels of real samples (cross-entropy against label 1).

    ``mask``: ``[B, ...]`` in (0, 1); ``weight``: ``[B]``. W is clamped to ``[floor, 1]``
    inside the log, so the loss is at most ``−log(floor)`` per pixel.
    """
    nll = -jnp.log(jnp.clip(mask, floor, 1.0))
    return masked_mean(nll, jnp.ones(mask.shape, dtype=bool), weight)


def rotation_weights(xi_vo: Array, threshold: float = 0.005, rot_weight: float = 4.0) -> Array:
    """Per-sample factor ``1 + λ_rot`` where ``‖φ_vo‖ ≥ γ``, else 1 (ss-DPC-Net eq. 10).

    ``xi_vo``: ``[B, 6]`` prior ``[ρ, φ]``; ``φ`` is ``Log(R_vo)``. -> ``[B]``.
    """
    angle = jnp.linalg.norm(xi_vo[..., 3:], axis=-1)
    return jnp.where(angle >= threshold, 1.0 + rot_weight, 1.0).astype(xi_vo.dtype)


def gradient_mask(image: Array, threshold: float = 0.03) -> Array:
    """High-gradient pixels ``(|∇x I| + |∇y I|) / 2 > γ_grad`` (ss-DPC-Net eq. 11).

    ``image``: ``[..., H, W, 3]`` RGB in [0, 1], converted to grey with BT.601 weights.
    Forward differences ``I(u+1, v) − I(u, v)`` and ``I(u, v+1) − I(u, v)``; the last column
    (row) has no forward neighbour and gets a zero x (y) difference. -> bool ``[..., H, W]``.
    """
    grey = jnp.tensordot(image, jnp.asarray(_GREY_WEIGHTS, dtype=image.dtype), axes=([-1], [0]))
    dx = jnp.abs(jnp.diff(grey, axis=-1, append=grey[..., -1:]))
    dy = jnp.abs(jnp.diff(grey, axis=-2, append=grey[..., -1:, :]))
    return 0.5 * (dx + dy) > threshold


def disparity_consistency_loss(
    disparity_left: Array, disparity_right: Array, weight: Array
) -> tuple[Array, Array]:
    """Left and right disparity-consistency terms (Zhang eq. 7–8), each a masked mean.

    ``disparity_*``: ``[B, ..., H, W]`` in pixels; errors are in units of the image width (see
    :func:`~dpc_jax.geometry.warp.disparity_consistency`). -> ``(L_disp^l, L_disp^r)``.
    """
    err_l, valid_l, err_r, valid_r = disparity_consistency(disparity_left, disparity_right)
    return masked_mean(err_l, valid_l, weight), masked_mean(err_r, valid_r, weight)


def per_sample_mean(values: Array, valid: Array) -> Array:
    """``Σ v e / Σ v`` over every axis but the first → ``[B]``; 0 for a sample with nothing valid."""
    axes = tuple(range(1, values.ndim))
    numerator = jnp.sum(jnp.where(valid, values, 0.0), axis=axes)
    count = jnp.sum(valid, axis=axes).astype(values.dtype)
    return jnp.where(count > 0, numerator / jnp.where(count > 0, count, 1.0), 0.0)
