"""Decoding a recording's image messages into the images every source gives.

``sensor_msgs/Image`` with encoding ``mono8`` (or ``8UC1``), ``rgb8``, ``bgr8`` or ``mono16`` (scaled to 8
bits by its high byte, as OpenCV reads a 16-bit PNG into 8 bits), and ``sensor_msgs/CompressedImage``
holding a PNG or a JPEG (told by its bytes, as ``image_transport``'s ``format`` strings vary). The result is
:func:`~dpc_jax.data.frames.load_image`'s: uint8 ``[H, W, 3]`` RGB (a grey image as three equal
channels), or uint8 ``[H, W]`` grey, the grey of a colour image being the one OpenCV's PNG decoder
gives (:func:`~dpc_jax.data.frames.png_grey`), so that the pixels of a PNG file and the same pixels in
a message decode alike.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from dpc_jax.data.frames import png_grey

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED)
# 8UC1 (OpenCV's name, which cv_bridge publishes for a grey cv::Mat) is mono8's layout.
ENCODINGS = ("mono8", "rgb8", "bgr8", "mono16", "8UC1")
_CHANNELS = {"mono8": 1, "rgb8": 3, "bgr8": 3, "mono16": 1, "8UC1": 1}
_MAGIC = {b"\x89PNG": "png", b"\xff\xd8\xff": "jpeg"}


def encoding_problem(msgtype: str, msg: Any) -> str | None:
    """Why an image message cannot be decoded here (its encoding or compressed format), or None."""
    if msgtype == IMAGE:
        if msg.encoding not in ENCODINGS:
            return f"encoding {msg.encoding!r}; expected one of {', '.join(ENCODINGS)}"
        return None
    data = bytes(msg.data[:4])
    if not any(data.startswith(magic) for magic in _MAGIC):
        return f"compressed format {msg.format!r} is neither PNG nor JPEG"
    return None


def raw_size(msg: Any) -> tuple[int, int]:
    """``(H, W)`` of a ``sensor_msgs/Image`` from its header fields (no decoding)."""
    return int(msg.height), int(msg.width)


def decode(msgtype: str, msg: Any, grey: bool, where: str) -> np.ndarray:
    """The image of a message: uint8 ``[H, W, 3]`` RGB, or ``[H, W]`` when ``grey``; ``ValueError``
    naming ``where`` (the recording, topic and stamp) when it cannot be decoded."""
    if msgtype == COMPRESSED:
        flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
        image = cv2.imdecode(np.frombuffer(msg.data, np.uint8), flag)
        if image is None:
            raise ValueError(f"{where}: cannot decode the compressed image (format {msg.format!r}, "
                             "truncated?)")
        return image if grey else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    problem = encoding_problem(msgtype, msg)
    if problem is not None:
        raise ValueError(f"{where}: {problem}")
    h, w = int(msg.height), int(msg.width)
    channels = _CHANNELS[msg.encoding]
    rows = _rows(msg, where)
    if msg.encoding == "mono16":
        mono = (_mono16(rows, msg) >> 8).astype(np.uint8)
        return mono if grey else np.repeat(mono[..., None], 3, axis=2)
    if channels == 1:
        mono = np.ascontiguousarray(rows)
        return mono if grey else np.repeat(mono[..., None], 3, axis=2)
    rgb = rows.reshape(h, w, 3)
    rgb = np.ascontiguousarray(rgb[..., ::-1] if msg.encoding == "bgr8" else rgb)
    return png_grey(rgb) if grey else rgb


def _rows(msg: Any, where: str) -> np.ndarray:
    """A raw image's rows, uint8 ``[H, W · channels · bytes]`` without the ``step``'s padding."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    channels = _CHANNELS[msg.encoding]
    itemsize = 2 if msg.encoding == "mono16" else 1
    data = np.asarray(msg.data, np.uint8)
    if step < w * channels * itemsize or data.size < h * step:
        raise ValueError(f"{where}: {data.size} bytes with step {step} for a {h}x{w} {msg.encoding} image; "
                         f"expected at least {h * w * channels * itemsize}")
    return data[: h * step].reshape(h, step)[:, : w * channels * itemsize]


def _mono16(rows: np.ndarray, msg: Any) -> np.ndarray:
    return rows.view(">u2" if msg.is_bigendian else "<u2")


def mono16_bits(msgtype: str, msg: Any, where: str) -> int | None:
    """The bits the values of a raw ``mono16`` image use (its largest value's), None for another image:
    data of 10 to 14 bits kept in the low bits comes out dark from the high byte."""
    if msgtype != IMAGE or msg.encoding != "mono16":
        return None
    return int(_mono16(_rows(msg, where), msg).max()).bit_length()
