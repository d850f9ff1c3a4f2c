"""How far the real excerpt's ground truth can judge a correction: its steps checked against the images.

The KITTI raw excerpt (2011_09_26_drive_0001) carries poses from the car's GPS/IMU, moved into the
camera frame by the calibration. ``experiments/protocols/kitti_raw_excerpt.py`` judges corrections against
them. This experiment asks the images, with no network involved, whether those poses are accurate
at the scale of the corrections being judged:

1. **Per-step photometric check.** Each pair (i, i+1) is warped at full resolution (1242×375, grey)
   with OpenCV StereoSGBM depth of frame i, metric through the baseline. It is warped with the
   ground-truth step, with our VO's and libviso2-s's steps, and with hybrids that exchange rotation
   and translation, or only the direction of travel. The mean L1 error is taken over the textured
   pixels (grey gradient ≥ 0.05, depth ≤ 40 m) that every candidate keeps in view. The table gives
   each candidate's mean error, and the share of pairs on which it beats our VO's step.
   The depth depends on the colour pair's disparity offset (a calibration residual), and so does
   the verdict: the check runs at 0, ½, 1 and 1.5 times the offset our VO measures (no ground
   truth), and the offset whose errors are lowest is the depth the images support best.
2. **Step lengths.** RMS difference of the step lengths: ground truth vs each VO, and VO vs VO.
3. **Direction of travel.** Mean elevation (upward angle) of each trajectory's step direction in
   the camera frame.
4. **A perfect rotation-only correction.** The trajectory that keeps a prior's translations and
   takes its rotations from the ground truth. This is the best any rotation-only correction
   (``rotation_only``, as the excerpt applies it) could produce. Its segment errors and m-ATE sit
   beside the prior's.

Writes ``WORKDIR/ground_truth_check.md`` and ``.csv``; our VO's prior is computed into (or reused
from) ``WORKDIR/priors/vo.txt``, as ``kitti_raw_excerpt.py`` does. A few minutes on a 2-core
CPU.

    python experiments/studies/excerpt_ground_truth.py --workdir runs/kitti_raw_excerpt
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.pipelines.protocol import path_argument

HERE = Path(__file__).resolve().parent
DEFAULT_ROOT = HERE.parents[2] / "shared" / "data" / "kitti-raw"
DATE, DRIVE = "2011_09_26", "0001"
LIBVISO2 = "libviso2/stereo_2011_09_26_drive_0001.mat"

MAX_DEPTH_M = 40.0  # farther pixels move by well under a pixel per step: they cannot tell poses apart
MIN_GRADIENT = 0.05  # grey levels per pixel (Sobel / 8): textureless pixels cannot either
OFFSET_FACTORS = (0.0, 0.5, 1.0, 1.5)  # times the disparity offset our VO measures


def step_geometry(relative: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Travel of each step ``T_{t+1,t}`` ``[N, 4, 4]`` in frame t: ``(length m, elevation rad, lateral rad)``.

    The camera looks along +z with y down; elevation is the upward angle of the travel direction,
    lateral its angle towards +x.
    """
    travel = -np.einsum("nji,nj->ni", relative[:, :3, :3], relative[:, :3, 3])
    length = np.linalg.norm(travel, axis=1)
    elevation = np.arctan2(-travel[:, 1], np.hypot(travel[:, 0], travel[:, 2]))
    lateral = np.arctan2(travel[:, 0], travel[:, 2])
    return length, elevation, lateral


def with_travel(rotation_from: np.ndarray, length: np.ndarray, elevation: np.ndarray,
                lateral: np.ndarray) -> np.ndarray:
    """Steps ``[N, 4, 4]`` with the rotations of ``rotation_from`` and the given travel in frame t."""
    direction = np.stack([np.cos(elevation) * np.sin(lateral), -np.sin(elevation),
                          np.cos(elevation) * np.cos(lateral)], axis=1)
    out = rotation_from.copy()
    out[:, :3, 3] = -np.einsum("nij,nj->ni", rotation_from[:, :3, :3], length[:, None] * direction)
    return out


def exchange(rotation_from: np.ndarray, translation_from: np.ndarray) -> np.ndarray:
    """Steps with the rotations of one set and the travel (in frame t) of the other."""
    return with_travel(rotation_from, *step_geometry(translation_from))


