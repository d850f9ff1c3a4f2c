"""Recordings written with ``rosbags``' writers: a plain MCAP file (``mcap``), a ROS 1 bag (``ros1``) or a
ROS 2 bag folder of MCAP storage (``rosbag2``), holding a stereo sequence (:func:`write_stereo`: images,
``CameraInfo``, poses as ``nav_msgs/Odometry``) or a trajectory (``dpc_jax.sources.odometry_out``).

A plain MCAP file is the storage file of a ROS 2 bag written beside it: the folder's ``metadata.yaml``
repeats what the file's own summary holds, so the file alone is the recording.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from dpc_jax._io import remove_stale, temp_name

KINDS = ("mcap", "ros1", "rosbag2")
ODOMETRY = "nav_msgs/msg/Odometry"
# The topics and frame ids of a stereo sequence written by write_stereo (docs/formats.md).
LEFT, RIGHT = "/stereo/left/image_raw", "/stereo/right/image_raw"
LEFT_FRAME, RIGHT_FRAME = "camera_left", "camera_right"


class RecordingWriter:
    """A new recording at ``path`` of ``kind`` (:data:`KINDS`), which must not exist (the caller stages
    it): ``with RecordingWriter(path, kind) as bag: bag.write(topic, stamp_ns, bag.odometry(...))``."""

    def __init__(self, path: str | Path, kind: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path, self.kind = Path(path), kind
        self.ros1 = kind == "ros1"
        self.store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.LATEST)
        self._connections: dict[str, Any] = {}
        self._folder = self.path
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self._writer: Any = Writer1(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            if kind == "mcap":
                # Named for this process, so that a later writer removes what a killed one left.
                remove_stale(self.path.parent, ".dpc-mcap-")
                self._folder = self.path.parent / temp_name(".dpc-mcap-") / "bag"
                self._folder.parent.mkdir()
            # Metadata version 8: version 9 writes the topics' QoS profiles as a YAML list, where the readers
            # of older ROS 2 releases (Humble, Iron) expect the string that version 8 writes.
            self._writer = Writer(self._folder, version=8, storage_plugin=StoragePlugin.MCAP)

    def __enter__(self) -> RecordingWriter:
        self._writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()
        if self.kind == "mcap":
            if exc[0] is None:
                (inner,) = self._folder.glob("*.mcap")
                inner.rename(self.path)
            shutil.rmtree(self._folder.parent)

    def write(self, topic: str, stamp: int, msg: Any) -> None:
        """Write ``msg`` on ``topic`` at ``stamp`` (ns; also the bag's record time)."""
        msgtype = msg.__msgtype__
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=self.store)
        serialize = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        self._writer.write(self._connections[topic], int(stamp), serialize(msg, msgtype))

    def msg(self, msgtype: str, **fields: Any) -> Any:
        return self.store.types[msgtype](**fields)

    def header(self, stamp: int, frame_id: str) -> Any:
        sec, nanosec = divmod(int(stamp), 1_000_000_000)
        time = self.msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
        seq = {"seq": 0} if self.ros1 else {}
        return self.msg("std_msgs/msg/Header", stamp=time, frame_id=frame_id, **seq)

    def image(self, stamp: int, frame_id: str, image: np.ndarray) -> Any:
        """A ``sensor_msgs/Image`` of uint8 ``[H, W]`` (``mono8``) or ``[H, W, 3]`` RGB (``rgb8``) pixels."""
        data = np.ascontiguousarray(image, np.uint8)
        h, w = data.shape[:2]
        return self.msg("sensor_msgs/msg/Image", header=self.header(stamp, frame_id), height=h, width=w,
                        encoding="mono8" if data.ndim == 2 else "rgb8", is_bigendian=0, step=data.strides[0],
                        data=data.reshape(-1))

    def compressed(self, stamp: int, frame_id: str, data: bytes, form: str) -> Any:
        return self.msg("sensor_msgs/msg/CompressedImage", header=self.header(stamp, frame_id), format=form,
                        data=np.frombuffer(data, np.uint8))

    def camera_info(self, stamp: int, frame_id: str, size: tuple[int, int], P: np.ndarray) -> Any:
        """The ``CameraInfo`` of a rectified camera of projection ``P`` ``[3, 4]`` (``K`` its left block,
        ``D`` zero, ``R`` the identity) for ``size`` ``(H, W)`` images."""
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        values = (np.zeros(5), np.ravel(P[:, :3]), np.eye(3).ravel(), np.ravel(P))
        matrices = {name: np.asarray(value, np.float64) for name, value in zip(names, values, strict=True)}
        roi = self.msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                       do_rectify=False)
        return self.msg("sensor_msgs/msg/CameraInfo", header=self.header(stamp, frame_id), height=size[0],
                        width=size[1], distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                        **matrices)

    def odometry(self, stamp: int, world: str, child: str, pose: np.ndarray) -> Any:
        """``nav_msgs/Odometry`` of camera-to-world ``pose`` ``[4, 4]`` (zero twist and covariances)."""
        x, y, z, w = (float(v) for v in Rotation.from_matrix(pose[:3, :3]).as_quat())
        px, py, pz = (float(v) for v in pose[:3, 3])
        zero = self.msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        position = self.msg("geometry_msgs/msg/Point", x=px, y=py, z=pz)
        orientation = self.msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)
        return self.msg(
            ODOMETRY, header=self.header(stamp, world), child_frame_id=child,
            pose=self.msg("geometry_msgs/msg/PoseWithCovariance",
                          pose=self.msg("geometry_msgs/msg/Pose", position=position, orientation=orientation),
                          covariance=np.zeros(36)),
            twist=self.msg("geometry_msgs/msg/TwistWithCovariance",
                           twist=self.msg("geometry_msgs/msg/Twist", linear=zero, angular=zero),
                           covariance=np.zeros(36)))


