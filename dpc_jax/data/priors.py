"""Visual-odometry priors: loading estimates, checking them against the frames, ξ_vo, rescaling.

A prior is the VO estimate of the whole sequence, camera-to-world ``[N, 4, 4]`` (docs/method.md §1),
one pose per camera frame. The network sees the relative poses ``T_vo_{t+1,t}`` as
``ξ_vo = Log(T_vo_{t+1,t})``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dpc_jax.data import poses_io
from dpc_jax.data.poses_io import validate_poses
from dpc_jax.geometry.poses import compose, log_poses, relative_poses

if TYPE_CHECKING:
    from dpc_jax.data.sequence_cache import SequenceCache


def load_prior(
    source: str | Path | np.ndarray, n_frames: int, format: str | None = None,
    *, frames: tuple[int, int] | None = None,
) -> np.ndarray:
    """VO estimate ``[N, 4, 4]`` float64, checked to hold one rigid pose per frame.

    ``source``: an array ``[N, 4, 4]`` or ``[N, 3, 4]``, or a file: KITTI pose text, TUM text, or
    the ss-DPC-Net ``.mat`` layout (its ``poses_est``). ``format`` (``kitti``|``tum``|``mat``)
    overrides the guess from the extension. Raises ``ValueError`` naming the source when the
    count differs from ``n_frames`` or a pose is not rigid. ``frames``: the ``(start, stop)`` range
    that will be cut from the sequence; a prior of exactly that many poses (what ``dpc-jax vo
    --frames START:STOP`` writes) is taken as the range's own and returned as it is, shorter than
    ``n_frames``.
    """
    if isinstance(source, np.ndarray):
        label = "prior array"
        poses = validate_poses(source, label)
    else:
        path = Path(source)
        label = str(path)
        if format is not None and format not in poses_io.FORMATS:
            raise ValueError(f"{path}: unknown prior format {format!r}; expected one of {poses_io.FORMATS}")
        poses = poses_io.read_trajectory(path, format)
    if frames is not None and poses.shape[0] == frames[1] - frames[0]:
        return poses
    if poses.shape[0] != n_frames:
        also = "" if frames is None else f", or one per frame of the range {frames[0]}:{frames[1]}"
        raise ValueError(
            f"{label}: {poses.shape[0]} prior poses for {n_frames} frames; expected one pose per frame{also}"
        )
    return poses


def prior_for_cache(
    cache: SequenceCache, source: str | os.PathLike[str] | np.ndarray, format: str | None = None
) -> np.ndarray:
    """A replacement VO prior for the frames of ``cache`` → ``[len(cache), 4, 4]`` float64.

    ``source`` (array, or KITTI/TUM/``.mat`` file as in :func:`dpc_jax.data.poses_io.read_trajectory`)
    holds either one pose per cached frame, or one pose per frame of the source range the cache
    was prepared from (``manifest["n_source_frames"]``), of which the cached frames
    (``cache.indices``) are taken. It is used as is (no monocular rescaling). Needs no JAX, so the
    command line checks a ``--prior`` with it before JAX starts.
    """
    n = len(cache)
    n_source = int(cache.manifest.get("n_source_frames", n))
    start = int(cache.manifest.get("parameters", {}).get("frames", [0])[0])
    if isinstance(source, np.ndarray):
        label, poses = "prior array", validate_poses(source, "prior array")
    else:
        label, poses = str(source), poses_io.read_trajectory(source, format)
    if poses.shape[0] == n:
        return poses
    if poses.shape[0] == n_source:
        return poses[np.asarray(cache.indices) - start]
    expected = f"{n}" if n_source == n else f"{n}, one per cached frame, or {n_source}, one per source frame"
    raise ValueError(
        f"{label}: {poses.shape[0]} prior poses for the sequence in {cache.path}; expected {expected}"
    )


def relative_xi(poses: np.ndarray) -> np.ndarray:
    """``ξ_{t+1,t} = Log(inv(T_{t+1}) T_t)`` of a trajectory ``[N, 4, 4]`` → ``[N-1, 6]`` (m, rad)."""
    return log_poses(relative_poses(poses))


def rescale_monocular(prior: np.ndarray, ground_truth: np.ndarray) -> np.ndarray:
    """Monocular prior with each step's translation rescaled to the ground-truth step length.

    ss-DPC-Net protocol: for every pair the relative translation of the (scale-free) monocular
    estimate is scaled so that its norm equals ``‖t_gt_{t+1,t}‖``; rotations are kept. The
    rescaled steps are composed from the ground-truth first pose. A step whose estimated
    translation is exactly zero has no direction to scale and stays zero.
    Inputs and output ``[N, 4, 4]`` float64.
    """
    if prior.shape != ground_truth.shape:
        raise ValueError(
            f"prior {prior.shape} and ground truth {ground_truth.shape} must have the same shape"
        )
    rel = relative_poses(prior).copy()
    gt_dist = np.linalg.norm(relative_poses(ground_truth)[:, :3, 3], axis=1)
    est_dist = np.linalg.norm(rel[:, :3, 3], axis=1)
    scale = np.divide(gt_dist, est_dist, out=np.zeros_like(gt_dist), where=est_dist > 0)
    rel[:, :3, 3] *= scale[:, None]
    return compose(rel, ground_truth[0])
