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

from dpc_jax._io import (
    beside_problem,
    foreign_files_problem,
    foreign_folder_problem,
    is_stdout,
    is_stream,
    output_problem,
    overlap_problem,
    stdout_problem,
)
from dpc_jax.cli._common import (
    Formatter,
    cache_folder_problem,
    file_path_option,
    frame_range,
    frames_problem,
    image_size,
    import_jax,
    input_problem,
    path_option,
    path_text,
    poses_problem,
    restore_problem,
    stored_config,
)
from dpc_jax.cli._source import add_source_arguments, open_recording, source_inputs, source_problem
from dpc_jax.correction.acceptance import DEFAULT_ALPHA
from dpc_jax.correction.decision import DEFAULT_MEAN_TEST, MEAN_TESTS
from dpc_jax.correction.judge import JUDGE_SIZE, Judge, JudgeRequest, judge_frames_problem, judge_policy
from dpc_jax.correction.outputs import REPORT_FILES, REPORT_WRITER, CorrectionOutputs, adapted_path
from dpc_jax.correction.raw_inputs import cache_folders_problem
from dpc_jax.data.holdout import DEFAULT_EVERY, MIN_EVERY, holdout_problem
from dpc_jax.data.poses_io import FORMATS, WRITE_FORMATS, frames_path
from dpc_jax.report.correction_report import applied_words
from dpc_jax.runtime.progress import progress_mode
from dpc_jax.sources.odometry_out import recording_kind
from dpc_jax.training.train_config import ACCEPTANCE_DEPTHS, DEFAULT_SELECTION, SELECTIONS

if TYPE_CHECKING:
    import numpy as np

    from dpc_jax.correction.corrector import CorrectedSequence
    from dpc_jax.correction.inference import TrainedRun
    from dpc_jax.data.sequence_cache import SequenceCache
    from dpc_jax.training.train_config import TrainConfig

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
    parser.add_argument("--decision", choices=tuple(MEAN_TESTS), default=DEFAULT_MEAN_TEST,
                        help="where and how the correction's mean is tested (docs/method.md §8): "
                        "mean-at-network (at both sizes), mean-at-judge (with a judge, at its "
                        "size only), mean-at-judge-a05 (the same at level 0.05), mean-noninferior (the same, "
                        "passing unless it costs 5 %% of the whole's gain or more)")
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


def _check_arguments(args: argparse.Namespace) -> str | None:
    """The first problem of the options, input paths and outputs (all checked without JAX), or None."""
    raw_only = {"--gt": args.gt, "--cache": args.cache, "--frames": args.frames,
                "--remove-static": args.remove_static or None, "--mono-rescale": args.mono_rescale or None,
                "--grey": args.grey or None}
    problem = source_problem(args)
    if problem is not None:
        return problem
    if args.data is not None:
        given = [name for name, value in raw_only.items() if value is not None]
        if given or args.sequence or args.date or args.drive:
            extra = given + [o for o, v in (("--sequence", args.sequence), ("--date", args.date),
                                            ("--drive", args.drive)) if v]
            return (f"{', '.join(extra)} only apply to raw inputs (--kitti-odometry/--kitti-raw/--bag), not "
                    "--data")
        problem = cache_folder_problem(args.data, "--data")
        if problem is not None:
            return problem
        if args.no_judge:
            return ("--no-judge goes with raw inputs (--kitti-odometry/--kitti-raw), whose default judge it "
                    "turns off; a --data cache is judged only with --judge CACHE")
    if args.data is None and args.prior is None and args.prior_topic is None:
        return ("--prior FILE is required with raw inputs (the VO estimate to correct; a recording: or "
                "--prior-topic TOPIC)")
    if args.prior is not None and args.prior_topic is not None:
        return "--prior and --prior-topic: give one prior"
    if args.format == "tum" and recording_kind(args.out) is not None:
        return f"--format tum: --out {args.out} is named as a recording; give a text file's name"
    if args.batch_size is not None and args.batch_size < 1:
        return f"--batch-size must be >= 1, got {args.batch_size}"
    if not 0.0 < args.alpha < 1.0:
        return f"--alpha must be in (0, 1), got {args.alpha}"
    adapt_options = (("--holdout-every", args.holdout_every), ("--adapt-lr", args.adapt_lr))
    adapt_only = [f"{option} {value}" for option, value in adapt_options if value is not None]
    if adapt_only and not args.adapt:
        return (f"{', '.join(adapt_only)}: only used with --adapt STEPS (fine-tuning on the sequence), "
                "which is not given")
    if args.adapt < 0:
        return f"--adapt {args.adapt}: expected 0 (no adaptation) or more steps"
    if args.holdout_every is not None and args.holdout_every < MIN_EVERY:
        return f"--holdout-every {args.holdout_every}: expected {MIN_EVERY} or more"
    if args.judge is not None and args.data is None:
        return "--judge CACHE goes with --data (raw inputs: --judge-size HxW)"
    if args.judge_size is not None and args.data is not None:
        return "--judge-size goes with raw inputs (with --data: --judge CACHE)"
    if args.adapt_lr is not None and not args.adapt_lr > 0:
        return f"--adapt-lr must be > 0, got {args.adapt_lr}"
    adapted = adapted_path(args.out) if args.adapt else None
    problem = (input_problem(args.judge, "--judge", folder=True)
               or input_problem(args.prior, "--prior") or input_problem(args.gt, "--gt")
               or output_problem(args.out, "--out") or output_problem(args.report, "--report", folder=True)
               or output_problem(args.cache, "--cache", folder=True)
               or output_problem(adapted, "--adapt", folder=True))
    if problem is not None:
        return problem
    if args.adapt and is_stream(args.out):
        return (f"--adapt: the adapted network goes beside --out (OUT's stem + '.adapted/'), and --out "
                f"{args.out} is a stream; give --out a file")
    inputs = [("--checkpoint", args.checkpoint), ("--data", args.data), ("--judge", args.judge),
              *source_inputs(args), ("--prior", args.prior), ("--gt", args.gt)]
    outputs = [("--out", args.out), ("--report", args.report), ("--cache", args.cache), ("--adapt", adapted)]
    problem = (overlap_problem(inputs, outputs)
               or stdout_problem(inputs)
               or (foreign_files_problem(args.report, REPORT_FILES, f"--report {args.report}",
                                         writer=REPORT_WRITER) if args.report is not None else None)
               or (beside_problem([(f"--out {args.out} (its frame list)", frames_path(args.out))])
                   if not is_stream(args.out) else None)
               or (foreign_folder_problem(adapted, f"--adapt (beside --out {args.out})",
                                          marker="checkpoints/config.json",
                                          made_by="an adapted network (`correct --adapt`)")
                   if adapted is not None else None))
    if problem is None and args.cache is not None:
        problem = _cache_folders_problem(args, judged=args.judge_size is not None)
    if problem is None:
        try:
            stored_config(args.checkpoint, "--checkpoint")
        except ValueError as error:
            problem = str(error)
    return problem or (_raw_inputs_problem(args) if args.data is None else None)


