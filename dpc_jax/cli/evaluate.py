"""``dpc-jax evaluate``: metrics of estimated trajectories against ground truth, reports and exports.

Everything is read, checked and computed before anything is written; bad input ends with a
message on stderr and exit status 2, before JAX is imported, and no file is written. The outputs
(``--json``, ``--report``, ``--export``) are written all or nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import is_stdout, output_problem, overlap_problem
from dpc_jax.cli._common import Formatter, import_jax, input_problem, path_option, path_text

if TYPE_CHECKING:
    import numpy as np

HELP = "Evaluate trajectories against ground truth (m-ATE, segment errors, ATE, RPE, loop closures)."
# No huge-page restart (dpc_jax.runtime.hugepages): it would not make the metrics faster, only add a start.
HUGE_PAGES = False

EPILOG = """examples:
  dpc-jax evaluate --mat stereo_00.mat --remove-static --json -
  dpc-jax evaluate --gt 00.txt --est prior.txt --est corrected.txt --label prior --label corrected \\
      --align se3 --report out/report --export out/trajectories
Formats by extension (.mat, .tum) or column count (12 KITTI, 8 TUM), or --format. A .mat given to --gt
is read for its poses_gt, given to --est for its poses_est (--mat reads both). Estimates are paired with
the ground truth pose by pose, in order."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--gt", type=path_option, metavar="FILE",
                        help="ground-truth trajectory (.mat: its poses_gt)")
    source.add_argument(
        "--mat", type=path_option, metavar="FILE",
        help="ss-DPC-Net .mat holding poses_gt and poses_est (label 'est')",
    )
    parser.add_argument(
        "--est", type=path_option, action="append", default=[], metavar="FILE",
        help="estimated trajectory (repeatable; with --gt; .mat: its poses_est)",
    )
    parser.add_argument(
        "--label", action="append", default=[], metavar="NAME",
        help="label of each --est, in order (default: the file name without extension)",
    )
    parser.add_argument(
        "--format", choices=("kitti", "tum", "mat"), default=None,
        help="format of --gt/--est files (default: from the extension or the column count)",
    )
    parser.add_argument(
        "--remove-static", action="store_true",
        help="drop static frames with the ss-DPC-Net rule read on the (first) estimate; the estimate "
        "is re-composed from its relative poses between kept frames",
    )
    parser.add_argument("--align", choices=("none", "se3", "sim3"), default="none",
                        help="alignment for ATE (the other metrics and the plots are not aligned)")
    parser.add_argument("--rpe-delta", type=int, default=1, metavar="N", help="frame offset of RPE")
    parser.add_argument(
        "--diagnose", action="store_true",
        help="also print what each estimate's error is made of: per-step mean (systematic) and spread "
        "(random) per axis, the share of the end-point drift the mean alone explains",
    )
    parser.add_argument(
        "--focal", type=float, default=None, metavar="PX",
        help="with --diagnose: focal length (px) for the mean rotation's image shift per step",
    )
    parser.add_argument("--json", type=path_text, metavar="PATH",
                        help="write the metrics as JSON to PATH ('-': stdout; there, as to /dev/stdout, "
                        "instead of the table)")
    parser.add_argument(
        "--report", type=path_option, metavar="DIR", help="write report.md, CSV tables and PNG plots"
    )
    parser.add_argument(
        "--export", type=path_option, metavar="DIR", help="write every trajectory as KITTI and TUM text (evo)"
    )


def _error(message: str) -> int:
    print(f"dpc-jax evaluate: error: {message}", file=sys.stderr)
    return 2


