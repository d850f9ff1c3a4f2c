"""Self-supervised losses of ss-DPC-Net and Stereo DPC (docs/method.md §2 and §4), their per-pair
errors for epoch selection and the acceptance test, and :func:`dpc_loss`, the training loss a config
names (DPC-Net's supervised loss is :mod:`dpc_jax.nn.supervised_loss`).

Pure ``jnp`` functions of a :class:`~dpc_jax.nn.outputs.DPCOutputs` and a
:class:`~dpc_jax.nn.batch.Batch`; they never import the models. They work under ``jax.jit`` (pass
the config as a static argument or close over it: it is a frozen, hashable dataclass) and are
dtype-preserving: the computation runs in the dtype of ``outputs.left.inv_depth`` (float32 in
training). Images arrive as uint8 and are divided by 255; float images are taken to be in
[0, 1] already (the tests pass exact float renderings).

Averaging: every term is a mean over *valid* pixels of *real* samples. A pixel that left the
source image or fell behind the camera, and every pixel of a padding sample
(``batch.weight == 0``), contributes nothing to the numerator or the denominator; samples are
weighted by ``batch.weight``. Explainability masks multiply the per-pixel error but do not enter
the denominator (the mask regulariser keeps them from collapsing to zero).

Relative poses: ``T_vo = Exp(ξ_vo)`` is ``T_{t+1,t}``, mapping frame-t points into frame t+1,
and ``T* = Exp(ξ_corr) · T_vo`` (:func:`~dpc_jax.geometry.pose_correction.apply_correction`). Reconstructing
frame t+1 from frame t therefore needs ``T_{t,t+1} = inv(T*)``, computed exactly.
"""

from __future__ import annotations

from typing import cast

import jax.numpy as jnp
import numpy as np
from jax import Array

from dpc_jax.geometry.lie import se3_exp, se3_inverse
from dpc_jax.geometry.pose_correction import apply_correction
from dpc_jax.geometry.warp import inverse_warp, stereo_warp
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.loss_terms import (
    disparity_consistency_loss,
    explainability_loss,
    gradient_mask,
    masked_mean,
    per_sample_mean,
    photometric_error,
    rotation_weights,
    to_unit_images,
)
from dpc_jax.nn.model_config import SSDPCLossConfig, StereoDPCLossConfig, SupervisedLossConfig
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs
from dpc_jax.nn.supervised_loss import supervised_dpc_loss


def _ssim_weight(outputs: DPCOutputs, fixed: float) -> float | Array:
    return fixed if outputs.ssim_weight is None else outputs.ssim_weight


def _check_branch(branch: BranchOutputs, frames: int, images: Array, name: str) -> None:
    expected = (images.shape[0], frames, *images.shape[2:4])
    for field in ("inv_depth", "mask"):
        shape = getattr(branch, field).shape
        if tuple(shape) != expected:
            raise ValueError(f"{name}.{field} has shape {tuple(shape)}, expected {expected} [B, F, H, W]")


def _corrected_pose(outputs: DPCOutputs, batch: Batch, rotation_only: bool, dtype: jnp.dtype) -> Array:
    """``T*_{t+1,t}`` ``[B, 4, 4]``."""
    T_vo = se3_exp(jnp.asarray(batch.xi_vo).astype(dtype))
    return apply_correction(jnp.asarray(outputs.xi_corr).astype(dtype), T_vo, rotation_only)


# --- ss-DPC-Net ---------------------------------------------------------------------------------


def _ss_dpc_reconstruction(
    outputs: DPCOutputs, batch: Batch, config: SSDPCLossConfig
) -> tuple[Array, Array, Array, Array]:
    """Target t+1, its reconstruction from t, validity, and dtype-cast weights."""
    dtype = outputs.left.inv_depth.dtype
    left = to_unit_images(batch.left, dtype)
    _check_branch(outputs.left, 1, left, "outputs.left")
    target, source = left[:, 1], left[:, 0]
    T_star = _corrected_pose(outputs, batch, config.rotation_only, dtype)
    K = jnp.asarray(batch.intrinsics).astype(dtype)
    recon, valid = inverse_warp(source, 1.0 / outputs.left.inv_depth[:, 0], se3_inverse(T_star), K,
                                config.depth_eps)
    return target, recon, valid, jnp.asarray(batch.weight).astype(dtype)


