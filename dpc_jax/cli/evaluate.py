"""``dpc-jax evaluate``: metrics of estimated trajectories against ground truth, reports and exports.

Everything is read, checked and computed before anything is written; bad input ends with a
message on stderr and exit status 2, before JAX is imported, and no file is written. The outputs
(``--json``, ``--report``, ``--export``) are written all or nothing.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import (
    InputWarning,
    foreign_files_problem,
    is_stdout,
    output_problem,
    overlap_problem,
    stdout_problem,
)
from dpc_jax.cli._common import Formatter, file_path_text, import_jax, input_problem, path_option
from dpc_jax.data.poses_io import FORMATS

if TYPE_CHECKING:
    import numpy as np

    from dpc_jax.eval.evaluation import Association

HELP = "Evaluate trajectories against ground truth (m-ATE, segment errors, ATE, RPE, loop closures)."
# No huge-page restart (dpc_jax.runtime.hugepages): it would not make the metrics faster, only add a start.
HUGE_PAGES = False

EPILOG = """examples:
  dpc-jax evaluate --mat stereo_00.mat --remove-static --json -
  dpc-jax evaluate --gt 00.txt --est prior.txt --est corrected.txt --label prior --label corrected \\
      --align se3 --report out/report --export out/trajectories
Formats by extension (.mat, .tum) or column count (12 KITTI, 8 TUM), or --format. A .mat given to --gt
is read for its poses_gt, given to --est for its poses_est (--mat reads both). Where the ground truth and
every estimate have times (TUM), poses are paired by time as evo does: the nearest times within
--t-max-diff (estimate times shifted by --t-offset); fewer than half matched is refused. Otherwise they
are paired pose by pose, in order. A pose topic of a ROS recording is a trajectory with times: REC:TOPIC
(nav_msgs/Odometry, PoseStamped or PoseWithCovarianceStamped; REC a .bag, .mcap or ROS 2 bag folder),
as --gt or --est, e.g. --gt run.bag:/ground_truth --est corrected.mcap:/dpc/odometry."""


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
        "--format", choices=FORMATS, default=None,
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
    parser.add_argument(
        "--t-max-diff", type=float, metavar="S",
        help="pairing by time: the largest time difference of two paired poses, in seconds (default: "
        "0.01, evo's)",
    )
    parser.add_argument(
        "--t-offset", type=float, metavar="S",
        help="pairing by time: seconds added to every estimate's times (default: 0)",
    )
    parser.add_argument("--json", type=file_path_text, metavar="PATH",
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


def _topic(path: Path | None) -> tuple[Path, str] | None:
    """``(recording, topic)`` of a ``REC:TOPIC`` trajectory argument, or None for a file."""
    if path is None or ":/" not in str(path):
        return None
    recording, topic = str(path).split(":/", 1)
    return Path(recording), "/" + topic


def _input_problem(path: Path | None, option: str) -> str | None:
    """:func:`input_problem` of a trajectory argument: a file, or the recording of ``REC:TOPIC``."""
    topic = _topic(path)
    if topic is None:
        return input_problem(path, option)
    return None if topic[0].exists() else f"{option} {path}: no such recording {topic[0]}"


def _format(path: Path, given: str | None) -> str:
    """The format of a trajectory argument: ``topic`` for ``REC:TOPIC``, else the file's."""
    from dpc_jax.data.poses_io import detect_format

    return "topic" if _topic(path) is not None else given or detect_format(path)


def _read(
    path: Path, given: str | None, mat_key: str = "poses_est", *, timed: bool = True,
    frames: dict[str, str] | None = None,
) -> tuple[np.ndarray | None, np.ndarray]:
    """``(times or None, poses)`` of a trajectory argument (a file, or ``REC:TOPIC``); not ``timed``: to be
    paired by order (a TUM file's jumps in time warn). ``frames`` gains, for a topic whose messages name
    it, the frame its poses are of."""
    from dpc_jax.data.poses_io import read_timed_trajectory, read_trajectory

    topic = _topic(path)
    if topic is None:
        if not timed:
            return None, read_trajectory(path, given, mat_key=mat_key)
        return read_timed_trajectory(path, given, mat_key=mat_key)
    from dpc_jax.sources.bag import read_pose_topic

    times, poses, frame = read_pose_topic(*topic)
    if frames is not None and frame is not None:
        frames[str(path)] = frame
    return times, poses


