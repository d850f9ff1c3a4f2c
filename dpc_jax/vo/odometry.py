"""The per-frame stereo VO loop: track, match, estimate motion, fall back, replenish.

For every new rectified grey pair ``k+1`` (see :class:`StereoVO`):

1. The points of frame ``k`` (left pixels with a valid stereo match, triangulated in camera ``k``)
   are tracked into the left image ``k+1`` with KLT, started at their position predicted by the
   previous motion (constant velocity) and kept only if tracking back lands where they began.
2. Buckets left short are topped up with new FAST corners; tracked and new points are matched
   into the right image ``k+1`` along their rows (:func:`stereo.match_stereo`; the tracked ones
   start at the disparity predicted by the previous motion).
3. ``T_{k+1,k}`` from the 3D points of frame ``k`` and their left/right observations in frame
   ``k+1`` (:func:`motion.estimate_motion`: P3P RANSAC + Gauss–Newton in both cameras).
4. If that fails (fewer than ``min_inliers``), the previous relative pose is reused (constant
   velocity; identity for the first pair) and the pair is flagged ``CONSTANT_VELOCITY``.
5. The inliers and the new points with a stereo match in ``k+1`` are triangulated there (fresh
   depth every frame, so depth errors do not accumulate along a track).

The trajectory is composed as ``T_w_{k+1} = T_w_k · inv(T_{k+1,k})`` (docs/method.md §1) from the given
first pose (identity by default).
"""

from __future__ import annotations

import enum
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from dpc_jax.data.kitti import StereoSequence
from dpc_jax.runtime.progress import Progress, progress_bar
from dpc_jax.vo.features import detect_bucketed, track
from dpc_jax.vo.motion import camera_pixels, estimate_motion
from dpc_jax.vo.stereo import match_stereo, triangulate

STAGES = ("track", "detect", "stereo", "motion")
# A VO result that falls back to constant velocity on more than this share of its pairs is mostly
# extrapolated, not measured: ``dpc-jax vo`` warns, the demo refuses to train on it.
FALLBACK_WARNING_SHARE = 0.05


class VOStatus(enum.IntEnum):
    """Per-pair status: ``OK`` (motion estimated) or ``CONSTANT_VELOCITY`` (fallback used)."""

    OK = 0
    CONSTANT_VELOCITY = 1


@dataclass(frozen=True)
class VOConfig:
    """Parameters of the stereo VO (pixels refer to the full-resolution KITTI images).

    Attributes:
      bucket_size: ``(width, height)`` of a bucket in pixels.
      per_bucket: points kept per bucket (tracked + new).
      min_distance: pixels; minimum spacing of new corners (one per cell of this size).
      fast_threshold: FAST intensity threshold (grey levels).
      margin: pixels ignored at the image border when detecting.
      window: KLT window side in pixels.
      track_levels: pyramid levels above full resolution for temporal tracking.
      stereo_levels: pyramid levels for left–right matching (disparities up to ~2^levels·window/2).
      max_backward_error: px, forward–backward (circular) consistency for both trackers.
      max_row_error: px, allowed departure of a right match from its rectified row.
      min_disparity, max_disparity: px, accepted disparities, offset included (far and near limits).
      ransac_iterations, ransac_threshold: P3P RANSAC (threshold in px).
      inlier_threshold: px, reprojection error (both cameras) of an inlier after refinement.
      min_inliers: fewer inliers is a failure → constant-velocity fallback.
      refine_iterations: Gauss–Newton steps per refinement round.
      reweight: libviso2's weighting of points by their distance from the principal point column.
      disparity_offset: px added to every measured disparity (``d_true = d + offset``); the
        starting value when ``estimate_offset``.
      estimate_offset: self-calibrate the disparity offset online: each pair estimates it jointly
        with the motion (it is observable through the right-camera term, since an offset distorts
        near and far depths differently), under the previous pairs' estimate as a prior whose
        information decays by ``offset_forgetting`` per pair (a recursive least-squares filter).
      offset_forgetting: in (0, 1]; 1 never forgets.
    """

    bucket_size: tuple[int, int] = (50, 50)
    per_bucket: int = 4
    min_distance: int = 10
    fast_threshold: int = 12
    margin: int = 10
    window: int = 11
    track_levels: int = 3
    stereo_levels: int = 4
    max_backward_error: float = 0.5
    max_row_error: float = 1.0
    min_disparity: float = 1.0
    max_disparity: float = 200.0
    ransac_iterations: int = 100
    ransac_threshold: float = 2.0
    inlier_threshold: float = 1.5
    min_inliers: int = 20
    refine_iterations: int = 10
    reweight: bool = True
    disparity_offset: float = 0.0
    estimate_offset: bool = True
    offset_forgetting: float = 0.9


