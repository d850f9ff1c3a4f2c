"""How far the real excerpt's ground truth can judge a correction: its steps checked against the images.

The KITTI raw excerpt (2011_09_26_drive_0001) carries poses from the car's GPS/IMU, moved into the camera
frame by the calibration; ``experiments/protocols/kitti_raw_excerpt.py`` judges corrections against them.
This study asks the images, with no network involved, whether those poses are accurate at the scale of
the corrections being judged:

1. **Per-step photometric check.** Each pair (i, i+1) is warped at full resolution (1242×375, grey) with
   OpenCV StereoSGBM depth of frame i, metric through the baseline, by the ground-truth step, our VO's and
   libviso2-s's, and hybrids that exchange rotation and translation, or only the direction of travel:
   the mean L1 error over the textured pixels (grey gradient ≥ 0.05, depth ≤ 40 m) every candidate keeps
   in view, and the share of pairs on which a candidate beats our VO's step. The depth depends on the
   colour pair's disparity offset (a calibration residual), and so does the verdict: the check runs at 0,
   ½, 1 and 1.5 times the offset our VO measures (no ground truth); the lowest errors mark the depth the
   images support best.
2. **Step lengths.** RMS difference of the step lengths: ground truth vs each VO, and VO vs VO.
3. **Direction of travel.** Mean elevation (upward angle) of each trajectory's steps in the camera frame.
4. **A perfect rotation-only correction.** A prior's translations with the ground truth's rotations: the
   best any rotation-only correction (as the excerpt applies) could do; its segment errors and m-ATE.

Writes ``WORKDIR/ground_truth_check.md`` and ``.csv``; our VO's prior is computed into (or reused from)
``WORKDIR/priors/vo.txt``, as ``kitti_raw_excerpt.py`` does. A few minutes on a 2-core CPU.

    python experiments/studies/excerpt_ground_truth.py --workdir runs/kitti_raw_excerpt
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from dpc_jax.experiments import script as kit
from dpc_jax.experiments.script import interruptible
from dpc_jax.experiments.steps import exchange, photometric_errors, step_geometry, with_travel
from dpc_jax.pipelines.protocol import path_argument

DATE, DRIVE = "2011_09_26", "0001"
LIBVISO2 = "libviso2/stereo_2011_09_26_drive_0001.mat"
OFFSET_FACTORS = (0.0, 0.5, 1.0, 1.5)  # times the disparity offset our VO measures

def build_parser() -> argparse.ArgumentParser:
    parser = kit.new_parser(__doc__)
    parser.add_argument("--workdir", type=path_argument, required=True,
                        help="output folder (priors/vo.txt is reused: kitti_raw_excerpt.py's work folder)")
    kit.add_kitti_raw_option(parser)
    kit.add_no_progress(parser)
    kit.add_results_page(parser)
    return parser


def candidates(steps: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The candidate steps ``[pairs, 4, 4]`` of section 1 (our VO's first: the others are held against it)."""
    length = step_geometry(steps["our VO"])[0]
    _, gt_elevation, gt_lateral = step_geometry(steps["ground truth"])
    return {
        "our VO": steps["our VO"], "libviso2-s": steps["libviso2-s"], "ground truth": steps["ground truth"],
        "ground-truth rotation, our VO's travel": exchange(steps["ground truth"], steps["our VO"]),
        "our VO's rotation, ground-truth travel": exchange(steps["our VO"], steps["ground truth"]),
        # The step lengths (whose scatter barely moves the positions) from our VO, the direction
        # (which m-ATE accumulates) from the ground truth.
        "our VO's rotation and step lengths, ground-truth direction": with_travel(
            steps["our VO"], length, gt_elevation, gt_lateral),
    }


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from dpc_jax._io import atomic_write
    from dpc_jax.data.kitti import open_raw
    from dpc_jax.data.poses_io import read_mat, read_trajectory
    from dpc_jax.eval.evaluation import evaluate
    from dpc_jax.geometry.poses import compose, relative_poses
    from dpc_jax.pipelines.protocol import vo_prior
    from dpc_jax.report.tables import records_csv, table

    progress = kit.progress_flag(args.no_progress)
    try:
        raw = kit.data_given(args.kitti_raw, "--kitti-raw")
        sequence = open_raw(raw, DATE, DRIVE, poses=raw / LIBVISO2)
        gt, libviso2 = read_mat(raw / LIBVISO2)
        kit.claim(args.workdir, [("--kitti-raw", raw)], script=__file__, page=args.results_page)
        record = vo_prior(sequence, args.workdir / "priors" / "vo.txt", progress)
        vo = read_trajectory(record["path"])
    except (OSError, ValueError, KeyError) as error:
        return kit.refuse("excerpt_ground_truth", error)
    trajectories = {"ground truth": gt, "our VO": vo, "libviso2-s": libviso2}
    steps = {name: relative_poses(poses) for name, poses in trajectories.items()}
    geometry = {name: step_geometry(rel) for name, rel in steps.items()}

    # 1: every candidate step, warped in one batch per pair and depth.
    named = candidates(steps)
    measured = float(record["disparity_offset_median_px"])
    offsets = [factor * measured for factor in OFFSET_FACTORS]
    photometric = photometric_errors(sequence, np.stack(list(named.values())), offsets, progress)
    best = int(np.argmin(photometric.mean(axis=(0, 2))))
    rows: list[dict[str, Any]] = []
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
    # 2 and 3: the step lengths and the direction of travel.
    pairs = (("ground truth", "our VO"), ("ground truth", "libviso2-s"), ("our VO", "libviso2-s"))
    rms = {f"{a} vs {b}": float(np.sqrt(np.mean((geometry[a][0] - geometry[b][0]) ** 2))) for a, b in pairs}
    elevation = {name: 1e3 * float(np.mean(g[1])) for name, g in geometry.items()}
    rows += [{"section": "step_length_rms_m", "item": k, "value": v, "extra": ""} for k, v in rms.items()]
    rows += [{"section": "elevation_mrad", "item": k, "value": v, "extra": ""} for k, v in elevation.items()]
    # 4: the prior's translations with the ground truth's rotations.
    perfect_rows = []
    keys = ("seg_trans_pct", "seg_rot_deg_per_100m", "m_ate_trans_m", "m_ate_rot_deg")
    for name in ("our VO", "libviso2-s"):
        perfect = compose(exchange(steps["ground truth"], steps[name]), gt[0])
        scores = evaluate(gt, {"prior": trajectories[name], "perfect": perfect}).estimates
        for label, key_ in (("prior", "prior"), ("perfect rotation-only correction", "perfect")):
            m = {key: scores[key_][key] for key in keys}
            perfect_rows.append([name, label, *(f"{m[key]:.4g}" for key in keys)])
            rows += [{"section": f"rotation_only/{label}", "item": f"{name} {key}", "value": value,
                      "extra": ""} for key, value in m.items()]
    offset_titles = [f"offset {o:+.2f} px{' *' if k == best else ''}" for k, o in enumerate(offsets)]
    text = "\n".join([
        "# Does the excerpt's ground truth agree with its images?", "",
        f"KITTI raw {sequence.name}, {len(sequence)} frames, {len(sequence) - 1} steps; written by "
        "`python experiments/studies/excerpt_ground_truth.py` (see its docstring for the method).", "",
        "## 1. Each step checked against the images (full resolution, StereoSGBM depth)", "",
        "Mean L1 error (grey, 0–1) of each candidate step, and in brackets the share of pairs on which it "
        "beats our VO's step, for each disparity offset added to SGBM's disparities (our VO measures "
        f"{measured:+.3f} px; the candidates' mean error is lowest, marked *, at {offsets[best]:+.3f} px).",
        "", *table(["step", *offset_titles], photometric_rows).splitlines(),
        "", "## 2. Step lengths", "",
        *table(["pair of trajectories", "RMS step-length difference (m)"],
               ([k, f"{v:.4f}"] for k, v in rms.items())).splitlines(),
        "", f"Mean step length: {geometry['ground truth'][0].mean():.3f} m (ground truth).", "",
        "## 3. Direction of travel (elevation, mrad, upward positive)", "",
        *table(["source", "mean elevation (mrad)"],
               ([k, f"{v:+.2f}"] for k, v in elevation.items())).splitlines(),
        "", "## 4. A perfect rotation-only correction (ground-truth rotations, the prior's travel)", "",
        table(["prior", "trajectory", "seg. t (%)", "seg. r (°/100 m)", "m-ATE (m)", "m-ATE (°)"],
              perfect_rows)])
    atomic_write(args.workdir / "ground_truth_check.csv", records_csv(rows))
    atomic_write(args.workdir / "ground_truth_check.md", text)
    kit.publish(text, args.results_page, __file__)
    return 0


if __name__ == "__main__":
    sys.exit(interruptible(main, __file__))
