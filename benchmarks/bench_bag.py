"""Reading and decoding a recording's stereo pairs beside KITTI's PNG files (frames/s).

    python benchmarks/bench_bag.py [--frames 108] [--repeats 3]

The first ``--frames`` frames of the KITTI excerpt's drive 0001 (colour, 1242×375) are written, with
``rosbags``' writers, as a plain MCAP file of raw ``rgb8`` images, one of the PNG files as
``CompressedImage``, and a ROS 1 bag of raw images (into a temporary folder, not timed). Timed: opening
each source (``dpc_jax.sources``: a recording's index pass, timed alone too) and decoding every stereo
pair to colour as ``prepare`` does, the median of ``--repeats`` runs, against the same frames read from
the PNG files. A recording is no bottleneck of ``prepare`` or ``live`` when its rate is at
least the PNG files'.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from dpc_jax.data.frames import ImageFiles
from dpc_jax.data.kitti import StereoSequence
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.sources import BagOptions, Source, open_source
from dpc_jax.sources.bag_writer import write_stereo

EXCERPT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-raw"
DATE, DRIVE = "2011_09_26", "0001"


def _write(path: Path, kind: str, compressed: bool, sequence: StereoSequence, stamps: list[int]) -> Path:
    """The frames of ``sequence`` (image files) as a recording of ``kind`` (``mcap`` or ``ros1``)."""
    K, baseline = sequence.K, sequence.baseline
    left = np.hstack([K, np.zeros((3, 1))])
    right = left.copy()
    right[0, 3] = -K[0, 0] * baseline
    files = sequence.images
    assert isinstance(files, ImageFiles)
    write_stereo(path, kind, files.left_paths, files.right_paths, np.asarray(stamps, np.int64), (left, right),
                 compressed=compressed)
    return path


def _rate(source: Source, repeats: int) -> tuple[float, float, int]:
    """Median frames/s of opening ``source`` and decoding every pair to colour, of opening it alone (a
    recording's index pass), and the frame count."""
    rates, opening = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        sequence = open_source(source).sequence
        opened = time.perf_counter()
        n = sum(1 for frame in sequence.images.stream(sequence.image_size) if frame.decode() is not None)
        rates.append(n / (time.perf_counter() - start))
        opening.append(n / (opened - start))
    return statistics.median(rates), statistics.median(opening), n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=EXCERPT, help="KITTI raw root holding 2011_09_26/")
    parser.add_argument("--frames", type=int, default=108)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    files = Source("kitti-raw", args.root, DRIVE, DATE)
    try:
        sequence = open_source(files).sequence.select(0, args.frames)
    except (OSError, ValueError) as error:  # one line, not a traceback
        raise SystemExit(f"bench_bag: error: --root {args.root}: {error}") from None
    stamps = [1_700_000_000_000_000_000 + round(t * 1e9) for t in sequence.times]
    h, w = sequence.image_size
    print(f"stereo pairs read and decoded to colour, {len(sequence)} frames of {w}x{h}, {args.repeats} "
          "repeats (median)")
    print(f"device: {this_cpu()}, OpenCV {cv2.__version__}, load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    # The files' rate is over the whole drive (opening lists its files and reads the first image).
    rows = [("KITTI PNG files", *_rate(files, args.repeats)[:2], 0)]
    with tempfile.TemporaryDirectory() as tmp:
        for name, kind, compressed, suffix in (("MCAP, rgb8", "mcap", False, ".mcap"),
                                               ("MCAP, PNG-compressed", "mcap", True, ".mcap"),
                                               ("ROS 1 bag, rgb8", "ros1", False, ".bag")):
            path = _write(Path(tmp) / f"{kind}-{compressed}{suffix}", kind, compressed, sequence, stamps)
            rate, index, n = _rate(Source("bag", path, bag=BagOptions(path)), args.repeats)
            assert n == len(sequence)
            rows.append((name, rate, index, path.stat().st_size))
    print(f"| {'source':<22} | {'frames/s':>8} | {'opening alone, frames/s':>23} | {'MB':>6} |")
    for name, rate, index, size in rows:
        megabytes = size / 1e6 if size else float("nan")
        print(f"| {name:<22} | {rate:>8.1f} | {index:>23.1f} | {megabytes:>6.0f} |")


if __name__ == "__main__":
    main()
