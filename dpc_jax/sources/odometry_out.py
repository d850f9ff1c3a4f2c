"""A trajectory written back as a recording that Foxglove, rviz or evo's ``evo_traj`` play: one
``nav_msgs/Odometry`` per frame on each topic (the corrected poses on :data:`CORRECTED`, the prior on
:data:`PRIOR`), stamped with the frames' stamps, in the world frame with the left camera as child frame.
Written with ``rosbags``' writers (``dpc_jax.sources.bag_writer``): a plain MCAP file (``.mcap``), a ROS 1
bag (``.bag``) or a ROS 2 bag folder of MCAP storage.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dpc_jax.sources.bag_writer import RecordingWriter

CORRECTED = "/dpc/odometry"
PRIOR = "/dpc/prior"
# The kinds of recording by the output's name: a plain MCAP file, a ROS 1 bag; else a ROS 2 bag folder.
SUFFIXES = {".mcap": "mcap", ".bag": "ros1"}


def recording_kind(path: str | Path) -> str | None:
    """``mcap`` or ``ros1`` for an output named as a recording file, else None."""
    return SUFFIXES.get(Path(path).suffix.lower())


def write_odometry(
    path: str | Path, kind: str, stamps: np.ndarray, world_frame: str, camera_frame: str,
    trajectories: dict[str, np.ndarray],
) -> None:
    """Write ``trajectories`` (topic → camera-to-world ``[N, 4, 4]``) at ``stamps`` (int ns ``[N]``) to a
    new recording at ``path`` of ``kind`` (``mcap``, ``ros1``, else a ROS 2 bag folder). ``path`` must
    not exist (the caller stages it: the command writes its outputs all or nothing)."""
    with RecordingWriter(path, kind if kind in ("mcap", "ros1") else "rosbag2") as bag:
        for k, stamp in enumerate(np.asarray(stamps, np.int64).tolist()):
            for topic, poses in trajectories.items():
                bag.write(topic, stamp, bag.odometry(stamp, world_frame, camera_frame, poses[k]))
