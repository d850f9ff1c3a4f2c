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

Published rows: libviso2-s and ss-DPC-Net (self-supervised; "best loss" and "loop closure" epoch
selection) are the ss-DPC-Net authors' released results table
(github.com/utiasSTARS/ss-dpc-net, ``paper_plots_and_data/stereo_results_kitti.csv`` and
``mono_results_kitti.csv``); DPC-Net (supervised, Peretroukhin & Kelly 2018) is the row the same
release's ``generate_stereo_results.py`` lists for 00, 02 and 05. Zhang et al. (Stereo DPC,
Sensors 2021) are not included: their tables could not be read from the sources available here.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from dpc_jax._io import atomic_write
from dpc_jax.pipelines.protocol import claim_workdir, path_argument
from dpc_jax.report.pages import check_results_page, write_results
from dpc_jax.report.tables import table

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data" / "kitti-libviso2"
SEQUENCES = ("00", "02", "05", "06", "07", "08", "09", "10")

# (seg. t %, seg. r °/100 m, m-ATE m, m-ATE °) as published; see the module docstring for the sources.
PUBLISHED: dict[str, dict[str, tuple[float, float, float, float]]] = {
    "stereo": {
        "00 libviso2-s": (2.791, 1.292, 53.766, 13.301),
        "00 + DPC-Net (supervised)": (1.62, 0.559, 15.68, 3.07),
        "00 + ss-DPC-Net, best loss": (0.991, 0.457, 12.589, 2.469),
        "00 + ss-DPC-Net, loop closure": (1.033, 0.444, 14.654, 3.322),
        "02 libviso2-s": (2.417, 0.923, 68.604, 12.554),
        "02 + DPC-Net (supervised)": (1.16, 0.436, 17.69, 2.86),
        "02 + ss-DPC-Net, best loss": (1.108, 0.499, 15.687, 3.524),
        "02 + ss-DPC-Net, loop closure": (0.83, 0.373, 21.308, 1.907),
        "05 libviso2-s": (2.313, 1.135, 19.677, 6.298),
        "05 + DPC-Net (supervised)": (1.34, 0.562, 9.82, 3.57),
        "05 + ss-DPC-Net, best loss": (1.327, 0.597, 10.924, 4.097),
        "05 + ss-DPC-Net, loop closure": (0.829, 0.304, 4.034, 1.178),
    },
    "mono": {
        "09 libviso2-m": (8.666, 2.755, 81.345, 15.4),
        "09 + ss-DPC-Net, best loss": (2.824, 0.757, 16.369, 3.46),
        "09 + ss-DPC-Net, loop closure": (2.132, 0.803, 11.129, 3.887),
        "10 libviso2-m": (7.991, 3.317, 51.633, 16.454),
        "10 + ss-DPC-Net, best loss": (3.806, 1.343, 13.038, 3.367),
        "10 + ss-DPC-Net, loop closure": (3.479, 1.377, 11.947, 3.515),
    },
}
KEYS = ("seg_trans_pct", "seg_rot_deg_per_100m", "m_ate_trans_m", "m_ate_rot_deg")
TITLES = ("seg. t (%)", "seg. r (°/100 m)", "m-ATE (m)", "m-ATE (°)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=path_argument, default=DATA, metavar="DIR",
                        help="folder with stereo_XX.mat (and mono_XX.mat) (default: %(default)s)")
    parser.add_argument("--mono", action="store_true", help="also libviso2-m (translation rescaled per step "
                        "to the ground-truth step length, the ss-DPC-Net protocol)")
    parser.add_argument("--translation", action="store_true",
                        help="fit and apply the translation part too (default: rotation only)")
    parser.add_argument("--json", type=path_argument, metavar="PATH", help="also write the figures as JSON")
    parser.add_argument("--results-page", type=path_argument, metavar="FILE",
                        help="also write the table into the results block of FILE (a docs/results/ page)")
    parser.add_argument("--demo", type=path_argument, metavar="OUT",
                        help="a finished `dpc-jax demo` folder: fit on its training sequences, test on its "
                        "test sequence")
    return parser


