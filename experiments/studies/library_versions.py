"""What a change of library versions (a new OpenCV) changes in our figures, measured on real frames.

Run once in each environment to compare (the same machine), each into a folder of its own; then once more
with both folders to compare them:

    python experiments/studies/library_versions.py --out runs/library_versions/cv50      # in one venv
    python experiments/studies/library_versions.py --out runs/library_versions/cv51      # in the other
    python experiments/studies/library_versions.py --compare runs/library_versions/cv50 \\
        runs/library_versions/cv51 --results-page docs/results/library_versions.md

A measurement (about a minute on a 2-core CPU) of KITTI raw 2011_09_26_drive_0001 (108 frames) writes into
its folder:

* ``measurement.json``: the stamp (machine, commit, library versions), our VO's summary and its metrics
  against the drive's ground truth (``poses_gt`` of its libviso2 ``.mat``, as
  ``experiments/protocols/kitti_raw_excerpt.py`` evaluates it): segment errors and m-ATE;
* ``vo.txt``: our VO's trajectory (``dpc_jax.vo.run_vo`` with the default ``VOConfig``, started at the
  first ground-truth pose: what ``dpc-jax vo ... --start gt`` writes), and ``vo_inliers.npy``, its
  inliers per pair;
* ``products.npz``: for frames 0, 35, 70 and 105 at full resolution (375×1242), 240×376 (the papers' and
  the judge's size) and 64×96 (the demo's network), each frame prepared as a cache prepares it
  (``dpc_jax.data.preparation.prepared_pair``: area resizing, the right image first moved by the
  calibration residual our VO measures, :data:`SHIFT_PX`): the grey images, StereoSGBM's disparity of
  both cameras (``dpc_jax.data.stereo_depth``'s settings) and the Farnebäck flow of the left camera to
  the next frame (``dpc_jax.data.cache_products.farneback_flow``).

The comparison prints (and with ``--results-page`` writes into that page) both folders' versions, our VO's
metrics side by side and how far the trajectories are apart, and for each product and size (the flow also
as a cache rounds it) the share of pixels that differ and the largest and mean absolute difference.
``--smoke`` measures one frame at 64×96 and the VO over the first 20 frames (m-ATE only: no 100 m
segment), in seconds: the wiring.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.experiments import script as kit
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.report.tables import number, table

DATE, DRIVE = "2011_09_26", "0001"
LIBVISO2 = "libviso2/stereo_2011_09_26_drive_0001.mat"
FRAMES = (0, 35, 70, 105)
SIZES = (None, (240, 376), (64, 96))  # None: the stored images' own size
# The right image is moved by the calibration residual our VO measures on this drive (its median offset,
# 1.1557 px) before resizing, as a drive's caches are (the demo's by +0.8 px): cv2.warpAffine takes part.
# A fixed value, so that the images of two environments are compared at the same shift.
SHIFT_PX = 1.156
SMOKE_FRAMES, SMOKE_VO_FRAMES = (0,), 20
METRICS = (("seg_trans_pct", "segment error t (%)"), ("seg_rot_deg_per_100m", "segment error r (°/100 m)"),
           ("m_ate_trans_m", "m-ATE t (m)"), ("m_ate_rot_deg", "m-ATE r (°)"))
SUMMARY = (("fallbacks", "constant-velocity fallbacks"), ("median_inliers", "median inliers"),
           ("disparity_offset_median_px", "measured disparity offset (px)"))
KINDS = ("images", "disparity", "flow")  # the products, in the order of the comparison's table
MEASUREMENT, PRODUCTS, TRAJECTORY, INLIERS = "measurement.json", "products.npz", "vo.txt", "vo_inliers.npy"


def build_parser() -> argparse.ArgumentParser:
    parser = kit.new_parser(__doc__)
    task = parser.add_mutually_exclusive_group(required=True)
    task.add_argument("--out", type=path_argument, metavar="DIR",
                      help="measure in this environment into DIR (a work folder of its own)")
    task.add_argument("--compare", type=path_argument, nargs=2, metavar=("DIR_A", "DIR_B"),
                      help="compare two measured folders (B against A)")
    kit.add_kitti_raw_option(parser)
    parser.add_argument("--smoke", action="store_true", help="one frame at 64×96, VO over 20 frames")
    kit.add_no_progress(parser)
    kit.add_results_page(parser)
    return parser


def size_name(shape: tuple[int, ...]) -> str:
    return f"{shape[0]}×{shape[1]}"


def measure(args: argparse.Namespace) -> int:
    from dpc_jax._io import atomic_write
    from dpc_jax.data.cache_products import farneback_flow, grey
    from dpc_jax.data.kitti import open_raw
    from dpc_jax.data.poses_io import write_kitti_poses
    from dpc_jax.data.preparation import prepared_pair, resized_image, resized_intrinsics
    from dpc_jax.eval.evaluation import evaluate
    from dpc_jax.experiments.stamp import stamp
    from dpc_jax.vo import VOConfig, run_vo
    from dpc_jax.vo.odometry import summary

    progress = kit.progress_flag(args.no_progress)
    try:
        if args.results_page is not None:
            raise ValueError("--results-page: only with --compare (a measurement writes its folder)")
        raw = kit.data_given(args.kitti_raw, "--kitti-raw")
        sequence = open_raw(raw, DATE, DRIVE, poses=raw / LIBVISO2)
        kit.claim(args.out, [("--kitti-raw", raw)], script=__file__, option="--out")
    except (OSError, ValueError, KeyError) as error:
        return kit.refuse("library_versions", error)
    clock = kit.Clock()
    frames, sizes = (SMOKE_FRAMES, SIZES[-1:]) if args.smoke else (FRAMES, SIZES)
    if args.smoke:
        sequence = sequence.select(0, SMOKE_VO_FRAMES)
    assert sequence.poses is not None  # open_raw was given them
    result = run_vo(sequence, VOConfig(), first_pose=sequence.poses[0], progress=progress)
    scores = evaluate(sequence.poses, {"vo": result.poses}).estimates["vo"]
    clock.say(f"our VO: {len(sequence)} frames")

    # Each frame and the next one (its flow's target), decoded once for every size.
    indices = sorted({i for k in frames for i in (k, k + 1)})
    decoded = {frame.index: frame.decode() for frame in sequence.images.stream(sequence.image_size, indices)}
    # Any: typed as arrays, mypy matches the ** of savez_compressed below against its allow_pickle: bool.
    arrays: dict[str, Any] = {}
    for shape in sizes:
        size = sequence.image_size if shape is None else shape
        K = resized_intrinsics(sequence.K, sequence.image_size, size)
        images, disparities, flows = [], [], []
        for k in frames:
            left, right, disparity = prepared_pair(*decoded[k], size, K, sequence.baseline, SHIFT_PX)
            assert disparity is not None  # every size here is wide enough for StereoSGBM
            following = resized_image(decoded[k + 1][0], size)
            images.append(np.stack([grey(left), grey(right)]))
            disparities.append(disparity)
            flows.append(farneback_flow(grey(left), grey(following)))
        name = size_name(size)
        arrays |= {f"images {name}": np.stack(images), f"disparity {name}": np.stack(disparities),
                   f"flow {name}": np.stack(flows)}
        clock.say(f"{name}: frames {', '.join(map(str, frames))} matched and flowed")
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    buffer_inliers = io.BytesIO()
    np.save(buffer_inliers, result.inliers)
    measured_with = stamp()
    record = {"stamp": measured_with, "drive": sequence.name, "frames": list(frames), "shift_px": SHIFT_PX,
              "vo_summary": summary(result), "vo_metrics": {key: scores[key] for key, _ in METRICS}}
    atomic_write(args.out / PRODUCTS, buffer.getvalue())
    atomic_write(args.out / INLIERS, buffer_inliers.getvalue())
    write_kitti_poses(args.out / TRAJECTORY, result.poses)
    # Written last: a folder with its record is a finished measurement.
    atomic_write(args.out / MEASUREMENT, json.dumps(record, indent=2) + "\n")
    clock.say(f"written {args.out} ({measured_with['libraries']})")
    return 0


def difference(a: np.ndarray, b: np.ndarray, kind: str) -> dict[str, float]:
    """How far ``b`` is from ``a`` (same shape), per pixel: ``differ`` (share of pixels that differ at
    all), ``max`` and ``mean`` (absolute difference; mean over all compared pixels) and, for a
    disparity, ``validity`` (share of pixels matched in one and not in the other).

    ``kind``: ``images`` (grey levels, ``[..., H, W]``), ``disparity`` (StereoSGBM's int16 in 1/16 px,
    compared in px where both matched) or ``flow`` (``[..., H, W, 2]`` px: the length of the difference
    vector).
    """
    from dpc_jax.data.sequence_cache import DISPARITY_UNITS, disparity_valid

    if a.shape != b.shape:
        raise ValueError(f"{kind}: shapes {a.shape} and {b.shape} differ")
    found: dict[str, float] = {}
    if kind == "flow":
        gap = np.linalg.norm(b.astype(np.float64) - a.astype(np.float64), axis=-1)
    elif kind == "disparity":
        valid_a, valid_b = disparity_valid(a), disparity_valid(b)
        found["validity"] = float(np.mean(valid_a != valid_b))
        gap = np.abs(b.astype(np.float64) - a.astype(np.float64))[valid_a & valid_b] / DISPARITY_UNITS
    elif kind == "images":
        gap = np.abs(b.astype(np.float64) - a.astype(np.float64))
    else:
        raise ValueError(f"unknown kind {kind!r}")
    return {"differ": float(np.mean(gap > 0)) if gap.size else 0.0,
            "max": float(gap.max(initial=0.0)), "mean": float(gap.mean()) if gap.size else 0.0, **found}


def as_cached(flow: np.ndarray) -> np.ndarray:
    """Flow ``[..., H, W, 2]`` (px) as a cache stores it and the network reads it: rounded to the int16
    units of its size (``dpc_jax.data.sequence_cache.flow_step``), in px again."""
    from dpc_jax.data.sequence_cache import decode_flow, encode_flow, flow_step

    step = flow_step(flow.shape[-3:-1])
    return decode_flow(encode_flow(flow, step), step)


def trajectory_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The largest distance (m) between the positions of two trajectories ``[N, 4, 4]`` and the largest
    angle (°) between their orientations, over all frames."""
    position = float(np.max(np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=-1)))
    # ‖R_a − R_b‖_F = 2√2 sin(θ/2): exact near θ = 0, where the trace's arccos is all rounding.
    chord = np.linalg.norm(a[:, :3, :3] - b[:, :3, :3], axis=(1, 2)) / (2 * np.sqrt(2))
    return position, float(np.degrees(2 * np.max(np.arcsin(np.clip(chord, 0.0, 1.0)))))