@dataclass
class FrameEstimate:
    """What :meth:`StereoVO.process` returns for a pair ``(k, k+1)``."""

    relative: np.ndarray
    inliers: int
    status: VOStatus
    tracked: int


@dataclass(frozen=True)
class VOResult:
    """Output of :func:`run_vo` for a sequence of ``N`` frames.

    Attributes:
      poses: ``float64 [N, 4, 4]`` camera-to-world ``T_w_k``; ``poses[0]`` is the first pose given.
      relative: ``float64 [N-1, 4, 4]`` ``T_{k+1,k}``.
      inliers: ``int [N-1]`` motion inliers per pair (0 on fallback).
      status: ``int8 [N-1]`` :class:`VOStatus` values.
      times: ``float64 [N-1]`` seconds of VO work per pair (frame ``k+1``; the initialisation of
        frame 0 is counted in the first pair), image loading excluded.
      disparity_offset: ``float64 [N-1]`` px, the disparity offset in use after each pair.
      stage_times: total seconds per stage (:data:`STAGES`).
    """

    poses: np.ndarray
    relative: np.ndarray
    inliers: np.ndarray
    status: np.ndarray
    times: np.ndarray
    disparity_offset: np.ndarray
    stage_times: dict[str, float] = field(default_factory=dict)


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    for name, image in (("left", left), ("right", right)):
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"{name} image must be grey uint8 [H, W], got {image.dtype} {image.shape}")
    if left.shape != right.shape:
        raise ValueError(f"left and right images differ in size: {left.shape} vs {right.shape}")


