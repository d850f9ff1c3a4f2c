"""The arrays of a cache folder being built, written in one streaming pass over its frames.

:func:`~dpc_jax.data.cache.prepare_sequence` hands :func:`write_frame_products` the decoded and
resized stereo pairs in order; each frame's StereoSGBM disparity (``dpc_jax.data.stereo_depth``)
is computed with it, and the Farnebäck flows (docs/method.md §6) of the pairs that end at it are
computed as soon as it arrives, so nothing is read back from the folder and only a few frames are
in memory at any time, however long the sequence. Arrays are appended to their ``.npy`` files with
plain writes (:class:`NpyWriter`): written pages are the page cache's, not the process's. Each file's
size and digests for the manifest (:class:`~dpc_jax.data.sequence_cache.ArrayDigest`) are computed
from the bytes as they are written, so nothing is read back for them either.
"""

from __future__ import annotations

import io
import logging
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypedDict

import cv2
import numpy as np

from dpc_jax.data.sequence_cache import DISPARITY_FILE, FLOW_FILES, PAIR_KINDS, ArrayDigest, encode_flow
from dpc_jax.runtime.progress import Progress, progress_bar

log = logging.getLogger(__name__)


class FarnebackParams(TypedDict):
    """Keyword arguments of ``cv2.calcOpticalFlowFarneback`` (besides ``flags``)."""

    pyr_scale: float
    levels: int
    winsize: int
    iterations: int
    poly_n: int
    poly_sigma: float


# docs/method.md §6: pyr_scale 0.5, 3 levels, window 15, 3 iterations, poly_n 5, poly_sigma 1.2.
FARNEBACK: FarnebackParams = {
    "pyr_scale": 0.5, "levels": 3, "winsize": 15, "iterations": 3, "poly_n": 5, "poly_sigma": 1.2
}


def farneback_flow(source_grey: np.ndarray, target_grey: np.ndarray) -> np.ndarray:
    """Dense flow source → target, float32 ``[H, W, 2]`` (Δx, Δy) px, docs/method.md §6 parameters.

    ``target(y + Δy, x + Δx) ≈ source(y, x)``.
    """
    # The output array is passed rather than None: OpenCV 5.0's stubs refuse None where 5.1's accept it.
    # Without OPTFLOW_USE_INITIAL_FLOW in ``flags`` its contents are not read.
    flow = np.empty((*source_grey.shape[:2], 2), np.float32)
    return cv2.calcOpticalFlowFarneback(source_grey, target_grey, flow, flags=0, **FARNEBACK)


def ordered_map(fn: Callable, items: Iterable, workers: int) -> Iterator:
    """``map`` over a thread pool (OpenCV releases the GIL), results in order, bounded look-ahead."""
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque[Future] = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > 2 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


class NpyWriter:
    """A ``.npy`` file of a known ``shape`` and ``dtype`` written row by row (along axis 0).

    The header is written first, then each :meth:`append`'s bytes; closing checks that exactly
    ``shape[0]`` rows came, so a short file is never left looking complete. :meth:`record` is the
    file's size and digests for the manifest, computed from the bytes written.
    """

    def __init__(self, path: Path, dtype: np.dtype | type, shape: tuple[int, ...]) -> None:
        self.path, self.dtype, self.shape = path, np.dtype(dtype), shape
        self.rows = 0
        header = io.BytesIO()
        descr = np.lib.format.dtype_to_descr(self.dtype)
        np.lib.format.write_array_header_1_0(header, {"descr": descr, "fortran_order": False, "shape": shape})
        self._digest = ArrayDigest(header.tell() + math.prod(shape) * self.dtype.itemsize)
        self._file = path.open("wb")
        self._write(header.getvalue())

    def _write(self, data: bytes) -> None:
        self._file.write(data)
        self._digest.update(data)

    def append(self, row: np.ndarray) -> None:
        if row.shape != self.shape[1:]:
            raise ValueError(f"{self.path}: row of shape {row.shape}, expected {self.shape[1:]}")
        self._write(np.ascontiguousarray(row, self.dtype).tobytes())
        self.rows += 1

    def close(self) -> None:
        self._file.close()

    def check_complete(self) -> None:
        if self.rows != self.shape[0]:
            raise RuntimeError(f"{self.path}: {self.rows} rows written, expected {self.shape[0]}")

    def record(self) -> dict[str, int | str]:
        """The manifest's record of the complete file (:meth:`ArrayDigest.record`)."""
        return self._digest.record()