def demo_table(out: Path) -> str:
    """The linear baseline on a finished demo's test sequence, beside the demo's rows."""
    from dpc_jax.data.poses_io import read_kitti_poses
    from dpc_jax.eval.linear_baseline import apply_linear_correction, fit_linear_correction

    summary = json.loads((out / "summary.json").read_text())
    # The demo names its training sequences train0, train1, … (dpc_jax.pipelines.synthetic_demo.DemoConfig).
    train = sorted(p.stem for p in (out / "data" / "poses").glob("train*.txt"))

    def pair(name: str) -> tuple[np.ndarray, np.ndarray]:
        poses = out / "data" / "poses" / f"{name}.txt"
        return read_kitti_poses(poses), read_kitti_poses(out / "vo" / f"{name}.txt")

    gt, prior = pair("test")
    rows = {"prior (our VO)": metrics(gt, prior)}
    for rotation_only, label in ((True, "rotation"), (False, "full 6-DoF")):
        model = fit_linear_correction([pair(n) for n in train], rotation_only=rotation_only)
        rows[f"linear, **supervised** ({label}; fit on {', '.join(train)})"] = metrics(
            gt, apply_linear_correction(model, prior)
        )
    supervision = summary["config"].get("training", {}).get("supervision", "self")
    trained_by = "DPC-Net's supervised loss" if supervision == "supervised" else "the self-supervised loss"
    labels = (("trained", f"network trained with {trained_by}"),
              ("adapted", "the same, then adapted to the test sequence (self-supervised)"))
    for key, label in labels:
        if key in summary["test"]:
            decision = summary["decisions"].get(key, "")
            rows[f"{label}; acceptance test: {decision}"] = {
                k: summary["test"][key][k] for k in KEYS
            }
    return table(["test sequence", *TITLES],
                 ([label, *(f"{v[k]:.3f}" for k in KEYS)] for label, v in rows.items()))


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
        check_results_page(args.results_page)
        # No work folder: the figures go to --json and the results page only.
        claim_workdir(None, [("--data", args.data), ("--demo", args.demo)],
                      files=[("--json", args.json), ("--results-page", args.results_page)])
    except (OSError, ValueError) as error:
        print(f"linear_baseline: error: {error}", file=sys.stderr)
        return 2
    if args.demo is not None:
        if not (args.demo / "summary.json").is_file():
            print(f"linear_baseline: error: {args.demo / 'summary.json'} not found (give a finished "
                  "`dpc-jax demo --out` folder)", file=sys.stderr)
            return 2
        import jax

        jax.config.update("jax_enable_x64", True)
        print(demo_table(args.demo))
        return 0
    kinds = ("stereo", "mono") if args.mono else ("stereo",)
    missing = [str(args.data / f"{k}_{s}.mat") for k in kinds for s in SEQUENCES
               if not (args.data / f"{k}_{s}.mat").is_file()]
    if missing:
        print(f"linear_baseline: error: {missing[0]} not found (need {{stereo,mono}}_XX.mat for XX in "
              f"{' '.join(SEQUENCES)} under --data)", file=sys.stderr)
        return 2
    import jax

    jax.config.update("jax_enable_x64", True)
    start = time.perf_counter()
    rotation_only = not args.translation
    report: dict[str, object] = {"rotation_only": rotation_only}
    fell = 0
    sections = []
    for kind in kinds:
        try:
            sequences = load(args.data, kind)
        except (ValueError, OSError) as error:
            print(f"linear_baseline: error: {error}", file=sys.stderr)
            return 2
        results = held_out_linear_metrics(sequences, rotation_only)
        report[kind] = results
        down = sum(
            r["linear"]["seg_rot_deg_per_100m"] < r["prior"]["seg_rot_deg_per_100m"] for r in results.values()
        )
        if kind == "stereo":
            fell = down
        sections.append(f"## libviso2-{kind[0]}: supervised linear correction, leave one sequence out\n\n"
                        f"{results_table(kind, results, rotation_only)}\n"
                        f"Rotational segment error fell on {down} of {len(results)} sequences.\n")
        print(sections[-1])
    seconds = time.perf_counter() - start
    print(f"({seconds:.0f} s)")
    if args.json is not None:
        atomic_write(args.json, json.dumps(report, indent=2) + "\n")
    if args.results_page is not None:
        write_results(args.results_page, "\n".join(sections), Path(__file__))
    return 0 if fell >= 6 else 1


if __name__ == "__main__":
    sys.exit(main())