class StereoVO:
    """Stateful frame-to-frame stereo odometry over rectified grey pairs.

    Args:
      K: ``[3, 3]`` intrinsics of the (rectified) left camera, pixels.
      baseline: metres, right camera at ``+baseline`` along x.
      config: :class:`VOConfig`.

    ``process(left, right)`` returns ``None`` for the first pair and a :class:`FrameEstimate` for
    each later one. ``stage_times`` accumulates seconds per stage.
    """

    def __init__(self, K: np.ndarray, baseline: float, config: VOConfig | None = None) -> None:
        K = np.asarray(K, np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be a finite [3, 3] intrinsic matrix with fu, fv > 0, got {K!r}")
        if not (np.isfinite(baseline) and baseline > 0):
            raise ValueError(f"baseline must be a positive number of metres, got {baseline!r}")
        self.K = K
        self.baseline = float(baseline)
        self.config = config or VOConfig()
        self.stage_times = dict.fromkeys(STAGES, 0.0)
        self._previous: np.ndarray | None = None
        self._points = np.zeros((0, 2), np.float32)
        self._xyz = np.zeros((0, 3))
        self._velocity = np.eye(4)
        self.disparity_offset = float(self.config.disparity_offset)
        self._offset_information = 0.0

    def _timed(self, stage: str, start: float) -> float:
        now = time.perf_counter()
        self.stage_times[stage] += now - start
        return now

    def process(self, left: np.ndarray, right: np.ndarray) -> FrameEstimate | None:
        """Consume the next rectified grey pair (``uint8 [H, W]`` each)."""
        _check_pair(left, right)
        if self._previous is not None and left.shape != self._previous.shape:
            raise ValueError(f"image size changed from {self._previous.shape} to {left.shape}")
        c = self.config
        t = time.perf_counter()
        tracked = np.zeros((0, 2), np.float32)
        xyz = np.zeros((0, 3))
        disparity_guess = np.zeros(0)
        if self._previous is not None:
            predicted, in_front = camera_pixels(self._velocity, self._xyz, self.K)
            guess = np.where(in_front[:, None], predicted, self._points).astype(np.float32)
            tracked, ok = track(
                self._previous, left, self._points, guess,
                window=c.window, levels=c.track_levels, max_backward_error=c.max_backward_error,
            )
            xyz, tracked = self._xyz[ok], tracked[ok]
            z_next = xyz @ self._velocity[2, :3] + self._velocity[2, 3]
            predicted = self.K[0, 0] * self.baseline / np.maximum(z_next, 1e-6) - self.disparity_offset
            disparity_guess = np.where(z_next > 0, predicted, 0.0)
            t = self._timed("track", t)

        # New corners are detected before the motion is known, around every tracked point: one
        # left–right KLT call then serves the tracked and the new points together.
        new_points = detect_bucketed(
            left, tracked, bucket_size=c.bucket_size, per_bucket=c.per_bucket,
            min_distance=c.min_distance, threshold=c.fast_threshold, margin=c.margin,
        )
        t = self._timed("detect", t)
        points = np.concatenate([tracked, new_points])
        matched, stereo_ok = match_stereo(
            left, right, points, np.concatenate([disparity_guess, np.zeros(len(new_points))]),
            window=c.window, levels=c.stereo_levels, max_backward_error=c.max_backward_error,
            max_row_error=c.max_row_error, min_disparity=c.min_disparity - self.disparity_offset,
            max_disparity=c.max_disparity - self.disparity_offset,
        )
        t = self._timed("stereo", t)

        estimate = None
        keep = stereo_ok.copy()
        n = len(tracked)
        if self._previous is not None:
            right_observed = matched[:n] - np.array([self.disparity_offset, 0.0], np.float32)
            motion = estimate_motion(
                xyz, tracked, right_observed, stereo_ok[:n], self.K, self.baseline,
                ransac_iterations=c.ransac_iterations, ransac_threshold=c.ransac_threshold,
                inlier_threshold=c.inlier_threshold, min_inliers=c.min_inliers,
                refine_iterations=c.refine_iterations, reweight=c.reweight,
                offset_prior=c.offset_forgetting * self._offset_information if c.estimate_offset else None,
            )
            if motion.success:
                self._velocity = motion.T
                self.disparity_offset += motion.offset_increment
                self._offset_information = motion.offset_information
                keep[:n] &= motion.inliers
                estimate = FrameEstimate(motion.T, int(motion.inliers.sum()), VOStatus.OK, n)
            else:
                estimate = FrameEstimate(self._velocity.copy(), 0, VOStatus.CONSTANT_VELOCITY, n)
            t = self._timed("motion", t)
        # The offset may have moved during this pair: the disparity range is checked again.
        disparity_now = points[:, 0] - matched[:, 0] + self.disparity_offset
        keep &= (disparity_now >= c.min_disparity) & (disparity_now <= c.max_disparity)
        self._points = points[keep]
        disparity = self._points[:, 0] - matched[keep, 0] + self.disparity_offset
        self._xyz = triangulate(self._points, disparity, self.K, self.baseline)
        self._previous = left
        self._timed("stereo", t)
        return estimate


def run_vo_frames(
    frames: Iterable[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    baseline: float,
    config: VOConfig | None = None,
    *,
    first_pose: np.ndarray | None = None,
    total: int | None = None,
    progress: Progress = False,
) -> VOResult:
    """Run :class:`StereoVO` over an iterable of grey ``(left, right)`` pairs.

    Args:
      frames: rectified grey ``uint8 [H, W]`` pairs, in order (at least two).
      K, baseline: intrinsics (pixels) and baseline (metres).
      first_pose: ``[4, 4]`` camera-to-world pose of frame 0 (identity when ``None``).
      total: number of frames, for the progress bar only.
      progress: a bar, or lines in a log (``dpc_jax.runtime.progress``).
    """
    vo = StereoVO(K, baseline, config)
    start = np.eye(4) if first_pose is None else np.asarray(first_pose, np.float64)
    poses, relative, inliers, status, times, offsets = [start], [], [], [], [], []
    pending = 0.0
    with progress_bar(total or 0, "vo", progress) as bar:
        for left, right in frames:
            t = time.perf_counter()
            estimate = vo.process(left, right)
            elapsed = time.perf_counter() - t
            bar.update(1)
            if estimate is None:
                pending += elapsed
                continue
            relative.append(estimate.relative)
            poses.append(poses[-1] @ np.linalg.inv(estimate.relative))
            inliers.append(estimate.inliers)
            status.append(int(estimate.status))
            times.append(elapsed + pending)
            offsets.append(vo.disparity_offset)
            pending = 0.0
    if not relative:
        raise ValueError("stereo VO needs at least two frames")
    return VOResult(
        poses=np.stack(poses),
        relative=np.stack(relative),
        inliers=np.asarray(inliers, np.int64),
        status=np.asarray(status, np.int8),
        times=np.asarray(times),
        disparity_offset=np.asarray(offsets),
        stage_times=dict(vo.stage_times),
    )


def _sequence_frames(sequence: StereoSequence) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The grey pairs of ``sequence``, in order; ``ValueError`` naming the file (or message) and frame for an
    image whose size is not the sequence's (the size its calibration was checked against)."""
    for frame in sequence.images.stream(sequence.image_size):
        yield frame.decode(grey=True)


def run_vo(
    sequence: StereoSequence,
    config: VOConfig | None = None,
    *,
    first_pose: np.ndarray | None = None,
    progress: Progress = False,
) -> VOResult:
    """Stereo VO over a sequence opened with :func:`dpc_jax.data.kitti.open_odometry` / ``open_raw``.

    Colour images are converted to grey on loading. ``first_pose``: camera-to-world pose of frame 0
    (identity when ``None``; pass ``sequence.poses[0]`` to start at the ground truth).

    Raises ``FileNotFoundError``/``ValueError`` naming the file (or message) when an image is missing or
    unreadable.
    """
    return run_vo_frames(
        _sequence_frames(sequence), sequence.K, sequence.baseline, config,
        first_pose=first_pose, total=len(sequence), progress=progress,
    )


class VOSummary(TypedDict):
    """The counts of a VO run (:func:`summary`)."""

    frames: int
    pairs: int
    fallbacks: int
    fallback_share: float
    median_inliers: float
    disparity_offset_px: float
    disparity_offset_median_px: float
    warning: str | None


def summary(result: VOResult) -> VOSummary:
    """Counts of a VO run: frames, fallbacks and their share, median inliers, the final disparity
    offset and its median over the second half of the run (the online estimate settles within tens
    of pairs: the rig's calibration residual as measured), and ``warning`` (a sentence, or None)
    when the fallback share exceeds :data:`FALLBACK_WARNING_SHARE`."""
    pairs = int(result.status.size)
    fallbacks = int(np.count_nonzero(result.status != VOStatus.OK))
    share = fallbacks / pairs
    warning = None
    if share > FALLBACK_WARNING_SHARE:
        warning = (f"{fallbacks} of {pairs} pairs ({100 * share:.0f} %) fell back to constant velocity, more "
                   f"than {100 * FALLBACK_WARNING_SHARE:.0f} %: the trajectory is largely extrapolated, not "
                   "measured (images too small, too noisy or too dark for the tracker?)")
    return {
        "frames": int(result.poses.shape[0]),
        "pairs": pairs,
        "fallbacks": fallbacks,
        "fallback_share": share,
        "median_inliers": float(np.median(result.inliers)),
        "disparity_offset_px": float(result.disparity_offset[-1]),
        "disparity_offset_median_px": float(np.median(result.disparity_offset[pairs // 2:])),
        "warning": warning,
    }


def per_frame_table(result: VOResult, first_frame: int = 0) -> str:
    """CSV text, one row per pair ``(k, k+1)``: ``frame`` (= k+1, numbered in the source sequence:
    ``first_frame`` is the number of the run's frame 0), ``inliers``, ``status``,
    ``disparity_offset_px``, ``time_s``."""
    rows = ["frame,inliers,status,disparity_offset_px,time_s"]
    for k, (inliers, status, offset, seconds) in enumerate(
        zip(result.inliers, result.status, result.disparity_offset, result.times, strict=True)
    ):
        status_name = VOStatus(int(status)).name.lower()
        rows.append(f"{first_frame + k + 1},{inliers},{status_name},{offset:.4f},{seconds:.6f}")
    return "\n".join(rows) + "\n"
