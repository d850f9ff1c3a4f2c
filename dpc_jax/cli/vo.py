"""``dpc-jax vo``: run the classical stereo VO over a KITTI (or synthetic) sequence."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax._io import (
    OutputSet,
    atomic_write,
    beside_problem,
    is_stream,
    output_problem,
    output_target,
    overlap_problem,
    record_beside,
    report_stream,
)
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
    restore_problem,
)
from dpc_jax.cli._live_options import (
    add_correction_arguments,
    beside_files,
    correction_problem,
    corrector,
    run_problem,
    text_output_problem,
)
from dpc_jax.cli._source import add_source_arguments, open_recording, source_inputs, source_problem
from dpc_jax.correction.judge import Judge
from dpc_jax.correction.stream import (
    LiveSummary,
    Pace,
    VOStep,
    correct_frames,
    live_outputs,
    network_words,
    sequence_arrivals,
    write_summary,
)
from dpc_jax.runtime.progress import progress_mode
from dpc_jax.vo import VOConfig

HELP = ("Classical stereo visual odometry (libviso2-s-like): write the trajectory and a per-frame CSV; "
        "with --correct RUN, each pose corrected live by a trained network as it is made.")
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): the VO is about 6 % faster.
HUGE_PAGES = True

EPILOG = """examples:
  dpc-jax vo --kitti-odometry ROOT --sequence 09 --out vo/09.txt
  dpc-jax vo --kitti-raw ROOT --date 2011_09_26 --drive 0001 \\
      --gt ROOT/libviso2/stereo_2011_09_26_drive_0001.mat --start gt --out vo/0001.txt
  dpc-jax vo --bag recording.mcap --out vo/recording.txt
The synthetic sequences use the odometry layout (--kitti-odometry). A recording (--bag: ROS 1 .bag, ROS 2
bag folder, .mcap) gives its stereo pair, calibration and, with --gt-topic, its ground truth.
The trajectory is KITTI pose text (camera-to-world of the left camera, one 3x4 row per frame) starting at
the identity, or at the ground truth's first pose with --start gt. The CSV (default: OUT with suffix
.csv) has one row per frame pair: frame (its number in the sequence), inliers, status (ok |
constant_velocity), disparity_offset_px, time_s. With ground truth the m-ATE and final-position error are
printed. OUT with suffix .json summarises the run (source_frames: the frames START, STOP it estimated,
which `prepare` and `correct` check the prior against; frames, fallbacks and their share, median inliers,
final offset, and a warning when more than 5 % of the pairs fell back to constant velocity, which is also
printed on stderr). The three files are written together or not at all; beside a stream (--out
/dev/stdout) no file is made: only the trajectory, and the CSV where --csv names it; with either on
standard output, the lines this command prints go to stderr.

Live correction (--correct RUN): each frame's pose is corrected by the run's network the moment the VO
has made it, behind sequential tests that apply a correction only once the frames seen so far show that
it helps (docs/method.md §8), and written at once: OUT gets one corrected KITTI pose row per frame,
flushed; the prior (this VO's poses, those `dpc-jax vo` writes without --correct) goes beside it, to
--prior-out (default: OUT's stem + '.prior' + its suffix, live.txt -> live.prior.txt, with the .json
record above); the CSV gets one row per frame with its pose: which state produced it (start, prior,
forced, or the part of the correction applied), the tests' events, the VO's columns and the time of
each stage (`dpc-jax live --help` lists the columns); OUT with suffix .json the summary at the end.
--realtime HZ replays the sequence at the camera's rate (without HZ at its own times: a recording's
header stamps, the layouts' times) and reports the frames whose pose was written after the next frame
was due. Ctrl-C: exit status 130, every line written so far whole.
  dpc-jax vo --kitti-raw ROOT --date 2011_09_26 --drive 0001 --gt GT.mat --start gt \\
      --correct runs/drive_0005 --realtime 10 --out live.txt"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    add_source_arguments(parser, parser.add_mutually_exclusive_group(required=True))
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
    parser.add_argument("--disparity-offset", type=float, default=VOConfig.disparity_offset, metavar="PX",
                        help="disparity offset (px added to measured disparities); the starting value "
                             "of the online estimate unless --fixed-offset")
    parser.add_argument("--fixed-offset", action="store_true",
                        help="do not self-calibrate the disparity offset online")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--correct", type=path_option, metavar="RUN",
                        help="correct each pose live with this training run's network (dpc-jax train "
                        "--workdir) and write it as soon as it is made; OUT is then the corrected trajectory")
    parser.add_argument("--prior-out", type=file_path_option, metavar="FILE",
                        help="with --correct: where the prior (this VO's poses) goes, as they are made "
                        "(default: OUT's stem + '.prior' + its suffix; none beside a stream)")
    add_correction_arguments(parser, requires="--correct")


