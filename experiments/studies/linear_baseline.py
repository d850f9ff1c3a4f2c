"""The supervised linear baseline on the real KITTI libviso2 trajectories, leave one sequence out.

For each of the eight sequences (KITTI odometry 00, 02, 05–10, ``../shared/data/kitti-libviso2``)
a correction linear in the prior's step (``dpc_jax.eval.linear_baseline``: a constant plus a gain
on each component of ``ξ_vo``, rotation only by default) is fit by least squares to the
ground-truth corrections of the *other seven* sequences and applied to the held-out one with the
network's composition ``T* = Exp(ξ_corr) · T_vo``. It is **supervised** (it reads ground truth to
fit) and needs no images. The table gives, per held-out sequence, libviso2's errors before → after
(segment errors, pyslam / ss-DPC-Net definition; m-ATE), beside the published rows of the papers
for the same sequences.

    python experiments/studies/linear_baseline.py                   # libviso2-s (stereo), rotation only
    python experiments/studies/linear_baseline.py --mono            # also libviso2-m, ss-DPC-Net rescaling
    python experiments/studies/linear_baseline.py --json out.json   # also the figures as JSON
    python experiments/studies/linear_baseline.py --demo runs/demo  # a finished `dpc-jax demo` folder instead

With ``--demo OUT`` the baseline is fit on the demo's training sequences (``OUT/data/poses``,
``OUT/vo``) and applied to its test sequence, rotation only and full 6-DoF, beside the demo's own
rows (``OUT/summary.json``: the prior, the network as trained and as adapted).

Prints the Markdown table and how many sequences' rotational segment error fell; exit status 0
when it fell on at least six of the eight stereo sequences, 1 otherwise, 2 for bad input.

The published rows and their sources: ``configs/linear_baseline.py``.
"""

from __future__ import annotations

import argparse
import json
import runpy
import sys
import time
from pathlib import Path

import numpy as np

from dpc_jax._io import atomic_write
from dpc_jax.experiments import script as kit
from dpc_jax.experiments.baselines import linear_baselines
from dpc_jax.experiments.script import interruptible
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.report.pages import write_results
from dpc_jax.report.tables import number, table
from dpc_jax.results.demo import SUMMARY, DemoSummary

CONFIG = runpy.run_path(str(Path(__file__).resolve().parent / "configs" / "linear_baseline.py"))
SEQUENCES, PUBLISHED = CONFIG["SEQUENCES"], CONFIG["PUBLISHED"]
KEYS = ("seg_trans_pct", "seg_rot_deg_per_100m", "m_ate_trans_m", "m_ate_rot_deg")
TITLES = ("seg. t (%)", "seg. r (°/100 m)", "m-ATE (m)", "m-ATE (°)")


def build_parser() -> argparse.ArgumentParser:
    parser = kit.new_parser(__doc__)
    kit.add_data_option(parser, "--data", "kitti-libviso2", metavar="DIR",
                        help="folder with stereo_XX.mat (and mono_XX.mat)")
    parser.add_argument("--mono", action="store_true", help="also libviso2-m (translation rescaled per step "
                        "to the ground-truth step length, the ss-DPC-Net protocol)")
    parser.add_argument("--translation", action="store_true",
                        help="fit and apply the translation part too (default: rotation only)")
    parser.add_argument("--json", type=path_argument, metavar="PATH", help="also write the figures as JSON")
    kit.add_results_page(parser)
    parser.add_argument("--demo", type=path_argument, metavar="OUT",
                        help="a finished `dpc-jax demo` folder: fit on its training sequences, test on its "
                        "test sequence")
    return parser


def demo_table(out: Path) -> str:
    """The linear baseline on a finished demo's test sequence, beside the demo's rows."""
    from dpc_jax.data.poses_io import read_kitti_poses

    summary = DemoSummary.read(out)
    # The demo names its training sequences train0, train1, … (dpc_jax.pipelines.synthetic_demo.DemoConfig).
    train = sorted(p.stem for p in (out / "data" / "poses").glob("train*.txt"))

    def pair(name: str) -> tuple[np.ndarray, np.ndarray]:
        return (read_kitti_poses(out / "data" / "poses" / f"{name}.txt"),
                read_kitti_poses(out / "vo" / f"{name}.txt"))

    fits = {"rotation": {"rotation_only": True}, "full": {"rotation_only": False}}
    figures = linear_baselines([pair(n) for n in train], *pair("test"), fits)
    rows = {"prior (our VO)": figures["prior"]}
    for fit, label in (("rotation", "rotation"), ("full", "full 6-DoF")):
        rows[f"linear, **supervised** ({label}; fit on {', '.join(train)})"] = figures[fit]
    supervision = summary.config.get("training", {}).get("supervision", "self")
    trained_by = "DPC-Net's supervised loss" if supervision == "supervised" else "the self-supervised loss"
    labels = (("trained", f"network trained with {trained_by}"),
              ("adapted", "the same, then adapted to the test sequence (self-supervised)"))
    for key, label in labels:
        if key in summary.test:
            rows[f"{label}; acceptance test: {summary.decisions.get(key, '')}"] = summary.test[key]
    return table(["test sequence", *TITLES],
                 ([label, *(number(v[k], ".3f") for k in KEYS)] for label, v in rows.items()))