def save_array(path: Path, array: np.ndarray) -> dict[str, int | str]:
    """``np.save(path, array)`` of a small array (poses, intrinsics, times); returns the manifest's
    record of the file (:class:`~dpc_jax.data.sequence_cache.ArrayDigest`) from the bytes written."""
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, np.asanyarray(array), allow_pickle=False)
    data = buffer.getvalue()
    path.write_bytes(data)
    digest = ArrayDigest(len(data))
    digest.update(data)
    return digest.record()


def write_frame_products(
    tmp: Path,
    frames: Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    n: int,
    size: tuple[int, int],
    *,
    depth: bool,
    flow_kinds: tuple[str, ...],
    flow_step: float,
    label: str,
    workers: int,
    progress: Progress,
) -> dict[str, dict[str, int | str]]:
    """Write ``left.npy``/``right.npy`` (uint8 ``[n, H, W, 3]``), with ``depth`` the disparity
    (int16 ``[n, 2, H, W]``) and the flows of ``flow_kinds`` (int16 ``[n - step, 2, H, W, 2]`` in
    units of ``flow_step`` px) into ``tmp``; return each file's record for the manifest (file name →
    :meth:`NpyWriter.record`).

    ``frames`` yields ``(left, right, disparity or None)`` of each of the ``n`` frames in order.
    The flows of the pairs ending at frame ``k`` are computed on ``workers`` threads while later
    frames are decoded; at most ``2·workers`` frames' flows wait to be written.
    """
    h, w = size
    for kind in flow_kinds:
        if n <= PAIR_KINDS[kind][0]:
            needed = PAIR_KINDS[kind][0] + 1
            raise ValueError(f"{n} frames are too few for {kind} flow (needs at least {needed})")
    writers = {"left": NpyWriter(tmp / "left.npy", np.uint8, (n, h, w, 3)),
               "right": NpyWriter(tmp / "right.npy", np.uint8, (n, h, w, 3))}
    if depth:
        writers["disparity"] = NpyWriter(tmp / DISPARITY_FILE, np.int16, (n, 2, h, w))
    for kind in flow_kinds:
        writers[kind] = NpyWriter(tmp / FLOW_FILES[kind], np.int16, (n - PAIR_KINDS[kind][0], 2, h, w, 2))

    def pair_flow(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Flow a → b of both cameras (``a``, ``b``: the grey left and right images of a frame)."""
        return encode_flow(np.stack([farneback_flow(a[c], b[c]) for c in (0, 1)]), flow_step)

    recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=2)  # grey pairs of frames k-2, k-1
    # Each frame brings one flow of each kind: waiting at 2·workers frames' worth keeps every flow
    # thread busy while the next frames are decoded.
    ahead = 2 * workers * max(1, len(flow_kinds))
    pending: deque[tuple[str, Future]] = deque()  # flows in the order each kind's file takes them
    try:
        bar_context = progress_bar(n, f"{label} prepare", progress)
        with ThreadPoolExecutor(max_workers=workers) as pool, bar_context as bar:
            for left, right, disparity in frames:
                writers["left"].append(left)
                writers["right"].append(right)
                if disparity is not None:
                    writers["disparity"].append(disparity)
                current = (grey(left), grey(right)) if flow_kinds else None
                for kind in flow_kinds:
                    step, backward = PAIR_KINDS[kind]
                    if current is not None and len(recent) >= step:
                        other = recent[-step]
                        a, b = (current, other) if backward else (other, current)
                        pending.append((kind, pool.submit(pair_flow, a, b)))
                if current is not None:
                    recent.append(current)
                while len(pending) > ahead:
                    kind, future = pending.popleft()
                    writers[kind].append(future.result())
                bar.update(1)
            while pending:
                kind, future = pending.popleft()
                writers[kind].append(future.result())
    finally:
        for writer in writers.values():
            writer.close()
    for writer in writers.values():
        writer.check_complete()
    return {writer.path.name: writer.record() for writer in writers.values()}
