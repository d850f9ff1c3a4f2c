"""Our VO over a sequence as a prior file: run once, then reused while its inputs are unchanged.

:func:`write_vo_prior` writes the trajectory (KITTI pose text) and beside it a record ``NAME.json``:
``inputs`` (a hash of the sequence's files, the VO configuration and the first pose, as
``dpc_jax.data.cache.input_hash`` identifies a cache's inputs) and the run's
``dpc_jax.vo.odometry.summary`` and the SHA-256 of the trajectory file it describes. A later call with
the same inputs and that very file reads the record instead of running the VO again; any change (other
images, another VO configuration, a changed VO code version, the file edited) runs it again.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax._io import atomic_write
from dpc_jax.data.kitti import StereoSequence
from dpc_jax.data.poses_io import write_kitti_poses
from dpc_jax.runtime.progress import Progress
from dpc_jax.vo.odometry import VOConfig, run_vo, summary

# Bump when the VO's output changes for the same inputs, so stored priors are recomputed.
VO_VERSION = 1


def write_vo_prior(
    sequence: StereoSequence,
    path: str | os.PathLike,
    config: VOConfig | None = None,
    *,
    first_pose: np.ndarray | None = None,
    progress: Progress = False,
) -> dict[str, Any]:
    """Our VO over ``sequence`` (from ``first_pose``, identity by default) as KITTI poses at ``path``
    and its record ``path`` with suffix ``.json``; reused when current. Returns the record's
    summary with ``path``."""
    from dpc_jax.data.cache import input_hash

    config = config or VOConfig()
    path = Path(path)
    record_path = path.with_suffix(".json")
    start = np.eye(4) if first_pose is None else np.asarray(first_pose, np.float64)
    parameters = {"vo_version": VO_VERSION, "vo_config": dataclasses.asdict(config)}
    inputs = input_hash(sequence, start, parameters)
    if path.is_file() and record_path.is_file():
        try:
            record = json.loads(record_path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError):
            record = {}
        # The trajectory the record describes: a file edited or replaced since is run again (a record
        # of an earlier version, without the digest, is taken at its word).
        written = record.get("sha256")
        if record.get("inputs") == inputs and (written is None or written == _digest(path)):
            return {**record["summary"], "path": str(path)}
    result = run_vo(sequence, config, first_pose=start, progress=progress)
    counts = summary(result)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_kitti_poses(path, result.poses)
    atomic_write(record_path, json.dumps({"inputs": inputs, "sha256": _digest(path), "summary": counts},
                                         indent=2) + "\n")
    return {**counts, "path": str(path)}


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
