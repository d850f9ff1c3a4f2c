"""``dpc-jax correct``: correct a VO trajectory with a trained DPC network and evaluate it.

The options and inputs are checked before JAX starts; then the library does the work: the raw inputs
prepared (``dpc_jax.correction.raw_inputs``) with the judge of ``dpc_jax.correction.judge.judge_policy``,
the correction (``dpc_jax.correction.corrector.correct_sequence``) and its outputs
(``dpc_jax.correction.outputs.write_corrected``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import is_stdout
from dpc_jax.cli._common import (
    Formatter,
    file_path_option,
    frame_range,
    image_size,
    import_jax,
    path_option,
    path_text,
    restore_problem,
)
from dpc_jax.cli._correct_checks import arguments_problem, holdout_every, inputs_problem, raw_prior
from dpc_jax.cli._source import add_source_arguments, open_recording
from dpc_jax.correction.acceptance import DEFAULT_ALPHA
from dpc_jax.correction.decision import DEFAULT_MEAN_TEST, MEAN_TESTS
from dpc_jax.correction.judge import JUDGE_SIZE, Judge
from dpc_jax.correction.outputs import CorrectionOutputs, adapted_path, output_recording
from dpc_jax.data.holdout import DEFAULT_EVERY, MIN_EVERY, holdout_problem
from dpc_jax.data.poses_io import FORMATS, WRITE_FORMATS
from dpc_jax.report.correction_report import applied_words
from dpc_jax.runtime.progress import progress_mode
from dpc_jax.training.train_config import ACCEPTANCE_DEPTHS, DEFAULT_SELECTION, SELECTIONS

if TYPE_CHECKING:
    from dpc_jax.correction.corrector import CorrectedSequence
    from dpc_jax.correction.inference import TrainedRun
    from dpc_jax.data.sequence_cache import SequenceCache

HELP = "Correct a VO trajectory with a trained network (T* = Exp(xi_corr) T_vo); evaluate it against GT."
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): the network runs about a quarter faster.
HUGE_PAGES = True

EPILOG = """The sequence (--data, one of):
  a prepared cache   --data cache/05   (from `dpc-jax prepare`; corrects its own prior unless --prior)
  KITTI odometry     --kitti-odometry ROOT --sequence 05 --prior FILE   (also the synthetic layout)
  KITTI raw          --kitti-raw ROOT --date 2011_09_26 --drive 1 --prior FILE
  a ROS recording    --bag REC --prior-topic TOPIC (or --prior FILE)   (docs/formats.md, "Recordings")
Raw inputs are prepared on the fly at the run's image size (with flow when the network reads flow) into
--cache DIR (kept, reused when up to date) or a temporary folder. Ground truth: poses/XX.txt (odometry),
else --gt, else the poses_gt of a .mat prior; a cache keeps the ground truth it was prepared with.

