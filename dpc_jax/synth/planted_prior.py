"""A prior made from an exact ground truth by planting a per-step rotation error of known structure.

The error is stated as :mod:`dpc_jax.eval.diagnosis` measures one: the correction each step of an
estimate needs is ``ξ_k = Log(G_{k+1,k} · inv(E_{k+1,k}))`` with ``X_{k+1,k} = inv(X_{k+1}) X_k``;
planting ``ξ_k = [0, φ_k]`` with ``φ_k = bias + noise_k`` (rad per step, camera axes x, y, z: pitch,
yaw, roll; ``noise_k`` Gaussian with the given per-axis standard deviation) gives the steps
``E_{k+1,k} = Exp(−ξ_k) · G_{k+1,k}``, chained from the first ground-truth pose. ``evaluate
--diagnose`` on such a prior reports ``bias`` as its mean and the noise as its spread (up to the
sampling error of the noise), so a study can plant the error a real VO was measured to have where
the ground truth is exact. Numpy and scipy, float64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dpc_jax.geometry import rigid


def planted_prior(
    ground_truth: np.ndarray,
    rotation_bias: np.ndarray | tuple[float, float, float],
    rotation_noise: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    seed: int = 0,
) -> np.ndarray:
    """The prior ``[N, 4, 4]`` (camera-to-world, float64) of ``ground_truth`` ``[N, 4, 4]`` with a
    per-step rotation error ``φ_k = rotation_bias + rotation_noise · n_k`` (rad, ``[3]`` each;
    ``n_k`` standard normal from ``seed``) planted as the module docstring states. Translation
    steps keep their length and are rotated with the step (``Exp(−[0, φ])`` acts on the whole
    step), as a rotation error of a VO does. Raises ``ValueError`` for fewer than two poses or
    non-finite arguments."""
    gt = np.asarray(ground_truth, np.float64)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or gt.shape[0] < 2:
        raise ValueError(f"ground_truth must be [N, 4, 4] with N >= 2, got {gt.shape}")
    bias = np.asarray(rotation_bias, np.float64).reshape(3)
    spread = np.asarray(rotation_noise, np.float64).reshape(3)
    finite = np.isfinite(gt).all() and np.isfinite(bias).all() and np.isfinite(spread).all()
    if not finite or (spread < 0).any():
        raise ValueError("ground_truth, rotation_bias and rotation_noise must be finite (noise >= 0)")
    steps = gt.shape[0] - 1
    phi = bias + spread * np.random.default_rng(seed).standard_normal((steps, 3))
    # G_{k+1,k} = inv(G_{k+1}) G_k, E_{k+1,k} = Exp(−[0, φ_k]) G_{k+1,k} = [R(−φ_k), 0] G_{k+1,k}.
    true_steps = rigid.inverse(gt[1:], np) @ gt[:-1]
    error = np.tile(np.eye(4), (steps, 1, 1))
    error[:, :3, :3] = Rotation.from_rotvec(-phi).as_matrix()
    estimated_steps = error @ true_steps
    prior = np.empty_like(gt)
    prior[0] = gt[0]
    for k in range(steps):  # E_{k+1} = E_k · inv(E_{k+1,k})
        prior[k + 1] = prior[k] @ rigid.inverse(estimated_steps[k], np)
    return prior
