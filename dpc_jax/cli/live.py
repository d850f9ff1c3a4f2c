"""``dpc-jax live``: an external VO's poses corrected as they arrive (docs/cli.md "Live correction").

The records (``dpc_jax.data.records``) or a recording's frames are corrected one at a time by the live
loop that ``dpc-jax vo --correct`` shares (``dpc_jax.correction.stream``): each frame's pose and CSV row
are written the moment it is computed, whole lines whatever interrupts them, and the summary at the
end. This module parses the options, checks them and the inputs before JAX starts, and calls it.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dpc_jax._io import (
    beside_problem,
    is_stream,
    output_problem,
    overlap_problem,
    report_stream,
    stdout_problem,
)
from dpc_jax.cli._common import (
    Formatter,
    file_path_option,
    finite_problem,
    image_size,
    import_jax,
    input_problem,
    offset_problem,
    path_option,
    path_text,
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
from dpc_jax.cli._source import add_source_arguments, open_recording, source_problem
from dpc_jax.correction.stream import (
    CSV_COLUMNS,
    OWN_TIMES,
    Arrived,
    Corrected,
    LiveSummary,
    Pace,
    correct_frames,
    live_outputs,
    network_words,
    prior_arrivals,
    record_arrivals,
    write_summary,
)
from dpc_jax.data.calibration import Calibration, NoImageSize, holds_both_pairs, load_calibration
from dpc_jax.data.records import (
    RECORD_SHAPE,
    Record,
    RecordError,
    checked_records,
    open_records,
    streamed_records,
)

HELP = "Correct an external VO's poses live, each as its stereo pair and pose arrive (records on stdin)."
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): the network runs about a quarter faster.
HUGE_PAGES = True

EPILOG = f"""Records (--records FILE, default standard input), one frame per line, as the VO makes them:
  [TIME] LEFT RIGHT r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz
LEFT, RIGHT: the rectified stereo pair's image files (PNG/JPEG at the calibration's size; paths without
spaces, relative to the current folder); then the VO's camera-to-world pose of the left camera as a
KITTI pose row; TIME (seconds, optional) is copied to the CSV. Blank lines and lines starting with #
are skipped. A stream is read as it grows: each record is corrected when its line arrives. A regular
file (or standard input redirected from one) is checked whole before the network is loaded.

