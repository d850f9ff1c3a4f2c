"""Frame-to-frame motion from 3D–2D correspondences of a stereo rig.

The points are triangulated in frame ``k`` (left camera, metres) and observed in the left and
(where matched) right image of frame ``k+1``. The motion is ``T = T_{k+1,k}`` (docs/method.md §1): it maps
a point expressed in frame ``k`` into frame ``k+1``.

Estimation follows libviso2-s (Geiger, Ziegler, Stiller, "StereoScan", IV 2011): a RANSAC
initialisation (here OpenCV's P3P ``solvePnPRansac`` on the left observations), then Gauss–Newton
on the reprojection error in *both* cameras over the inliers, re-selecting inliers with the
refined pose. The right-camera term is what pins the depth of the motion: with the left image
alone a forward translation error trades off against the noisy depths of the triangulated points.
Optionally each point is weighted by ``1 / (|u − cu| / cu + 0.05)`` (libviso2's "reweighting"):
points near the image centre move little under rotation, and their reprojection error is more
informative about translation along the optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from dpc_jax.geometry.projective import perspective_divide


@dataclass(frozen=True)
class MotionEstimate:
    """Result of :func:`estimate_motion`.

    Attributes:
      T: ``float64 [4, 4]`` the relative pose ``T_{k+1,k}`` (identity when ``success`` is false).
      inliers: ``bool [N]`` correspondences consistent with ``T``.
      success: whether enough inliers were found.
      rms: root-mean-square reprojection error of the inliers in pixels (``nan`` on failure).
      offset_increment: px, the disparity-offset increment estimated jointly with ``T`` on the
        inliers (0 unless requested): ``T`` is the pose for the points and right observations
        corrected by it (:func:`apply_offset`).
      offset_information: px⁻², the posterior information of the offset (0 unless requested).
    """

    T: np.ndarray
    inliers: np.ndarray
    success: bool
    rms: float
    offset_increment: float = 0.0
    offset_information: float = 0.0


def camera_pixels(
    T: np.ndarray, points: np.ndarray, K: np.ndarray, offset_x: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of ``T·X`` in a camera shifted by ``offset_x`` metres along x (the right camera: ``B``).

    ``K`` without skew; the principal point is added after the division. Returns
    ``(uv [N, 2], in_front [N] bool)``; ``uv`` is meaningless where ``in_front`` is false.
    """
    camera = points @ T[:3, :3].T + T[:3, 3]
    camera[:, 0] -= offset_x
    x, y, z = camera[:, 0], camera[:, 1], camera[:, 2]
    u, v, in_front = perspective_divide(K[0, 0] * x, K[1, 1] * y, z, 1e-6, np)
    return np.stack([u + K[0, 2], v + K[1, 2]], axis=1), in_front


def reprojection_errors(
    T: np.ndarray,
    points: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    right_valid: np.ndarray,
    K: np.ndarray,
    baseline: float,
) -> np.ndarray:
    """Per-point error in pixels: the larger of the left and (where matched) right reprojection errors.

    ``inf`` for points that land behind either camera.
    """
    uv_l, front_l = camera_pixels(T, points, K)
    uv_r, front_r = camera_pixels(T, points, K, baseline)
    err_l = np.linalg.norm(uv_l - left, axis=1)
    err_r = np.where(right_valid, np.linalg.norm(uv_r - right, axis=1), 0.0)
    err = np.maximum(err_l, err_r)
    return np.where(front_l & front_r, err, np.inf)