def _raw_inputs_problem(args: argparse.Namespace) -> str | None:
    """Why ``--frames``, ``--prior`` or ``--gt`` do not fit the raw inputs' sequence (its frame count, one
    rigid pose per frame), or None: read before JAX starts, so that such a mistake costs no JAX start-up."""
    try:
        sequence = open_recording(args, args.sequence or args.drive).sequence
    except (OSError, ValueError, KeyError) as error:
        return str(error)
    return (frames_problem(args.frames, len(sequence), sequence.name)
            or poses_problem(sequence, _prior(args), args.prior_format, args.frames, args.gt))


def _prior(args: argparse.Namespace) -> str | np.ndarray:
    """The prior of the raw inputs: ``--prior FILE``, or the recording's ``--prior-topic``."""
    if args.prior is not None:
        return str(args.prior)
    prior = open_recording(args, None).prior
    assert prior is not None, "_check_arguments asks for a prior"
    return prior


def _cache_folders_problem(args: argparse.Namespace, *, judged: bool) -> str | None:
    """Why a folder that preparing the raw inputs into ``--cache`` would replace is not a cache, or None
    (the sequence opened for its name, no JAX)."""
    try:
        name = open_recording(args, args.sequence or args.drive).sequence.name
    except (OSError, ValueError, KeyError) as error:
        return str(error)
    return cache_folders_problem(args.cache, name, judged, f"--cache {args.cache}")


def _run_problem(args: argparse.Namespace, checked: SequenceCache | None) -> tuple[str | None, Judge]:
    """The first option or input that does not fit the run's stored config (its method, image size and
    flow), or None, and the judge (:func:`~dpc_jax.correction.judge.judge_policy`); read without JAX.
    ``checked``: the ``--data`` cache, loaded (None: raw inputs, prepared later at the run's size)."""
    try:
        config = stored_config(args.checkpoint, "--checkpoint")
        if config.method != "stereo_dpc" and args.acceptance_depth == "sgbm":
            return (f"--acceptance-depth sgbm: StereoSGBM depth needs a stereo run (stereo_dpc); the run "
                    f"{args.checkpoint} is {config.method}, which has no stereo pair"), Judge()
        source = None if checked is not None else open_recording(args, args.sequence or args.drive).sequence
    except (OSError, ValueError, KeyError) as error:
        return str(error), Judge()
    run_size = (int(config.resolved_image_size[0]), int(config.resolved_image_size[1]))
    images = None if source is None else (int(source.image_size[0]), int(source.image_size[1]))
    request = JudgeRequest(size=args.judge_size, cache=args.judge, off=args.no_judge, force=args.force)
    judge = judge_policy(config.method, run_size, images, request, f"the run {args.checkpoint}")
    if judge.problem is not None or checked is None:
        return judge.problem, judge
    return _cache_problem(args, config, checked), judge


