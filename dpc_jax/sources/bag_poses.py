"""Poses in a recording: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``,
``PoseWithCovarianceStamped`` and the transforms of ``tf2_msgs/TFMessage`` (``/tf``, ``/tf_static``), as
float64 ``[4, 4]`` matrices (the pose of a child frame in its parent frame: x_parent = T · x_child), and
the static transform between two frames from ``/tf_static``.
"""

from __future__ import annotations

from collections import deque
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

ODOMETRY = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
POSE_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (ODOMETRY, POSE, POSE_COVARIANCE, TF)


class PoseSample(NamedTuple):
    """One pose: header stamp (ns), parent frame, child frame (None: the message names none), ``[4, 4]``."""

    stamp: int
    parent: str
    child: str | None
    matrix: np.ndarray


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header``'s stamp in integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _matrix(translation: Any, rotation: Any, where: str) -> np.ndarray:
    quaternion = np.array([rotation.x, rotation.y, rotation.z, rotation.w], np.float64)
    position = np.array([translation.x, translation.y, translation.z], np.float64)
    norm = float(np.linalg.norm(quaternion))
    if not (np.all(np.isfinite(quaternion)) and np.all(np.isfinite(position))) or abs(norm - 1.0) > 1e-3:
        raise ValueError(f"{where}: a pose with quaternion {quaternion.tolist()} (norm {norm:.4g}) and "
                         f"position {position.tolist()}; expected finite numbers and a unit quaternion")
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    matrix[:3, 3] = position
    return matrix


def samples(msgtype: str, msg: Any, where: str) -> list[PoseSample]:
    """The poses one message holds (a ``TFMessage`` may hold several)."""
    if msgtype == TF:
        return [PoseSample(stamp_ns(t.header), t.header.frame_id, t.child_frame_id,
                           _matrix(t.transform.translation, t.transform.rotation, where))
                for t in msg.transforms]
    pose = msg.pose.pose if msgtype in (ODOMETRY, POSE_COVARIANCE) else msg.pose
    child = msg.child_frame_id if msgtype == ODOMETRY else None
    return [PoseSample(stamp_ns(msg.header), msg.header.frame_id, child,
                       _matrix(pose.position, pose.orientation, where))]


def static_link(edges: dict[tuple[str, str], np.ndarray], source: str, target: str) -> np.ndarray | None:
    """``T_source_target`` (x_source = T · x_target) through the static transforms ``edges``
    (``{(parent, child): T_parent_child}``), followed either way; None when they do not link the frames."""
    links: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (parent, child), matrix in edges.items():
        links.setdefault(parent, []).append((child, matrix))
        links.setdefault(child, []).append((parent, np.linalg.inv(matrix)))
    found = {source: np.eye(4)}
    queue = deque([source])
    while queue:
        frame = queue.popleft()
        if frame == target:
            return found[frame]
        for other, matrix in links.get(frame, []):
            if other not in found:
                found[other] = found[frame] @ matrix
                queue.append(other)
    return None
