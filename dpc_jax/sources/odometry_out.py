"""A trajectory written back as a recording that Foxglove, rviz or evo's ``evo_traj`` play: one
``nav_msgs/Odometry`` per frame on each topic (the corrected poses on :data:`CORRECTED`, the prior on
:data:`PRIOR`), stamped with the frames' stamps, in the world frame with the left camera as child frame.
Written with ``rosbags``' writers: a plain MCAP file (``.mcap``), a ROS 1 bag (``.bag``) or a ROS 2 bag
folder of MCAP storage.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

CORRECTED = "/dpc/odometry"
PRIOR = "/dpc/prior"
ODOMETRY = "nav_msgs/msg/Odometry"
# The kinds of recording by the output's name: a plain MCAP file, a ROS 1 bag; else a ROS 2 bag folder.
SUFFIXES = {".mcap": "mcap", ".bag": "ros1"}


def recording_kind(path: str | Path) -> str | None:
    """``mcap`` or ``ros1`` for an output named as a recording file, else None."""
    return SUFFIXES.get(Path(path).suffix.lower())


class _Messages:
    """``nav_msgs/Odometry`` messages of one ROS version's types, serialized."""

    def __init__(self, ros1: bool) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)

    def _msg(self, msgtype: str, **fields: Any) -> Any:
        return self.store.types[msgtype](**fields)

    def odometry(self, stamp: int, world: str, camera: str, pose: np.ndarray) -> bytes | memoryview:
        sec, nanosec = divmod(int(stamp), 1_000_000_000)
        time = self._msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
        header = (self._msg("std_msgs/msg/Header", seq=0, stamp=time, frame_id=world) if self.ros1
                  else self._msg("std_msgs/msg/Header", stamp=time, frame_id=world))
        x, y, z, w = (float(v) for v in Rotation.from_matrix(pose[:3, :3]).as_quat())
        px, py, pz = (float(v) for v in pose[:3, 3])
        point = self._msg("geometry_msgs/msg/Point", x=px, y=py, z=pz)
        quaternion = self._msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)
        zero = self._msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        msg = self._msg(
            ODOMETRY, header=header, child_frame_id=camera,
            pose=self._msg("geometry_msgs/msg/PoseWithCovariance",
                           pose=self._msg("geometry_msgs/msg/Pose", position=point, orientation=quaternion),
                           covariance=np.zeros(36)),
            twist=self._msg("geometry_msgs/msg/TwistWithCovariance",
                            twist=self._msg("geometry_msgs/msg/Twist", linear=zero, angular=zero),
                            covariance=np.zeros(36)))
        serialize = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        return serialize(msg, ODOMETRY)


def write_odometry(
    path: str | Path, kind: str, stamps: np.ndarray, world_frame: str, camera_frame: str,
    trajectories: dict[str, np.ndarray],
) -> None:
    """Write ``trajectories`` (topic → camera-to-world ``[N, 4, 4]``) at ``stamps`` (int ns ``[N]``) to a
    new recording at ``path`` of ``kind`` (``mcap``, ``ros1``, else a ROS 2 bag folder). ``path`` must
    not exist (the caller stages it: the command writes its outputs all or nothing)."""
    path = Path(path)
    messages = _Messages(ros1=kind == "ros1")
    if kind == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        writer: Any = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        # A plain MCAP file is the storage file of a ROS 2 bag written beside it (removed after).
        folder = path
        if kind == "mcap":
            folder = Path(tempfile.mkdtemp(prefix=".dpc-mcap-", dir=path.parent)) / "bag"
        writer = Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP)
    with writer:
        connections = {topic: writer.add_connection(topic, ODOMETRY, typestore=messages.store)
                       for topic in trajectories}
        for k, stamp in enumerate(np.asarray(stamps, np.int64)):
            for topic, poses in trajectories.items():
                writer.write(connections[topic], int(stamp),
                             messages.odometry(int(stamp), world_frame, camera_frame, poses[k]))
    if kind == "mcap":
        # The storage file of a ROS 2 MCAP bag is a complete MCAP file; its folder's metadata.yaml repeats
        # what the file's own summary holds.
        (inner,) = folder.glob("*.mcap")
        inner.rename(path)
        shutil.rmtree(folder.parent)
