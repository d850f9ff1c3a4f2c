"""Throughput of the input pipeline: batches/s of stereo pairs (with flow) read from a cache.

    python benchmarks/bench_data.py                      # synthetic cache of random data in a temp dir
    python benchmarks/bench_data.py --cache CACHE/09     # a prepared cache (dpc-jax prepare)

The synthetic cache has the layout and sizes of a real one (uint8 frames, float32 flows of all
four pair kinds, float64 poses); its arrays are random, which makes no difference to copying.
Reported: the inline loader (``workers=0``: the cost of assembling one batch) and the prefetching
loader (background threads), as batches/s with a consumer that does no work and as process CPU
time per batch, medians over repeated epochs after a warm-up epoch (page cache warm). Compare
with the train step: a batch is consumed every step, so batches/s must be several times the
steps/s of training.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from dpc_jax.data.pipeline import TrainLoader
from dpc_jax.data.sequence_cache import (
    CACHE_VERSION,
    DISPARITY_FILE,
    FLOW_FILES,
    MANIFEST,
    PAIR_KINDS,
    file_record,
    flow_step,
    load_cache,
)
from dpc_jax.runtime.machine import this_cpu


def write_random_cache(
    path: Path, frames: int, size: tuple[int, int], flow_kinds: tuple[str, ...], seed: int
) -> Path:
    """A cache folder of random frames and flows (``flow_kinds``) with the layout ``dpc_jax.data.cache``
    writes; its content does not change the cost of reading or of a step."""
    rng = np.random.default_rng(seed)
    path.mkdir(parents=True)
    h, w = size
    for camera in ("left", "right"):
        np.save(path / f"{camera}.npy", rng.integers(0, 256, (frames, h, w, 3), dtype=np.uint8))
    for kind in flow_kinds:
        count = frames - PAIR_KINDS[kind][0]
        # int16 units of flow_step px, as prepare stores flow: about ±2 px.
        flow = np.lib.format.open_memmap(path / FLOW_FILES[kind], "w+", np.int16, (count, 2, h, w, 2))
        for k in range(count):
            flow[k] = rng.integers(-2 / flow_step(size), 2 / flow_step(size), (2, h, w, 2), dtype=np.int16)
        flow.flush()
        del flow
    # The StereoSGBM disparity a prepared cache holds (dpc_jax.data.cache), in SGBM's 1/16 px: random,
    # 0 to 40 px, 80 % matched.
    disparity = np.lib.format.open_memmap(path / DISPARITY_FILE, "w+", np.int16, (frames, 2, h, w))
    for k in range(frames):
        matched = rng.random((2, h, w)) < 0.8
        disparity[k] = np.where(matched, rng.integers(1, 640, (2, h, w)), -16)
    disparity.flush()
    del disparity
    # A straight drive at 1.2 m per frame with a small sway, so priors and corrections are not all equal.
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, 2, 3] = np.arange(frames) * 1.2
    poses[:, 0, 3] = 0.1 * np.sin(np.arange(frames) / 5.0)
    for name in ("prior", "gt"):
        np.save(path / f"{name}.npy", poses)
    np.save(path / "K.npy", np.array([[0.58 * w, 0, w / 2], [0, 1.92 * h, h / 2], [0, 0, 1]]))
    np.save(path / "baseline.npy", np.float64(0.54))
    np.save(path / "indices.npy", np.arange(frames))
    np.save(path / "times.npy", np.arange(frames) * 0.1)
    manifest = {"version": CACHE_VERSION, "name": path.name, "n_frames": frames, "image_size": [h, w],
                "has_gt": True, "flows": list(flow_kinds), "flow_step": flow_step(size), "stereo_depth": True,
                "arrays": {file.name: file_record(file) for file in sorted(path.glob("*.npy"))}}
    (path / MANIFEST).write_text(json.dumps(manifest))
    for file in path.iterdir():  # finish the write-back now, not during the timed epochs
        with file.open("rb") as f:
            os.fsync(f.fileno())
    return path


def synthetic_cache(root: Path, frames: int, size: tuple[int, int], seed: int = 0) -> Path:
    """A random cache with every kind of flow, ``root/synthetic``."""
    return write_random_cache(root / "synthetic", frames, size, tuple(FLOW_FILES), seed)



def epoch_rate(loader: TrainLoader, epoch: int) -> tuple[float, float]:
    """(batches per second, process CPU ms per batch) of one epoch; the consumer does nothing.

    The CPU time (all threads) is the figure to trust on a loaded machine: wall-clock rates
    there mostly measure how long the process waited for a core.
    """
    start, cpu = time.perf_counter(), time.process_time()
    count = 0
    for batch in loader.epoch(epoch):
        count += int(batch.left.shape[0] > 0)
    return count / (time.perf_counter() - start), 1000 * (time.process_time() - cpu) / count


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--cache", type=Path, help="a prepared cache folder (default: synthetic)")
    parser.add_argument("--frames", type=int, default=160, help="frames of the synthetic cache")
    parser.add_argument("--size", default="240x376", help="HxW of the synthetic cache")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5, help="timed epochs per configuration")
    args = parser.parse_args()
    h, w = (int(v) for v in args.size.split("x"))

    with tempfile.TemporaryDirectory(prefix="bench_data_") as tmp:
        path = args.cache or synthetic_cache(Path(tmp), args.frames, (h, w))
        cache = load_cache(path)
        print(f"cache: {path} ({len(cache)} frames, {cache.image_size[0]}×{cache.image_size[1]}, "
              f"flows: {', '.join(cache.flows) or 'none'})")
        print(f"machine: {this_cpu()}, load average {os.getloadavg()[0]:.1f}")
        rows = []
        configs = [
            ("inline (workers=0)", {"workers": 0}, None),
            ("prefetch (1 thread, depth 3)", {"workers": 1, "depth": 3}, None),
            ("prefetch (2 threads, depth 4)", {"workers": 2, "depth": 4}, None),
            ("prefetch (4 threads, depth 8)", {"workers": 4, "depth": 8}, None),
            ("inline, no flow", {"workers": 0}, False),
            ("prefetch, no flow (1 thread)", {"workers": 1, "depth": 3}, False),
        ]
        for label, kwargs, flow in configs:
            loader = TrainLoader([cache], args.batch, frame_skip=True, flow=flow, **kwargs)
            first = next(iter(loader.epoch(0)))
            mbytes = sum(a.nbytes for a in first if a is not None) / 2**20
            epoch_rate(loader, 0)  # warm-up: page cache and threads
            timings = [epoch_rate(loader, e) for e in range(1, args.repeats + 1)]
            rate = statistics.median(t[0] for t in timings)
            cpu_ms = statistics.median(t[1] for t in timings)
            flow_shape = "-" if first.flow is None else tuple(first.flow.shape)
            shape = f"{tuple(first.left.shape)} + flow {flow_shape}"
            rows.append((label, shape, len(loader), rate, rate * mbytes, cpu_ms))
        header = f"{'loader':30} {'batch (left; right alike)':50} {'batches':>7} {'batch/s':>8} {'MB/s':>6}"
        print(f"\n{header} {'CPU ms/batch':>12}")
        for label, shape, n, rate, mbs, cpu_ms in rows:
            print(f"{label:30} {shape:50} {n:7d} {rate:8.1f} {mbs:6.0f} {cpu_ms:12.1f}")


if __name__ == "__main__":
    main()