def ss_dpc_loss(outputs: DPCOutputs, batch: Batch, config: SSDPCLossConfig) -> tuple[Array, dict[str, Array]]:
    """ss-DPC-Net loss (docs/method.md §4, Wagstaff et al. eq. 7–10). Single scale, left camera only.

    Target = frame t+1 (``batch.left[:, 1]``), source = frame t (``batch.left[:, 0]``), target
    depth ``1 / outputs.left.inv_depth[:, 0]``, mask ``W = outputs.left.mask[:, 0]``.
    ``loss = masked_mean(W · e) · (1 + λ_rot)[large rotation] + λ_exp · mean(−log W)`` with
    ``e`` the per-pixel photometric error (L1 unless ``ssim_weight`` says otherwise).

    Returns ``(loss, metrics)``; metrics: ``loss``, ``photometric`` (after rotation weighting),
    ``explainability``, ``valid_fraction``, ``ssim_weight``.
    """
    target, recon, valid, weight = _ss_dpc_reconstruction(outputs, batch, config)
    mask = outputs.left.mask[:, 0]
    ssim_weight = _ssim_weight(outputs, config.ssim_weight)
    error = photometric_error(target, recon, ssim_weight, valid)
    scale = rotation_weights(jnp.asarray(batch.xi_vo).astype(error.dtype), config.rot_threshold,
                             config.rot_weight)
    photometric = masked_mean(mask * error, valid, weight, scale)
    explainability = explainability_loss(mask, weight, config.mask_floor)
    loss = photometric + config.exp_weight * explainability
    metrics = {
        "loss": loss,
        "photometric": photometric,
        "explainability": explainability,
        "valid_fraction": masked_mean(valid.astype(error.dtype), jnp.ones_like(valid), weight),
        "ssim_weight": jnp.asarray(ssim_weight, dtype=error.dtype),
    }
    return loss, metrics


# --- Stereo DPC ---------------------------------------------------------------------------------


def _left_to_right(baseline: Array) -> Array:
    """Extrinsic ``C`` ``[B, 4, 4]`` mapping left-camera points to right-camera points."""
    translation = jnp.stack([-baseline, jnp.zeros_like(baseline), jnp.zeros_like(baseline)], axis=-1)
    eye = jnp.broadcast_to(jnp.eye(4, dtype=baseline.dtype), (*baseline.shape, 4, 4))
    return eye.at[..., :3, 3].set(translation)


def _stereo_temporal(
    images: Array, branch: BranchOutputs, T_star: Array, K: Array, eps: float
) -> tuple[tuple[Array, Array, Array], tuple[Array, Array, Array]]:
    """Both temporal reconstructions of one camera.

    Returns ``((target k+1, recon of k+1 from k, valid), (target k, recon of k from k+1, valid))``.
    """
    depth = 1.0 / branch.inv_depth
    recon_k1, valid_k1 = inverse_warp(images[:, 0], depth[:, 1], se3_inverse(T_star), K, eps)
    recon_k, valid_k = inverse_warp(images[:, 1], depth[:, 0], T_star, K, eps)
    return (images[:, 1], recon_k1, valid_k1), (images[:, 0], recon_k, valid_k)


def _stereo_setup(
    outputs: DPCOutputs, batch: Batch, config: StereoDPCLossConfig
) -> tuple[Array, Array, Array, Array, dict[str, Array], Array]:
    """Unit images, intrinsics, weights and per-camera ``T*`` for the stereo loss."""
    if outputs.right is None:
        raise ValueError("stereo_dpc_loss needs outputs.right (a StereoDPC model's outputs)")
    dtype = outputs.left.inv_depth.dtype
    left = to_unit_images(batch.left, dtype)
    right = to_unit_images(batch.right, dtype)
    _check_branch(outputs.left, 2, left, "outputs.left")
    _check_branch(outputs.right, 2, right, "outputs.right")
    K = jnp.asarray(batch.intrinsics).astype(dtype)
    baseline = jnp.asarray(batch.baseline).astype(dtype)
    T_star = _corrected_pose(outputs, batch, config.rotation_only, dtype)
    # The rig is rigid: the right camera's motion is the left one's conjugated by the extrinsic.
    C = _left_to_right(baseline)
    poses = {"left": T_star, "right": C @ T_star @ se3_inverse(C)}
    return left, right, K, baseline, poses, jnp.asarray(batch.weight).astype(dtype)


