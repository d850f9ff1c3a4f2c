"""What a corrected sequence leaves behind, written all or nothing: the corrected trajectory (with
its frame list), optionally its report, and after adaptation the adapted network.

``dpc-jax correct``, the experiment protocol and the demo write a
:class:`~dpc_jax.correction.corrector.CorrectedSequence` with :func:`write_corrected`, each naming
its places in :class:`CorrectionOutputs`. Importing this module needs no JAX: the command line takes
:func:`adapted_path` and :data:`REPORT_FILES` for its checks before JAX starts.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import OutputSet, is_stream, record_beside, record_own_files
from dpc_jax.report.evaluation_report import REPORT_FILES as EVALUATION_FILES
from dpc_jax.sources.odometry_out import recording_kind

if TYPE_CHECKING:
    from dpc_jax.correction.corrector import CorrectedSequence
    from dpc_jax.results.correction import Correction

# Every file a report folder may receive (dpc_jax.report.correction_report.write_correction_report):
# with ground truth the evaluation's report and metrics.json, and always report.md and summary.json.
REPORT_FILES = (*EVALUATION_FILES, "metrics.json", "summary.json")
# Who the report's files are recorded as written by (dpc_jax._io.record_own_files): a later
# `correct --report` may replace them, no other writer's.
REPORT_WRITER = "correct --report"


def adapted_path(trajectory: str | os.PathLike[str]) -> Path:
    """Where ``dpc-jax correct --adapt`` puts the adapted network: ``corrected.txt`` →
    ``corrected.adapted/`` beside it."""
    path = Path(trajectory)
    return path.with_name(f"{path.stem}.adapted")


@dataclass(frozen=True)
class CorrectionOutputs:
    """Where :func:`write_corrected` writes.

    ``trajectory``: the corrected trajectory: a KITTI or TUM text file (``format`` ``kitti`` or
    ``tum``; a stream such as ``-`` takes the poses alone), a recording named ``.mcap`` or ``.bag``,
    or with ``format="rosbag2"`` a ROS 2 bag folder (``nav_msgs/Odometry`` of the corrected
    trajectory and the prior at the frames' stamps: ``first_stamp`` ns plus the frame times, in the
    ``frame_ids`` (world, camera) of the recording read, if any). ``report``: a folder for the
    correction's report (None: none). ``adapted``: a folder for the adapted network, written when the
    sequence was adapted (None: not kept).
    """

    trajectory: Path
    format: str = "kitti"
    report: Path | None = None
    adapted: Path | None = None
    first_stamp: int = 0
    frame_ids: tuple[str, str] = ("world", "camera")


def output_recording(out: str | Path, format: str) -> str | None:
    """The kind of recording the trajectory ``out`` of ``format`` is written as (``mcap``, ``ros1`` by its
    name, ``rosbag2`` by ``format``), or None for a pose text file."""
    return recording_kind(out) or ("rosbag2" if format == "rosbag2" else None)


def write_corrected(done: CorrectedSequence, to: CorrectionOutputs) -> list[Path]:
    """Write the final correction of ``done`` (its ``result``), its report and the adapted network
    where ``to`` says, all or nothing (:class:`~dpc_jax._io.OutputSet`); missing folders are created.
    Returns the trajectory's files: the trajectory, then its frame list when one was written
    (:func:`~dpc_jax.correction.corrector.write_trajectory`)."""
    from dpc_jax.correction.adapt import save_adapted
    from dpc_jax.correction.corrector import write_trajectory
    from dpc_jax.report.correction_report import write_correction_report

    correction, out = done.result, Path(to.trajectory)
    with OutputSet() as outputs:
        kind = output_recording(out, to.format)
        if kind is not None:
            staged = [_write_recording(outputs, out, kind, correction, to)]
        else:
            staged = write_trajectory(outputs.file(out), correction, to.format)
            if not is_stream(out):
                record_beside([out.parent / path.name for path in staged[1:]], outputs)
        if to.report is not None:
            folder = outputs.folder(to.report)
            reported = write_correction_report(folder, correction, f"DPC correction: {correction.name}")
            record_own_files(folder, to.report, [path.name for path in reported], writer=REPORT_WRITER)
        if to.adapted is not None and done.adaptation is not None and done.adapted is not None:
            save_adapted(outputs.folder(to.adapted), done.adaptation,
                         {"delta": done.adapted.acceptance.mean_delta})
        outputs.commit()
    if is_stream(out):
        # A stream takes the trajectory only; the frame list staged beside it is not made.
        return [out]
    return [out.parent / path.name for path in staged]


def _write_recording(
    outputs: OutputSet, out: Path, kind: str, correction: Correction, to: CorrectionOutputs
) -> Path:
    """Stage ``out`` as a recording of ``kind`` holding the corrected trajectory and the prior; return
    its final path."""
    import numpy as np

    from dpc_jax.geometry.poses import invert_poses
    from dpc_jax.sources.odometry_out import CORRECTED, PRIOR, write_odometry

    stamps = to.first_stamp + np.round(np.asarray(correction.times, np.float64) * 1e9).astype(np.int64)
    # Both topics are in the prior's world frame (its frame id): the corrected trajectory starts where the
    # prior does, not at the ground truth's first pose that the text outputs and the evaluation start from.
    corrected, prior = correction.corrected, correction.prior
    on_prior = prior[0] @ invert_poses(corrected[:1])[0] @ corrected
    trajectories = {CORRECTED: on_prior, PRIOR: prior}
    if kind == "rosbag2":
        # A ROS 2 bag is a folder the writer must create: written beside, then moved into the staging.
        # Named as the output, since the bag's data file takes the folder's name.
        folder = outputs.folder(out)
        staged = folder / out.name
        write_odometry(staged, kind, stamps, *to.frame_ids, trajectories)
        for item in staged.iterdir():
            item.rename(folder / item.name)
        staged.rmdir()
    else:
        write_odometry(outputs.file(out), kind, stamps, *to.frame_ids, trajectories)
    return out
