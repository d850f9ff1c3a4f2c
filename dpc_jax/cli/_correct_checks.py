"""What ``dpc-jax correct`` refuses before JAX starts: its options, input paths and outputs
(:func:`arguments_problem`), then its inputs against the run's stored config and the judge it takes
(:func:`inputs_problem`). Each problem is one line; the checks of the library are called where it has
them (the judge, the hold-out split, priors and pose files, the cache folders to replace)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import (
    beside_problem,
    foreign_files_problem,
    foreign_folder_problem,
    is_stream,
    output_problem,
    overlap_problem,
    stdout_problem,
)
from dpc_jax.cli._common import (
    cache_folder_problem,
    frames_problem,
    input_problem,
    mean_options_problem,
    poses_problem,
    stored_config,
)
from dpc_jax.cli._source import open_recording, source_inputs, source_problem
from dpc_jax.correction.judge import Judge, JudgeRequest, judge_frames_problem, judge_policy
from dpc_jax.correction.outputs import REPORT_FILES, REPORT_WRITER, adapted_path
from dpc_jax.correction.raw_inputs import cache_folders_problem
from dpc_jax.data.holdout import DEFAULT_EVERY, MIN_EVERY, holdout_problem
from dpc_jax.data.poses_io import frames_path
from dpc_jax.sources.odometry_out import CORRECTED, PRIOR, recording_kind

if TYPE_CHECKING:
    import numpy as np

    from dpc_jax.data.sequence_cache import SequenceCache
    from dpc_jax.training.train_config import TrainConfig


def _out_problem(args: argparse.Namespace) -> str | None:
    """Why ``--out`` cannot take the trajectory: a file's problem, or for ``--format rosbag2`` a folder's,
    which may be replaced only when it is a bag this command wrote (its topics /dpc/odometry, /dpc/prior)."""
    if args.format != "rosbag2":
        return output_problem(args.out, "--out")
    problem = output_problem(args.out, "--out", folder=True)
    out = Path(args.out)
    if problem is not None or not out.is_dir() or not any(out.iterdir()):
        return problem
    metadata = out / "metadata.yaml"
    written = metadata.is_file() and all(f"name: {topic}" in metadata.read_text(errors="replace")
                                         for topic in (CORRECTED, PRIOR))
    if written:
        return None
    return (f"--out {args.out}: holds files but is not a ROS 2 bag that `correct` wrote (its metadata.yaml "
            f"naming {CORRECTED} and {PRIOR}), and this command would write over it; move it away or choose "
            "another path")


def arguments_problem(args: argparse.Namespace) -> str | None:
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
    if args.no_mean_test and args.decision is not None:
        return mean_options_problem(args.decision)
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
               or _out_problem(args) or output_problem(args.report, "--report", folder=True)
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
            or poses_problem(sequence, raw_prior(args), args.prior_format, args.frames, args.gt))


def raw_prior(args: argparse.Namespace) -> str | np.ndarray:
    """The prior of the raw inputs: ``--prior FILE``, or the recording's ``--prior-topic``."""
    if args.prior is not None:
        return str(args.prior)
    prior = open_recording(args, None).prior
    assert prior is not None, "arguments_problem asks for a prior"
    return prior


def _cache_folders_problem(args: argparse.Namespace, *, judged: bool) -> str | None:
    """Why a folder that preparing the raw inputs into ``--cache`` would replace is not a cache, or None
    (the sequence opened for its name, no JAX)."""
    try:
        name = open_recording(args, args.sequence or args.drive).sequence.name
    except (OSError, ValueError, KeyError) as error:
        return str(error)
    return cache_folders_problem(args.cache, name, judged, f"--cache {args.cache}")


def inputs_problem(args: argparse.Namespace, checked: SequenceCache | None) -> tuple[str | None, Judge]:
    """The first option or input that does not fit the run's stored config (its method, image size and
    flow) or its judge, or None, and the judge (:func:`~dpc_jax.correction.judge.judge_policy`); read
    without JAX. ``checked``: the ``--data`` cache, loaded (None: raw inputs, prepared later at the run's
    size; the hold-out split of ``--adapt`` is checked on them once prepared)."""
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
    problem = judge.problem or (_cache_problem(args, config, checked) if checked is not None else None)
    if problem is None and checked is not None and args.adapt:
        problem = holdout_problem(len(checked), holdout_every(args), checked.path)
    if problem is None and judge.size is not None and args.cache is not None:
        problem = _cache_folders_problem(args, judged=True)
    return problem, judge


def holdout_every(args: argparse.Namespace) -> int:
    """``--holdout-every``, or its default when not given (the option has none, so that giving it
    without ``--adapt`` can be refused)."""
    return DEFAULT_EVERY if args.holdout_every is None else int(args.holdout_every)


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
