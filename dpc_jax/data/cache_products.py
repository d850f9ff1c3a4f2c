"""What :func:`~dpc_jax.data.cache.prepare_sequence` derives from the stored pairs: Farnebäck flow
(docs/method.md §6) and the StereoSGBM depth (``dpc_jax.data.stereo_depth``), written into the
cache folder being built, and the bounded thread-pool map that decodes and derives in parallel.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypedDict

import cv2
import numpy as np

from dpc_jax._progress import Progress, progress_bar
from dpc_jax.data.sequence_cache import FLOW_FILES, STEREO_DEPTH_FILES
from dpc_jax.data.stereo_depth import sequence_inverse_depth, sgbm_fits

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
    # OpenCV's stubs require an output array ``flow``; None (allocate one) is what OpenCV accepts.
    flow = cv2.calcOpticalFlowFarneback(  # type: ignore[call-overload]
        source_grey, target_grey, None, flags=0, **FARNEBACK
    )
    return flow.astype(np.float32, copy=False)


def ordered_map(fn, items: list, workers: int) -> Iterator:
    """``map`` over a thread pool (OpenCV releases the GIL), results in order, bounded look-ahead."""
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending = []
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > 2 * workers:
                yield pending.pop(0).result()
        for future in pending:
            yield future.result()


def grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def write_flows(
    tmp: Path, left: np.ndarray, right: np.ndarray, augment: bool, workers: int, progress: Progress
) -> None:
    n = left.shape[0]
    kinds = {"forward": (1, False)}
    if augment:
        kinds |= {"reverse": (1, True), "skip": (2, False), "skip_reverse": (2, True)}
    for kind, (step, backward) in kinds.items():
        count = n - step
        if count < 1:
            raise ValueError(f"{n} frames are too few for {kind} flow (needs at least {step + 1})")
        out = np.lib.format.open_memmap(
            tmp / FLOW_FILES[kind], mode="w+", dtype=np.float32, shape=(count, 2, *left.shape[1:3], 2)
        )

        def pair_flow(k: int, step: int = step, backward: bool = backward) -> np.ndarray:
            a, b = (k + step, k) if backward else (k, k + step)
            return np.stack([
                farneback_flow(grey(cam[a]), grey(cam[b])) for cam in (left, right)
            ])

        results = ordered_map(pair_flow, list(range(count)), workers)
        with progress_bar(count, f"flow ({kind})", progress, unit="pair") as bar:
            for k, flow in enumerate(results):
                out[k] = flow
                bar.update(1)
        out.flush()
        del out


def write_stereo_depth(tmp: Path, fu: float, baseline: float, label: str, workers: int,
                        progress: Progress) -> None:
    """Write the StereoSGBM inverse depth and validity of the stored pairs of ``tmp`` (``fu``: focal
    length of the stored images, px; ``baseline``: m), unless they are too narrow for it."""
    left, right = (np.load(tmp / f"{camera}.npy", mmap_mode="r") for camera in ("left", "right"))
    n, h, w = left.shape[:3]
    if not sgbm_fits(w, fu, baseline):
        log.info("%s: images %d px wide are too narrow for StereoSGBM; no stereo depth stored", label, w)
        return
    inverse = np.lib.format.open_memmap(tmp / STEREO_DEPTH_FILES[0], mode="w+", dtype=np.float32,
                                        shape=(n, 2, h, w))
    valid = np.lib.format.open_memmap(tmp / STEREO_DEPTH_FILES[1], mode="w+", dtype=bool, shape=(n, 2, h, w))

    with progress_bar(n, f"{label} stereo depth", progress) as bar:
        sequence_inverse_depth(left, right, fu, baseline, workers=workers, out=(inverse, valid),
                               done=lambda: bar.update(1))
    inverse.flush()
    valid.flush()