def stereo_dpc_loss(
    outputs: DPCOutputs, batch: Batch, config: StereoDPCLossConfig
) -> tuple[Array, dict[str, Array]]:
    """Stereo DPC loss (docs/method.md §4, Zhang et al. eq. 14).

    ``α1 (L^l + L^r) + α2 (L_disp^l + L_disp^r) + α3 Σ temporal + α4 L_exp``:

    * spatial ``L^l``: left images of frames k and k+1 rebuilt from the right ones with
      ``d_l = fu · B · inv_depth_l``, photometric error (SSIM + L1), one masked mean over both
      frames; ``L^r`` symmetrically with ``d_r``. No explainability mask.
    * disparity consistency of both cameras over both frames, in units of the image width.
    * temporal, per camera: frame k+1 rebuilt from k with the depth of k+1 and ``inv(T*)``,
      weighted by the mask of k+1; frame k rebuilt from k+1 with the depth of k and ``T*``,
      weighted by the mask of k. The right camera uses ``C T* C⁻¹`` (``C`` = left→right
      extrinsic, a translation by ``−B`` along x), exact for a rigid rig.
    * ``L_exp``: the sum over the four masks (left/right × k/k+1) of ``mean(−log W)``, one
      regulariser per mask-weighted temporal term.

    Returns ``(loss, metrics)``; metrics hold every term separately plus ``loss`` and
    ``ssim_weight``.
    """
    left, right, K, baseline, poses, weight = _stereo_setup(outputs, batch, config)
    assert outputs.right is not None  # _stereo_setup raised otherwise
    ssim_weight = _ssim_weight(outputs, config.ssim_weight)
    a_spatial, a_disp, a_temporal, a_exp = config.alpha

    focal_baseline = (K[:, 0, 0] * baseline)[:, None, None, None]
    disp_l = focal_baseline * outputs.left.inv_depth
    disp_r = focal_baseline * outputs.right.inv_depth
    recon_l, valid_l = stereo_warp(right, disp_l, "right_to_left")
    recon_r, valid_r = stereo_warp(left, disp_r, "left_to_right")
    metrics = {
        "spatial_left": masked_mean(photometric_error(left, recon_l, ssim_weight, valid_l), valid_l, weight),
        "spatial_right": masked_mean(
            photometric_error(right, recon_r, ssim_weight, valid_r), valid_r, weight
        ),
    }
    metrics["disparity_left"], metrics["disparity_right"] = disparity_consistency_loss(disp_l, disp_r, weight)

    temporal_names = []
    explainability = jnp.zeros((), left.dtype)
    for camera, images, branch in (("left", left, outputs.left), ("right", right, outputs.right)):
        forward, backward = _stereo_temporal(images, branch, poses[camera], K, config.depth_eps)
        for (target, recon, valid), mask, name in (
            (forward, branch.mask[:, 1], f"temporal_{camera}_k_to_k1"),
            (backward, branch.mask[:, 0], f"temporal_{camera}_k1_to_k"),
        ):
            error = photometric_error(target, recon, ssim_weight, valid)
            metrics[name] = masked_mean(mask * error, valid, weight)
            temporal_names.append(name)
            explainability = explainability + explainability_loss(mask, weight, config.mask_floor)
    metrics["explainability"] = explainability

    loss = (
        a_spatial * (metrics["spatial_left"] + metrics["spatial_right"])
        + a_disp * (metrics["disparity_left"] + metrics["disparity_right"])
        + a_temporal * sum(metrics[name] for name in temporal_names)
        + a_exp * explainability
    )
    metrics["loss"] = loss
    metrics["ssim_weight"] = jnp.asarray(ssim_weight, dtype=left.dtype)
    return loss, metrics


def dpc_loss(
    outputs: DPCOutputs, batch: Batch, config: SSDPCLossConfig | StereoDPCLossConfig | SupervisedLossConfig
) -> tuple[Array, dict[str, Array]]:
    """The training loss the config names: :func:`ss_dpc_loss`, :func:`stereo_dpc_loss` or
    :func:`supervised_dpc_loss`."""
    if isinstance(config, SSDPCLossConfig):
        return ss_dpc_loss(outputs, batch, config)
    if isinstance(config, StereoDPCLossConfig):
        return stereo_dpc_loss(outputs, batch, config)
    if isinstance(config, SupervisedLossConfig):
        return supervised_dpc_loss(outputs, batch, config)
    raise TypeError(
        "config must be SSDPCLossConfig, StereoDPCLossConfig or SupervisedLossConfig, "
        f"got {type(config).__name__}"
    )


