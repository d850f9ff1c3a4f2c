"""The real KITTI raw drives through a ROS recording: `dpc-jax vo` writes the same trajectory and `dpc-jax
prepare` the same cache, byte for byte, from a drive written as a recording as from the raw layout's files.

    nice -n 10 python experiments/studies/recorded_drives.py --workdir runs/recorded_drives \\
        --results-page docs/results/recorded_drives.md

For each drive (``--drive``, default 0001 and 0005 of 2011_09_26, every frame) the script writes the
drive's rectified pair (colour where the drive has one, else grey) into the work folder as recordings, with
``rosbags``' writers (``dpc_jax.sources.bag_writer.write_stereo``): each camera's images at the stamps of
its ``timestamps.txt`` and ``CameraInfo`` with the ``P_rect`` rows of ``calib_cam_to_cam.txt``, as

* a plain MCAP file of raw images (``rgb8``; ``mono8`` for a grey pair),
* a ROS 1 bag of the PNG files as ``CompressedImage``,
* a ROS 2 bag folder (MCAP storage) of raw images.

Then it runs `dpc-jax vo` (default options) and `dpc-jax prepare` (``--size 64x96``; the prior and the
ground truth: the drive's libviso2 ``stereo_*.mat`` for the frames written, as KITTI text) on the raw
layout and on each recording, and compares the trajectory files (``vo.txt``) and every array of the
caches (``*.npy``: images, calibration, prior, ground truth, times) byte for byte. It prints (and with
``--results-page`` writes into that page) one row per drive and recording. The recordings stay in the
work folder (``DRIVE/*.mcap``, ``*.bag``, ``rosbag2/``) for rviz, Foxglove or ``ros2 bag play``; the
data folder is only read. ``--frames N`` takes the first N frames (the wiring, in seconds).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dpc_jax.experiments import script as kit
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.report.tables import table

DATE = "2011_09_26"
DRIVES = ("0001", "0005")
SIZE = "64x96"
# (name in the table, dpc_jax.sources.bag_writer's kind, file name in the drive's folder, PNG-compressed)
RECORDINGS = (("MCAP file, raw", "mcap", "drive.mcap", False),
              ("ROS 1 bag, PNG-compressed", "ros1", "drive.bag", True),
              ("ROS 2 bag folder (MCAP), raw", "rosbag2", "rosbag2", False))


def build_parser() -> argparse.ArgumentParser:
    parser = kit.new_parser(__doc__)
    parser.add_argument("--workdir", type=path_argument, required=True, metavar="DIR",
                        help="work folder (recordings, trajectories, caches)")
    kit.add_kitti_raw_option(parser)
    parser.add_argument("--drive", nargs="+", default=list(DRIVES), metavar="NNNN", help="drives of DATE")
    parser.add_argument("--frames", type=int, metavar="N", help="only the first N frames of each drive")
    kit.add_results_page(parser)
    return parser


def _camera_stamps(folder: Path, frames: int) -> np.ndarray:
    """int64 ns ``[frames]`` of a camera folder's ``timestamps.txt``."""
    lines = [line.strip() for line in (folder / "timestamps.txt").read_text().splitlines() if line.strip()]
    return np.array([np.datetime64(line.replace(" ", "T"), "ns") for line in lines[:frames]]).astype(np.int64)


def write_recordings(root: Path, drive: str, frames: int | None, out: Path) -> tuple[list[Path], int, int]:
    """The drive's pair as each recording of :data:`RECORDINGS` in ``out``: their paths, the frames written
    and the drive's frames."""
    from dpc_jax.data.kitti import open_raw
    from dpc_jax.sources.bag_writer import write_stereo

    sequence = open_raw(root, DATE, drive)
    files = sequence.images
    n = len(sequence) if frames is None else min(frames, len(sequence))
    left, right = files.left_paths[:n], files.right_paths[:n]  # type: ignore[attr-defined]
    cameras = [path.parent.parent.name[-2:] for path in (left[0], right[0])]  # "02"/"03" or "00"/"01"
    rows = {}
    for line in (root / DATE / "calib_cam_to_cam.txt").read_text().splitlines():
        key, _, values = line.partition(":")
        if key.startswith("P_rect_"):
            rows[key[7:]] = np.array(values.split(), np.float64).reshape(3, 4)
    stamps = np.stack([_camera_stamps(path.parent.parent, n) for path in (left[0], right[0])], axis=1)
    paths = []
    for _, kind, name, compressed in RECORDINGS:
        path = out / name
        if not path.exists():  # a finished recording of an earlier run (each is written to a new name)
            staged = out / f".{name}.partial"
            if staged.is_dir():
                import shutil

                shutil.rmtree(staged)
            staged.unlink(missing_ok=True)
            write_stereo(staged, kind, left, right, stamps, (rows[cameras[0]], rows[cameras[1]]),
                         compressed=compressed)
            staged.rename(path)
        paths.append(path)
    return paths, n, len(sequence)


