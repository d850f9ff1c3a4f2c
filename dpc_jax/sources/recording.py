"""What a command asks of a source (:class:`Source`, with a recording's :class:`BagOptions`) and what every
source gives it: the opened sequence, with what a recording adds to it (:class:`Recording`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dpc_jax.data.kitti import StereoSequence

# Left and right images further apart than this are not one frame; also how far a pose may be from its
# frame. KITTI's grey pair is up to 3.5 ms apart; a rig without a hardware trigger is further.
DEFAULT_TOLERANCE = 0.01


@dataclass(frozen=True)
class BagOptions:
    """What to read from a recording (the command line's ``--bag`` options; ``dpc_jax.sources.bag``)."""

    path: Path
    left_topic: str | None = None
    right_topic: str | None = None
    tolerance: float = DEFAULT_TOLERANCE
    calib: Path | None = None
    prior_topic: str | None = None
    gt_topic: str | None = None
    pose_frame: str | None = None


@dataclass(frozen=True)
class Source:
    """Where the frames are, as the command line names them (``dpc_jax.sources`` lists the kinds).

    * ``kind``: ``kitti-odometry``, ``kitti-raw`` or ``bag``; ``path``: its root folder or recording;
    * ``key``: the odometry sequence or the raw drive (None for a recording); ``date``: the raw drive's;
    * ``grey``: the KITTI layouts' grey pair; ``gt``: a raw drive's ground-truth file;
    * ``bag``: what to read from a recording (:class:`BagOptions`).
    """

    kind: str
    path: Path
    key: str | None = None
    date: str | None = None
    grey: bool = False
    gt: Path | None = None
    bag: BagOptions | None = None


@dataclass(frozen=True)
class Recording:
    """An opened source: its ``sequence`` (with ground truth where the source has it), the ``prior`` it
    holds (float64 ``[N, 4, 4]`` camera-to-world, or None: a prior file is given separately), the stamp of
    its first frame (ns; the sequence's times count from it), the camera's and the world's frame ids (for
    a corrected odometry topic) and the ``notes`` worth a line on stderr."""

    sequence: StereoSequence
    prior: np.ndarray | None = None
    first_stamp: int = 0
    camera_frame: str = "camera"
    world_frame: str = "world"
    notes: tuple[str, ...] = ()
