"""DPC-Net's supervised loss (Peretroukhin & Kelly, RA-L 2018; docs/method.md "The supervised loss"):
the covariance-weighted SE(3) error of ``ξ_corr`` against the ground-truth correction, and the
precision ``Σ⁻¹`` computed from the training pairs' target corrections.

Like the self-supervised losses (:mod:`dpc_jax.nn.losses`), pure ``jnp`` functions of a
:class:`~dpc_jax.nn.outputs.DPCOutputs` and a :class:`~dpc_jax.nn.batch.Batch` that never import
the models; :func:`target_precision` and :func:`with_target_precision` read values and run outside
``jax.jit``.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from dpc_jax.geometry.lie import se3_exp, se3_inverse, se3_log, so3_exp, so3_log
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.model_config import SSDPCLossConfig, StereoDPCLossConfig, SupervisedLossConfig
from dpc_jax.nn.outputs import DPCOutputs


def target_corrections(xi_vo: ArrayLike, xi_gt: ArrayLike) -> Array:
    """The correction each pair needs, ``T_target = Exp(ξ_gt) · inv(Exp(ξ_vo))`` → ``[B, 4, 4]``.

    ``xi_vo``, ``xi_gt``: ``[B, 6]`` prior and ground-truth relative poses ``Log(T_{k+1,k})``; then
    ``T_target · T_vo = T_gt``, the correction a perfect network outputs (``T* = Exp(ξ_corr) · T_vo``).
    """
    return se3_exp(jnp.asarray(xi_gt)) @ se3_inverse(se3_exp(jnp.asarray(xi_vo)))


def target_precision(xi_target: ArrayLike, rotation_only: bool = False) -> Array:
    """DPC-Net's weight: the inverse sample covariance of target corrections ``[M, 6]`` → ``[6, 6]``.

    With ``rotation_only`` the rotation block is inverted alone (translation rows and columns 0).
    Raises ``ValueError`` when the targets have (almost) no spread along some direction, where the
    inverse does not exist (give the precision explicitly then); it reads the values, so it runs
    outside ``jax.jit``.
    """
    xi = jnp.asarray(xi_target)
    if xi.ndim != 2 or xi.shape[1] != 6 or xi.shape[0] < 7:
        raise ValueError(f"target corrections must have shape [M, 6] with M ≥ 7, got {xi.shape}")
    centred = xi - jnp.mean(xi, axis=0)
    covariance = centred.T @ centred / (xi.shape[0] - 1)
    block = covariance[3:, 3:] if rotation_only else covariance
    eigenvalues = jnp.linalg.eigvalsh(block)
    if not float(eigenvalues[0]) > 1e-9 * float(eigenvalues[-1]):
        raise ValueError(
            "the target corrections have (almost) no spread along some direction, so their covariance "
            "has no inverse; give the precision explicitly"
        )
    if rotation_only:
        return jnp.zeros_like(covariance).at[3:, 3:].set(jnp.linalg.inv(block))
    return jnp.linalg.inv(covariance)


def with_target_precision(
    config: SSDPCLossConfig | StereoDPCLossConfig | SupervisedLossConfig,
    xi_vo: ArrayLike,
    xi_gt: ArrayLike | None,
) -> SSDPCLossConfig | StereoDPCLossConfig | SupervisedLossConfig:
    """A supervised config without ``precision`` gets DPC-Net's: :func:`target_precision` of the
    target corrections of the training pairs (``xi_vo``, ``xi_gt``: ``[M, 6]``); any other config
    is returned as is. Raises ``ValueError`` when the pairs' ground truth is missing."""
    if not isinstance(config, SupervisedLossConfig) or config.precision is not None:
        return config
    if xi_gt is None:
        raise ValueError("the supervised loss needs the training pairs' ground truth for its precision")
    import jax
    import numpy as np

    # In float64: rotation variances are ~10⁶ times smaller than translation ones.
    with jax.enable_x64(True):
        xi_vo, xi_gt = (jnp.asarray(np.asarray(x, np.float64)) for x in (xi_vo, xi_gt))
        targets = se3_log(target_corrections(xi_vo, xi_gt))
        precision = np.asarray(target_precision(targets, config.rotation_only), np.float64)
    return dataclasses.replace(config, precision=tuple(float(v) for v in precision.ravel()))


def supervised_dpc_loss(
    outputs: DPCOutputs, batch: Batch, config: SupervisedLossConfig
) -> tuple[Array, dict[str, Array]]:
    """DPC-Net's covariance-weighted SE(3) loss of ``ξ_corr`` against the ground-truth correction.

    Per sample, with ``T_target`` of :func:`target_corrections` and ``P = Σ⁻¹``
    (``config.precision``)::

        g = Log(Exp(ξ_corr) · inv(T_target))        (the correction's error, [ρ, φ])
        ℓ = ½ gᵀ P g − ½ g₀ᵀ P g₀,   g₀ = Log(inv(T_target))   (g for ξ_corr = 0)

    averaged over samples with ``batch.weight``. The second term does not depend on the network; as
    in DPC-Net's code it makes the loss the improvement over no correction (negative is better).
    With ``config.rotation_only`` the same on SO(3): ``g = Log(Exp(φ_corr) · R_targetᵀ)`` and the
    rotation block of P. Metrics: ``loss``, ``supervised_error`` (the mean of ½ gᵀ P g) and
    ``no_correction`` (the mean of ½ g₀ᵀ P g₀). Raises ``ValueError`` when the batch carries no
    ground truth.
    """
    if batch.xi_gt is None:
        raise ValueError("the supervised loss needs ground truth: the batch has no xi_gt")
    xi_corr = jnp.asarray(outputs.xi_corr)
    dtype = jnp.result_type(xi_corr.dtype, jnp.float32)
    xi_corr = xi_corr.astype(dtype)
    target = target_corrections(jnp.asarray(batch.xi_vo, dtype), jnp.asarray(batch.xi_gt, dtype))
    precision = jnp.asarray(config.precision_matrix(), dtype)
    if config.rotation_only:
        r_inv = jnp.swapaxes(target[..., :3, :3], -1, -2)
        error = so3_log(so3_exp(xi_corr[:, 3:]) @ r_inv)
        baseline = so3_log(r_inv)
        precision = precision[3:, 3:]
    else:
        t_inv = se3_inverse(target)
        error = se3_log(se3_exp(xi_corr) @ t_inv)
        baseline = se3_log(t_inv)
    weight = jnp.asarray(batch.weight, dtype)
    total = jnp.sum(weight)

    def mean_quadratic(v: Array) -> Array:
        return jnp.sum(weight * 0.5 * jnp.einsum("bi,ij,bj->b", v, precision, v)) / total

    corrected, uncorrected = mean_quadratic(error), mean_quadratic(baseline)
    loss = corrected - uncorrected
    return loss, {"loss": loss, "supervised_error": corrected, "no_correction": uncorrected}