def photometric_errors(sequence: Any, candidates: np.ndarray, offsets_px: Sequence[float],
                       progress: bool) -> np.ndarray:
    """Mean L1 grey error ``[pairs, offsets, C]`` of each candidate step ``[C, pairs, 4, 4]`` with
    the depth of each disparity offset (px, added to SGBM's disparities; see the module doc)."""
    import cv2
    import jax
    import jax.numpy as jnp

    from dpc_jax.data.kitti import load_image
    from dpc_jax.data.stereo_depth import sgbm_inverse_depth
    from dpc_jax.geometry.warp import inverse_warp

    K = jnp.asarray(sequence.K, jnp.float32)
    fb = float(sequence.K[0, 0] * sequence.baseline)

    @jax.jit
    def errors(source: jax.Array, target: jax.Array, depth: jax.Array, keep: jax.Array,
               steps: jax.Array) -> jax.Array:
        # Rebuild frame t from frame t+1 with frame t's depth: T_source_target = T_{t+1,t}.
        rebuilt, valid = inverse_warp(source[..., None], depth, steps, K)
        common = keep & jnp.all(valid, axis=0)
        residual = jnp.abs(rebuilt[..., 0] - target)
        return jnp.sum(residual * common, axis=(1, 2)) / jnp.maximum(jnp.sum(common), 1)

    def grey(k: int) -> np.ndarray:
        return load_image(sequence.left_paths[k], grey=True).astype(np.float32) / 255

    pairs = candidates.shape[1]
    out = np.zeros((pairs, len(offsets_px), candidates.shape[0]))
    source = grey(0)
    for i in range(pairs):
        inv_depth, valid, _, _ = sgbm_inverse_depth(load_image(sequence.left_paths[i]),
                                                    load_image(sequence.right_paths[i]),
                                                    sequence.K[0, 0], sequence.baseline)
        target, source = source, grey(i + 1)  # each frame is decoded once as grey
        gradient = np.hypot(cv2.Sobel(target, cv2.CV_32F, 1, 0), cv2.Sobel(target, cv2.CV_32F, 0, 1)) / 8
        steps = jnp.asarray(candidates[:, i], jnp.float32)
        for k, offset in enumerate(offsets_px):
            shifted = np.where(valid, inv_depth + offset / fb, 0.0)
            keep = valid & (shifted >= 1 / MAX_DEPTH_M) & (gradient >= MIN_GRADIENT)
            depth = np.where(keep, 1 / np.maximum(shifted, 1e-6), 1.0).astype(np.float32)
            out[i, k] = np.asarray(errors(source, target, depth, keep, steps))
        if progress:
            print(f"\rpair {i + 1}/{pairs}", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", type=path_argument, required=True,
                        help="output folder (priors/vo.txt is reused: kitti_raw_excerpt.py's work folder)")
    parser.add_argument("--kitti-raw", type=path_argument, default=DEFAULT_ROOT, metavar="ROOT",
                        help="raw root holding DATE/ and libviso2/")
    parser.add_argument("--no-progress", action="store_true", help="no progress line on stderr")
    parser.add_argument("--results-page", type=path_argument, metavar="FILE",
                        help="also write the table into the results block of FILE (a docs/results/ page)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from dpc_jax._io import atomic_write
    from dpc_jax.report.pages import check_results_page, write_results
    from dpc_jax.report.tables import records_csv, table

    try:
        check_results_page(args.results_page)
    except (OSError, ValueError) as error:
        print(f"excerpt_ground_truth: error: {error}", file=sys.stderr)
        return 2

    progress = not args.no_progress and sys.stderr.isatty()
    try:
        from dpc_jax.data.kitti import open_raw
        from dpc_jax.data.poses_io import read_mat, read_trajectory
        from dpc_jax.eval.evaluation import evaluate
        from dpc_jax.geometry.poses import compose, relative_poses
        from dpc_jax.pipelines import protocol as P

        sequence = open_raw(args.kitti_raw, DATE, DRIVE, poses=args.kitti_raw / LIBVISO2)
        gt, libviso2 = read_mat(args.kitti_raw / LIBVISO2)
        P.claim_workdir(args.workdir, [("--kitti-raw", args.kitti_raw)],
                        files=[("--results-page", args.results_page)])
        record = P.vo_prior(sequence, args.workdir / "priors" / "vo.txt", progress)
        vo = read_trajectory(record["path"])
    except (OSError, ValueError, KeyError) as error:
        print(f"excerpt_ground_truth: error: {error}", file=sys.stderr)
        return 2
    steps = {"ground truth": relative_poses(gt), "our VO": relative_poses(vo),
             "libviso2-s": relative_poses(libviso2)}
    length, elevation, lateral = {}, {}, {}
    for name, rel in steps.items():
        length[name], elevation[name], lateral[name] = step_geometry(rel)

    # 1: every candidate step, warped in one batch per pair and depth.
    named = {
        "our VO": steps["our VO"],
        "libviso2-s": steps["libviso2-s"],
        "ground truth": steps["ground truth"],
        "ground-truth rotation, our VO's travel": exchange(steps["ground truth"], steps["our VO"]),
        "our VO's rotation, ground-truth travel": exchange(steps["our VO"], steps["ground truth"]),
        # The step lengths (whose scatter barely moves the positions) from our VO, the direction
        # (which m-ATE accumulates) from the ground truth.
        "our VO's rotation and step lengths, ground-truth direction": with_travel(
            steps["our VO"], length["our VO"], elevation["ground truth"], lateral["ground truth"]),
    }
    measured = float(record["disparity_offset_median_px"])
    offsets = [factor * measured for factor in OFFSET_FACTORS]
    photometric = photometric_errors(sequence, np.stack(list(named.values())), offsets, progress)
    best = int(np.argmin(photometric.mean(axis=(0, 2))))

    rows: list[dict[str, Any]] = []
    lines = ["# Does the excerpt's ground truth agree with its images?", "",
             f"KITTI raw {sequence.name}, {len(sequence)} frames, {len(sequence) - 1} steps; "
             "written by `python experiments/studies/excerpt_ground_truth.py` (see its docstring for the "
             "method).",
             "", "## 1. Each step checked against the images (full resolution, StereoSGBM depth)", "",
             "Mean L1 error (grey, 0–1) of each candidate step, and in brackets the share of pairs on "
             "which it beats our VO's step, for each disparity offset added to SGBM's disparities "
             f"(our VO measures {measured:+.3f} px; the candidates' mean error is lowest, marked *, at "
             f"{offsets[best]:+.3f} px).", ""]
    photometric_rows = []
    for c, name in enumerate(named):
        cells = []
        for k, offset in enumerate(offsets):
            errors = photometric[:, k, c]
            better = float(np.mean(errors < photometric[:, k, 0]))
            cells.append(f"{errors.mean():.5f}" + ("" if c == 0 else f" ({100 * better:.0f} %)"))
            rows.append({"section": f"photometric/offset {offset:+.3f} px", "item": name,
                         "value": errors.mean(), "extra": better})
        photometric_rows.append([name, *cells])
    offset_titles = [f"offset {o:+.2f} px{' *' if k == best else ''}" for k, o in enumerate(offsets)]
    lines += table(["step", *offset_titles], photometric_rows).splitlines()
    lengths_rows = []
    for a, b in (("ground truth", "our VO"), ("ground truth", "libviso2-s"), ("our VO", "libviso2-s")):
        rms = float(np.sqrt(np.mean((length[a] - length[b]) ** 2)))
        lengths_rows.append([f"{a} vs {b}", f"{rms:.4f}"])
        rows.append({"section": "step_length_rms_m", "item": f"{a} vs {b}", "value": rms, "extra": ""})
    lines += ["", "## 2. Step lengths", "",
              *table(["pair of trajectories", "RMS step-length difference (m)"], lengths_rows).splitlines()]
    elevation_rows = []
    for name in steps:
        value = 1e3 * float(np.mean(elevation[name]))
        elevation_rows.append([name, f"{value:+.2f}"])
        rows.append({"section": "elevation_mrad", "item": name, "value": value, "extra": ""})
    lines += ["", f"Mean step length: {length['ground truth'].mean():.3f} m (ground truth).", "",
              "## 3. Direction of travel (elevation, mrad, upward positive)", "",
              *table(["source", "mean elevation (mrad)"], elevation_rows).splitlines()]
    perfect_rows = []
    keys = ("seg_trans_pct", "seg_rot_deg_per_100m", "m_ate_trans_m", "m_ate_rot_deg")
    for name, poses in (("our VO", vo), ("libviso2-s", libviso2)):
        perfect = compose(exchange(steps["ground truth"], steps[name]), gt[0])
        scores = evaluate(gt, {"prior": poses, "perfect": perfect})["estimates"]
        for label, key_ in (("prior", "prior"), ("perfect rotation-only correction", "perfect")):
            m = {key: scores[key_][key] for key in keys}
            perfect_rows.append([name, label, *(f"{m[key]:.4g}" for key in keys)])
            rows += [{"section": f"rotation_only/{label}", "item": f"{name} {key}", "value": value,
                      "extra": ""} for key, value in m.items()]
    lines += ["", "## 4. A perfect rotation-only correction (ground-truth rotations, the prior's travel)", "",
              table(["prior", "trajectory", "seg. t (%)", "seg. r (°/100 m)", "m-ATE (m)", "m-ATE (°)"],
                    perfect_rows)]
    text = "\n".join(lines)
    args.workdir.mkdir(parents=True, exist_ok=True)
    atomic_write(args.workdir / "ground_truth_check.csv", records_csv(rows))
    atomic_write(args.workdir / "ground_truth_check.md", text)
    print(text, end="")
    if args.results_page is not None:
        write_results(args.results_page, text, Path(__file__))
    return 0


if __name__ == "__main__":
    sys.exit(main())