Outputs: --out gets one KITTI pose row per frame, written and flushed the moment it is computed; the
CSV (default OUT with suffix .csv; none beside a stream unless --csv) one row per frame with its pose:
{",".join(CSV_COLUMNS)}
(state: start, prior (no part accepted), forced, or the part applied: rotation, rotation − mean, full,
full − mean; events: the tests accepted or withdrawn at that frame, ';'-separated; the stage times in
ms: decoding, our VO, the pair's preparation, the network, the measurement of Δ for the tests; latency:
from the frame's arrival to its pose written). OUT with suffix .json gets the summary at
the end. Ctrl-C: exit status 130, every line written so far whole.

--realtime HZ replays a recording at the camera's rate: record k is due HZ⁻¹·k s after the first, the
command waits for it, and it misses its deadline when its pose is written after record k+1 is due.
--realtime without HZ replays a ROS recording (--bag) at its own header stamps instead.

examples:
  my_vo --stream | dpc-jax live --checkpoint runs/own_data --calib KITTI/sequences/05/calib.txt \\
      --image-size 375x1242 --out live_05.txt
  dpc-jax live --checkpoint runs/excerpt --calib ROOT/2011_09_26/calib_cam_to_cam.txt \\
      --records records.txt --realtime 10 --out live.txt
  dpc-jax live --checkpoint runs/own_data --bag run.mcap --prior-topic /odom --realtime --out live.txt
A ROS recording (--bag REC) replaces the records: its stereo frames, its CameraInfo (or --calib) and the
external VO's poses from --prior-topic (docs/formats.md, "Recordings")."""


def _calibration(args: argparse.Namespace) -> Calibration:
    """The stereo calibration of ``--calib`` (``dpc_jax.data.calibration.load_calibration``: its colour
    pair, or the grey one with ``--grey``) for images of ``--image-size`` (or the file's ``S_rect_XX``);
    ``ValueError`` naming the file, :class:`_UsageError` where it gives no size and none is given."""
    # A KITTI file with both pairs: the records' images say which pair they are (_pair_problem).
    args.both_pairs = holds_both_pairs(args.calib)
    try:
        return load_calibration(args.calib, grey=args.grey, image_size=args.image_size)
    except NoImageSize as missing:
        raise _UsageError(f"--calib {args.calib}: does not give the images' size ({missing.reason}); give "
                          "--image-size HxW") from None


def _recorded(args: argparse.Namespace) -> tuple[Calibration, str, np.ndarray]:
    """``--bag``: the recording's calibration (``dpc_jax.sources``: its CameraInfo, or ``--calib``), how
    messages name it and its frames' times ``[N]`` (s since the first stamp); the recording is opened
    here, before JAX starts, and its frames read later."""
    sequence = open_recording(args).sequence
    return Calibration.of(sequence), f"--bag {args.bag}", sequence.times


def _arrivals(args: argparse.Namespace, records: Iterator[Record], name: str,
              size: tuple[int, int]) -> Iterator[Arrived]:
    """The frames to correct, read as they are corrected: the records', or those of ``--bag`` (opened
    again) with their poses of ``--prior-topic``."""
    if args.bag is None:
        yield from record_arrivals(records, name, size)
        return
    recording = open_recording(args)
    assert recording.prior is not None, "_check asks for --prior-topic"
    yield from prior_arrivals(recording.sequence, recording.prior)


def _pair_problem(record: Record, where: str, *, args: argparse.Namespace) -> None:
    """With a KITTI calibration holding both pairs (grey P_rect_00/01, colour P_rect_02/03, with other
    baselines), the first record's left image must be of the pair chosen (``--grey`` or not)."""
    import cv2

    if not getattr(args, "both_pairs", False):
        return
    image = cv2.imread(str(record.left), cv2.IMREAD_UNCHANGED)
    grey = image is not None and (image.ndim == 2 or image.shape[2] == 1)
    if grey != bool(args.grey):
        fix = ("give --grey (the calibration's grey pair)" if grey
               else "leave --grey out (the calibration's colour pair)")
        raise RecordError(f"{where}: left image {record.left} is {'grey' if grey else 'colour'}, and --calib "
                          f"{args.calib} holds both pairs, with other baselines: {fix}")


class _UsageError(Exception):
    """A command-line mistake found while reading an input: exit status 2."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    parser.add_argument("--checkpoint", required=True, type=path_option, metavar="RUN",
                        help="training run folder (dpc-jax train --workdir)")
    parser.add_argument("--calib", type=path_option, metavar="FILE",
                        help="the rig's KITTI calibration: calib.txt (P2/P3) or calib_cam_to_cam.txt "
                        "(P_rect_02/P_rect_03); with --bag only for a recording without CameraInfo")
    parser.add_argument("--grey", action="store_true",
                        help="the calibration's grey pair (P0/P1, P_rect_00/P_rect_01) instead of the colour "
                        "one")
    parser.add_argument("--image-size", type=image_size, metavar="HxW",
                        help="the size of the records' images (default: the calibration's S_rect_XX)")
    records = parser.add_mutually_exclusive_group()
    records.add_argument("--records", type=path_text, metavar="FILE",
                         help="the records (default: standard input, read as it grows)")
    add_source_arguments(parser, records, prior_topic=True, layouts=False)
    parser.add_argument("--out", required=True, type=file_path_option, metavar="POSES_TXT",
                        help="corrected poses, one KITTI row per frame as it is corrected")
    parser.add_argument("--csv", type=file_path_option, metavar="FILE",
                        help="per-frame CSV (default: OUT with suffix .csv; none beside a stream)")
    parser.add_argument("--disparity-offset", type=float, default=0.0, metavar="PX",
                        help="the rig's disparity calibration residual the right images are resampled by, as "
                        "`dpc-jax prepare --disparity-offset` (px at the images' size)")
    add_correction_arguments(parser, requires=None)


def _check(args: argparse.Namespace) -> str | None:
    """The first problem of the options, paths and outputs (no JAX), or None."""
    streamed = is_stream(args.out)
    args.csv_path = args.csv if args.csv is not None or streamed else args.out.with_suffix(".csv")
    args.json_path = None if streamed else args.out.with_suffix(".json")
    records = None if args.records in (None, "-") else Path(args.records)
    problem = (correction_problem(args, "--checkpoint", args.checkpoint) or source_problem(args)
               or ("--calib FILE is required with records (the rig's calibration)"
                   if args.calib is None and args.bag is None else None)
               or ("--prior-topic TOPIC is required with --bag (the poses of the VO to correct)"
                   if args.bag is not None and args.prior_topic is None else None)
               or ("--realtime without HZ replays a recording (--bag) at its own stamps; records have none: "
                   "give the camera's rate, --realtime HZ" if args.realtime == OWN_TIMES and args.bag is None
                   else None)
               or input_problem(args.calib, "--calib") or input_problem(records, "--records")
               or finite_problem(disparity_offset=args.disparity_offset)
               or text_output_problem(args.out, "--out", "live")
               or output_problem(args.out, "--out") or output_problem(args.csv_path, "--csv")
               or output_problem(args.json_path, "--out (its .json summary)"))
    if problem is not None:
        return problem
    if records is not None and records.is_dir():
        return f"--records {records}: is a folder; expected a file of records"
    inputs = [("--checkpoint", args.checkpoint), ("--calib", args.calib), ("--records", records),
              ("--bag", args.bag)]
    return (overlap_problem(inputs, [("--out", args.out), ("--csv", args.csv_path),
                                     ("--out (its .json summary)", args.json_path)])
            or stdout_problem(inputs) or beside_problem(beside_files(args.out, args.csv, args.csv_path,
                                                                     args.json_path)))


def run(args: argparse.Namespace) -> int:
    def error(message: str, status: int) -> int:
        print(f"dpc-jax live: error: {message}", file=sys.stderr)
        return status

    problem = _check(args)
    if problem is not None:
        return error(problem, 2)
    try:
        calibration, where, times = _recorded(args) if args.bag is not None else (
            _calibration(args), f"--calib {args.calib}", None)
    except _UsageError as usage:
        return error(str(usage), 2)
    except (OSError, ValueError) as content:
        return error(str(content), 1)
    size = calibration.image_size
    problem, judge = run_problem(args, args.checkpoint, "--checkpoint", size, where)
    problem = problem or offset_problem(args.disparity_offset, size[1], where)
    if problem is not None:
        return error(problem, 2)
    stream, name, regular = (None, str(args.bag), True) if args.bag is not None else open_records(
        None if args.records in (None, "-") else args.records)
    with contextlib.closing(stream) if stream not in (None, sys.stdin.buffer) else contextlib.nullcontext():
        records: Iterator[Record]
        first = functools.partial(_pair_problem, args=args)
        if stream is None:  # a recording, opened and checked before JAX starts
            records = iter(())
        elif regular:  # a file of records: checked whole before JAX starts
            try:
                records = iter(checked_records(stream.readlines(), name, size, first))
            except RecordError as content:
                return error(str(content), 1)
        else:
            records = streamed_records(stream, name, first)
        import_jax()
        from dpc_jax.training.checkpoints import CheckpointError

        began = time.perf_counter()
        try:
            live = corrector(args, args.checkpoint, calibration, judge,
                             disparity_offset=args.disparity_offset)
        except CheckpointError as failed:
            return error(restore_problem(failed.folder, failed.__cause__ or failed), 1)
        summary = LiveSummary(Pace.of(args.realtime, times), time.perf_counter() - began)
        report = report_stream(args.out, args.csv_path)
        outputs = live_outputs(args.out, None, args.csv_path, stale=(args.json_path,),
                               beside=[path for _, path in beside_files(args.out, args.csv, args.csv_path,
                                                                        args.json_path)])

        def step(loaded: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Corrected:
            return Corrected(live(loaded[0], loaded[1], loaded[2]))

        try:
            with outputs:
                correct_frames(_arrivals(args, records, name, size), step, outputs, summary, live.hold)
        except KeyboardInterrupt:
            print(f"dpc-jax live: interrupted after {summary.frames} frames; their poses in {args.out} are "
                  "whole lines", file=sys.stderr)
            raise
        except (OSError, ValueError) as content:
            return error(f"{content} (the {summary.frames} frames before it are written)", 1)
        finally:
            live.close()
    if summary.frames == 0:
        return error(f"{name}: no records; expected one line per frame: {RECORD_SHAPE}", 1)
    network = {"checkpoint": str(args.checkpoint), "epoch": live.run.epoch, "method": live.run.config.method,
               "image_size": list(live.size)}
    write_summary(args.json_path, {"records": name, **network, **summary.record()})
    print(f"{name}: {summary.frames} frames corrected live by {network_words(live, args.checkpoint)}",
          file=report)
    for line in summary.lines():
        print(line, file=report)
    written = [path for path in (args.out, args.csv_path, args.json_path) if path is not None]
    print(f"wrote {', '.join(map(str, written))}", file=report)
    return 0