Judge: with raw inputs, a stereo_dpc run smaller than 240x376 is judged by default: the frames are also
prepared at 240x376 (the papers' input size; CACHE/NAME_judge) and the acceptance test is measured there
(--judge-size HxW: at another size; --no-judge: at the run's size only). A --data cache holds no larger
frames: its test is measured at its own size unless --judge CACHE gives the same frames at 240x376.

Frames: the trajectory has one pose per cached frame. When the cached frames are not the source frames
0, 1, 2, ... (static frames removed by --remove-static here or at prepare time, or a frame range not
starting at 0), the source frame number of every pose is written to OUT's stem + '.frames.txt'
(corrected.txt -> corrected.frames.txt). TUM output uses the frame times.

examples:
  dpc-jax correct --checkpoint runs/kitti_00 --data cache/00 --out corrected_00.txt --report report_00
  dpc-jax correct --checkpoint runs/excerpt --select loop --kitti-raw data/kitti-raw --date 2011_09_26 \\
      --drive 1 --prior data/kitti-raw/libviso2/stereo_2011_09_26_drive_0001.mat --out corrected.txt
  dpc-jax correct --checkpoint runs/own_data --bag run.mcap --prior-topic /odom --out corrected.mcap
OUT.mcap, OUT.bag or --format rosbag2 write the corrected trajectory and the prior as nav_msgs/Odometry
(/dpc/odometry, /dpc/prior) at the frames' stamps."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    parser.add_argument("--checkpoint", required=True, type=path_option, metavar="WORKDIR",
                        help="training run folder (dpc-jax train --workdir)")
    parser.add_argument("--select", choices=tuple(SELECTIONS), default=DEFAULT_SELECTION,
                        help="epoch: most negative validation Δ (none if no epoch beats no correction), best "
                        "validation gradient loss, most loop closures, or the newest")
    data = parser.add_mutually_exclusive_group(required=True)
    data.add_argument("--data", type=path_option, metavar="CACHE", help="a prepared sequence cache folder")
    add_source_arguments(parser, data, prior_topic=True)
    parser.add_argument("--prior", type=path_text, metavar="FILE",
                        help="VO estimate to correct (KITTI/TUM text or .mat); required with raw inputs (a "
                        "recording: or --prior-topic)")
    parser.add_argument("--prior-format", choices=FORMATS, help="override the extension")
    parser.add_argument("--gt", type=path_text, metavar="FILE",
                        help="raw inputs: ground-truth pose file (KITTI/TUM/.mat)")
    parser.add_argument("--cache", type=path_option, metavar="DIR",
                        help="raw inputs: keep the prepared cache here")
    parser.add_argument("--frames", type=frame_range, metavar="START:STOP",
                        help="raw inputs: only these frames")
    parser.add_argument("--remove-static", action="store_true",
                        help="raw inputs: drop static frames first (ss-DPC-Net rule, read on the prior)")
    parser.add_argument("--mono-rescale", action="store_true",
                        help="raw inputs: rescale each prior step to the ground-truth step (monocular VO)")
    parser.add_argument("--out", required=True, type=file_path_option, metavar="FILE",
                        help="corrected trajectory; OUT.mcap (an MCAP file), OUT.bag (a ROS 1 bag) or "
                        "--format rosbag2 (a ROS 2 bag folder): nav_msgs/Odometry per frame, the prior "
                        "beside it")
    parser.add_argument("--format", choices=(*WRITE_FORMATS, "rosbag2"), default=WRITE_FORMATS[0],
                        help="format of --out (a name ending in .mcap or .bag: that recording)")
    parser.add_argument("--rotation-only", action=argparse.BooleanOptionalAction, default=None,
                        help="apply only the rotation of the correction (default: the run's rotation_only)")
    parser.add_argument("--batch-size", type=int, metavar="N", help="inference batch (default: the run's)")
    parser.add_argument("--force", action="store_true",
                        help="apply the correction even when the acceptance test rejects it")
    parser.add_argument("--alpha", type=float, default=DEFAULT_ALPHA, metavar="P",
                        help="level of the one-sided acceptance tests on Δ")
    parser.add_argument("--no-mean-test", action="store_true",
                        help="do not test the correction's mean over the sequence on its own (the earlier "
                        "decision: a correction that passes as a whole is applied whole)")
    parser.add_argument("--decision", choices=tuple(MEAN_TESTS),
                        help=f"where and how the correction's mean is tested (docs/method.md §8; default: "
                        f"{DEFAULT_MEAN_TEST}): mean-at-network (at both sizes), mean-at-judge (with a "
                        "judge, at its size only), mean-at-judge-a05 (the same at level 0.05), "
                        "mean-noninferior (the same, passing unless it costs 5 %% of the whole's gain or "
                        "more)")
    parser.add_argument("--acceptance-depth", choices=ACCEPTANCE_DEPTHS,
                        help="depth Δ is measured with: sgbm, StereoSGBM on the cached pair (default for a "
                        "stereo run), or network, the network's own depth")
    judge = parser.add_mutually_exclusive_group()
    judge.add_argument("--judge", type=path_option, metavar="CACHE",
                       help="with --data: the same frames prepared at a larger size; the acceptance test is "
                       "measured there (StereoSGBM depth, no network) and picks the scale of the correction "
                       "(default: none, the test is measured at the cache's size)")
    judge.add_argument("--judge-size", type=image_size, metavar="HxW",
                       help="raw inputs: prepare the frames also at this size and judge there (default for a "
                       f"stereo_dpc run smaller than {JUDGE_SIZE[0]}x{JUDGE_SIZE[1]}: "
                       f"{JUDGE_SIZE[0]}x{JUDGE_SIZE[1]}, the papers' input size)")
    judge.add_argument("--no-judge", action="store_true",
                       help="raw inputs: measure the acceptance test at the run's image size only, without "
                       f"the default judge at {JUDGE_SIZE[0]}x{JUDGE_SIZE[1]}")
    parser.add_argument("--adapt", type=int, default=0, metavar="STEPS",
                        help="also fine-tune the network for STEPS steps on this sequence's own images (no "
                        "ground truth); its correction is applied only if it passes its test and beats the "
                        "network as trained on the kept-out pairs; the adapted network and its log go to "
                        "OUT's stem + '.adapted/'")
    parser.add_argument("--holdout-every", type=int, metavar="K",
                        help=f"with --adapt: every K-th frame pair (K >= {MIN_EVERY}) is kept out of "
                        "adaptation with every pair that touches its frames, for the test (default: "
                        f"{DEFAULT_EVERY})")
    parser.add_argument("--adapt-lr", type=float, metavar="LR",
                        help="with --adapt: learning rate (default: the run's)")
    parser.add_argument("--report", type=path_option, metavar="DIR",
                        help="write report.md (the acceptance test; with ground truth also the metrics, "
                        "CSV tables, plots, metrics.json) and summary.json")
    parser.add_argument("--verify", action="store_true",
                        help="check every byte of the caches read (--data, --judge; raw inputs: a --cache "
                        "reused) against the digests of their manifests (default: their sizes and a sample "
                        "of their bytes)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _error(message: str) -> int:
    print(f"dpc-jax correct: error: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    problem = arguments_problem(args)
    if problem is not None:
        return _error(problem)
    from dpc_jax.data.sequence_cache import load_cache

    # The cache is checked before JAX starts (the reader imports none) and the network is restored.
    try:
        checked = load_cache(args.data, verify=args.verify) if args.data is not None else None
    except (OSError, ValueError) as error:
        return _error(str(error))
    problem, judge = inputs_problem(args, checked)
    if problem is not None:
        return _error(problem)
    import_jax()
    # Orbax logs a warning per read-only checkpoint manager; they say nothing useful here.
    logging.getLogger("absl").setLevel(logging.ERROR)
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.outputs import write_corrected
    from dpc_jax.training.checkpoints import CheckpointError

    try:
        run_ = load_run(args.checkpoint, args.select)
    except CheckpointError as error:
        return _error(restore_problem(error.folder, error.__cause__ or error))
    except (OSError, ValueError, KeyError) as error:
        return _error(str(error))
    # The stack holds the temporary cache of raw inputs, removed before the outputs are written.
    with contextlib.ExitStack() as stack:
        try:
            done = _correct(args, run_, checked, judge, stack)
        except (OSError, ValueError, KeyError) as error:
            return _error(str(error))
    written = write_corrected(done, _outputs(args))
    # With the trajectory on standard output, the summary goes to stderr, so that what reads standard
    # output gets the trajectory alone.
    with contextlib.redirect_stdout(sys.stderr) if is_stdout(args.out) else contextlib.nullcontext():
        _print_summary(args, run_, done, written, judge)
    return 0


def _outputs(args: argparse.Namespace) -> CorrectionOutputs:
    """Where the outputs go; a recording written from raw inputs takes their stamps and frame names."""
    to = CorrectionOutputs(args.out, args.format, args.report, adapted_path(args.out) if args.adapt else None)
    if args.data is None and output_recording(args.out, args.format):
        source = open_recording(args, args.sequence or args.drive)
        to = dataclasses.replace(to, first_stamp=source.first_stamp,
                                 frame_ids=(source.world_frame, source.camera_frame))
    return to


def _correct(args: argparse.Namespace, run_: TrainedRun, checked: SequenceCache | None, judge: Judge,
             stack: contextlib.ExitStack) -> CorrectedSequence:
    """Correct the ``--data`` cache (``checked``) or the raw inputs, prepared at the run's image size
    (and at the ``judge``'s) into ``--cache`` or a temporary folder that ``stack`` removes."""
    from dpc_jax.correction.adapt import AdaptConfig
    from dpc_jax.correction.corrector import correct_sequence
    from dpc_jax.correction.raw_inputs import prepared_inputs
    from dpc_jax.data.sequence_cache import load_cache

    show = progress_mode(args.no_progress)
    cache, prior, judged = checked, args.prior, args.judge
    if cache is None:
        sequence = open_recording(args, args.sequence or args.drive).sequence
        prepared, judged = stack.enter_context(prepared_inputs(
            sequence, raw_prior(args), args.cache, size=run_.image_size, flow=run_.use_flow,
            judge_size=judge.size, remove_static=args.remove_static, mono_rescale=args.mono_rescale,
            frames=args.frames, prior_format=args.prior_format, ground_truth=args.gt, verify=args.verify,
            progress=show))
        cache, prior = load_cache(prepared), None
        problem = holdout_problem(len(cache), holdout_every(args), sequence.name) if args.adapt else None
        if problem is not None:
            raise ValueError(problem)
    how = (AdaptConfig(args.adapt, holdout_every=holdout_every(args), learning_rate=args.adapt_lr)
           if args.adapt else None)
    mean = MEAN_TESTS[args.decision or DEFAULT_MEAN_TEST]
    return correct_sequence(run_, cache, prior, adapt=how, prior_format=args.prior_format, progress=show,
                            rotation_only=args.rotation_only, batch_size=args.batch_size,
                            acceptance_depth=args.acceptance_depth, alpha=args.alpha, force=args.force,
                            mean_test=not args.no_mean_test, mean=mean, judge=judged)


def _print_summary(args: argparse.Namespace, run_: TrainedRun, done: CorrectedSequence, written: list[Path],
                   judge: Judge) -> None:
    """Print what was applied and written, the metrics against ground truth and the adaptation's outcome."""
    from dpc_jax.report.evaluation_report import format_table

    correction, adaptation = done.result, done.adaptation
    criterion = {"delta": "most negative validation Δ", "gradient": "best gradient loss",
                 "loop": "most loop closures", "last": "newest"}[args.select]
    if args.select == "delta" and not run_.improves_on_prior:
        # load_run fell back to the newest epoch: the run holds no best-Δ checkpoint.
        criterion = "the newest epoch, as the run holds no best-Δ checkpoint (best_delta/)"
    if correction.part == "none":
        print(f"{correction.name}: correction NOT applied, the prior is written unchanged; --force applies "
              "it anyway")
    print(f"{correction.name}: {correction.corrected.shape[0]} poses, correction applied: "
          f"{applied_words(correction.acceptance, correction.rotation_only)} (network: epoch {run_.epoch} of "
          f"{args.checkpoint}, {criterion}) -> {', '.join(map(str, written))}")
    print(f"acceptance tests: {correction.acceptance.reason}")
    if not correction.all_source_frames:
        where = f"frame numbers in {written[-1]}" if len(written) > 1 else "no frame list beside a stream"
        print(f"note: the trajectory holds {correction.frames.size} cached frames, not every source frame "
              f"({where})")
    if correction.evaluation is None:
        print("no ground truth: nothing to evaluate")
    else:
        sys.stdout.write(format_table(correction.evaluation))
    if adaptation is not None and correction.choice is not None:
        print(f"adapted: {args.adapt} steps in {adaptation.seconds / 60:.1f} min on {correction.name}'s own "
              f"pairs, {adaptation.held_out.size} kept out for the test -> {adapted_path(args.out)}")
        print(f"final: {correction.choice['final']} ({correction.choice['reason']})")
    if judge.note is not None:
        print(judge.note)
    if args.data is not None and output_recording(args.out, args.format):
        # A cache keeps frame times, not the recording's stamps and frame ids.
        world, camera = CorrectionOutputs(args.out).frame_ids
        print(f"note: {args.out} is stamped from 0 s at the cache's frame times, its odometry in frame "
              f"{world!r} of {camera!r} (a cache keeps no recording's stamps or frame ids); correct from the "
              "recording itself (--bag) to keep them")
    if args.report is not None:
        print(f"report: {args.report / 'report.md'}")
