"""The records an external VO gives the live correction (``dpc-jax live``; docs/formats.md), one frame a
line::

    [TIME] LEFT RIGHT r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz

LEFT, RIGHT: the rectified stereo pair's image files; then the VO's camera-to-world pose of the left
camera as a KITTI pose row; TIME (s, optional) increasing from line to line. Blank lines and lines
starting with ``#`` are skipped. A file is checked whole (:func:`checked_records`) before the network is
loaded; a stream is read as it grows (:func:`streamed_records`). Every mistake is a
:class:`RecordError` naming the line and what was expected. NumPy only (OpenCV to decode an image).
"""

from __future__ import annotations

import math
import os
import stat
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from dpc_jax.geometry.poses import validate_poses

# The fields of one record: LEFT RIGHT and a KITTI pose row, optionally preceded by TIME.
POSE_FIELDS = 12
RECORD_SHAPE = "LEFT RIGHT and the 12 numbers of a KITTI pose row (camera-to-world), optionally TIME first"


class RecordError(ValueError):
    """A frame that cannot be used; its message names the frame (the record's line, the sequence's frame)."""


@dataclass(frozen=True)
class Record:
    """One parsed record: ``line`` (its number in the stream, from 1), ``time_s`` (None when not given),
    the image paths and the ``[4, 4]`` pose."""

    line: int
    time_s: float | None
    left: Path
    right: Path
    pose: np.ndarray


# A check of the first record (its images of the calibration's pair), given where it is: a RecordError.
FirstCheck = Callable[[Record, str], None]


def parse_record(text: str, line: int, source: str) -> Record | None:
    """The record on line ``line`` of ``source`` (``records`` or the file), None for a blank line or a
    comment; :class:`RecordError` naming the line and what was expected."""
    fields = text.split()
    if not fields or fields[0].startswith("#"):
        return None
    where = f"{source} line {line}"
    if len(fields) not in (POSE_FIELDS + 2, POSE_FIELDS + 3):
        raise RecordError(f"{where}: {len(fields)} fields; expected {RECORD_SHAPE}")
    if len(fields) == POSE_FIELDS + 2 and _is_number(fields[0]) and not _is_number(fields[2]):
        # TIME LEFT RIGHT and a pose short of a number: not LEFT RIGHT and a pose whose first value is RIGHT.
        raise RecordError(f"{where}: {len(fields)} fields, TIME LEFT RIGHT and {len(fields) - 3} numbers; "
                          f"expected {RECORD_SHAPE}")
    time_s = None
    if len(fields) == POSE_FIELDS + 3:
        try:
            time_s = float(fields[0])
        except ValueError:
            raise RecordError(f"{where}: TIME {fields[0]!r} is not a number; expected "
                              f"{RECORD_SHAPE}") from None
        if not math.isfinite(time_s):
            raise RecordError(f"{where}: TIME {fields[0]} is not finite")
        fields = fields[1:]
    try:
        numbers = np.array([float(v) for v in fields[2:]], np.float64)
    except ValueError:
        bad = next(v for v in fields[2:] if not _is_number(v))
        raise RecordError(f"{where}: pose value {bad!r} is not a number; expected {RECORD_SHAPE}") from None
    pose = np.eye(4)
    pose[:3] = numbers.reshape(3, 4)
    try:
        validate_poses(pose[None], "pose")
    except ValueError as error:
        reason = str(error).removeprefix("pose: pose 0 ").removeprefix("pose: pose 0")
        raise RecordError(f"{where}: the pose {reason}; expected a rigid camera-to-world pose (a rotation "
                          "and a translation)") from None
    return Record(line, time_s, Path(fields[0]), Path(fields[1]), pose)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def record_image(path: Path, size: tuple[int, int], where: str, side: str) -> np.ndarray:
    """The record's ``side`` image, decoded (RGB) and checked to be ``size`` = ``(H, W)``."""
    from dpc_jax.data.kitti import load_image

    if not path.is_file():
        raise RecordError(f"{where}: {side} image {path}: no such file")
    try:
        image = load_image(path)
    except (OSError, ValueError) as error:
        raise RecordError(f"{where}: {side} image: {error}") from None
    if image.shape[:2] != tuple(size):
        raise RecordError(f"{where}: {side} image {path} is {image.shape[0]}x{image.shape[1]}, expected "
                          f"{size[0]}x{size[1]} (the calibration's image size)")
    return image


def open_records(path: str | None) -> tuple[IO[bytes], str, bool]:
    """The records' stream (``path``, or standard input for None), its name in messages (``records`` for
    standard input), and whether it is a regular file (read whole first)."""
    if path is None:
        stream, name = sys.stdin.buffer, "records"
    else:
        stream, name = open(path, "rb"), str(path)
    try:
        regular = stat.S_ISREG(os.fstat(stream.fileno()).st_mode)
    except (OSError, ValueError):
        regular = False
    return stream, name, regular


def checked_records(lines: list[bytes], name: str, size: tuple[int, int], first: FirstCheck) -> list[Record]:
    """Every record of a file ``name`` of ``lines``, parsed and its files found, its times increasing;
    the first pair decoded for its ``size`` = ``(H, W)`` and checked by ``first``."""
    records: list[Record] = []
    for number, raw in enumerate(lines, start=1):
        record = parse_record(raw.decode("utf-8", "replace"), number, name)
        if record is None:
            continue
        where = f"{name} line {number}"
        _check_time(record, records[-1] if records else None, name)
        for side, path in (("left", record.left), ("right", record.right)):
            if not path.is_file():
                raise RecordError(f"{where}: {side} image {path}: no such file")
            if not records:
                record_image(path, size, where, side)
        if not records:
            first(record, where)
        records.append(record)
    if not records:
        raise RecordError(f"{name}: no records; expected one line per frame: {RECORD_SHAPE}")
    return records


def streamed_records(stream: IO[bytes], name: str, first: FirstCheck) -> Iterator[Record]:
    """The records of a stream, each as soon as its line is complete (times increasing; the first one
    checked by ``first``)."""
    number, previous = 0, None
    while True:
        raw = stream.readline()
        if not raw:
            return
        number += 1
        record = parse_record(raw.decode("utf-8", "replace"), number, name)
        if record is not None:
            _check_time(record, previous, name)
            if previous is None:
                first(record, f"{name} line {number}")
            previous = record
            yield record


def _check_time(record: Record, previous: Record | None, name: str) -> None:
    """A record's TIME must come after the previous record's (a duplicated or reordered line otherwise)."""
    if record.time_s is not None and previous is not None and previous.time_s is not None \
            and record.time_s <= previous.time_s:
        raise RecordError(f"{name} line {record.line}: TIME {record.time_s:g} is not after line "
                          f"{previous.line}'s {previous.time_s:g}; expected increasing times, one record "
                          "per frame")
