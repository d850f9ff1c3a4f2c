"""A supervised linear pose correction: the baseline a learned correction should beat.

**Supervised**: it is fit to ground truth. For each step of a training sequence the correction the
prior needs is ``ξ_gt = Log(G_{k+1,k} · inv(T_vo_{k+1,k}))`` (:func:`dpc_jax.eval.metrics.step_corrections`,
``[ρ (m), φ (rad)]``), and the model is linear in the prior's own step ``ξ_vo = Log(T_vo_{k+1,k})``:

    ξ_corr = W · [ξ_vo, 1]        W: [6, 7] (a constant per axis plus a gain on each component)

fit by ordinary least squares over all training steps, one output axis at a time. With
``rotation_only`` only the rotation rows are fit and the translation rows are zero (ss-DPC-Net's
setting for stereo priors). With ``constant_only`` only the constant column is fit (the mean
correction per step, a per-axis bias): the gains on the prior's step extrapolate poorly to a log
driven at other speeds than the training one, a bias does not depend on them. It is applied
exactly as the network's correction, ``T* = Exp(ξ_corr) · T_vo``
(:func:`dpc_jax.geometry.pose_correction.corrected_trajectory`), so its numbers compare with a network's.

The math (:func:`design_matrix`, :func:`fit_weights`, :func:`predict`) is pure ``jnp``; run it with
``jax_enable_x64`` for float64. :func:`fit_linear_correction` and :func:`apply_linear_correction`
take and return trajectories.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from jax import Array
    from jax.typing import ArrayLike

FEATURES: tuple[str, ...] = ("ρx", "ρy", "ρz", "φx", "φy", "φz", "1")


def design_matrix(xi_vo: ArrayLike) -> Array:
    """Features of the prior's steps ``[M, 6]`` (m, rad) → ``[M, 7]``: the step and a constant 1."""
    import jax.numpy as jnp

    xi_vo = jnp.asarray(xi_vo)
    if xi_vo.ndim != 2 or xi_vo.shape[1] != 6:
        raise ValueError(f"prior steps must have shape [M, 6], got {xi_vo.shape}")
    return jnp.concatenate([xi_vo, jnp.ones_like(xi_vo[:, :1])], axis=1)


def fit_weights(
    xi_vo: ArrayLike, xi_gt: ArrayLike, rotation_only: bool = True, constant_only: bool = False
) -> Array:
    """Least-squares ``W [6, 7]`` with ``xi_gt ≈ design_matrix(xi_vo) @ Wᵀ`` (both ``[M, 6]``).

    Each output axis is an independent least-squares problem; with ``rotation_only`` the rows of
    ρ are zero. Needs ``M ≥ 7`` steps whose features span the 7 dimensions (else the minimum-norm
    solution is returned, as ``jnp.linalg.lstsq`` does). ``constant_only``: every gain is zero and
    the constant column is the least-squares constant, the mean of ``xi_gt`` per axis.
    """
    import jax.numpy as jnp

    x = design_matrix(xi_vo)
    y = jnp.asarray(xi_gt, x.dtype)
    if y.shape != (x.shape[0], 6):
        raise ValueError(f"ground-truth corrections must have shape {(x.shape[0], 6)}, got {y.shape}")
    if x.shape[0] < x.shape[1]:
        raise ValueError(f"need at least {x.shape[1]} steps to fit the coefficients, got {x.shape[0]}")
    if constant_only:
        weights = jnp.zeros((6, x.shape[1]), x.dtype).at[:, -1].set(jnp.mean(y, axis=0))
    else:
        # Columns scaled to unit RMS so the solve is well conditioned (steps in m and rad differ by ~10³).
        scale = jnp.sqrt(jnp.mean(x * x, axis=0))
        scale = jnp.where(scale > 0, scale, 1.0)
        solution, *_ = jnp.linalg.lstsq(x / scale, y)
        weights = (solution / scale[:, None]).T
    if rotation_only:
        weights = weights.at[:3].set(0.0)
    return weights