def _warn_of_frames(frames: dict[str, str]) -> None:
    """Topics are compared as recorded (no ``/tf``): a warning when they hold the poses of other frames,
    whose relative errors would mix the two frames' motions."""
    if len(set(frames.values())) > 1:
        listed = ", ".join(f"{path} of {frame!r}" for path, frame in frames.items())
        warnings.warn(f"the trajectories are the poses of different frames ({listed}); evaluate compares "
                      "them as recorded, without /tf, so their relative errors mix the frames' motions",
                      InputWarning, stacklevel=2)


def _inputs(
    args: argparse.Namespace,
) -> tuple[np.ndarray, dict[str, np.ndarray], Association | None]:
    """Read ground truth and estimates -> ``(gt, {label: estimate}, association)``, paired: by time where
    every file has times (``association`` says how), else by order; raises ValueError/OSError."""
    from dpc_jax.data.poses_io import MAX_TIME_DIFF, read_mat
    from dpc_jax.eval.evaluation import associate_by_time, check_label

    timing = [f"{option} {value:g}" for option, value in (("--t-max-diff", args.t_max_diff),
                                                         ("--t-offset", args.t_offset)) if value is not None]
    if args.mat is not None:
        if args.est or args.label:
            raise ValueError("--mat holds the estimate; do not combine it with --est or --label")
        if timing:
            raise ValueError(f"{', '.join(timing)}: pairing by time needs times, and --mat {args.mat} has "
                             "none")
        gt, est = read_mat(args.mat)
        return gt, {"est": est}, None
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
    if args.t_max_diff is not None and not (0.0 <= args.t_max_diff < float("inf")):
        raise ValueError(f"--t-max-diff {args.t_max_diff}: expected a time difference >= 0 in seconds")
    if args.t_offset is not None and not abs(args.t_offset) < float("inf"):
        raise ValueError(f"--t-offset {args.t_offset}: expected a finite number of seconds")
    # Paired by time only where every file has times: a file without them is paired by order, and then
    # so is every other (and a jump in a TUM file's times warns).
    files = [args.gt, *args.est]
    timed = all(_format(path, args.format) in ("tum", "topic") for path in files)
    if timing and not timed:
        untimed = next(path for path in files if _format(path, args.format) not in ("tum", "topic"))
        raise ValueError(f"{', '.join(timing)}: pairing by time needs times in every file, and {untimed} "
                         "has none (a KITTI or .mat trajectory is paired by order)")
    frames: dict[str, str] = {}
    if not timed:
        gt = _read(args.gt, args.format, mat_key="poses_gt", timed=False, frames=frames)[1]
        estimates = {label: _read(path, args.format, timed=False, frames=frames)[1]
                     for label, path in zip(labels, args.est, strict=True)}
        _warn_of_frames(frames)
        for path, est in zip(args.est, estimates.values(), strict=True):
            if est.shape[0] != gt.shape[0]:
                raise ValueError(
                    f"{path} has {est.shape[0]} poses but the ground truth {args.gt} has {gt.shape[0]}"
                )
        return gt, estimates, None
    gt_times, gt = _read(args.gt, args.format, mat_key="poses_gt", frames=frames)
    read = {label: _read(path, args.format, frames=frames)
            for label, path in zip(labels, args.est, strict=True)}
    _warn_of_frames(frames)
    # Every file is TUM here, so every one has its times.
    assert gt_times is not None and all(stamps is not None for stamps, _ in read.values())
    times = {label: stamps for label, (stamps, _) in read.items() if stamps is not None}
    try:
        association = associate_by_time(
            gt_times, times, max_diff=MAX_TIME_DIFF if args.t_max_diff is None else args.t_max_diff,
            offset=args.t_offset or 0.0,
            sources={label: f"--est {path}" for label, path in zip(labels, args.est, strict=True)})
    except ValueError as error:
        raise ValueError(f"{error} (--t-offset S shifts the estimate's times, --t-max-diff S sets the "
                         "tolerance)") from None
    picked = {label: est[association.indices[label]] for label, (_, est) in read.items()}
    return gt[association.gt_indices], picked, association