def _open(args: argparse.Namespace):  # -> StereoSequence (imported lazily)
    problem = source_problem(args) or (
        "--gt FILE goes with --kitti-raw (odometry: ROOT/poses/XX.txt; a recording: --gt-topic)"
        if args.gt is not None and args.kitti_raw is None else None)
    if problem is not None:
        raise _UsageError(problem)
    return open_recording(args, args.sequence or args.drive, gt=args.gt).sequence


class _UsageError(Exception):
    pass


def _same_file_problem(out: Path, csv_path: Path | None, json_path: Path | None) -> str | None:
    """Why the trajectory, the CSV and the summary would not be three files because of the names
    derived from ``--out``, or None: the one rule (:func:`~dpc_jax._io.overlap_problem`) finds these
    too, this says which name to change. None paths (beside a stream) are not written."""
    if json_path is None or csv_path is None:
        return None
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


def prior_path(out: Path) -> Path:
    """Where ``--correct`` writes the prior by default: ``live.txt`` → ``live.prior.txt`` (``live`` →
    ``live.prior.txt``, so that its ``.json`` record is not the output's)."""
    return out.with_name(f"{out.stem}.prior{out.suffix or '.txt'}")


def run(args: argparse.Namespace) -> int:
    # Nothing is made beside a stream (/dev/stdout, /dev/null, a FIFO): only what was asked is
    # written, the trajectory and a --csv given, never /dev/stdout.csv.
    streamed = is_stream(args.out)
    csv_path = args.csv if args.csv is not None or streamed else args.out.with_suffix(".csv")
    json_path = None if streamed else args.out.with_suffix(".json")
    prior_out = None
    if args.correct is not None:
        prior_out = args.prior_out if args.prior_out is not None or streamed else prior_path(args.out)
    prior_json = None if prior_out is None or is_stream(prior_out) else prior_out.with_suffix(".json")
    problem = (source_problem(args) or input_problem(args.gt, "--gt")
               or correction_problem(args, "--correct", args.correct)
               or (f"--prior-out {args.prior_out}: only used with --correct RUN (the live correction), which "
                   "is not given" if args.prior_out is not None and args.correct is None else None)
               or text_output_problem(args.out, "--out", "vo")
               or text_output_problem(args.prior_out, "--prior-out", "vo")
               or output_problem(args.out, "--out") or output_problem(csv_path, "--csv")
               or output_problem(json_path, "--out") or output_problem(prior_out, "--prior-out")
               or finite_problem(disparity_offset=args.disparity_offset))
    if problem is None:
        inputs = [*source_inputs(args), ("--gt", args.gt), ("--correct", args.correct)]
        problem = _same_file_problem(args.out, csv_path, json_path) or overlap_problem(
            inputs, [("--out", args.out), ("--csv", csv_path), ("--out (its .json summary)", json_path),
                     ("--prior-out", prior_out), ("--prior-out (its .json record)", prior_json)])
    # The files named after --out (or --prior-out), not by the user: only a command's own are replaced.
    beside = [*beside_files(args.out, args.csv, csv_path, json_path),
              *([(f"--out {args.out} (the prior's default path; --prior-out names another)", prior_out)]
                if args.prior_out is None else []),
              (f"--prior-out {prior_out} (its .json record)", prior_json)]
    problem = problem or beside_problem(beside)
    if problem is not None:
        print(f"dpc-jax vo: error: {problem}", file=sys.stderr)
        return 2
    from dpc_jax.data.poses_io import write_kitti_poses
    from dpc_jax.data.priors import FRAMES_KEY
    from dpc_jax.vo import run_vo
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
    if args.correct is not None:
        problem, judge = run_problem(args, args.correct, "--correct", sequence.image_size, sequence.name)
        if problem is not None:
            print(f"dpc-jax vo: error: {problem}", file=sys.stderr)
            return 2
        return _correct_live(args, sequence, config, judge, (first, stop), csv_path, json_path, prior_out,
                             prior_json, tuple(path for _, path in beside))
    first_pose = sequence.poses[0] if args.start == "gt" else None
    try:
        result = run_vo(sequence, config, first_pose=first_pose, progress=progress_mode(args.no_progress))
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
        record_beside((path for _, path in beside), outputs)
        outputs.commit()

    # With the trajectory (or the CSV) on standard output, the summary goes to stderr, so that what
    # reads standard output gets the file alone.
    report = report_stream(args.out, csv_path)
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
        print(f"vs ground truth: {_versus(sequence.poses, result.poses)}", file=report)
    written = [str(path) for path in (args.out, csv_path, json_path) if path is not None]
    print(f"wrote {', '.join(written)}", file=report)
    return 0


