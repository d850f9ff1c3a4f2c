"""ROS recordings for the tests, written by ``rosbags``' own writers (not by dpc_jax): a KITTI odometry
sequence's frames as a ROS 1 bag, a ROS 2 bag (sqlite3 or MCAP storage) or a plain MCAP file, with raw or
PNG-compressed images, each camera's ``CameraInfo`` and poses as ``nav_msgs/Odometry``."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

# The stamp of the first frame: a recording's clock is the epoch's, not the sequence's.
EPOCH_NS = 1_700_000_000_123_456_789
KINDS = ("ros1", "sqlite3", "mcap-folder", "mcap")
LEFT, RIGHT = "/stereo/left/image_raw", "/stereo/right/image_raw"
CAMERA_FRAME = "cam_left"


def stamps_of(times: Iterable[float]) -> list[int]:
    """The recording's stamps (ns) of frame times in seconds."""
    return [EPOCH_NS + round(float(t) * 1e9) for t in times]


class Bag:
    """A recording being written: ``topic(name, msgtype)`` then ``write(topic, stamp_ns, msg)``; messages are
    built with ``msg(msgtype, **fields)`` and ``header(stamp_ns, frame_id)``."""

    def __init__(self, path: Path, kind: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path, self.kind = path, kind
        self.ros1 = kind == "ros1"
        self.store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.LATEST)
        self.connections: dict[str, Any] = {}
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self.writer: Any = Writer1(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.folder = path if kind != "mcap" else Path(tempfile.mkdtemp()) / "bag"
            storage = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
            self.writer = Writer(self.folder, version=9, storage_plugin=storage)
        self.writer.open()

    def msg(self, msgtype: str, **fields: Any) -> Any:
        return self.store.types[msgtype](**fields)

    def header(self, stamp: int, frame_id: str) -> Any:
        sec, nanosec = divmod(stamp, 1_000_000_000)
        time = self.msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
        if self.ros1:
            return self.msg("std_msgs/msg/Header", seq=0, stamp=time, frame_id=frame_id)
        return self.msg("std_msgs/msg/Header", stamp=time, frame_id=frame_id)

    def write(self, topic: str, stamp: int, msg: Any) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        serialize = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        data = serialize(msg, msgtype)
        self.writer.write(self.connections[topic], stamp, data)

    def close(self) -> Path:
        self.writer.close()
        if self.kind == "mcap":
            (inner,) = self.folder.glob("*.mcap")
            shutil.move(inner, self.path)
            shutil.rmtree(self.folder.parent)
        return self.path

    # ------------------------------------------------------------------ messages

    def image(self, stamp: int, frame_id: str, image: np.ndarray, encoding: str) -> Any:
        """A ``sensor_msgs/Image`` of uint8 ``[H, W]`` / ``[H, W, 3]`` (or uint16 ``[H, W]``) pixels."""
        data = np.ascontiguousarray(image)
        h, w = data.shape[:2]
        return self.msg("sensor_msgs/msg/Image", header=self.header(stamp, frame_id), height=h, width=w,
                        encoding=encoding, is_bigendian=0, step=data.strides[0],
                        data=np.frombuffer(data.tobytes(), np.uint8))

    def compressed(self, stamp: int, frame_id: str, data: bytes, form: str) -> Any:
        return self.msg("sensor_msgs/msg/CompressedImage", header=self.header(stamp, frame_id), format=form,
                        data=np.frombuffer(data, np.uint8))

    def camera_info(
        self, stamp: int, frame_id: str, size: tuple[int, int], P: np.ndarray, D: np.ndarray | None = None,
        R: np.ndarray | None = None, K: np.ndarray | None = None,
    ) -> Any:
        d = np.zeros(5) if D is None else np.asarray(D, np.float64)
        k = P[:, :3] if K is None else K
        r = np.eye(3) if R is None else R
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        matrices = dict(zip(names, (d, np.ravel(k).astype(np.float64), np.ravel(r).astype(np.float64),
                                    np.ravel(P).astype(np.float64)), strict=True))
        roi = self.msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                       do_rectify=False)
        return self.msg("sensor_msgs/msg/CameraInfo", header=self.header(stamp, frame_id), height=size[0],
                        width=size[1], distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                        **matrices)

    def odometry(self, stamp: int, frame_id: str, child: str, pose: np.ndarray) -> Any:
        vector = self.msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        twist = self.msg("geometry_msgs/msg/TwistWithCovariance",
                         twist=self.msg("geometry_msgs/msg/Twist", linear=vector, angular=vector),
                         covariance=np.zeros(36))
        return self.msg("nav_msgs/msg/Odometry", header=self.header(stamp, frame_id), child_frame_id=child,
                        pose=self.msg("geometry_msgs/msg/PoseWithCovariance", pose=self.pose(pose),
                                      covariance=np.zeros(36)), twist=twist)

    def pose(self, matrix: np.ndarray) -> Any:
        x, y, z, w = (float(v) for v in Rotation.from_matrix(matrix[:3, :3]).as_quat())
        px, py, pz = (float(v) for v in matrix[:3, 3])
        position = self.msg("geometry_msgs/msg/Point", x=px, y=py, z=pz)
        return self.msg("geometry_msgs/msg/Pose", position=position,
                        orientation=self.msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w))

    def transform(self, stamp: int, parent: str, child: str, matrix: np.ndarray) -> Any:
        x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
        transform = self.msg(
            "geometry_msgs/msg/Transform",
            translation=self.msg("geometry_msgs/msg/Vector3", x=float(matrix[0, 3]), y=float(matrix[1, 3]),
                                 z=float(matrix[2, 3])),
            rotation=self.msg("geometry_msgs/msg/Quaternion", x=float(x), y=float(y), z=float(z), w=float(w)))
        stamped = self.msg("geometry_msgs/msg/TransformStamped", header=self.header(stamp, parent),
                           child_frame_id=child, transform=transform)
        return self.msg("tf2_msgs/msg/TFMessage", transforms=[stamped])