def _cache_problem(args: argparse.Namespace, config: TrainConfig, checked: SequenceCache) -> str | None:
    """Why the ``--data`` cache (``checked``), its ``--judge`` or the ``--prior`` replacing its own do not
    fit the run's ``config`` or ``--format``, or None."""
    import numpy as np

    from dpc_jax.data.priors import prior_for_cache
    from dpc_jax.data.sequence_cache import load_cache

    h, w = config.resolved_image_size
    if checked.image_size != (h, w):
        return (f"--data {args.data}: images are {checked.image_size[0]}x{checked.image_size[1]}, but the "
                f"run {args.checkpoint} was trained at {h}x{w}; prepare the sequence with --size {h}x{w}")
    if config.use_flow and "forward" not in checked.flows:
        return (f"--data {args.data}: no forward flow in the cache, which the network of {args.checkpoint} "
                f"({config.method}) reads; prepare it with `dpc-jax prepare ... --flow`")
    if args.judge is not None:
        try:
            judged = load_cache(args.judge, verify=args.verify)
        except (OSError, ValueError) as error:
            return f"--judge {error}"
        problem = judge_frames_problem(judged, checked, f"--judge {args.judge}", f"--data {args.data}")
        if problem is not None:
            return problem
    if args.prior is not None:
        try:
            prior_for_cache(checked, args.prior, args.prior_format)
        except (OSError, ValueError) as error:
            return f"--prior {error}"
    back = np.flatnonzero(np.diff(np.asarray(checked.times)) <= 0)
    if args.format == "tum" and back.size:  # write_tum refuses them, as read_tum would
        k = int(back[0]) + 1
        return (f"--format tum: the frame times of --data {args.data} do not increase at cached frame {k} "
                f"({checked.times[k]:.15g} s after {checked.times[k - 1]:.15g} s); a TUM file needs "
                "increasing times: use --format kitti")
    return None


def run(args: argparse.Namespace) -> int:
    problem = _check_arguments(args)
    if problem is not None:
        return _error(problem)
    from dpc_jax.data.sequence_cache import load_cache

    # The cache is checked before JAX starts (the reader imports none) and the network is restored.
    try:
        checked = load_cache(args.data, verify=args.verify) if args.data is not None else None
    except (OSError, ValueError) as error:
        return _error(str(error))
    problem, judge = _run_problem(args, checked)
    if problem is None and checked is not None and args.adapt:
        problem = holdout_problem(len(checked), _holdout_every(args), checked.path)
    if problem is None and judge.size is not None and args.cache is not None:
        problem = _cache_folders_problem(args, judged=True)
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
    if args.data is None and (recording_kind(args.out) or args.format == "rosbag2"):
        source = open_recording(args, args.sequence or args.drive)
        to = dataclasses.replace(to, first_stamp=source.first_stamp,
                                 frame_ids=(source.world_frame, source.camera_frame))
    return to


def _holdout_every(args: argparse.Namespace) -> int:
    """``--holdout-every``, or its default when not given (the option has none, so that giving it
    without ``--adapt`` can be refused)."""
    return DEFAULT_EVERY if args.holdout_every is None else int(args.holdout_every)


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
            sequence, _prior(args), args.cache, size=run_.image_size, flow=run_.use_flow,
            judge_size=judge.size, remove_static=args.remove_static, mono_rescale=args.mono_rescale,
            frames=args.frames, prior_format=args.prior_format, ground_truth=args.gt, verify=args.verify,
            progress=show))
        cache, prior = load_cache(prepared), None
        problem = holdout_problem(len(cache), _holdout_every(args), sequence.name) if args.adapt else None
        if problem is not None:
            raise ValueError(problem)
    how = (AdaptConfig(args.adapt, holdout_every=_holdout_every(args), learning_rate=args.adapt_lr)
           if args.adapt else None)
    return correct_sequence(run_, cache, prior, adapt=how, prior_format=args.prior_format, progress=show,
                            rotation_only=args.rotation_only, batch_size=args.batch_size,
                            acceptance_depth=args.acceptance_depth, alpha=args.alpha, force=args.force,
                            mean_test=not args.no_mean_test, mean=MEAN_TESTS[args.decision], judge=judged)


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
    if correction.applied == "none":
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
    if args.report is not None:
        print(f"report: {args.report / 'report.md'}")
