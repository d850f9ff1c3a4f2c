"""Left–right matching along the rows of a rectified pair, and triangulation.

Conventions (docs/method.md §1): rectified pair, right camera at ``+B`` along the left camera's x axis,
disparity ``d = u_l − u_r = fu · B / Z`` in pixels.
"""

from __future__ import annotations

import numpy as np

from dpc_jax.vo.features import track


def match_stereo(
    left: np.ndarray,
    right: np.ndarray,
    points_left: np.ndarray,
    disparity_guess: np.ndarray,
    *,
    window: int,
    levels: int,
    max_backward_error: float,
    max_row_error: float,
    min_disparity: float,
    max_disparity: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Find each left point in the right image with sub-pixel KLT, constrained to its row.

    KLT is two-dimensional; the epipolar constraint of the rectified pair is enforced by rejecting
    matches that leave the row by more than ``max_row_error`` px, and the match must survive the
    right-to-left check (circular consistency, ``max_backward_error`` px).

    Args:
      left, right: the rectified grey pair, ``uint8 [H, W]``.
      points_left: ``float32 [N, 2]`` left points.
      disparity_guess: ``[N]`` pixels, initial disparity (0 where nothing is known).
      min_disparity, max_disparity: accepted disparity range in pixels (far/near limits).

    Returns:
      ``(points_right [N, 2] float32, ok [N] bool)``.
    """
    guess = np.asarray(points_left, np.float32).copy()
    guess[:, 0] -= np.asarray(disparity_guess, np.float32)
    matched, ok = track(
        left, right, points_left, guess,
        window=window, levels=levels, max_backward_error=max_backward_error,
    )
    disparity = points_left[:, 0] - matched[:, 0]
    ok &= np.abs(matched[:, 1] - points_left[:, 1]) < max_row_error
    ok &= (disparity >= min_disparity) & (disparity <= max_disparity)
    return matched, ok


def triangulate(points_left: np.ndarray, disparity: np.ndarray, K: np.ndarray, baseline: float) -> np.ndarray:
    """3D points in the left camera frame from left pixels and disparities.

    ``Z = fu·B/d``, ``X = (u − cu)·Z/fu``, ``Y = (v − cv)·Z/fv``.

    Args:
      points_left: ``[N, 2]`` left pixels ``(u, v)``.
      disparity: ``[N]`` pixels, positive.
      K: ``[3, 3]`` intrinsics; baseline: metres.

    Returns:
      ``float64 [N, 3]`` metres.
    """
    fu, fv, cu, cv = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = fu * baseline / np.asarray(disparity, np.float64)
    x = (points_left[:, 0] - cu) * z / fu
    y = (points_left[:, 1] - cv) * z / fv
    return np.stack([x, y, z], axis=1)