def _inputs(args: argparse.Namespace) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read ground truth and estimates -> ``(gt, {label: estimate})``; raises ValueError/OSError."""
    from dpc_jax.data.poses_io import read_mat, read_trajectory
    from dpc_jax.eval.evaluation import check_label

    if args.mat is not None:
        if args.est or args.label:
            raise ValueError("--mat holds the estimate; do not combine it with --est or --label")
        gt, est = read_mat(args.mat)
        return gt, {"est": est}
    if not args.est:
        raise ValueError("--gt needs at least one --est FILE")
    if args.label and len(args.label) != len(args.est):
        raise ValueError(f"{len(args.label)} --label for {len(args.est)} --est; give one label per estimate")
    labels = args.label or [Path(p).name.split(".")[0] for p in args.est]
    for label, path in zip(labels, args.est, strict=True):
        try:
            check_label(label)
        except ValueError as error:
            if args.label:
                raise
            # The label came from the file name, which the user did not choose as a label.
            raise ValueError(f"--est {path}: {error}; the label comes from the file name, so give "
                             "one with --label NAME (one --label per --est)") from None
    if len(set(labels)) != len(labels):
        raise ValueError(f"estimate labels must be unique, got {labels}; use --label")
    gt = read_trajectory(args.gt, args.format, mat_key="poses_gt")
    estimates: dict[str, np.ndarray] = {}
    for label, path in zip(labels, args.est, strict=True):
        est = read_trajectory(path, args.format)
        if est.shape[0] != gt.shape[0]:
            raise ValueError(
                f"{path} has {est.shape[0]} poses but the ground truth {args.gt} has {gt.shape[0]}"
            )
        estimates[label] = est
    return gt, estimates


def run(args: argparse.Namespace) -> int:
    problem = (
        input_problem(args.mat, "--mat") or input_problem(args.gt, "--gt")
        or next(filter(None, (input_problem(path, "--est") for path in args.est)), None)
        or output_problem(None if args.json == "-" else args.json, "--json")
        or output_problem(args.report, "--report", folder=True)
        or output_problem(args.export, "--export", folder=True)
        or overlap_problem([("--mat", args.mat), ("--gt", args.gt), *(("--est", path) for path in args.est)],
                           [("--json", None if args.json == "-" else args.json), ("--report", args.report),
                            ("--export", args.export)])
    )
    if problem is not None:
        return _error(problem)
    try:
        gt, estimates = _inputs(args)
        if args.focal is not None and not (args.focal > 0 and args.focal < float("inf")):
            raise ValueError(f"--focal must be a positive focal length in pixels, got {args.focal}")
        if args.focal is not None and not args.diagnose:
            raise ValueError("--focal is used only with --diagnose")
        if gt.shape[0] < 2:
            source = args.mat if args.mat is not None else args.gt
            raise ValueError(f"{source}: holds {gt.shape[0]} pose; a trajectory to evaluate needs at least 2")
        if not 1 <= args.rpe_delta < gt.shape[0]:
            # Checked here too (evaluate checks it after static-frame removal) so that the mistake
            # is reported before JAX is imported.
            raise ValueError(f"--rpe-delta must be in [1, {gt.shape[0] - 1}] for {gt.shape[0]} poses, "
                             f"got {args.rpe_delta}")
        import_jax()
        from dpc_jax._io import OutputSet, atomic_write
        from dpc_jax.eval.evaluation import evaluate
        from dpc_jax.report.evaluation_report import export_trajectories, format_table, write_report

        result = evaluate(gt, estimates, remove_static=args.remove_static, align=args.align,
                          rpe_delta=args.rpe_delta, diagnose=args.diagnose, focal_px=args.focal)
    except (ValueError, OSError) as error:
        return _error(str(error))

    with OutputSet() as outputs:
        if args.json not in (None, "-"):
            atomic_write(outputs.file(args.json), result.to_json())
        if args.report is not None:
            source = args.mat if args.mat is not None else args.gt
            write_report(outputs.folder(args.report), result, title=f"Trajectory evaluation: {source.name}")
        if args.export is not None:
            export_trajectories(outputs.folder(args.export), result)
        outputs.commit()
    if args.json == "-":
        sys.stdout.write(result.to_json())
    elif args.json is None or not is_stdout(args.json):
        # The table would follow the JSON that --json /dev/stdout streamed there, which no JSON
        # reader then accepts.
        sys.stdout.write(format_table(result))
        if result.diagnoses:
            from dpc_jax.report.evaluation_report import format_diagnosis

            sys.stdout.write("\n" + format_diagnosis(result.diagnoses))
    return 0
