"""A recording's stereo calibration: from the two cameras' ``CameraInfo`` (docs/formats.md, "Recordings") or
from a KITTI ``calib.txt`` given for a recording without it.

Images on an ``image_rect…`` topic (``image_proc`` / ``stereo_image_proc``'s output) are rectified already:
``P`` is used as it is, whatever ``D`` and ``R`` say, since the ``CameraInfo`` beside them is the raw
camera's (ROS's convention: rectified images are described by ``P`` alone). Other images with all-zero ``D``
are taken as rectified too (a note when ``R`` is not the identity); with distortion (``plumb_bob``,
``rational_polynomial``) every image is rectified with OpenCV from ``D``, ``K``, ``R`` and ``P``, as
``image_proc`` does (a note says so). ``K`` and the baseline come from the two ``P``
(:func:`~dpc_jax.data.kitti.rectified_pair`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dpc_jax.data.kitti import read_calibration, rectified_pair, stereo_calibration

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
# The numbers of distortion coefficients OpenCV's camera model takes.
DISTORTION_SIZES = (4, 5, 8, 12, 14)


def info_topic(image_topic: str, topics: dict[str, str]) -> str | None:
    """The ``camera_info`` beside an image topic (``/cam/image_raw`` → ``/cam/camera_info``, also for
    ``/cam/image_raw/compressed``)."""
    parts = image_topic.rstrip("/").split("/")
    for cut in (1, 2):
        topic = "/".join([*parts[:-cut], "camera_info"])
        if topics.get(topic) == CAMERA_INFO:
            return topic
    return None


def rectified_topic(image_topic: str) -> bool:
    """Whether an image topic is ROS's rectified output (``…/image_rect``, ``…/image_rect_color``, also
    under ``/compressed``)."""
    parts = image_topic.rstrip("/").split("/")
    name = parts[-2] if parts[-1] == "compressed" and len(parts) > 1 else parts[-1]
    return name.startswith("image_rect")


def _field(msg: Any, name: str) -> np.ndarray:
    """A ``CameraInfo`` matrix field (ROS 2: ``k``; ROS 1: ``K``) as float64."""
    value = getattr(msg, name, None)
    return np.asarray(value if value is not None else getattr(msg, name.upper()), np.float64)


def calibration(
    path: Path, infos: dict[str, Any], cameras: tuple[str, str], size: tuple[int, int],
    calib: Path | None, notes: list[str],
) -> tuple[np.ndarray, float, tuple[Any, Any] | None, tuple[Path, ...]]:
    """``(K, baseline, rectification maps or None, calibration files read)``."""
    if calib is not None:
        entries = read_calibration(calib)
        keys = ("P2", "P3") if "P2" in entries else ("P0", "P1")
        K, baseline = stereo_calibration(calib, *keys, size)
        return K, baseline, None, (calib,)
    missing = [camera for camera in cameras if camera not in infos]
    if missing:
        raise ValueError(f"{path}: no CameraInfo beside {missing[0]} (expected a camera_info topic in its "
                        "namespace) and no --calib FILE; pass --calib with the pair's P matrices")
    h, w = size
    projections: list[np.ndarray] = []
    maps: list[Any] = []
    distorted = False
    for camera in cameras:
        topic, msg = infos[camera]
        where = f"{path}: {topic}"
        if (int(msg.height), int(msg.width)) != (h, w):
            raise ValueError(f"{where}: CameraInfo is for {msg.height}x{msg.width} images, but {camera} "
                            f"holds {h}x{w}; expected the images' size")
        d, k, r, p = (_field(msg, name) for name in ("d", "k", "r", "p"))
        finite = np.all(np.isfinite(np.concatenate([d, k, r, p])))
        if k.size != 9 or r.size != 9 or p.size != 12 or not finite:
            raise ValueError(f"{where}: CameraInfo with K, R, P of {k.size}, {r.size}, {p.size} numbers; "
                            "expected 9, 9 and 12 finite numbers")
        P = p.reshape(3, 4)
        if rectified_topic(camera):
            maps.append(None)
            if np.any(d != 0) or not np.allclose(r.reshape(3, 3), np.eye(3)):
                notes.append(f"{where}: {camera} is a rectified topic, so its images are used as they are "
                             "with P (the CameraInfo's D and R, the raw camera's, are not applied again)")
        elif np.any(d != 0):
            if msg.distortion_model not in DISTORTION_MODELS:
                raise ValueError(f"{where}: distortion model {msg.distortion_model!r}; expected one of "
                                f"{', '.join(DISTORTION_MODELS)}, or rectified images (all-zero D, or an "
                                "image_rect topic)")
            if d.size not in DISTORTION_SIZES:
                raise ValueError(f"{where}: D holds {d.size} coefficients; expected "
                                f"{', '.join(map(str, DISTORTION_SIZES))} (OpenCV's distortion models)")
            distorted = True
            notes.append(f"{where}: {camera} is rectified here with D, K, R and P (a raw camera's images; "
                         "an image_rect topic is used as it is)")
            maps.append(cv2.initUndistortRectifyMap(k.reshape(3, 3), d, r.reshape(3, 3), P[:, :3], (w, h),
                                                    cv2.CV_32FC1))
        else:
            maps.append(None)
            if not np.allclose(r.reshape(3, 3), np.eye(3)):
                notes.append(f"{where}: D is all zero, so the images are taken as rectified and P used as it "
                             "is, but R is not the identity")
        projections.append(P)
    K, baseline = rectified_pair(projections[0], projections[1], size,
                                 *(f"{path}: {infos[camera][0]} P" for camera in cameras))
    if distorted:
        identity = (None, None)
        maps = [m if m is not None else identity for m in maps]
        return K, baseline, (maps[0], maps[1]), ()
    return K, baseline, None, ()