def _load(folder: Path) -> tuple[dict[str, Any], dict[str, np.ndarray], np.ndarray, np.ndarray]:
    from dpc_jax.data.poses_io import read_trajectory

    record_path = folder / MEASUREMENT
    if not record_path.is_file():
        raise ValueError(f"{folder}: no {MEASUREMENT} (not a finished measurement: run --out {folder} first)")
    record = json.loads(record_path.read_text(encoding="utf-8"))
    with np.load(folder / PRODUCTS) as products:
        arrays = {name: products[name] for name in products.files}
    return record, arrays, read_trajectory(folder / TRAJECTORY), np.load(folder / INLIERS)


def _change(a: float | None, b: float | None) -> str:
    if a is None or b is None:
        return number(None)
    return "identical" if a == b else number(b - a, "+.4g")


def compare_text(folders: Sequence[Path], loaded: Sequence[tuple[dict[str, Any], dict[str, np.ndarray],
                                                                  np.ndarray, np.ndarray]]) -> str:
    """The comparison's Markdown: B (the second folder) against A."""
    (record_a, arrays_a, poses_a, inliers_a), (record_b, arrays_b, poses_b, inliers_b) = loaded
    for key in ("drive", "frames", "shift_px"):
        if record_a[key] != record_b[key]:
            raise ValueError(f"{folders[1]}: {key} {record_b[key]} where {folders[0]} has {record_a[key]}")
    if sorted(arrays_a) != sorted(arrays_b):
        raise ValueError(f"{folders[1]}: products {sorted(arrays_b)} where {folders[0]} has "
                         f"{sorted(arrays_a)}")
    stamps = (record_a["stamp"], record_b["stamp"])
    versions = table(["", "folder", "libraries", "machine", "commit"],
                     ([label, f"`{folder}`", s["libraries"], s["machine"], s["commit"]]
                      for label, folder, s in zip("AB", folders, stamps, strict=True)))
    rows = []
    for key, title in METRICS:
        a, b = record_a["vo_metrics"][key], record_b["vo_metrics"][key]
        rows.append([title, number(a), number(b), _change(a, b)])
    for key, title in SUMMARY:
        a, b = record_a["vo_summary"][key], record_b["vo_summary"][key]
        rows.append([title, number(a), number(b), _change(a, b)])
    position, angle = trajectory_gap(poses_a, poses_b)
    differ = int(np.count_nonzero(inliers_a != inliers_b))
    vo = table(["our VO", "A", "B", "B − A"], rows)
    product_rows = []
    units = {"images": "grey levels", "disparity": "px", "flow": "px (length of the difference)"}
    for name in [name for kind in KINDS for name in arrays_a if name.split()[0] == kind]:
        kind, size = name.split()
        pairs = {kind: (arrays_a[name], arrays_b[name])}
        if kind == "flow":
            pairs["flow as cached"] = (as_cached(arrays_a[name]), as_cached(arrays_b[name]))
        for label, (a, b) in pairs.items():
            found = difference(a, b, kind)
            product_rows.append([label, size, f"{100 * found['differ']:.3g} %", number(found["max"]),
                                 number(found["mean"]), units[kind],
                                 f"{100 * found['validity']:.3g} %" if "validity" in found else ""])
    products = table(["product", "size", "pixels that differ", "max abs diff", "mean abs diff", "unit",
                      "matched in one only"], product_rows)
    frames = ", ".join(map(str, record_a["frames"]))
    return "\n".join([
        "# What the library versions change", "", versions,
        f"Our VO on {record_a['drive']} (started at the ground truth's first pose; metrics against its "
        "ground truth):", "", vo,
        f"The two trajectories are at most {position:.4g} m and {angle:.4g}° apart; the inlier count differs "
        f"on {differ} of {inliers_a.size} pairs.", "",
        f"Frames {frames} (flow: to the next frame) prepared at each size (the right image moved by "
        f"{record_a['shift_px']} px first). Images: the grey left and right images as prepared; disparity: "
        "StereoSGBM, both cameras, compared where both matched; flow: Farnebäck, left camera; flow as "
        "cached: rounded to the int16 units a cache stores (ss-DPC-Net's input).", "", products])


def compare(args: argparse.Namespace) -> int:
    try:
        kit.claim(None, [("--compare", folder) for folder in args.compare], script=__file__,
                  page=args.results_page)
        loaded = [_load(folder) for folder in args.compare]
        text = compare_text(args.compare, loaded)
    except (OSError, ValueError, KeyError) as error:
        return kit.refuse("library_versions", error)
    kit.publish(text, args.results_page, __file__)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return measure(args) if args.out is not None else compare(args)


if __name__ == "__main__":
    sys.exit(kit.interruptible(main, __file__))
