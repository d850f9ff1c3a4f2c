"""Reading and decoding a recording's stereo pairs beside KITTI's PNG files (frames/s).

    python benchmarks/bench_bag.py [--frames 108] [--repeats 3]

The first ``--frames`` frames of the KITTI excerpt's drive 0001 (colour, 1242×375) are written, with
``rosbags``' writers, as a plain MCAP file of raw ``rgb8`` images, one of the PNG files as
``CompressedImage``, and a ROS 1 bag of raw images (into a temporary folder, not timed). Timed: opening
each source (``dpc_jax.sources``: a recording's index pass reads every message once) and decoding every
stereo pair to colour as ``prepare`` does, the median of ``--repeats`` runs, against the same frames
read from the PNG files. A recording is no bottleneck of ``prepare`` or ``live`` when its rate is at
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

from dpc_jax.runtime.machine import this_cpu
from dpc_jax.sources import Source, open_source
from dpc_jax.sources.bag import BagOptions

EXCERPT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-raw"
DATE, DRIVE = "2011_09_26", "0001"


def _write(path: Path, kind: str, compressed: bool, sequence: object, stamps: list[int]) -> Path:
    """The frames of ``sequence`` (image files) as a recording of ``kind`` (``mcap`` or ``ros1``)."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path.with_suffix(""), version=9, storage_plugin=StoragePlugin.MCAP)
    types = store.types
    K, baseline = sequence.K, sequence.baseline  # type: ignore[attr-defined]
    h, w = sequence.image_size  # type: ignore[attr-defined]
    msgtype = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with writer:
        connections = {}
        for side in ("left", "right"):
            connections[side] = writer.add_connection(f"/{side}/image", msgtype, typestore=store)
            connections[f"{side}_info"] = writer.add_connection(f"/{side}/camera_info",
                                                                "sensor_msgs/msg/CameraInfo", typestore=store)
        files = sequence.images  # type: ignore[attr-defined]
        for stamp, left, right in zip(stamps, files.left_paths, files.right_paths, strict=True):
            sec, nanosec = divmod(stamp, 1_000_000_000)
            time_msg = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
            header = (types["std_msgs/msg/Header"](seq=0, stamp=time_msg, frame_id="cam") if ros1
                      else types["std_msgs/msg/Header"](stamp=time_msg, frame_id="cam"))
            for side, file, tx in (("left", left, 0.0), ("right", right, -K[0, 0] * baseline)):
                P = np.hstack([K, [[tx], [0.0], [0.0]]])
                names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
                values = (np.zeros(5), K.ravel(), np.eye(3).ravel(), P.ravel())
                matrices = dict(zip(names, values, strict=True))
                roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                  do_rectify=False)
                info = types["sensor_msgs/msg/CameraInfo"](header=header, height=h, width=w,
                                                           distortion_model="plumb_bob", binning_x=0,
                                                           binning_y=0, roi=roi, **matrices)
                if compressed:
                    image = types[msgtype](header=header, format="png",
                                           data=np.frombuffer(file.read_bytes(), np.uint8))
                else:
                    rgb = np.ascontiguousarray(cv2.cvtColor(cv2.imread(str(file)), cv2.COLOR_BGR2RGB))
                    image = types[msgtype](header=header, height=h, width=w, encoding="rgb8", is_bigendian=0,
                                           step=3 * w, data=rgb.reshape(-1))
                serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
                info_bytes = serialize(info, "sensor_msgs/msg/CameraInfo")
                writer.write(connections[f"{side}_info"], stamp, info_bytes)
                writer.write(connections[side], stamp, serialize(image, msgtype))
    if ros1:
        return path
    (inner,) = path.with_suffix("").glob("*.mcap")
    inner.rename(path)
    return path


def _rate(source: Source, repeats: int) -> tuple[float, int]:
    """Median frames/s of opening ``source`` and decoding every pair to colour, and the frame count."""
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        sequence = open_source(source).sequence
        n = sum(1 for frame in sequence.images.stream(sequence.image_size) if frame.decode() is not None)
        rates.append(n / (time.perf_counter() - start))
    return statistics.median(rates), n


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
    rows = [("KITTI PNG files", _rate(files, args.repeats)[0], 0)]
    with tempfile.TemporaryDirectory() as tmp:
        for name, kind, compressed, suffix in (("MCAP, rgb8", "mcap", False, ".mcap"),
                                               ("MCAP, PNG-compressed", "mcap", True, ".mcap"),
                                               ("ROS 1 bag, rgb8", "ros1", False, ".bag")):
            path = _write(Path(tmp) / f"{kind}-{compressed}{suffix}", kind, compressed, sequence, stamps)
            rate, n = _rate(Source("bag", path, bag=BagOptions(path)), args.repeats)
            assert n == len(sequence)
            rows.append((name, rate, path.stat().st_size))
    print(f"| {'source':<22} | {'frames/s':>8} | {'MB':>6} |")
    for name, rate, size in rows:
        print(f"| {name:<22} | {rate:>8.1f} | {size / 1e6 if size else float('nan'):>6.0f} |")


if __name__ == "__main__":
    main()