def _own_files_problem(args: argparse.Namespace, labels: list[str]) -> str | None:
    """Why ``--report`` or ``--export`` would replace a file that no dpc-jax command wrote there, or None."""
    from dpc_jax.report.evaluation_report import REPORT_FILES, export_files

    return ((foreign_files_problem(args.report, REPORT_FILES, f"--report {args.report}",
                                   writer="evaluate --report") if args.report is not None else None)
            or (foreign_files_problem(args.export, export_files(labels), f"--export {args.export}",
                                      writer="evaluate --export") if args.export is not None else None))


def run(args: argparse.Namespace) -> int:
    inputs = [("--mat", args.mat), ("--gt", args.gt), *(("--est", path) for path in args.est)]
    problem = (
        input_problem(args.mat, "--mat") or _input_problem(args.gt, "--gt")
        or next(filter(None, (_input_problem(path, "--est") for path in args.est)), None)
        or output_problem(None if args.json == "-" else args.json, "--json")
        or output_problem(args.report, "--report", folder=True)
        or output_problem(args.export, "--export", folder=True)
        or overlap_problem(inputs, [("--json", None if args.json == "-" else args.json),
                                    ("--report", args.report), ("--export", args.export)])
        or stdout_problem(inputs)
    )
    if problem is not None:
        return _error(problem)
    try:
        gt, estimates, association = _inputs(args)
        problem = _own_files_problem(args, list(estimates))
        if problem is not None:
            return _error(problem)
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
        import dataclasses

        from dpc_jax._io import OutputSet, atomic_write, record_own_files
        from dpc_jax.eval.evaluation import evaluate
        from dpc_jax.report.evaluation_report import (
            association_line,
            export_trajectories,
            format_table,
            write_report,
        )

        result = evaluate(gt, estimates, remove_static=args.remove_static, align=args.align,
                          rpe_delta=args.rpe_delta, diagnose=args.diagnose, focal_px=args.focal)
        if association is not None:
            # The evaluated frames as indices into the ground-truth file, not into its matched poses.
            result = dataclasses.replace(result, frames=association.gt_indices[result.frames],
                                         association=association.to_dict())
    except (ValueError, OSError) as error:
        return _error(str(error))

    with OutputSet() as outputs:
        if args.json not in (None, "-"):
            atomic_write(outputs.file(args.json), result.to_json())
        if args.report is not None:
            source = args.mat if args.mat is not None else args.gt
            staged = outputs.folder(args.report)
            written = write_report(staged, result, title=f"Trajectory evaluation: {source.name}")
            record_own_files(staged, args.report, [path.name for path in written], writer="evaluate --report")
        if args.export is not None:
            staged = outputs.folder(args.export)
            record_own_files(staged, args.export, [path.name for path in export_trajectories(staged, result)],
                             writer="evaluate --export")
        outputs.commit()
    if args.json == "-":
        sys.stdout.write(result.to_json())
    elif args.json is None or not is_stdout(args.json):
        # The table would follow the JSON that --json /dev/stdout streamed there, which no JSON
        # reader then accepts.
        paired = association_line(result)
        if paired is not None:
            print(paired)
        sys.stdout.write(format_table(result))
        if result.diagnoses:
            from dpc_jax.report.evaluation_report import format_diagnosis

            sys.stdout.write("\n" + format_diagnosis(result.diagnoses))
    return 0
