"""Stereo VO speed on the real KITTI excerpt (1242×375): frames/s and time per stage.

    python benchmarks/bench_vo.py [--repeats 3] [--frames 108]

Images are decoded (colour → grey) once, outside the timed loop, and the decode time per pair is
reported on its own line. After a warm-up run on the first frames, the whole sequence is run
``--repeats`` times; the table gives the median over repeats of the time per frame of each stage
(track: temporal KLT with its backward check; detect: bucketed FAST; stereo: left–right KLT with
its check and triangulation; motion: RANSAC + Gauss–Newton; other: the loop's bookkeeping).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from dpc_jax.data.kitti import load_image, open_raw
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.vo import STAGES, VOConfig, run_vo_frames

EXCERPT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-raw"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=EXCERPT, help="KITTI raw root holding 2011_09_26/")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=108)
    args = parser.parse_args()

    try:
        sequence = open_raw(args.root, "2011_09_26", "0001")
    except (OSError, ValueError) as error:  # one line, not a traceback
        raise SystemExit(f"bench_vo: error: --root {args.root}: {error}") from None
    n = min(args.frames, len(sequence))
    start = time.perf_counter()
    frames = [
        (load_image(left, grey=True), load_image(right, grey=True))
        for left, right in zip(sequence.images.left_paths[:n], sequence.images.right_paths[:n], strict=True)
    ]
    decode_ms = (time.perf_counter() - start) / n * 1e3
    config = VOConfig()
    run_vo_frames(frames[: min(10, n)], sequence.K, sequence.baseline, config)  # warm-up

    totals, stages = [], {name: [] for name in (*STAGES, "other")}
    for _ in range(args.repeats):
        start = time.perf_counter()
        result = run_vo_frames(frames, sequence.K, sequence.baseline, config)
        elapsed = time.perf_counter() - start
        totals.append(elapsed / n * 1e3)
        for name in STAGES:
            stages[name].append(result.stage_times[name] / n * 1e3)
        stages["other"].append(totals[-1] - sum(result.stage_times[name] / n * 1e3 for name in STAGES))

    height, width = frames[0][0].shape
    per_frame = statistics.median(totals)
    print(f"stereo VO, {n} frames of {width}x{height} grey pairs, {args.repeats} repeats (median)")
    print(f"device: {this_cpu()}, OpenCV {cv2.__version__} with {cv2.getNumThreads()} threads, load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print(f"{'stage':<10}{'ms/frame':>10}{'share':>8}")
    for name, values in stages.items():
        value = statistics.median(values)
        print(f"{name:<10}{value:>10.2f}{value / per_frame:>8.0%}")
    print(f"{'total':<10}{per_frame:>10.2f}{1:>8.0%}")
    slowest, fastest = 1e3 / max(totals), 1e3 / min(totals)
    print(f"frames/s (VO only): {1e3 / per_frame:.1f}   [repeats: {slowest:.1f} to {fastest:.1f}]")
    print(f"decode colour PNG pair to grey: {decode_ms:.1f} ms/frame → with decoding "
          f"{1e3 / (per_frame + decode_ms):.1f} frames/s; median inliers {int(np.median(result.inliers))}")


if __name__ == "__main__":
    main()
