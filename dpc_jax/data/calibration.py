"""A rectified stereo camera's calibration, and its reader from a KITTI calibration file.

:class:`Calibration` is what the live correction needs of a camera (``dpc_jax.correction.live``);
:func:`load_calibration` reads it from a KITTI odometry ``calib.txt`` (``P0``–``P3``) or a raw drive's
``calib_cam_to_cam.txt`` (``P_rect_00``–``P_rect_03`` and the images' sizes ``S_rect_XX``), the pair
chosen as the layouts choose it: the colour pair (cameras 2 and 3), or the grey one (0 and 1). NumPy
only: the command line reads it before JAX starts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.data.kitti import read_calibration, stereo_calibration

# The keys of each pair (True: grey) in the two KITTI files: the raw layout's, then the odometry's.
PAIR_KEYS: dict[bool, tuple[tuple[str, str], ...]] = {
    True: (("P_rect_00", "P_rect_01"), ("P0", "P1")),
    False: (("P_rect_02", "P_rect_03"), ("P2", "P3")),
}


@dataclass(frozen=True)
class Calibration:
    """A rectified stereo camera: ``K`` ``[3, 3]`` (px) of its full-size images of ``image_size`` =
    ``(H, W)`` px, the right camera ``baseline`` m along x of the left one."""

    K: np.ndarray
    baseline: float
    image_size: tuple[int, int]

    @classmethod
    def of(cls, sequence: Any) -> Calibration:
        """The calibration of an opened sequence (``dpc_jax.data.kitti.StereoSequence``)."""
        return cls(np.asarray(sequence.K, np.float64), float(sequence.baseline), tuple(sequence.image_size))


class NoImageSize(ValueError):
    """A calibration file that does not say its images' size (a ``calib.txt``, or no ``S_rect_XX``), read
    without one given; ``reason`` says which."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: does not give the images' size ({reason}); give the image size (H, W)")
        self.reason = reason


def pair_keys(entries: dict[str, tuple[int, str]], grey: bool) -> tuple[str, str] | None:
    """The keys of the grey (``grey``) or colour pair's projection matrices in a calibration file's
    ``entries`` (``dpc_jax.data.kitti.read_calibration``), or None where it holds neither form."""
    return next((pair for pair in PAIR_KEYS[grey] if all(key in entries for key in pair)), None)


def holds_both_pairs(path: Path | str) -> bool:
    """Whether a KITTI calibration file holds both the grey and the colour pair (whose baselines differ):
    the images must then say which pair they are. ``OSError``, ``ValueError`` for a file that cannot be
    read."""
    entries = read_calibration(Path(path))
    return all(pair_keys(entries, grey) is not None for grey in (True, False))


def load_calibration(path: Path | str, *, grey: bool = False,
                     image_size: tuple[int, int] | None = None) -> Calibration:
    """The stereo calibration in a KITTI calibration file.

    ``path``: a ``calib.txt`` or ``calib_cam_to_cam.txt``; ``grey``: its grey pair (``P0``/``P1``,
    ``P_rect_00``/``P_rect_01``) instead of the colour one (``P2``/``P3``, ``P_rect_02``/``P_rect_03``);
    ``image_size``: ``(H, W)`` px of the images (default: the file's ``S_rect_XX``, which only
    ``calib_cam_to_cam.txt`` has). ``K`` is the left projection's 3×3 block and ``baseline`` (m)
    ``(P_left[0, 3] − P_right[0, 3]) / fu`` (docs/method.md §6). ``ValueError`` naming the file and line
    for a file without the pair or whose pair does not fit the images (:class:`NoImageSize` without a
    size to read), ``FileNotFoundError`` for no file.
    """
    path = Path(path)
    entries = read_calibration(path)
    keys = pair_keys(entries, grey)
    if keys is None:
        wanted = " or ".join(f"{a}/{b}" for a, b in PAIR_KEYS[grey])
        raise ValueError(f"{path}: no {'grey' if grey else 'colour'} stereo pair; expected the keys {wanted} "
                         "(a KITTI calib.txt or calib_cam_to_cam.txt)")
    if image_size is None:
        if not keys[0].startswith("P_rect_"):
            raise NoImageSize(path, "a calib.txt has none")
        key = "S_rect_" + keys[0].removeprefix("P_rect_")
        if key not in entries:
            raise NoImageSize(path, f"no {key}")
        try:
            width, height = (int(float(v)) for v in entries[key][1].split())
        except ValueError:
            raise ValueError(f"{path}, line {entries[key][0]}: {key} must hold 2 numbers (width "
                             "height)") from None
        image_size = (height, width)
    size = (int(image_size[0]), int(image_size[1]))
    K, baseline = stereo_calibration(path, keys[0], keys[1], size)
    return Calibration(K, baseline, size)
