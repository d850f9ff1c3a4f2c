"""``dpc-jax correct``: correct a VO trajectory with a trained DPC network and evaluate it."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import tempfile
from pathlib import Path

from dpc_jax.cli._common import Formatter, frame_range

HELP = "Correct a VO trajectory with a trained network (T* = Exp(xi_corr) T_vo); evaluate it against GT."

EPILOG = """The sequence (--data, one of):
  a prepared cache   --data cache/05   (from `dpc-jax prepare`; corrects its own prior unless --prior)
  KITTI odometry     --kitti-odometry ROOT --sequence 05 --prior FILE   (also the synthetic layout)
  KITTI raw          --kitti-raw ROOT --date 2011_09_26 --drive 1 --prior FILE
Raw inputs are prepared on the fly at the run's image size (with flow when the network reads flow) into
--cache DIR (kept, reused when up to date) or a temporary folder. Ground truth: poses/XX.txt (odometry),
else --gt, else the poses_gt of a .mat prior; a cache keeps the ground truth it was prepared with.

Frames: the trajectory has one pose per cached frame. When static frames were removed (--remove-static
here or at prepare time) or a frame range was cached, the source frame number of every pose is written to
OUT's stem + '.frames.txt' (corrected.txt -> corrected.frames.txt). TUM output uses the frame times.

