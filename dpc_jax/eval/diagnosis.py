"""What a trajectory's error is made of: per-step bias against noise, per axis.

The correction each step of an estimate needs is ``ξ_k = Log(G_{k+1,k} · inv(E_{k+1,k}))``
(:func:`dpc_jax.eval.metrics.step_corrections`, ``[ρ (m), φ (rad)]``, ``X_{k+1,k} = inv(X_{k+1}) X_k``).
Over the M steps of a sequence:

* its **mean** is the systematic part, the same every step: what a correction can learn from the
  prior alone (a constant is the simplest such correction); its **spread** (sample standard
  deviation) is the random part, which averages out over a segment; the **standard error** of the
  mean is ``spread / √M``;
* the **share of the final drift that the mean explains**: the end-point drift of the estimate,
  as a position vector ``d_E = p_E,N − p_G,N`` (m) and a heading vector ``Log(R_G,Nᵀ R_E,N)`` (°),
  against the drift ``d_B`` of the *bias-only* trajectory, the ground truth with every step
  carrying the mean error and nothing else (``B_{k+1,k} = Exp(−mean) · G_{k+1,k}``, the inverse of
  the network's composition ``T* = Exp(ξ) · T_vo``, from the first ground-truth pose):
  ``share = d_B · d_E / ‖d_E‖²``, the part of the drift along the bias's own. 1 means the bias alone
  produces the drift; 0 that it produces none of it; above 1 that the random part cancelled some of
  the bias. Read it with the standard error: over one sequence the mean of a pure random error is
  not zero, and it "explains" a part of that error's own drift (for heading, which sums the
  per-step rotations, nearly all of it), so a share means little unless the mean is many standard
  errors from zero;
* **pixels**: the image shift that the mean rotation per step causes for a camera of focal length
  ``f`` px, small-angle: ``f · φ`` for pitch (φx) and yaw (φy) — a point at the principal point moves
  by ``f · ‖(φx, φy)‖``; roll (φz) moves a point ``r`` px from the principal point by ``r · φz``,
  reported at ``r = f`` (a point 45° off the optical axis). Whether a photometric loss can see the
  bias depends on these shifts.

Units in the result: translation in mm, rotation in mrad (per step), drift in m and °, shifts in px.
:func:`diagnose` is the one implementation; ``dpc-jax evaluate --diagnose``, :func:`dpc_jax.evaluate`
and the demo's report use it (its Markdown: :func:`dpc_jax.report.evaluation_report.format_diagnosis`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from jax import Array

# JAX is imported inside the functions: dpc_jax.eval.evaluation imports this module and must stay
# importable without JAX (the command line checks its inputs before JAX starts).

AXES: tuple[str, ...] = ("ρx", "ρy", "ρz", "φx", "φy", "φz")
# Per-step values are reported in mm (ρ) and mrad (φ).
_MILLI = 1e3


@dataclass(frozen=True)
class Diagnosis:
    """Per-step error composition of one estimate (see the module docstring for every definition)."""

    steps: int  # M, the number of consecutive pairs
    mean: tuple[float, ...]  # [6] ρ mm, φ mrad: systematic part per step
    spread: tuple[float, ...]  # [6] sample standard deviation per step, same units
    standard_error: tuple[float, ...]  # [6] spread / √M
    drift_trans_m: float  # ‖d_E‖, end-point position error of the estimate
    drift_rot_deg: float  # end-point heading error
    bias_drift_trans_m: float  # ‖d_B‖, the same of the bias-only trajectory
    bias_drift_rot_deg: float
    drift_trans_explained: float  # d_B · d_E / ‖d_E‖² (NaN when the estimate has no drift)
    drift_rot_explained: float
    focal_px: float | None = None
    mean_rot_px: tuple[float, float, float] | None = None  # (f·φx, f·φy, f·φz) px per step, signed
    mean_rot_px_norm: float | None = None  # f·‖(φx, φy)‖ px per step

    def to_dict(self) -> dict[str, object]:
        """JSON-ready: every field and the two shares (NaN becomes ``None``)."""
        def clean(value: float | None) -> float | None:
            return None if value is None or math.isnan(value) else value

        out: dict[str, object] = {
            "steps": self.steps,
            "axes": list(AXES),
            "mean": list(self.mean),
            "spread": list(self.spread),
            "standard_error": list(self.standard_error),
            "drift_trans_m": self.drift_trans_m,
            "drift_rot_deg": self.drift_rot_deg,
            "bias_drift_trans_m": self.bias_drift_trans_m,
            "bias_drift_rot_deg": self.bias_drift_rot_deg,
            "drift_trans_explained": clean(self.drift_trans_explained),
            "drift_rot_explained": clean(self.drift_rot_explained),
            "focal_px": self.focal_px,
            "mean_rot_px": None if self.mean_rot_px is None else list(self.mean_rot_px),
            "mean_rot_px_norm": self.mean_rot_px_norm,
        }
        return out


def _share(bias: np.ndarray, drift: np.ndarray) -> float:
    norm2 = float(drift @ drift)
    return float("nan") if norm2 == 0.0 else float(bias @ drift) / norm2


def step_statistics(xi: Array) -> tuple[Array, Array, Array]:
    """Mean, sample standard deviation and standard error of per-step corrections ``[M, 6]`` → 3 × ``[6]``.

    Pure ``jnp`` in the dtype of ``xi`` (units as given). ``M ≥ 2``.
    """
    import jax.numpy as jnp

    xi = jnp.asarray(xi)
    m = xi.shape[0]
    if xi.ndim != 2 or xi.shape[1] != 6 or m < 2:
        raise ValueError(f"per-step corrections must have shape [M, 6] with M ≥ 2, got {xi.shape}")
    mean = jnp.mean(xi, axis=0)
    spread = jnp.sqrt(jnp.sum((xi - mean) ** 2, axis=0) / (m - 1))
    return mean, spread, spread / jnp.sqrt(jnp.asarray(m, xi.dtype))


def end_point_drift(gt: Array, est: Array) -> tuple[Array, Array]:
    """End-point drift of ``est`` against ``gt`` (both ``[N, 4, 4]``): position ``p_E,N − p_G,N`` ``[3]`` (m)
    and heading ``Log(R_G,Nᵀ R_E,N)`` ``[3]`` (°, in the last ground-truth camera frame)."""
    import jax.numpy as jnp

    from dpc_jax.geometry.lie import so3_log

    return est[-1, :3, 3] - gt[-1, :3, 3], jnp.degrees(so3_log(gt[-1, :3, :3].T @ est[-1, :3, :3]))


def diagnose(gt: np.ndarray, est: np.ndarray, focal_px: float | None = None) -> Diagnosis:
    """:class:`Diagnosis` of an estimate ``[N, 4, 4]`` against the ground truth ``[N, 4, 4]`` (camera→world).

    The estimate should start at the first ground-truth pose (:func:`dpc_jax.eval.evaluation.evaluate`
    re-anchors it); the drift is measured at the last pose. Computed in float64. ``focal_px`` (> 0)
    adds the image shifts. Raises ``ValueError`` for bad shapes or a non-positive focal length.
    """
    import jax
    import jax.numpy as jnp

    from dpc_jax.eval.metrics import step_corrections
    from dpc_jax.geometry.lie import se3_exp
    from dpc_jax.geometry.poses import compose, relative_poses

    gt = np.asarray(gt, np.float64)
    est = np.asarray(est, np.float64)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or gt.shape != est.shape or gt.shape[0] < 3:
        raise ValueError(
            "ground truth and estimate must both have shape [N, 4, 4] with N ≥ 3; "
            f"got {gt.shape} and {est.shape}"
        )
    if focal_px is not None and not (math.isfinite(focal_px) and focal_px > 0):
        raise ValueError(f"focal length must be a positive number of pixels, got {focal_px}")
    with jax.enable_x64(True):
        xi = np.asarray(step_corrections(gt, est), np.float64)
        mean, spread, sem = (np.asarray(v, np.float64) for v in step_statistics(jnp.asarray(xi)))
        # The bias-only trajectory: each ground-truth step with the mean error, Exp(−mean) · G_{k+1,k}.
        bias_steps = np.asarray(se3_exp(jnp.asarray(-mean)), np.float64) @ relative_poses(gt)
        bias_only = compose(bias_steps, gt[0])
        d_trans, d_rot = (
            np.asarray(v, np.float64) for v in end_point_drift(jnp.asarray(gt), jnp.asarray(est))
        )
        b_trans, b_rot = (
            np.asarray(v, np.float64) for v in end_point_drift(jnp.asarray(gt), jnp.asarray(bias_only))
        )
    px: tuple[float, float, float] | None = None
    px_norm: float | None = None
    if focal_px is not None:
        px = (float(focal_px * mean[3]), float(focal_px * mean[4]), float(focal_px * mean[5]))
        px_norm = float(focal_px * math.hypot(mean[3], mean[4]))
    return Diagnosis(
        steps=int(xi.shape[0]),
        mean=tuple(float(v) for v in _MILLI * mean),
        spread=tuple(float(v) for v in _MILLI * spread),
        standard_error=tuple(float(v) for v in _MILLI * sem),
        drift_trans_m=float(np.linalg.norm(d_trans)),
        drift_rot_deg=float(np.linalg.norm(d_rot)),
        bias_drift_trans_m=float(np.linalg.norm(b_trans)),
        bias_drift_rot_deg=float(np.linalg.norm(b_rot)),
        drift_trans_explained=_share(b_trans, d_trans),
        drift_rot_explained=_share(b_rot, d_rot),
        focal_px=None if focal_px is None else float(focal_px),
        mean_rot_px=px,
        mean_rot_px_norm=px_norm,
    )
