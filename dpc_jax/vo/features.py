"""Bucketed corner detection and pyramidal KLT tracking with a forward–backward check.

Images are grey ``uint8 [H, W]``; points are ``float32 [N, 2]`` pixel coordinates ``(u, v)``
(column, row) of the image they lie in. (OpenCV's Python binding of ``calcOpticalFlowPyrLK`` does
not accept prebuilt pyramids, so each call builds its own; the caller batches points to keep the
number of calls per frame small.)

Bucketing (as in libviso2) spreads features over the whole image: a rotation is best
constrained by far points everywhere in the field of view and a translation by near points, so
a detector left to itself (which favours one richly textured region) gives poorer motion.
"""

from __future__ import annotations

import cv2
import numpy as np


def detect_bucketed(
    image: np.ndarray,
    existing: np.ndarray,
    *,
    bucket_size: tuple[int, int],
    per_bucket: int,
    min_distance: int,
    threshold: int,
    margin: int,
) -> np.ndarray:
    """New FAST corners in the buckets that hold fewer than ``per_bucket`` existing points.

    Args:
      image: grey ``uint8 [H, W]``.
      existing: ``[M, 2]`` points already tracked; each bucket is topped up to ``per_bucket``
        and no new corner lies in the same or a neighbouring ``min_distance`` cell as one of them.
      bucket_size: ``(width, height)`` of a bucket in pixels.
      per_bucket: target number of points per bucket.
      min_distance: pixels; at most one new corner per ``min_distance`` cell (strongest wins).
      threshold: FAST intensity threshold (grey levels).
      margin: pixels; corners closer than this to the border are ignored (the KLT window must fit).

    Returns:
      ``float32 [K, 2]`` new corners, strongest first within each bucket.
    """
    height, width = image.shape
    keypoints = cv2.FastFeatureDetector_create(threshold, True).detect(image)  # type: ignore[attr-defined]  # missing from cv2's stubs
    if not keypoints:
        return np.zeros((0, 2), np.float32)
    points = np.array([k.pt for k in keypoints], np.float32)
    response = np.array([k.response for k in keypoints], np.float32)
    inside = (
        (points[:, 0] >= margin) & (points[:, 0] < width - margin)
        & (points[:, 1] >= margin) & (points[:, 1] < height - margin)
    )
    points, response = points[inside], response[inside]
    order = np.argsort(-response, kind="stable")
    points = points[order]

    cells_w = width // min_distance + 1
    cells_h = height // min_distance + 1
    cell = (points[:, 1] // min_distance).astype(np.int64) * cells_w + (points[:, 0] // min_distance).astype(
        np.int64
    )
    occupied = np.zeros((cells_h, cells_w), np.uint8)
    if len(existing):
        ex = np.clip((existing // min_distance).astype(np.int64), 0, [cells_w - 1, cells_h - 1])
        occupied[ex[:, 1], ex[:, 0]] = 1
        occupied = cv2.dilate(occupied, np.ones((3, 3), np.uint8))
    # One corner per cell, the strongest: np.unique returns the first index of each value, and
    # the points are sorted by decreasing response.
    _, first = np.unique(cell, return_index=True)
    first = np.sort(first)
    first = first[occupied.ravel()[cell[first]] == 0]
    points = points[first]

    buckets_w = -(-width // bucket_size[0])
    buckets_h = -(-height // bucket_size[1])
    n_buckets = buckets_w * buckets_h

    def bucket_of(p: np.ndarray) -> np.ndarray:
        bx = np.clip((p[:, 0] // bucket_size[0]).astype(np.int64), 0, buckets_w - 1)
        by = np.clip((p[:, 1] // bucket_size[1]).astype(np.int64), 0, buckets_h - 1)
        return by * buckets_w + bx

    quota = per_bucket - np.bincount(bucket_of(existing), minlength=n_buckets) if len(existing) else np.full(
        n_buckets, per_bucket
    )
    bucket = bucket_of(points)
    # Rank of each point within its bucket (the points are already sorted by response).
    by_bucket = np.argsort(bucket, kind="stable")
    sorted_bucket = bucket[by_bucket]
    starts = np.searchsorted(sorted_bucket, sorted_bucket, side="left")
    rank = np.empty(len(points), np.int64)
    rank[by_bucket] = np.arange(len(points)) - starts
    return points[rank < quota[bucket]]


def track(
    image_from: np.ndarray,
    image_to: np.ndarray,
    points: np.ndarray,
    guess: np.ndarray,
    *,
    window: int,
    levels: int,
    max_backward_error: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas–Kanade from one image into another, kept only if tracking back agrees.

    Args:
      image_from, image_to: grey ``uint8 [H, W]`` images.
      points: ``float32 [N, 2]`` points in the first image.
      guess: ``float32 [N, 2]`` initial positions in the second image (e.g. predicted by the
        previous motion, or shifted by a guessed disparity); the pyramid absorbs what is left.
      window: KLT window side in pixels.
      levels: pyramid levels above the full resolution.
      max_backward_error: pixels; a point tracked back must land this close to where it started.

    Returns:
      ``(tracked [N, 2] float32, ok [N] bool)``; entries with ``ok`` false are meaningless.
    """
    if len(points) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    points = np.ascontiguousarray(points, np.float32)
    forward, status_f, _ = cv2.calcOpticalFlowPyrLK(
        image_from, image_to, points, np.ascontiguousarray(guess, np.float32).copy(),
        winSize=(window, window), maxLevel=levels, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    backward, status_b, _ = cv2.calcOpticalFlowPyrLK(
        image_to, image_from, forward, points.copy(),
        winSize=(window, window), maxLevel=levels, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    height, width = image_to.shape
    ok = (
        (status_f.ravel() == 1) & (status_b.ravel() == 1)
        & (np.linalg.norm(backward - points, axis=1) < max_backward_error)
        & (forward[:, 0] >= 0) & (forward[:, 0] <= width - 1)
        & (forward[:, 1] >= 0) & (forward[:, 1] <= height - 1)
    )
    return forward, ok