def _run(argv: list[str]) -> None:
    """A `dpc-jax` command in this process, its printed lines kept out of the table."""
    from dpc_jax.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        status = main(argv)
    if status != 0:
        raise RuntimeError(f"dpc-jax {' '.join(argv)} exited {status}: {printed.getvalue().strip()[-300:]}")


def _same_arrays(a: Path, b: Path) -> tuple[int, list[str]]:
    """How many ``*.npy`` the caches ``a`` and ``b`` hold, and those that differ or one of them lacks."""
    names = sorted({p.name for p in a.glob("*.npy")} | {p.name for p in b.glob("*.npy")})
    differ = [name for name in names if not ((a / name).is_file() and (b / name).is_file()
                                             and (a / name).read_bytes() == (b / name).read_bytes())]
    return len(names), differ


def study(args: argparse.Namespace) -> str:
    from dpc_jax.data.poses_io import read_mat, write_kitti_poses

    start = time.perf_counter()
    header = ["drive", "frames", "source", "VO median inliers", "vo.txt", "cache arrays",
              "seconds (vo + prepare)"]
    rows = []
    for drive in args.drive:
        out = args.workdir / drive
        out.mkdir(parents=True, exist_ok=True)
        recordings, n, total = write_recordings(args.kitti_raw, drive, args.frames, out)
        # The libviso2 estimate and ground truth as KITTI text: of the drive's frames for the layout (its
        # --frames takes the first n; the excerpt of 0005 is shorter than its .mat), of the n frames
        # written for the recordings.
        gt, estimate = read_mat(args.kitti_raw / "libviso2" / f"stereo_{DATE}_drive_{drive}.mat")
        poses = {}
        for part, count in (("all", total), ("written", n)):
            poses[part] = (out / f"prior_{part}.txt", out / f"gt_{part}.txt")
            write_kitti_poses(poses[part][0], estimate[:count])
            write_kitti_poses(poses[part][1], gt[:count])
        frames = ["--frames", f"0:{n}"]
        layout = ["--kitti-raw", str(args.kitti_raw), "--date", DATE, "--drive", drive]
        named = zip(RECORDINGS, recordings, strict=True)
        sources = [("raw layout (files)", layout, "layout"),
                   *((name, ["--bag", str(path)], kind) for (name, kind, *_), path in named)]
        reference: tuple[bytes, Path] | None = None
        for name, source, key in sources:
            began = time.perf_counter()
            vo = out / f"vo_{key}.txt"
            _run(["vo", *source, *frames, "--out", str(vo), "--no-progress"])
            cache = out / f"cache_{key}"
            prior, truth = poses["all" if key == "layout" else "written"]
            _run(["prepare", *source, "--prior", str(prior), "--gt", str(truth), "--size", SIZE, "--out",
                  str(cache), "--no-progress", *(frames if key == "layout" else [])])
            (folder,) = [p for p in cache.iterdir() if p.is_dir()]
            seconds = f"{time.perf_counter() - began:.0f}"
            inliers = f"{json.loads(vo.with_suffix('.json').read_text())['median_inliers']:.0f}"
            if reference is None:
                reference = (vo.read_bytes(), folder)
                count = len(list(folder.glob("*.npy")))
                rows.append([drive, str(n), name, inliers, "reference", f"{count} arrays", seconds])
                continue
            same_vo = "identical bytes" if vo.read_bytes() == reference[0] else "DIFFERENT"
            count, differ = _same_arrays(reference[1], folder)
            arrays = f"{count} of {count} identical" if not differ else f"DIFFERENT: {', '.join(differ)}"
            rows.append([drive, str(n), name, inliers, same_vo, arrays, seconds])
    minutes = (time.perf_counter() - start) / 60
    return (f"KITTI raw drives of {DATE} through ROS recordings written with rosbags' writers: `dpc-jax vo` "
            f"(default options) and `dpc-jax prepare --size {SIZE}` (prior and ground truth: libviso2's "
            f"stereo_*.mat) on the raw layout and on each recording, the outputs compared byte for byte. "
            f"{minutes:.1f} minutes in all.\n\n" + table(header, rows))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.frames is not None and args.frames < 2:
            raise ValueError(f"--frames {args.frames}: expected at least 2")
        args.kitti_raw = kit.data_given(args.kitti_raw, "--kitti-raw")
        kit.claim(args.workdir, [("--kitti-raw", args.kitti_raw)], script=__file__, page=args.results_page)
        text = study(args)
    except (OSError, ValueError, RuntimeError) as error:
        return kit.refuse("recorded_drives", error, 1 if isinstance(error, RuntimeError) else 2)
    kit.publish(text, args.results_page, __file__)
    return 0


if __name__ == "__main__":
    sys.exit(kit.interruptible(main, __file__))