# --- epoch selection and the acceptance test -----------------------------------------------------


def _valid_depth(depth_valid: Array | None, frame: int) -> Array | bool:
    return True if depth_valid is None else jnp.asarray(depth_valid)[:, frame] > 0


def temporal_pair_errors(
    outputs: DPCOutputs,
    batch: Batch,
    config: SSDPCLossConfig | StereoDPCLossConfig,
    depth_valid: tuple[Array | None, Array | None] | None = None,
) -> Array:
    """Per-sample photometric error of the temporal reconstructions on high-gradient pixels → ``[B]``.

    The ss-DPC-Net selection criterion (§IV) per frame pair: the per-pixel photometric error of
    the temporal reconstruction (λ_s as in the training loss) averaged over pixels that are valid
    *and* in the :func:`gradient_mask` of the target image. No explainability mask and no
    rotation weighting: it measures geometric agreement only, so a model cannot lower it by
    masking pixels out. :class:`SSDPCLossConfig`: frame t+1 rebuilt from t (left camera);
    :class:`StereoDPCLossConfig`: the mean of the four temporal terms (both cameras, both
    directions). ``depth_valid`` (optional, ``(left, right)`` ``[B, F, H, W]``): pixels whose
    depth is unknown (e.g. an external stereo depth's holes) are left out. Padding samples are
    not special-cased here (weight them downstream).
    """
    left_valid, right_valid = depth_valid if depth_valid is not None else (None, None)
    if isinstance(config, SSDPCLossConfig):
        target, recon, valid, _ = _ss_dpc_reconstruction(outputs, batch, config)
        error = photometric_error(target, recon, _ssim_weight(outputs, config.ssim_weight), valid)
        keep = valid & _valid_depth(left_valid, 0) & gradient_mask(target, config.grad_threshold)
        return per_sample_mean(error, keep)
    if not isinstance(config, StereoDPCLossConfig):
        raise TypeError(f"config must be SSDPCLossConfig or StereoDPCLossConfig, got {type(config).__name__}")
    left, right, K, _, poses, _ = _stereo_setup(outputs, batch, config)
    assert outputs.right is not None  # _stereo_setup raised otherwise
    ssim_weight = _ssim_weight(outputs, config.ssim_weight)
    terms: list[Array] = []
    cameras = (("left", left, outputs.left, left_valid), ("right", right, outputs.right, right_valid))
    for camera, images, branch, depth_ok in cameras:
        forward, backward = _stereo_temporal(images, branch, poses[camera], K, config.depth_eps)
        # The forward term uses the depth of frame k+1, the backward one that of frame k.
        for (target, recon, valid), frame in ((forward, 1), (backward, 0)):
            error = photometric_error(target, recon, ssim_weight, valid)
            keep = valid & _valid_depth(depth_ok, frame) & gradient_mask(target, config.grad_threshold)
            terms.append(per_sample_mean(error, keep))
    # sum() starts from the int 0, which the type checker keeps in the result's type; there are
    # always four terms, so the sum is an Array.
    return cast(Array, sum(terms)) / len(terms)


def gradient_loss(
    outputs: DPCOutputs, batch: Batch, config: SSDPCLossConfig | StereoDPCLossConfig
) -> Array:
    """The gradient loss of a batch (ss-DPC-Net §IV, epoch selection): the ``batch.weight``-weighted
    mean over samples of :func:`temporal_pair_errors`. Returns a scalar; padding samples
    (weight 0) contribute nothing."""
    errors = temporal_pair_errors(outputs, batch, config)
    weight = jnp.asarray(batch.weight).astype(errors.dtype)
    total = jnp.sum(weight)
    return jnp.where(total > 0, jnp.sum(weight * errors) / jnp.where(total > 0, total, 1.0), 0.0)