def write_stereo(
    path: str | Path, kind: str, left: Sequence[Path], right: Sequence[Path], stamps: np.ndarray,
    projections: tuple[np.ndarray, np.ndarray], *, compressed: bool,
    poses: dict[str, np.ndarray] | None = None, world_frame: str = "world",
) -> None:
    """The stereo frames of image files ``left``/``right`` (``N`` each) as a new recording at ``path``:
    on :data:`LEFT`/:data:`RIGHT` the images at ``stamps`` (int ns, ``[N]``, or ``[N, 2]``: each
    camera's), raw (``rgb8``, or ``mono8`` for a grey file) or ``compressed`` (the very files' bytes as
    ``CompressedImage``: their pixels without a decoding and encoding between), each camera's
    ``CameraInfo`` (rectified, ``P`` from ``projections``) beside them, and each of ``poses`` (topic →
    camera-to-world ``[N, 4, 4]``) as ``nav_msgs/Odometry`` of the left camera in ``world_frame`` at the
    left image's stamp."""
    sides = ((LEFT, LEFT_FRAME, left, projections[0]), (RIGHT, RIGHT_FRAME, right, projections[1]))
    pairs = np.asarray(stamps, np.int64).reshape(len(left), -1)[:, [0, -1]].tolist()
    with RecordingWriter(path, kind) as bag:
        for k, (stamp, right_stamp) in enumerate(pairs):
            for (topic, frame_id, files, P), at in zip(sides, (stamp, right_stamp), strict=True):
                file = files[k]
                image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
                if image is None or image.dtype != np.uint8:
                    raise ValueError(f"{file}: cannot decode an 8-bit image")
                size = (int(image.shape[0]), int(image.shape[1]))
                info = bag.camera_info(at, frame_id, size, P)
                bag.write(topic.rsplit("/", 1)[0] + "/camera_info", at, info)
                if compressed:
                    form = "png" if file.suffix.lower() == ".png" else "jpeg"
                    data = file.read_bytes()
                    bag.write(topic + "/compressed", at, bag.compressed(at, frame_id, data, form))
                else:
                    rgb = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
                    bag.write(topic, at, bag.image(at, frame_id, rgb))
            for topic, trajectory in (poses or {}).items():
                bag.write(topic, stamp, bag.odometry(stamp, world_frame, LEFT_FRAME, trajectory[k]))
