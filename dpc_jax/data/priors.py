"""Visual-odometry priors: loading estimates, checking them against the frames, ξ_vo, rescaling.

A prior is the VO estimate of the whole sequence, camera-to-world ``[N, 4, 4]`` (docs/method.md §1),
one pose per camera frame. The network sees the relative poses ``T_vo_{t+1,t}`` as
``ξ_vo = Log(T_vo_{t+1,t})``.

A prior knows its frames where ``dpc-jax vo`` wrote it: the record beside the trajectory (its path
with suffix ``.json``) holds ``source_frames = [START, STOP]``, the source frames it estimated
(:func:`recorded_frames`). Such a prior is taken only for frames inside that range, whatever its
length; a prior without a record is taken by its length, one pose per frame.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dpc_jax.data import poses_io
from dpc_jax.data.poses_io import validate_poses
from dpc_jax.geometry.poses import compose, log_poses, relative_poses

if TYPE_CHECKING:
    from dpc_jax.data.sequence_cache import SequenceCache


# The key of a prior's record (``dpc-jax vo``'s summary beside the trajectory) that holds its frames.
FRAMES_KEY = "source_frames"


def recorded_frames(path: str | os.PathLike[str], n_poses: int) -> tuple[int, int] | None:
    """The source frames ``(start, stop)`` of the prior file ``path`` (holding ``n_poses`` poses) as
    its record says (``path`` with suffix ``.json``, written by ``dpc-jax vo``), or None when there is
    no record: no such file, not a JSON object, or no ``source_frames`` in it.

    Raises ``ValueError`` naming the record when its range is not ``[START, STOP]`` with
    ``0 <= START < STOP`` or does not hold ``n_poses`` frames (it describes another trajectory).
    """
    record_path = Path(path).with_suffix(".json")
    if record_path == Path(path) or not record_path.is_file():
        return None
    try:
        record = json.loads(record_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(record, dict) or FRAMES_KEY not in record:
        return None
    frames = record[FRAMES_KEY]
    if not (isinstance(frames, list) and len(frames) == 2 and all(type(v) is int for v in frames)
            and 0 <= frames[0] < frames[1]):
        raise ValueError(f"{record_path}: field {FRAMES_KEY!r} is {frames!r}; expected [START, STOP] with "
                         "0 <= START < STOP")
    start, stop = frames
    if stop - start != n_poses:
        raise ValueError(f"{record_path}: records frames {start}:{stop} for {path}, which holds {n_poses} "
                         "poses; the record is another trajectory's: write the prior again with `dpc-jax vo` "
                         "or remove the record")
    return start, stop


def _outside_record(
    label: str, recorded: tuple[int, int], record_path: Path, wanted: str, hint: str
) -> ValueError:
    """The refusal of a prior whose recorded frames do not hold the frames ``wanted`` (words)."""
    return ValueError(f"{label}: holds the VO of frames {recorded[0]}:{recorded[1]} (recorded in "
                      f"{record_path}), not of {wanted}; {hint}")


def load_prior(
    source: str | Path | np.ndarray, n_frames: int, format: str | None = None,
    *, frames: tuple[int, int] | None = None,
) -> np.ndarray:
    """VO estimate ``[N, 4, 4]`` float64, checked to hold one rigid pose per frame.

    ``source``: an array ``[N, 4, 4]`` or ``[N, 3, 4]``, or a file: KITTI pose text, TUM text, or
    the ss-DPC-Net ``.mat`` layout (its ``poses_est``). ``format`` (``kitti``|``tum``|``mat``)
    overrides the guess from the extension. ``frames``: the ``(start, stop)`` range that will be cut
    from the sequence of ``n_frames`` frames (None: all of them).

    A file with a record of its frames (:func:`recorded_frames`) is taken when the record's range
    holds the frames asked for, and only their poses are returned (``stop - start``, or
    ``n_frames`` without ``frames``); a record of other frames raises ``ValueError`` naming both
    files. Without a record the count decides: a prior of ``n_frames`` poses is the whole
    sequence's (returned whole), and with ``frames`` one of exactly ``stop - start`` poses (what
    ``dpc-jax vo --frames START:STOP`` writes) is taken as the range's own and returned as it is.
    Raises ``ValueError`` naming the source when the count fits neither or a pose is not rigid.
    """
    path = None
    if isinstance(source, np.ndarray):
        label = "prior array"
        poses = validate_poses(source, label)
        recorded = None
    else:
        path = Path(source)
        label = str(path)
        if format is not None and format not in poses_io.FORMATS:
            raise ValueError(f"{path}: unknown prior format {format!r}; expected one of {poses_io.FORMATS}")
        poses = poses_io.read_trajectory(path, format)
        recorded = recorded_frames(path, poses.shape[0])
    if recorded is not None and path is not None:
        start, stop = frames if frames is not None else (0, n_frames)
        if recorded[0] <= start and stop <= recorded[1] <= n_frames:
            return poses[start - recorded[0]:stop - recorded[0]]
        wanted = (f"frames {start}:{stop} (--frames {start}:{stop})" if frames is not None
                  else f"the {n_frames} frames 0:{n_frames} of the sequence")
        hint = (f"the sequence has {n_frames} frames, so the prior is another sequence's"
                if recorded[1] > n_frames else
                f"write the prior of frames {start}:{stop} with `dpc-jax vo --frames {start}:{stop}`"
                if frames is not None else
                f"pass --frames {recorded[0]}:{recorded[1]} to take the frames it estimated")
        raise _outside_record(label, recorded, path.with_suffix(".json"), wanted, hint)
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
    (``cache.indices``) are taken; a file with a record of its frames (:func:`recorded_frames`) is
    taken when its range holds every cached frame, whose poses are taken from it, and refused
    otherwise. It is used as is (no monocular rescaling). Needs no JAX, so the command line checks a
    ``--prior`` with it before JAX starts.
    """
    n = len(cache)
    n_source = int(cache.manifest.get("n_source_frames", n))
    start = int(cache.manifest.get("parameters", {}).get("frames", [0])[0])
    record_path, recorded = None, None
    if isinstance(source, np.ndarray):
        label, poses = "prior array", validate_poses(source, "prior array")
    else:
        label, poses = str(source), poses_io.read_trajectory(source, format)
        record_path, recorded = Path(source).with_suffix(".json"), recorded_frames(source, poses.shape[0])
    indices = np.asarray(cache.indices)
    if recorded is not None and record_path is not None:
        if recorded[0] <= int(indices.min()) and int(indices.max()) < recorded[1]:
            return poses[indices - recorded[0]]
        wanted = f"the frames {start}:{start + n_source} of the cache {cache.path}"
        hint = "give the prior of those frames, or leave out --prior to correct the cache's own"
        raise _outside_record(label, recorded, record_path, wanted, hint)
    if poses.shape[0] == n:
        return poses
    if poses.shape[0] == n_source:
        return poses[indices - start]
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