def calib_rows(calib: Path) -> dict[str, np.ndarray]:
    """The ``P`` rows of a KITTI ``calib.txt`` as 3×4 matrices."""
    rows = {}
    for line in calib.read_text().splitlines():
        key, _, values = line.partition(":")
        if key.startswith("P"):
            rows[key] = np.array([float(v) for v in values.split()]).reshape(3, 4)
    return rows


def write_recording(
    path: Path, kitti: Path, name: str = "00", *, kind: str = "mcap", compressed: bool = False,
    poses: dict[str, np.ndarray] | None = None, frames: Callable[[Bag, int, int], None] | None = None,
    camera_info: bool = True, right_offset_ns: int = 1_000_000,
) -> Path:
    """The colour pair of KITTI odometry sequence ``kitti/sequences/NAME`` as a recording at ``path``.

    Images as ``rgb8`` (``compressed``: the very PNG files as ``CompressedImage``), the right camera
    ``right_offset_ns`` after the left (a real rig's two cameras are not exact), ``CameraInfo`` from
    ``P2``/``P3``, and each of ``poses`` (topic → ``[N, 4, 4]``) as ``nav_msgs/Odometry`` of the left
    camera's frame at the left image's stamp. ``frames``: writes more per frame (bag, frame, stamp).
    """
    folder = kitti / "sequences" / name
    times = [float(line) for line in (folder / "times.txt").read_text().split()]
    rows = calib_rows(folder / "calib.txt")
    bag = Bag(path, kind)
    left_files = sorted((folder / "image_2").glob("*.png"))
    right_files = sorted((folder / "image_3").glob("*.png"))
    size = cv2.imread(str(left_files[0])).shape[:2]
    for k, stamp in enumerate(stamps_of(times)):
        for topic, files, key, frame_id, offset in ((LEFT, left_files, "P2", CAMERA_FRAME, 0),
                                                    (RIGHT, right_files, "P3", "cam_right", right_offset_ns)):
            at = stamp + offset
            if camera_info:
                info = bag.camera_info(at, frame_id, size, rows[key])
                bag.write(topic.rsplit("/", 1)[0] + "/camera_info", at, info)
            if compressed:
                png = files[k].read_bytes()
                bag.write(topic + "/compressed", at, bag.compressed(at, frame_id, png, "png"))
            else:
                rgb = cv2.cvtColor(cv2.imread(str(files[k])), cv2.COLOR_BGR2RGB)
                bag.write(topic, at, bag.image(at, frame_id, rgb, "rgb8"))
        for topic, trajectory in (poses or {}).items():
            bag.write(topic, stamp, bag.odometry(stamp, "odom", CAMERA_FRAME, trajectory[k]))
        if frames is not None:
            frames(bag, k, stamp)
    return bag.close()


def write_raw_recording(path: Path, root: Path, date: str, drive: str, frames: int, *, kind: str = "mcap",
                        compressed: bool = False) -> Path:
    """The first ``frames`` frames of KITTI raw drive ``DATE_drive_DRIVE_sync``'s colour pair (grey where it
    has none) as a recording: the images (``rgb8``/``mono8``, or the PNG files), stamped with the drive's
    ``timestamps.txt``, and ``CameraInfo`` with the ``P_rect`` rows of ``calib_cam_to_cam.txt``."""
    folder = root / date / f"{date}_drive_{drive}_sync"
    cameras = ("02", "03") if (folder / "image_02").is_dir() else ("00", "01")
    calib = {}
    for line in (root / date / "calib_cam_to_cam.txt").read_text().splitlines():
        key, _, values = line.partition(":")
        if key.startswith("P_rect_"):
            calib[key[7:]] = np.array([float(v) for v in values.split()]).reshape(3, 4)
    bag = Bag(path, kind)
    for camera in cameras:
        lines = (folder / f"image_{camera}" / "timestamps.txt").read_text().split("\n")[:frames]
        stamps = np.array([np.datetime64(t.strip().replace(" ", "T"), "ns") for t in lines]).astype(np.int64)
        files = sorted((folder / f"image_{camera}" / "data").glob("*.png"))[:frames]
        side = "left" if camera == cameras[0] else "right"
        for stamp, file in zip(stamps.tolist(), files, strict=True):
            image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
            size = image.shape[:2]
            info = bag.camera_info(stamp, f"cam{camera}", size, calib[camera])
            bag.write(f"/kitti/{side}/camera_info", stamp, info)
            if compressed:
                bag.write(f"/kitti/{side}/image/compressed", stamp,
                          bag.compressed(stamp, f"cam{camera}", file.read_bytes(), "png"))
            elif image.ndim == 2:
                bag.write(f"/kitti/{side}/image", stamp, bag.image(stamp, f"cam{camera}", image, "mono8"))
            else:
                bag.write(f"/kitti/{side}/image", stamp,
                          bag.image(stamp, f"cam{camera}", cv2.cvtColor(image, cv2.COLOR_BGR2RGB), "rgb8"))
    return bag.close()
