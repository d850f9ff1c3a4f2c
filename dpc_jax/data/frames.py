"""The images of a stereo sequence, wherever they are stored.

A :class:`~dpc_jax.data.kitti.StereoSequence` holds its images as :class:`StereoFrames`: a list of
frames that can be cut (:meth:`StereoFrames.select`) and read in order (:meth:`StereoFrames.stream`),
each frame read as stored and decoded later (:meth:`StereoFrame.decode`), so that the reading stays
in order (a recording is read front to back) and the decoding runs on worker threads. Image files
(the KITTI layouts, the synthetic world) are :class:`ImageFiles`; a recording's frames are
``dpc_jax.sources.bag``'s.

Decoded images are as :func:`load_image` gives them: uint8 ``[H, W, 3]`` RGB, or ``[H, W]`` grey,
where grey is the value OpenCV's PNG decoder gives for a colour PNG read as grey (libpng's
fixed-point ``rgb_to_gray`` with weights 0.299 / 0.587 / 0.114, truncated: :func:`png_grey`), so that
the same pixels give the same grey whether they come from a PNG file or from raw bytes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

# libpng's rgb_to_gray coefficients for OpenCV's weights (0.299, 0.587): 29900 · 32768 / 100000 and
# 58700 · 32768 / 100000, truncated; blue takes the rest of 32768.
_PNG_GREY = (9797, 19234, 32768 - 9797 - 19234)


def png_grey(rgb: np.ndarray) -> np.ndarray:
    """uint8 ``[H, W]`` grey of uint8 ``[H, W, 3]`` RGB, exactly as OpenCV decodes a colour PNG as grey:
    ``(9797 r + 19234 g + 9737 b) >> 15`` (libpng's integer conversion; ``cv2.cvtColor`` rounds
    differently and differs by 1 on about half of the pixels)."""
    rgb32 = rgb.astype(np.uint32)
    red, green, blue = _PNG_GREY
    return ((red * rgb32[..., 0] + green * rgb32[..., 1] + blue * rgb32[..., 2]) >> 15).astype(np.uint8)


def load_image(path: str | Path, grey: bool = False) -> np.ndarray:
    """Decode an image file: uint8 ``[H, W, 3]`` RGB, or ``[H, W]`` when ``grey``.

    Raises ``FileNotFoundError`` when the file is missing and ``ValueError`` naming the file when
    it cannot be decoded (truncated or not an image).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file not found")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"{path}: cannot decode the image (truncated or not a PNG/JPEG file)")
    if image.dtype != np.uint8:
        raise ValueError(f"{path}: expected an 8-bit image, got {image.dtype}")
    return image if grey else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def checked_size(image: np.ndarray, size: tuple[int, int], where: str) -> np.ndarray:
    """``image``, unless its ``(H, W)`` is not ``size``: ``ValueError`` naming ``where``."""
    if image.shape[:2] != size:
        raise ValueError(f"{where}: image is {image.shape[0]}×{image.shape[1]}, expected {size[0]}×{size[1]} "
                         "like the sequence's first frame")
    return image


@dataclass(frozen=True)
class StereoFrame:
    """One frame as read, not yet decoded.

    * ``index``: its position among the frames it was streamed from;
    * ``where``: the file or the recording's topic and stamp, for messages;
    * ``read``: ``grey`` → the decoded ``(left, right)`` (:func:`load_image`'s types), each checked to
      be of the sequence's size.
    """

    index: int
    where: str
    read: Callable[[bool], tuple[np.ndarray, np.ndarray]]

    def decode(self, grey: bool = False) -> tuple[np.ndarray, np.ndarray]:
        return self.read(grey)


class StereoFrames(Protocol):
    """The images of a stereo sequence: ``len`` frames, cut by :meth:`select`, read by :meth:`stream`."""

    def __len__(self) -> int:
        """The number of stereo frames."""

    def select(self, start: int, stop: int) -> StereoFrames:
        """The frames ``start <= i < stop``."""

    def stream(self, size: tuple[int, int], indices: Sequence[int] | None = None) -> Iterator[StereoFrame]:
        """The frames ``indices`` (increasing; all when None) in order, each decoding to ``size`` ``(H, W)``
        images or raising ``ValueError`` naming it."""

    def identity(self) -> list[str]:
        """Texts that change when the frames' stored bytes may have changed (a cache's input hash)."""

    def locations(self) -> dict[str, str]:
        """Where the left and right images are (``left_images``, ``right_images``), for a manifest."""


@dataclass(frozen=True)
class ImageFiles:
    """A stereo pair of image folders: the N files of the left and of the right camera, in order."""

    left_paths: tuple[Path, ...]
    right_paths: tuple[Path, ...]

    def __post_init__(self) -> None:
        n_left, n_right = len(self.left_paths), len(self.right_paths)
        if n_left != n_right:
            raise ValueError(
                f"{n_left} left images ({self.left_paths[0].parent if n_left else '?'}) but {n_right} right "
                f"images ({self.right_paths[0].parent if n_right else '?'}); expected one right image per "
                "left one"
            )

    def __len__(self) -> int:
        return len(self.left_paths)

    def select(self, start: int, stop: int) -> ImageFiles:
        return ImageFiles(self.left_paths[start:stop], self.right_paths[start:stop])

    def stream(self, size: tuple[int, int], indices: Sequence[int] | None = None) -> Iterator[StereoFrame]:
        for k in range(len(self)) if indices is None else indices:
            left, right = self.left_paths[k], self.right_paths[k]

            def read(grey: bool, left: Path = left, right: Path = right) -> tuple[np.ndarray, np.ndarray]:
                return (checked_size(load_image(left, grey), size, str(left)),
                        checked_size(load_image(right, grey), size, str(right)))

            yield StereoFrame(k, str(left), read)

    def identity(self) -> list[str]:
        # Path, size and modification time: hashing gigabytes of PNGs on every run would cost more than
        # the check saves, and a replaced image changes its mtime.
        texts = []
        for path in (*self.left_paths, *self.right_paths):
            st = path.stat()
            texts.append(f"{path.resolve()}:{st.st_size}:{st.st_mtime_ns}")
        return texts

    def locations(self) -> dict[str, str]:
        return {"left_images": str(self.left_paths[0].parent.resolve()),
                "right_images": str(self.right_paths[0].parent.resolve())}
