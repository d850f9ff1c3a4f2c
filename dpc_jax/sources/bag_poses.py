"""Poses in a recording: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``,
``PoseWithCovarianceStamped`` and the transforms of ``tf2_msgs/TFMessage`` (``/tf``, ``/tf_static``), as
float64 ``[4, 4]`` matrices (the pose of a child frame in its parent frame: x_parent = T · x_child), and
the transform between two frames at given stamps through ``/tf_static`` and ``/tf`` (:func:`link`).
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
Edge = tuple[str, str]  # (parent frame, child frame) of a transform


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


def nearest(stamps: np.ndarray, of: np.ndarray) -> np.ndarray:
    """Per stamp of ``of``, the index of the nearest of the increasing ``stamps`` (on a tie the earlier)."""
    after = np.clip(np.searchsorted(stamps, of), 0, stamps.size - 1)
    before = np.clip(after - 1, 0, stamps.size - 1)
    return np.where(np.abs(stamps[before] - of) <= np.abs(stamps[after] - of), before, after)


def nearest_within(stamps: np.ndarray, of: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, int | None]:
    """:func:`nearest`, and the first position in ``of`` whose nearest stamp is further than
    ``tolerance_ns`` (None: every one is within it)."""
    chosen = nearest(stamps, of)
    far = np.flatnonzero(np.abs(stamps[chosen] - of) > tolerance_ns)
    return chosen, int(far[0]) if far.size else None


def _route(edges: set[Edge], source: str, target: str) -> list[tuple[Edge, bool]] | None:
    """The edges from ``source`` to ``target`` through ``edges`` (``(parent, child)``, followed either way;
    True: against its direction), fewest first; None when they do not link the frames."""
    links: dict[str, list[tuple[str, Edge, bool]]] = {}
    for parent, child in sorted(edges):
        links.setdefault(parent, []).append((child, (parent, child), False))
        links.setdefault(child, []).append((parent, (parent, child), True))
    found: dict[str, list[tuple[Edge, bool]]] = {source: []}
    queue = deque([source])
    while queue:
        frame = queue.popleft()
        if frame == target:
            return found[frame]
        for other, edge, backwards in links.get(frame, []):
            if other not in found:
                found[other] = [*found[frame], (edge, backwards)]
                queue.append(other)
    return None


def link(
    static: dict[Edge, np.ndarray], moving: dict[Edge, list[tuple[int, np.ndarray]]],
    source: str, target: str, stamps: np.ndarray, tolerance_ns: int, where: str,
) -> np.ndarray | None:
    """``T_source_target`` ``[N, 4, 4]`` (x_source = T · x_target) at each of ``stamps`` (int ns ``[N]``)
    through the static transforms ``static`` (``{(parent, child): T_parent_child}``, ``/tf_static``) and the
    moving ones ``moving`` (``{(parent, child): [(stamp, T_parent_child), ...]}``, ``/tf``: at each stamp
    the transform nearest it, within ``tolerance_ns``, else ``ValueError`` naming ``where``, the edge and
    the stamp); None when they do not link the frames."""
    route = _route(set(static) | set(moving), source, target)
    if route is None:
        return None
    chain = np.tile(np.eye(4), (stamps.size, 1, 1))
    for edge, backwards in route:
        if edge in static:
            step = np.broadcast_to(static[edge], chain.shape)
        else:
            order = sorted(moving[edge], key=lambda sample: sample[0])
            known = np.asarray([stamp for stamp, _ in order], np.int64)
            chosen, k = nearest_within(known, stamps, tolerance_ns)
            if k is not None:
                raise ValueError(f"{where}: /tf has no transform {edge[0]} → {edge[1]} within "
                                 f"{tolerance_ns / 1e6:g} ms of frame {k} (stamp {stamps[k] / 1e9:.9f} s); "
                                 "expected the chain to the camera at every frame")
            step = np.stack([order[i][1] for i in chosen])
        chain = chain @ (np.linalg.inv(step) if backwards else step)
    return chain