def load(data: Path, kind: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{sequence: (ground truth, prior)}``; mono priors rescaled to the ground-truth step lengths."""
    from dpc_jax.data.poses_io import read_mat
    from dpc_jax.data.priors import rescale_monocular

    out = {}
    for name in SEQUENCES:
        gt, est = read_mat(data / f"{kind}_{name}.mat")
        out[name] = (gt, rescale_monocular(est, gt) if kind == "mono" else est)
    return out


def metrics(gt: np.ndarray, est: np.ndarray) -> dict[str, float]:
    """Segment errors (pyslam / ss-DPC-Net definition) and m-ATE of an estimate re-anchored on ``gt[0]``."""
    from dpc_jax.eval.metrics import m_ate, segment_errors

    est = gt[0] @ np.linalg.inv(est[0]) @ est
    seg = segment_errors(gt, est)
    trans, rot = m_ate(gt, est)
    values = (seg.trans_pct, seg.rot_deg_per_100m, trans, rot)
    return {key: float(v) for key, v in zip(KEYS, values, strict=True)}


def held_out_linear_metrics(
    sequences: dict[str, tuple[np.ndarray, np.ndarray]], rotation_only: bool
) -> dict[str, dict[str, dict[str, float]]]:
    """``{sequence: {"prior": metrics, "linear": metrics}}``; each corrected by a fit on the others."""
    from dpc_jax.eval.linear_baseline import apply_linear_correction, fit_from_steps, sequence_steps

    steps = {name: sequence_steps(gt, prior) for name, (gt, prior) in sequences.items()}
    results = {}
    for name, (gt, prior) in sequences.items():
        model = fit_from_steps([s for other, s in steps.items() if other != name], rotation_only)
        corrected = apply_linear_correction(model, prior)
        results[name] = {"prior": metrics(gt, prior), "linear": metrics(gt, corrected)}
    return results


def results_table(kind: str, results: dict[str, dict[str, dict[str, float]]], rotation_only: bool) -> str:
    """Per sequence: the prior, its leave-one-out linear correction and the published rows."""
    prior = "libviso2-s" if kind == "stereo" else "libviso2-m (rescaled)"
    fitted = "rotation" if rotation_only else "rotation and translation"
    rows = []
    for name, figures in results.items():
        before, after = figures["prior"], figures["linear"]
        rows.append([name, f"{prior} (this data)", *(f"{before[k]:.3f}" for k in KEYS)])
        rows.append([name, f"+ linear, **supervised**, leave-one-out ({fitted})",
                     *(f"{before[k]:.3f} → **{after[k]:.3f}**" for k in KEYS)])
        rows += [[name, f"{label[3:]} (published)", *(f"{v:g}" for v in values)]
                 for label, values in PUBLISHED[kind].items() if label.startswith(name + " ")]
    return table(["sequence", "estimator", *TITLES], rows)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        # No work folder: the figures go to --json and the results page only.
        kit.claim(None, [("--data", args.data), ("--demo", args.demo)], page=args.results_page,
                  files=[("--json", args.json)], script=__file__)
    except (OSError, ValueError) as error:
        return kit.refuse("linear_baseline", error)
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.demo is not None:
        if not (args.demo / SUMMARY).is_file():
            return kit.refuse("linear_baseline", f"{args.demo / SUMMARY} not found (give a finished "
                              "`dpc-jax demo --out` folder)")
        print(demo_table(args.demo))
        return 0
    kinds = ("stereo", "mono") if args.mono else ("stereo",)
    try:
        data = kit.data_given(args.data, "--data")
    except ValueError as error:
        return kit.refuse("linear_baseline", error)
    missing = [str(data / f"{k}_{s}.mat") for k in kinds for s in SEQUENCES
               if not (data / f"{k}_{s}.mat").is_file()]
    if missing:
        return kit.refuse("linear_baseline", f"{missing[0]} not found (need {{stereo,mono}}_XX.mat for XX "
                          f"in {' '.join(SEQUENCES)} under --data)")
    start, rotation_only = time.perf_counter(), not args.translation
    report: dict[str, object] = {"rotation_only": rotation_only}
    fell, sections = 0, []
    for kind in kinds:
        try:
            sequences = load(data, kind)
        except (ValueError, OSError) as error:
            return kit.refuse("linear_baseline", error)
        results = held_out_linear_metrics(sequences, rotation_only)
        report[kind] = results
        down = sum(r["linear"]["seg_rot_deg_per_100m"] < r["prior"]["seg_rot_deg_per_100m"]
                   for r in results.values())
        fell = down if kind == "stereo" else fell
        sections.append(f"## libviso2-{kind[0]}: supervised linear correction, leave one sequence out\n\n"
                        f"{results_table(kind, results, rotation_only)}\n"
                        f"Rotational segment error fell on {down} of {len(results)} sequences.\n")
        print(sections[-1])
    print(f"({time.perf_counter() - start:.0f} s)")
    if args.json is not None:
        atomic_write(args.json, json.dumps(report, indent=2) + "\n")
    if args.results_page is not None:
        write_results(args.results_page, "\n".join(sections), Path(__file__))
    return 0 if fell >= 6 else 1


if __name__ == "__main__":
    sys.exit(interruptible(main, __file__))
