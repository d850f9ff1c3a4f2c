"""Depth from a rectified stereo pair with OpenCV's semi-global matching, independent of any network.

The acceptance test (``dpc_jax.correction.acceptance``) can measure a correction's photometric effect with
this depth instead of the network's own, so that the test does not lean on a depth that was
trained together with the pose it judges. Metric through the baseline: ``1/Z = d / (fu · B)``
(docs/method.md §1). Numpy/OpenCV only.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import Executor, ThreadPoolExecutor

import cv2
import numpy as np

from dpc_jax.data.sequence_cache import disparity_valid, inverse_depth_from_disparity

# Nearest depth (m) the disparity search covers; nearer pixels are left out (invalid).
MIN_DEPTH = 1.5


def _matcher(max_disparity: float, block: int) -> cv2.StereoSGBM:
    channels = 1
    return cv2.StereoSGBM_create(  # type: ignore[attr-defined]  # missing from cv2's stubs
        minDisparity=0,
        numDisparities=16 * max(1, math.ceil(max_disparity / 16)),
        blockSize=block,
        P1=8 * channels * block * block,
        P2=32 * channels * block * block,
        uniquenessRatio=5,
        disp12MaxDiff=1,
        mode=cv2.STEREO_SGBM_MODE_HH,
    )


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def sgbm_fits(width: int, fu: float, baseline: float, block: int = 5) -> bool:
    """Whether images ``width`` px wide leave StereoSGBM room for its disparity search (down to
    :data:`MIN_DEPTH`) and window; narrower ones make OpenCV refuse the pair."""
    search = 16 * max(1, math.ceil(float(fu) * float(baseline) / MIN_DEPTH / 16))
    return width - search > block // 2


def sgbm_disparity(
    left: np.ndarray, right: np.ndarray, fu: float, baseline: float, block: int = 5,
    pool: Executor | None = None,
) -> np.ndarray:
    """StereoSGBM disparity of both cameras of one rectified pair, in SGBM's own fixed point.

    ``left``, ``right``: uint8 ``[H, W, 3]`` RGB (or ``[H, W]`` grey); ``fu``: focal length (px)
    of these images; ``baseline`` (m). Returns int16 ``[camera, H, W]`` (left, right) in 1/16 px
    (``DISPARITY_UNITS``), ≤ 0 where there is no match (occluded, or nearer than
    :data:`MIN_DEPTH`): exactly what OpenCV computes, 2 bytes a pixel, which is what a cache
    stores. The right camera's disparity is computed by matching the mirrored pair (the right
    image becomes the reference); with ``pool`` on one of its threads, beside the left camera's (the
    same numbers: a matcher each, OpenCV releases the interpreter while it matches).
    """
    if left.shape != right.shape or left.dtype != np.uint8:
        raise ValueError(f"need two uint8 images of one size, got {left.dtype} {left.shape}, {right.shape}")
    if not (fu > 0 and baseline > 0):
        raise ValueError(f"fu and baseline must be positive, got {fu}, {baseline}")
    search = float(fu) * float(baseline) / MIN_DEPTH
    grey_l, grey_r = _grey(left), _grey(right)
    mirrored = (grey_r[:, ::-1].copy(), grey_l[:, ::-1].copy())

    def matched(reference: np.ndarray, other: np.ndarray) -> np.ndarray:
        return _matcher(search, block).compute(reference, other)

    right_job = None if pool is None else pool.submit(matched, *mirrored)
    out = np.empty((2, *grey_l.shape), np.int16)
    out[0] = matched(grey_l, grey_r)
    out[1] = (matched(*mirrored) if right_job is None else right_job.result())[:, ::-1]
    return out


def sgbm_inverse_depth(
    left: np.ndarray, right: np.ndarray, fu: float, baseline: float, block: int = 5
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse depth (1/m) of both cameras of one rectified pair by StereoSGBM
    (:func:`sgbm_disparity`, ``1/Z = d / (fu · B)``).

    Returns ``(inv_left, valid_left, inv_right, valid_right)``, float32 / bool ``[H, W]``;
    invalid pixels hold 0.
    """
    fixed = sgbm_disparity(left, right, fu, baseline, block)
    inverse = inverse_depth_from_disparity(fixed, float(fu) * float(baseline))
    valid = disparity_valid(fixed)
    return inverse[0], valid[0], inverse[1], valid[1]


def sequence_inverse_depth(
    left: np.ndarray, right: np.ndarray, fu: float, baseline: float, *, workers: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sgbm_inverse_depth` of every frame: ``left``/``right`` uint8 ``[N, H, W, 3]`` →
    ``(inverse depth float32 [N, 2, H, W], valid bool [N, 2, H, W])``, camera axis (left, right).

    ``workers`` threads match frames in parallel (OpenCV releases the GIL; default: CPU count);
    each frame's result does not depend on them.
    """
    fixed = np.empty((left.shape[0], 2, *left.shape[1:3]), np.int16)

    def frame(k: int) -> None:
        fixed[k] = sgbm_disparity(left[k], right[k], fu, baseline)

    with ThreadPoolExecutor(workers or os.cpu_count() or 1) as pool:
        list(pool.map(frame, range(left.shape[0])))
    return inverse_depth_from_disparity(fixed, float(fu) * float(baseline)), disparity_valid(fixed)