examples:
  dpc-jax correct --checkpoint runs/kitti_00 --data cache/00 --out corrected_00.txt --report report_00
  dpc-jax correct --checkpoint runs/excerpt --select loop --kitti-raw data/kitti-raw --date 2011_09_26 \\
      --drive 1 --prior data/kitti-raw/libviso2/stereo_2011_09_26_drive_0001.mat --out corrected.txt"""




def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    parser.add_argument("--checkpoint", required=True, type=Path, metavar="WORKDIR",
                        help="training run folder (dpc-jax train --workdir)")
    parser.add_argument("--select", choices=("gradient", "loop", "last"), default="gradient",
                        help="epoch: best validation gradient loss, most loop closures, or the newest")
    data = parser.add_mutually_exclusive_group(required=True)
    data.add_argument("--data", type=Path, metavar="CACHE", help="a prepared sequence cache folder")
    data.add_argument("--kitti-odometry", type=Path, metavar="ROOT",
                      help="odometry (or synthetic) layout root")
    data.add_argument("--kitti-raw", type=Path, metavar="ROOT", help="raw layout root (holds DATE/)")
    parser.add_argument("--sequence", metavar="XX", help="odometry sequence")
    parser.add_argument("--date", help="raw: recording date, e.g. 2011_09_26")
    parser.add_argument("--drive", metavar="NNNN", help="raw: drive number")
    parser.add_argument("--prior", metavar="FILE",
                        help="VO estimate to correct (KITTI/TUM text or .mat); required with raw inputs")
    parser.add_argument("--prior-format", choices=("kitti", "tum", "mat"), help="override the extension")
    parser.add_argument("--gt", metavar="FILE", help="raw inputs: ground-truth pose file (KITTI/TUM/.mat)")
    parser.add_argument("--cache", type=Path, metavar="DIR", help="raw inputs: keep the prepared cache here")
    parser.add_argument("--frames", type=frame_range, metavar="START:STOP",
                        help="raw inputs: only these frames")
    parser.add_argument("--remove-static", action="store_true",
                        help="raw inputs: drop static frames first (ss-DPC-Net rule, read on the prior)")
    parser.add_argument("--mono-rescale", action="store_true",
                        help="raw inputs: rescale each prior step to the ground-truth step (monocular VO)")
    parser.add_argument("--out", required=True, type=Path, metavar="FILE", help="corrected trajectory")
    parser.add_argument("--format", choices=("kitti", "tum"), default="kitti", help="format of --out")
    parser.add_argument("--rotation-only", action=argparse.BooleanOptionalAction, default=None,
                        help="apply only the rotation of the correction (default: the run's rotation_only)")
    parser.add_argument("--batch-size", type=int, metavar="N", help="inference batch (default: the run's)")
    parser.add_argument("--report", type=Path, metavar="DIR",
                        help="write report.md, CSV tables, plots and metrics.json (needs ground truth)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _error(message: str) -> int:
    print(f"dpc-jax correct: error: {message}", file=sys.stderr)
    return 2


def _check_arguments(args: argparse.Namespace) -> str | None:
    """The first inconsistency of the options, or None."""
    raw_only = {"--gt": args.gt, "--cache": args.cache, "--frames": args.frames,
                "--remove-static": args.remove_static or None, "--mono-rescale": args.mono_rescale or None}
    if args.data is not None:
        given = [name for name, value in raw_only.items() if value is not None]
        if given or args.sequence or args.date or args.drive:
            extra = given + [o for o, v in (("--sequence", args.sequence), ("--date", args.date),
                                            ("--drive", args.drive)) if v]
            return f"{', '.join(extra)} only apply to raw inputs (--kitti-odometry/--kitti-raw), not --data"
        if not args.data.is_dir():
            return f"--data {args.data}: not a folder (expected a cache prepared by `dpc-jax prepare`)"
    elif args.kitti_odometry is not None:
        if not args.sequence or args.date or args.drive:
            return "--kitti-odometry needs --sequence (and no --date/--drive)"
    elif not args.date or not args.drive or args.sequence:
        return "--kitti-raw needs --date and --drive (and no --sequence)"
    if args.data is None and args.prior is None:
        return "--prior FILE is required with raw inputs (the VO estimate to correct)"
    if args.batch_size is not None and args.batch_size < 1:
        return f"--batch-size must be >= 1, got {args.batch_size}"
    if not args.out.parent.is_dir():
        return f"--out {args.out}: directory {args.out.parent} does not exist"
    if args.report is not None and args.report.exists() and not args.report.is_dir():
        return f"--report {args.report}: exists and is not a directory"
    if not (args.checkpoint / "checkpoints" / "config.json").is_file():
        return (f"--checkpoint {args.checkpoint}: not a training run (expected "
                f"{args.checkpoint / 'checkpoints' / 'config.json'}, written by `dpc-jax train`)")
    return None


def run(args: argparse.Namespace) -> int:
    problem = _check_arguments(args)
    if problem is not None:
        return _error(problem)
    # Orbax logs a warning per read-only checkpoint manager; they say nothing useful here.
    logging.getLogger("absl").setLevel(logging.ERROR)
    from dpc_jax.correct import correct_cache, load_run, write_correction_report, write_trajectory
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry, open_raw
    from dpc_jax.evaluation import format_table

    progress = False if args.no_progress else None
    show = sys.stderr.isatty() and not args.no_progress
    with contextlib.ExitStack() as stack:
        try:
            run_ = load_run(args.checkpoint, args.select)
            if args.data is not None:
                cache, prior = args.data, args.prior
            else:
                if args.kitti_odometry is not None:
                    sequence = open_odometry(args.kitti_odometry, args.sequence)
                else:
                    sequence = open_raw(args.kitti_raw, args.date, args.drive)
                cache_root = args.cache or Path(
                    stack.enter_context(tempfile.TemporaryDirectory(prefix="dpc-correct-"))
                )
                cache = prepare_sequence(
                    sequence, args.prior, cache_root, size=run_.image_size, flow=run_.use_flow,
                    remove_static=args.remove_static, mono_rescale=args.mono_rescale, frames=args.frames,
                    prior_format=args.prior_format, ground_truth=args.gt, progress=progress,
                )
                prior = None
            correction = correct_cache(
                run_, cache, prior, rotation_only=args.rotation_only, prior_format=args.prior_format,
                batch_size=args.batch_size, progress=show,
            )
        except (OSError, ValueError, KeyError) as error:
            return _error(str(error))
    if correction.evaluation is None and args.report is not None:
        return _error(f"--report {args.report}: {correction.name} has no ground truth to evaluate against")
    written = write_trajectory(args.out, correction, args.format)
    how = "rotation only" if correction.rotation_only else "full 6-DoF"
    criterion = {"gradient": "best gradient loss", "loop": "most loop closures", "last": "newest"}
    criterion = criterion[args.select]
    print(f"{correction.name}: corrected {correction.corrected.shape[0]} poses ({how}) with epoch "
          f"{run_.epoch} of {args.checkpoint} ({criterion}) -> {', '.join(map(str, written))}")
    if not correction.all_source_frames:
        print(f"note: the trajectory holds {correction.frames.size} cached frames, not every source frame "
              f"(frame numbers in {written[-1]})")
    if correction.evaluation is None:
        print("no ground truth: nothing to evaluate")
        return 0
    sys.stdout.write(format_table(correction.evaluation))
    if args.report is not None:
        write_correction_report(args.report, correction, f"DPC correction: {correction.name}")
        print(f"report: {args.report / 'report.md'}")
    return 0