def _stacked_residuals(
    T: np.ndarray, points: np.ndarray, left: np.ndarray, right: np.ndarray, right_valid: np.ndarray,
    K: np.ndarray, baseline: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ``[N, 4]`` (left u, v, right u, v) and their Jacobians ``[N, 4, 7]``.

    Columns 0–5: w.r.t. ``δ = [ρ, φ]`` of a left perturbation ``T ← Exp(δ) T``, under which a
    transformed point ``P = R X + t`` moves by ``dP/dδ = [I, −P^]``. Column 6: w.r.t. an increment
    ``Δ`` of the disparity offset (see :func:`apply_offset`): the triangulated point scales as
    ``dX/dΔ = −X·Z/(fu·B)`` and the right observation moves by ``−Δ``. Missing right observations
    get zero rows.
    """
    fu, fv = K[0, 0], K[1, 1]
    R = T[:3, :3]
    P = points @ R.T + T[:3, 3]
    n = len(points)
    dP = np.zeros((n, 3, 7))
    dP[:, 0, 0] = dP[:, 1, 1] = dP[:, 2, 2] = 1.0
    # −P^ = [[0, z, −y], [−z, 0, x], [y, −x, 0]]
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    dP[:, 0, 4], dP[:, 0, 5] = z, -y
    dP[:, 1, 3], dP[:, 1, 5] = -z, x
    dP[:, 2, 3], dP[:, 2, 4] = y, -x
    dP[:, :, 6] = -(points @ R.T) * (points[:, 2:] / (fu * baseline))
    residuals = np.zeros((n, 4))
    jacobians = np.zeros((n, 4, 7))
    inv_z = 1.0 / z
    for row, offset, observed in ((0, 0.0, left), (2, baseline, right)):
        xc = x - offset
        d_proj = np.zeros((n, 2, 3))
        d_proj[:, 0, 0] = fu * inv_z
        d_proj[:, 0, 2] = -fu * xc * inv_z**2
        d_proj[:, 1, 1] = fv * inv_z
        d_proj[:, 1, 2] = -fv * y * inv_z**2
        residuals[:, row] = fu * xc * inv_z + K[0, 2] - observed[:, 0]
        residuals[:, row + 1] = fv * y * inv_z + K[1, 2] - observed[:, 1]
        jacobians[:, row:row + 2] = d_proj @ dP
    jacobians[:, 2, 6] += 1.0
    residuals[:, 2:] *= right_valid[:, None]
    jacobians[:, 2:] *= right_valid[:, None, None]
    return residuals, jacobians


def apply_offset(
    points: np.ndarray, right: np.ndarray, increment: float, K: np.ndarray, baseline: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Re-triangulate ``points`` and shift ``right`` for a disparity offset larger by ``increment`` px.

    A constant offset ``δ`` between measured and true disparity (``d_true = d_measured + δ``, e.g.
    a sub-pixel mismatch of the two rectified principal points) makes depth errors grow with depth
    and biases the translation. With ``Z = fu·B/(d + δ)``, raising ``δ`` by ``Δ`` scales a point by
    ``1 / (1 + Δ·Z/(fu·B))``; the right observations move by ``−Δ``.

    Returns ``(points [N, 3], right [N, 2])``.
    """
    scale = 1.0 / (1.0 + increment * points[:, 2] / (K[0, 0] * baseline))
    shifted = np.array(right, np.float64)
    shifted[:, 0] -= increment
    return points * scale[:, None], shifted


def refine_pose(
    T: np.ndarray,
    points: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    right_valid: np.ndarray,
    K: np.ndarray,
    baseline: float,
    weights: np.ndarray,
    iterations: int,
    *,
    offset_prior: float | None = None,
) -> tuple[np.ndarray, float, float]:
    """Gauss–Newton on ``Σ w_i (‖e_left,i‖² + ‖e_right,i‖²)`` starting from ``T``.

    Args:
      T: ``[4, 4]`` initial ``T_{k+1,k}``.
      points: ``[N, 3]`` metres in frame ``k``; left/right: ``[N, 2]`` pixels in frame ``k+1``;
      right_valid: ``bool [N]``; weights: ``[N]`` non-negative.
      iterations: maximum number of steps (stops earlier once the step is below 1e-10).
      offset_prior: when given, also estimate an increment ``Δ`` of the disparity offset
        (:func:`apply_offset`) under a Gaussian prior ``Δ ~ N(0, 1/offset_prior)`` (px⁻²; 0 for
        none). The pixel noise that scales the data term is estimated from the residuals at ``T``.

    Returns:
      ``(T, Δ, information)``: the refined pose (a step uses the retraction ``[[Exp(φ), ρ], [0, 1]]·T``,
      which has the same fixed points as ``Exp(δ)·T``); the offset increment in pixels and its
      posterior information in px⁻² (the Schur complement of the pose in the Hessian, prior
      included) — both 0 without ``offset_prior``.
    """
    T = np.array(T, np.float64)
    with_offset = offset_prior is not None
    size = 7 if with_offset else 6
    increment = 0.0
    base_points, base_right = points, right
    prior = 0.0
    if offset_prior is not None:  # = with_offset, spelled out so the type checker narrows it
        r, _ = _stacked_residuals(T, points, left, right, right_valid, K, baseline)
        observations = 2 * len(points) + 2 * int(right_valid.sum())
        noise = float(np.einsum("n,nk->", weights, r**2)) / max(observations - size, 1)
        # The data term is Σw‖r‖²; in those units the prior's weight is its information times σ².
        prior = float(offset_prior) * max(noise, 1e-12)
    H = np.eye(size)
    for _ in range(iterations):
        r, J = _stacked_residuals(T, points, left, right, right_valid, K, baseline)
        J = J[:, :, :size]
        H = np.einsum("n,nki,nkj->ij", weights, J, J)
        g = np.einsum("n,nki,nk->i", weights, J, r)
        if with_offset:
            H[6, 6] += prior
            g[6] += prior * increment
        try:
            delta = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        step = np.eye(4)
        step[:3, :3] = cv2.Rodrigues(delta[3:6])[0]
        step[:3, 3] = delta[:3]
        T = step @ T
        if with_offset:
            increment += float(delta[6])
            points, right = apply_offset(base_points, base_right, increment, K, baseline)
        if float(delta @ delta) < 1e-20:
            break
    if not with_offset:
        return T, 0.0, 0.0
    try:
        schur = float(H[6, 6] - H[6, :6] @ np.linalg.solve(H[:6, :6], H[:6, 6]))
    except np.linalg.LinAlgError:
        return T, 0.0, 0.0
    return T, increment, max(schur / max(noise, 1e-12), 0.0)


def estimate_motion(
    points: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    right_valid: np.ndarray,
    K: np.ndarray,
    baseline: float,
    *,
    ransac_iterations: int,
    ransac_threshold: float,
    inlier_threshold: float,
    min_inliers: int,
    refine_iterations: int,
    reweight: bool,
    offset_prior: float | None = None,
) -> MotionEstimate:
    """``T_{k+1,k}`` from points triangulated in frame ``k`` and observed in frame ``k+1``.

    Args:
      points: ``[N, 3]`` metres, left camera of frame ``k``.
      left: ``[N, 2]`` pixels in the left image of frame ``k+1``.
      right: ``[N, 2]`` pixels in the right image of frame ``k+1`` (used where ``right_valid``).
      K: ``[3, 3]``; baseline: metres.
      ransac_iterations, ransac_threshold: P3P RANSAC on the left observations (threshold in px).
      inlier_threshold: px; after refinement a point is an inlier when both its reprojection
        errors are below this.
      min_inliers: fewer inliers than this is a failure.
      refine_iterations: Gauss–Newton steps per refinement round (two rounds).
      reweight: apply libviso2's weighting by horizontal distance from the principal point.
      offset_prior: when given (px⁻²), a final refinement on the inliers estimates an increment of
        the disparity offset jointly with the pose under this prior information
        (:func:`refine_pose`).
    """
    n = len(points)
    failure = MotionEstimate(np.eye(4), np.zeros(n, bool), False, float("nan"))
    if n < max(min_inliers, 4):
        return failure
    ok, rvec, tvec, ransac_inliers = cv2.solvePnPRansac(
        points.astype(np.float64), left.astype(np.float64), K.astype(np.float64), None,
        iterationsCount=ransac_iterations, reprojectionError=ransac_threshold, confidence=0.999,
        flags=cv2.SOLVEPNP_P3P,
    )
    if not ok or ransac_inliers is None or len(ransac_inliers) < min_inliers:
        return failure
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    inliers = np.zeros(n, bool)
    inliers[ransac_inliers.ravel()] = True
    if reweight:
        weights_all = 1.0 / (np.abs(left[:, 0] - K[0, 2]) / abs(K[0, 2]) + 0.05)
    else:
        weights_all = np.ones(n)
    for _ in range(2):
        T, _, _ = refine_pose(
            T, points[inliers], left[inliers], right[inliers], right_valid[inliers], K, baseline,
            weights_all[inliers], refine_iterations,
        )
        errors = reprojection_errors(T, points, left, right, right_valid, K, baseline)
        inliers = errors < inlier_threshold
        if inliers.sum() < min_inliers:
            return failure
    rms = float(np.sqrt(np.mean(errors[inliers] ** 2)))
    increment = information = 0.0
    if offset_prior is not None:
        T, increment, information = refine_pose(
            T, points[inliers], left[inliers], right[inliers], right_valid[inliers], K, baseline,
            weights_all[inliers], refine_iterations, offset_prior=offset_prior,
        )
    return MotionEstimate(T, inliers, True, rms, increment, information)
