"""Applying the network's pose correction to the VO prior (docs/method.md §1, both papers eq. 1–2): one
relative pose (:func:`apply_correction`) or a whole trajectory (:func:`corrected_trajectory`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from dpc_jax.geometry.lie import se3_exp
from dpc_jax.geometry.poses import compose, relative_poses, validate_poses


def apply_correction(xi_corr: ArrayLike, T_vo: ArrayLike, rotation_only: bool = False) -> Array:
    """Corrected relative pose ``T* = Exp(ξ_corr) · T_vo`` (correction on the left).

    ``xi_corr``: ``[..., 6]`` as ``[ρ (m), φ (rad)]``; ``T_vo``: ``[..., 4, 4]`` with leading
    axes broadcasting -> ``[..., 4, 4]``. With ``rotation_only`` the translation part ``ρ`` of
    the correction is zeroed, so only the rotation of the prior is corrected (ss-DPC-Net's
    setting for the stereo estimator). The result has the promoted dtype of the inputs.
    """
    xi_corr, T_vo = jnp.asarray(xi_corr), jnp.asarray(T_vo)
    if xi_corr.ndim < 1 or xi_corr.shape[-1] != 6:
        raise ValueError(f"xi_corr must have shape [..., 6], got {xi_corr.shape}")
    if T_vo.ndim < 2 or T_vo.shape[-2:] != (4, 4):
        raise ValueError(f"T_vo must have shape [..., 4, 4], got {T_vo.shape}")
    dtype = jnp.result_type(xi_corr.dtype, T_vo.dtype, jnp.float32)
    xi_corr, T_vo = xi_corr.astype(dtype), T_vo.astype(dtype)
    if rotation_only:
        xi_corr = jnp.concatenate([jnp.zeros_like(xi_corr[..., :3]), xi_corr[..., 3:]], axis=-1)
    return se3_exp(xi_corr) @ T_vo


def corrected_trajectory(
    xi_corr: np.ndarray, prior: np.ndarray, first_pose: np.ndarray, rotation_only: bool = False
) -> np.ndarray:
    """Compose ``T*_{t+1,t} = Exp(ξ_corr,t) · T_vo_{t+1,t}`` from ``first_pose`` → ``[N, 4, 4]`` float64.

    ``xi_corr``: ``[N-1, 6]`` corrections of the consecutive pairs; ``prior``: ``[N, 4, 4]``
    camera-to-world VO trajectory; ``first_pose``: ``[4, 4]``. The prior's and the first pose's rotation
    blocks are projected onto SO(3) first, as the trajectory readers do
    (:func:`~dpc_jax.geometry.poses.validate_poses`): a step is composed back with the rigid inverse
    (Rᵀ), which inverts a rotation only, and a prior stored in float32 is orthonormal to about 1e-7,
    which over the 4,541 steps of KITTI 00 moved the positions by millimetres. The exponential and the
    products run in float64 (in a local ``enable_x64`` scope), so ξ_corr = 0 with ``first_pose`` the
    prior's first pose gives back the prior's positions up to float64 rounding, and its rotations as
    projected (they move by at most their own deviation from a rotation).

    ``ValueError`` naming the argument for a prior or first pose that the trajectory readers would
    refuse (:func:`~dpc_jax.geometry.poses.validate_poses`) and for a non-finite correction, which
    would make every later pose NaN.
    """
    xi_corr = np.asarray(xi_corr, np.float64)
    prior = np.asarray(prior, np.float64)
    if prior.ndim != 3 or prior.shape[1:] != (4, 4) or xi_corr.shape != (prior.shape[0] - 1, 6):
        raise ValueError(
            f"need xi_corr [N-1, 6] for a prior [N, 4, 4], got {xi_corr.shape} and {prior.shape}"
        )
    # Projected (see above): the rigid inverse of relative_poses and compose is exact for rotations only.
    prior = validate_poses(prior, "prior")
    first_pose = validate_poses(np.asarray(first_pose, np.float64)[None], "first_pose")[0]
    check_finite(xi_corr)
    with jax.enable_x64(True):
        corrected = np.asarray(_applied(xi_corr, relative_poses(prior), rotation_only), np.float64)
    return compose(corrected, first_pose)


def check_finite(xi_corr: np.ndarray, what: str = "xi_corr", first: int | None = None) -> None:
    """Raise ``ValueError`` naming the first pair whose correction (``xi_corr [M, 6]``: a sequence's, or with
    ``first`` its pairs ``first`` … ``first + M − 1``) is not finite (NaN or inf): composed, it would turn
    every later pose into NaN."""
    bad = np.flatnonzero(~np.isfinite(np.asarray(xi_corr)).all(axis=1))
    if bad.size:
        start = first or 0
        among = f"{len(xi_corr)} pairs" if first is None else f"pairs {start}–{start + len(xi_corr) - 1}"
        raise ValueError(f"{what}: the correction of pair {start + int(bad[0])} is not finite (NaN or inf); "
                         f"{bad.size} of {among} are")


# Compiled once per shape (and per float precision): a corrector of one pair at a time calls it per frame.
_applied = jax.jit(apply_correction, static_argnames="rotation_only")
