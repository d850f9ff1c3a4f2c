"""``dpc-jax vo``: run the classical stereo VO over a KITTI (or synthetic) sequence."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dpc_jax._io import output_problem
from dpc_jax.cli._common import (
    Formatter,
    file_path_option,
    finite_problem,
    frame_range,
    frames_problem,
    import_jax,
    input_problem,
    offset_problem,
    path_option,
)

HELP = "Classical stereo visual odometry (libviso2-s-like): write the trajectory and a per-frame CSV."
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): the VO is about 6 % faster.
HUGE_PAGES = True

EPILOG = """examples:
  dpc-jax vo --kitti-odometry ROOT --sequence 09 --out vo/09.txt
  dpc-jax vo --kitti-raw ROOT --date 2011_09_26 --drive 0001 \\
      --gt ROOT/libviso2/stereo_2011_09_26_drive_0001.mat --start gt --out vo/0001.txt
The synthetic sequences use the odometry layout (--kitti-odometry). The trajectory is KITTI pose text
(camera-to-world of the left camera, one 3x4 row per frame) starting at the identity, or at the ground
truth's first pose with --start gt. The CSV (default: OUT with suffix .csv) has one row per frame pair:
frame (its number in the sequence), inliers, status (ok | constant_velocity), disparity_offset_px, time_s.
With ground truth the m-ATE and final-position error are printed. OUT with suffix .json summarises the run
(source_frames: the frames START, STOP it estimated, which `prepare` and `correct` check the prior against;
frames, fallbacks and their share, median inliers, final offset, and a warning when more than 5 % of the
pairs fell back to constant velocity, which is also printed on stderr). The three files are written
together or not at all; beside a stream (--out /dev/stdout) no file is made: only the trajectory, and the
CSV where --csv names it; with either on standard output, the lines this command prints go to stderr."""




def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    layout = parser.add_mutually_exclusive_group(required=True)
    layout.add_argument("--kitti-odometry", type=path_option, metavar="ROOT",
                        help="odometry layout root (holds sequences/ and poses/); also the synthetic layout")
    layout.add_argument("--kitti-raw", type=path_option, metavar="ROOT", help="raw layout root (holds DATE/)")
    parser.add_argument("--sequence", metavar="XX", help="odometry: sequence")
    parser.add_argument("--grey", action="store_true",
                        help="the grey pair (odometry: image_0/image_1; raw: image_00/image_01); default: "
                        "the colour pair, or for a raw drive without one its grey pair")
    parser.add_argument("--date", metavar="YYYY_MM_DD", help="raw: recording date, e.g. 2011_09_26")
    parser.add_argument("--drive", metavar="NNNN", help="raw: drive number")
    parser.add_argument("--gt", type=path_option, metavar="FILE",
                        help="raw: ground truth (KITTI/TUM text or .mat, its poses_gt)")
    parser.add_argument("--out", required=True, type=file_path_option, metavar="POSES_TXT",
                        help="trajectory file to write")
    parser.add_argument("--csv", type=file_path_option, metavar="FILE",
                        help="per-frame CSV (default: OUT with suffix .csv)")
    parser.add_argument("--start", choices=("identity", "gt"), default="identity",
                        help="first pose of the written trajectory")
    parser.add_argument("--frames", type=frame_range, metavar="START:STOP",
                        help="use only these frames (the trajectory then holds their poses only, and its "
                        ".json and CSV say which: `prepare`/`correct` take it for frames in this range only)")
    parser.add_argument("--disparity-offset", type=float, default=0.0, metavar="PX",
                        help="disparity offset (px added to measured disparities); the starting value "
                             "of the online estimate unless --fixed-offset")
    parser.add_argument("--fixed-offset", action="store_true",
                        help="do not self-calibrate the disparity offset online")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _open(args: argparse.Namespace):  # -> StereoSequence (imported lazily)
    from dpc_jax.data.kitti import open_odometry, open_raw

    if args.kitti_odometry is not None:
        if not args.sequence or args.date or args.drive or args.gt:
            raise _UsageError("--kitti-odometry needs --sequence (and no --date/--drive/--gt)")
        return open_odometry(args.kitti_odometry, args.sequence, grey=args.grey)
    if not args.date or not args.drive or args.sequence:
        raise _UsageError("--kitti-raw needs --date and --drive (and no --sequence)")
    return open_raw(args.kitti_raw, args.date, args.drive, poses=args.gt,
                    cameras="grey" if args.grey else "auto")


class _UsageError(Exception):
    pass


def _same_file_problem(out: Path, csv_path: Path | None, json_path: Path | None) -> str | None:
    """Why the trajectory, the CSV and the summary would not be three files because of the names
    derived from ``--out``, or None: the one rule (:func:`~dpc_jax._io.overlap_problem`) finds these
    too, this says which name to change. None paths (beside a stream) are not written."""
    if json_path is None or csv_path is None:
        return None
    from dpc_jax._io import output_target

    targets = {name: output_target(path) for name, path in (("--out", out), ("csv", csv_path),
                                                             ("json", json_path))}
    if targets["--out"][0] != "stream" and targets["--out"][1] == targets["json"][1]:
        return (f"--out {out}: the run summary goes to OUT with suffix .json, the same file; "
                "give the trajectory another suffix, such as .txt")
    if targets["csv"][0] != "stream" and targets["csv"][1] == targets["--out"][1]:
        return f"--csv {csv_path}: the same file as --out; give the CSV another name"
    if targets["csv"][0] != "stream" and targets["csv"][1] == targets["json"][1]:
        return (f"--csv {csv_path}: the same file as the run summary {json_path} (--out with suffix "
                ".json); give the CSV another name")
    return None


def run(args: argparse.Namespace) -> int:
    from dpc_jax._io import is_stdout, is_stream, overlap_problem

    # Nothing is made beside a stream (/dev/stdout, /dev/null, a FIFO): only what was asked is
    # written, the trajectory and a --csv given, never /dev/stdout.csv.
    streamed = is_stream(args.out)
    csv_path = args.csv if args.csv is not None or streamed else args.out.with_suffix(".csv")
    json_path = None if streamed else args.out.with_suffix(".json")
    problem = (input_problem(args.kitti_odometry, "--kitti-odometry", folder=True)
               or input_problem(args.kitti_raw, "--kitti-raw", folder=True) or input_problem(args.gt, "--gt")
               or output_problem(args.out, "--out") or output_problem(csv_path, "--csv")
               or output_problem(json_path, "--out")
               or finite_problem(disparity_offset=args.disparity_offset))
    if problem is None:
        problem = _same_file_problem(args.out, csv_path, json_path) or overlap_problem(
            [("--kitti-odometry", args.kitti_odometry), ("--kitti-raw", args.kitti_raw), ("--gt", args.gt)],
            [("--out", args.out), ("--csv", csv_path), ("--out (its .json summary)", json_path)])
    if problem is not None:
        print(f"dpc-jax vo: error: {problem}", file=sys.stderr)
        return 2
    import numpy as np

    from dpc_jax._io import OutputSet, atomic_write
    from dpc_jax.data.poses_io import write_kitti_poses
    from dpc_jax.data.priors import FRAMES_KEY
    from dpc_jax.vo import VOConfig, run_vo
    from dpc_jax.vo.odometry import per_frame_table, summary

    try:
        sequence = _open(args)
        problem = (frames_problem(args.frames, len(sequence), sequence.name)
                   or offset_problem(args.disparity_offset, sequence.image_size[1], sequence.name))
        if problem is not None:
            raise _UsageError(problem)
        # The source frames of the run, recorded with it: a prior knows which frames it estimated.
        first, stop = args.frames if args.frames is not None else (0, len(sequence))
        if args.frames is not None:
            sequence = sequence.select(*args.frames)
        if args.start == "gt" and sequence.poses is None:
            raise _UsageError(f"--start gt: no ground truth for {sequence.name} (poses/XX.txt or --gt)")
    except _UsageError as error:
        print(f"dpc-jax vo: error: {error}", file=sys.stderr)
        return 2
    except (OSError, ValueError, KeyError) as error:
        print(f"dpc-jax vo: error: {error}", file=sys.stderr)
        return 1

    config = VOConfig(disparity_offset=args.disparity_offset, estimate_offset=not args.fixed_offset)
    first_pose = sequence.poses[0] if args.start == "gt" else None
    try:
        progress = not args.no_progress and sys.stderr.isatty()
        result = run_vo(sequence, config, first_pose=first_pose, progress=progress)
    except (OSError, ValueError) as error:
        print(f"dpc-jax vo: error: {sequence.name}: {error}", file=sys.stderr)
        return 1

    counts = summary(result)
    with OutputSet() as outputs:
        write_kitti_poses(outputs.file(args.out), result.poses)
        if csv_path is not None:
            atomic_write(outputs.file(csv_path), per_frame_table(result, first_frame=first))
        if json_path is not None:
            record = {"sequence": sequence.name, FRAMES_KEY: [first, stop], **counts}
            atomic_write(outputs.file(json_path), json.dumps(record, indent=2) + "\n")
        outputs.commit()

    # With the trajectory (or the CSV) on standard output, the summary goes to stderr, so that what
    # reads standard output gets the file alone.
    report = sys.stderr if any(is_stdout(path) for path in (args.out, csv_path) if path is not None) else None
    rate = len(result.times) / result.times.sum()
    print(
        f"{sequence.name}: {len(result.poses)} frames, {rate:.1f} frames/s (VO only), "
        f"median inliers {int(np.median(result.inliers))}, constant-velocity fallbacks {counts['fallbacks']}"
        f" ({100 * counts['fallback_share']:.1f} %), "
        f"disparity offset {result.disparity_offset[-1]:+.2f} px",
        file=report,
    )
    if counts["warning"] is not None:
        print(f"dpc-jax vo: warning: {sequence.name}: {counts['warning']}", file=sys.stderr)
    if sequence.poses is not None:
        import_jax()  # the VO itself runs without JAX; the metric is jitted
        from dpc_jax.eval.metrics import m_ate

        gt = sequence.poses
        est = gt[0] @ np.linalg.inv(result.poses[0]) @ result.poses
        trans, rot = m_ate(gt, est)
        final = float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))
        print(
            f"vs ground truth: m-ATE {float(trans):.3f} m / {float(rot):.3f} deg, "
            f"final-position error {final:.3f} m",
            file=report,
        )
    written = [str(path) for path in (args.out, csv_path, json_path) if path is not None]
    print(f"wrote {', '.join(written)}", file=report)
    return 0