def with_stereo_depth(
    outputs: DPCOutputs, depth: tuple[Array | np.ndarray, Array | np.ndarray]
) -> tuple[DPCOutputs, tuple[Array, Array]]:
    """``outputs`` with an independent stereo depth in place of both branches' → ``(outputs, valid)``.

    ``depth``: ``(inverse depth (1/m), valid)`` ``[B, camera, frame, H, W]``
    (``Batch.stereo_depth``). Holes get inverse depth 1 (any finite value would do) and are left
    out of every term through ``valid = (valid_left, valid_right)`` ``[B, frame, H, W]``, the
    ``depth_valid`` of :func:`correction_deltas` and :func:`temporal_pair_errors`.
    """
    if outputs.right is None:
        raise ValueError("a stereo depth replaces both cameras' depth: it needs Stereo DPC's outputs")
    inverse, ok = jnp.asarray(depth[0]), jnp.asarray(depth[1])
    left = outputs.left._replace(inv_depth=jnp.where(ok[:, 0], inverse[:, 0], 1.0))
    right = outputs.right._replace(inv_depth=jnp.where(ok[:, 1], inverse[:, 1], 1.0))
    return outputs._replace(left=left, right=right), (ok[:, 0], ok[:, 1])


def correction_deltas(
    outputs: DPCOutputs,
    batch: Batch,
    config: SSDPCLossConfig | StereoDPCLossConfig,
    depth_valid: tuple[Array | None, Array | None] | None = None,
    names: tuple[str, ...] = ("full", "rotation"),
) -> dict[str, Array]:
    """Paired effect of the network's correction per sample: ``Δ = L(ξ_corr) − L(0)`` → ``{name: [B]}``.

    ``L`` is :func:`temporal_pair_errors` with the *same* depth and validity in every term, so Δ
    isolates the pose: ``full`` applies ξ_corr as the loss config does (only its rotation with
    ``rotation_only``), ``rotation`` only its rotation part ``[0, φ]``; ``none`` is ``L(0)`` itself
    (the prior). Δ < 0: the corrected pose explains the images better than the prior. What the
    validation of an epoch reads; any other correction is measured by :func:`candidate_deltas`.
    ``names``: which of ``full`` and ``rotation`` are measured.
    """
    xi = jnp.asarray(outputs.xi_corr)
    made = {"full": xi, "rotation": jnp.concatenate([jnp.zeros_like(xi[:, :3]), xi[:, 3:]], axis=-1)}
    deltas = candidate_deltas(outputs, batch, config, jnp.stack([made[n] for n in names]), depth_valid)
    return {"none": deltas["none"], **{n: deltas["delta"][i] for i, n in enumerate(names)}}


def candidate_deltas(
    outputs: DPCOutputs,
    batch: Batch,
    config: SSDPCLossConfig | StereoDPCLossConfig,
    candidates: Array,
    depth_valid: tuple[Array | None, Array | None] | None = None,
    none: Array | None = None,
) -> dict[str, Array]:
    """Δ of each of ``C`` candidate corrections per sample → ``{"none": L(0) [B], "delta": [C, B]}``.

    ``candidates``: ``[C, B, 6]`` corrections ``[ρ (m), φ (rad)]`` put in place of
    ``outputs.xi_corr`` one at a time, with the outputs' depth (or the independent one whose
    validity is ``depth_valid``, :func:`with_stereo_depth`); ``Δ_c = L(ξ_c) − L(0)`` with
    :func:`temporal_pair_errors`, exactly 0 where the candidate moves no pose. ``none``: ``L(0)``
    ``[B]`` when already measured with this depth, which spares its evaluation.
    """
    candidates = jnp.asarray(candidates)
    if none is None:
        none = temporal_pair_errors(outputs._replace(xi_corr=jnp.zeros_like(candidates[0])), batch, config,
                                    depth_valid)
    deltas = []
    for c in range(candidates.shape[0]):
        applied = candidates[c][:, 3:] if config.rotation_only else candidates[c]
        delta = temporal_pair_errors(outputs._replace(xi_corr=candidates[c]), batch, config, depth_valid)
        delta -= none
        # A candidate that moves no pose has Δ = 0 exactly, not the rounding by which two evaluations of L(0)
        # in one program can differ: XLA's CPU code generators other than the default one differ there.
        deltas.append(jnp.where(jnp.all(applied == 0, axis=-1), jnp.zeros_like(delta), delta))
    return {"none": none, "delta": jnp.stack(deltas)}