def predict(weights: ArrayLike, xi_vo: ArrayLike) -> Array:
    """Corrections ``[M, 6]`` = ``design_matrix(xi_vo) @ Wᵀ`` for weights ``[6, 7]``."""
    import jax.numpy as jnp

    weights = jnp.asarray(weights)
    if weights.shape != (6, len(FEATURES)):
        raise ValueError(f"weights must have shape (6, {len(FEATURES)}), got {weights.shape}")
    return design_matrix(xi_vo) @ weights.T


@dataclass(frozen=True)
class LinearCorrection:
    """A fitted linear correction: ``weights [6, 7]`` (rows ρx…φz, columns :data:`FEATURES`)."""

    weights: np.ndarray
    rotation_only: bool
    steps: int  # number of training steps it was fit on


def sequence_steps(gt: np.ndarray, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(ξ_vo [M, 6], ξ_gt [M, 6])`` of one sequence (ground truth and prior ``[N, 4, 4]``), float64.

    ``ξ_gt`` equals :func:`dpc_jax.eval.metrics.step_corrections`; both logarithms go through
    :func:`dpc_jax.data.priors.log_poses`, which compiles once per power-of-two length bucket, so a
    leave-one-out over sequences of many lengths compiles a few times, not once per sequence.
    """
    import jax

    from dpc_jax.data.priors import log_poses
    from dpc_jax.geometry.poses import invert_poses, relative_poses

    gt, prior = np.asarray(gt, np.float64), np.asarray(prior, np.float64)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or gt.shape != prior.shape or gt.shape[0] < 2:
        raise ValueError(
            f"ground truth and prior must both have shape [N, 4, 4], N ≥ 2; got {gt.shape} and {prior.shape}"
        )
    steps = relative_poses(prior)
    with jax.enable_x64(True):
        xi_vo = np.asarray(log_poses(steps), np.float64)
        xi_gt = np.asarray(log_poses(relative_poses(gt) @ invert_poses(steps)), np.float64)
    return xi_vo, xi_gt


def fit_linear_correction(
    sequences: Sequence[tuple[np.ndarray, np.ndarray]],
    rotation_only: bool = True,
    constant_only: bool = False,
) -> LinearCorrection:
    """Fit on training sequences ``[(ground truth [N, 4, 4], prior [N, 4, 4]), …]`` (all steps pooled)."""
    steps = [sequence_steps(gt, prior) for gt, prior in sequences]
    return fit_from_steps(steps, rotation_only, constant_only)


def fit_from_steps(
    pairs: Sequence[tuple[np.ndarray, np.ndarray]], rotation_only: bool = True, constant_only: bool = False
) -> LinearCorrection:
    """Fit on the :func:`sequence_steps` ``(ξ_vo, ξ_gt)`` of training sequences (all steps pooled)."""
    import jax

    if not pairs:
        raise ValueError("no training sequence to fit the linear correction on")
    xi_vo = np.concatenate([p[0] for p in pairs])
    xi_gt = np.concatenate([p[1] for p in pairs])
    with jax.enable_x64(True):
        weights = np.asarray(fit_weights(xi_vo, xi_gt, rotation_only, constant_only), np.float64)
    return LinearCorrection(weights=weights, rotation_only=rotation_only, steps=int(xi_vo.shape[0]))


def apply_linear_correction(model: LinearCorrection, prior: np.ndarray) -> np.ndarray:
    """Corrected trajectory ``[N, 4, 4]``: ``T* = Exp(ξ_corr) · T_vo`` each step from the prior's 1st pose."""
    import jax

    from dpc_jax.data.priors import relative_xi
    from dpc_jax.geometry.pose_correction import corrected_trajectory

    prior = np.asarray(prior, np.float64)
    with jax.enable_x64(True):
        xi_vo = np.asarray(relative_xi(prior), np.float64)
        xi_corr = np.asarray(predict(model.weights, xi_vo), np.float64)
    return corrected_trajectory(xi_corr, prior, prior[0], rotation_only=model.rotation_only)
