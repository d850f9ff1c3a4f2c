"""Applying the network's pose correction to the VO prior (DESIGN §1, both papers eq. 1–2)."""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from dpc_jax.lie import se3_exp


def apply_correction(xi_corr: Array, T_vo: Array, rotation_only: bool = False) -> Array:
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