def _correct_live(
    args: argparse.Namespace, sequence: Any, config: Any, judge: Judge, frames: tuple[int, int],
    csv_path: Path | None, json_path: Path | None, prior_out: Path | None, prior_json: Path | None,
    beside: tuple[Path | None, ...],
) -> int:
    """``--correct``: the VO and the run's correction frame by frame, each pose written as it is made
    (``dpc_jax.correction.stream``); then, as without it, the VO's summary, the evaluation against ground
    truth and the ``.json`` records. ``judge``: :func:`~dpc_jax.cli._live_options.run_problem`'s;
    ``frames``: the source frames ``(START, STOP)`` of ``sequence``."""
    from concurrent.futures import ThreadPoolExecutor

    from dpc_jax.data.calibration import Calibration
    from dpc_jax.data.priors import FRAMES_KEY
    from dpc_jax.vo import StereoVO
    from dpc_jax.vo.odometry import summary

    import_jax()
    from dpc_jax.training.checkpoints import CheckpointError

    first, stop = frames
    began = time.perf_counter()
    try:
        live = corrector(args, args.correct, Calibration.of(sequence), judge)
    except CheckpointError as failed:
        problem = restore_problem(failed.folder, failed.__cause__ or failed)
        print(f"dpc-jax vo: error: {problem}", file=sys.stderr)
        return 1
    live_summary = LiveSummary(Pace.of(args.realtime, sequence.times), time.perf_counter() - began)
    step = VOStep(StereoVO(sequence.K, sequence.baseline, config), live,
                  sequence.poses[0] if args.start == "gt" else np.eye(4))
    report = report_stream(args.out, csv_path, prior_out)
    outputs = live_outputs(args.out, prior_out, csv_path, stale=(json_path, prior_json), beside=beside)
    try:
        with ThreadPoolExecutor(2) as decoder, outputs:
            correct_frames(sequence_arrivals(sequence, first, decoder), step, outputs, live_summary,
                           live.hold)
    except KeyboardInterrupt:
        print(f"dpc-jax vo: interrupted after {live_summary.frames} frames; their poses in {args.out} are "
              "whole lines", file=sys.stderr)
        raise
    except (OSError, ValueError) as error:
        print(f"dpc-jax vo: error: {error} (the {live_summary.frames} frames before it are written)",
              file=sys.stderr)
        return 1
    finally:
        live.close()

    result = step.result()
    counts = summary(result)
    write_summary(prior_json, {"sequence": sequence.name, FRAMES_KEY: [first, stop], **counts})
    write_summary(json_path, {"sequence": sequence.name, FRAMES_KEY: [first, stop],
                              "prior": None if prior_out is None else str(prior_out),
                              "checkpoint": str(args.correct), "epoch": live.run.epoch,
                              "method": live.run.config.method, "image_size": list(live.size),
                              **live_summary.record()})
    rate = len(result.times) / result.times.sum()
    print(f"{sequence.name}: {len(result.poses)} frames, VO {rate:.1f} frames/s alone, median inliers "
          f"{int(np.median(result.inliers))}, constant-velocity fallbacks {counts['fallbacks']} "
          f"({100 * counts['fallback_share']:.1f} %), disparity offset "
          f"{result.disparity_offset[-1]:+.2f} px; corrected live by {network_words(live, args.correct)}",
          file=report)
    for line in live_summary.lines():
        print(line, file=report)
    if counts["warning"] is not None:
        print(f"dpc-jax vo: warning: {sequence.name}: {counts['warning']}", file=sys.stderr)
    if sequence.poses is not None:
        for name, poses in (("prior", result.poses), ("corrected", step.corrected)):
            print(f"vs ground truth, {name}: {_versus(sequence.poses, poses)}", file=report)
    written = [path for path in (args.out, prior_out, csv_path, json_path, prior_json) if path is not None]
    print(f"wrote {', '.join(map(str, written))}", file=report)
    return 0


def _versus(gt: np.ndarray, poses: np.ndarray) -> str:
    """The m-ATE and final-position error of ``poses`` ``[N, 4, 4]`` (aligned at the first pose) against
    the ground truth ``gt`` ``[N, 4, 4]``, in words (JAX imported: the metric is jitted)."""
    from dpc_jax.eval.metrics import m_ate

    est = gt[0] @ np.linalg.inv(poses[0]) @ poses
    trans, rot = m_ate(gt, est)
    final = float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))
    return f"m-ATE {float(trans):.3f} m / {float(rot):.3f} deg, final-position error {final:.3f} m"
