"""The options of the live correction, shared by ``dpc-jax live`` and ``dpc-jax vo --correct``: their
arguments, their checks before JAX starts, the corrector they build and the files named after ``--out``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax.cli._common import image_size, input_problem, mean_options_problem
from dpc_jax.correction.acceptance import DEFAULT_ALPHA
from dpc_jax.correction.decision import DEFAULT_MEAN_TEST, MEAN_TESTS
from dpc_jax.correction.judge import JUDGE_SIZE, Judge, JudgeRequest, judge_policy
from dpc_jax.correction.stream import MIN_RATE_HZ, OWN_TIMES
from dpc_jax.sources.odometry_out import recording_kind
from dpc_jax.training.train_config import SELECTIONS

if TYPE_CHECKING:
    from dpc_jax.correction.live import LiveCorrector
    from dpc_jax.data.calibration import Calibration


def add_correction_arguments(parser: argparse.ArgumentParser, *, requires: str | None) -> None:
    """The options of the live correction. ``requires``: the option they need (``--correct``), or None
    (always in effect); their defaults are None, so that one given without it can be named."""
    but = "" if requires is None else f"with {requires}: "
    parser.add_argument("--select", choices=tuple(SELECTIONS),
                        help=f"{but}the run's epoch: most negative validation Δ (default; the newest epoch "
                        "when none beats no correction), best validation gradient loss, most loop closures, "
                        "or the newest")
    parser.add_argument("--rotation-only", action=argparse.BooleanOptionalAction, default=None,
                        help=f"{but}apply only the rotation of the correction (default: the run's "
                        "rotation_only)")
    parser.add_argument("--force", action="store_true",
                        help=f"{but}apply the correction to every pair, whatever the sequential tests say")
    parser.add_argument("--alpha", type=float, metavar="P",
                        help=f"{but}level of the sequential tests on Δ (default: {DEFAULT_ALPHA:g}): the "
                        "chance that a correction that does not help is ever accepted, however long the run")
    parser.add_argument("--no-mean-test", action="store_true",
                        help=f"{but}do not test the correction's running mean apart (whole parts only)")
    parser.add_argument("--decision", choices=tuple(MEAN_TESTS),
                        help=f"{but}where and how the correction's mean is tested, as `correct --decision` "
                        f"(docs/method.md §8; default: {DEFAULT_MEAN_TEST})")
    judge = parser.add_mutually_exclusive_group()
    judge.add_argument("--judge-size", type=image_size, metavar="HxW",
                       help=f"{but}a part of the correction is applied only once its sequential test passes "
                       "also on the frames prepared at this size (StereoSGBM depth, no network; default for "
                       f"a stereo_dpc run: {JUDGE_SIZE[0]}x{JUDGE_SIZE[1]}, no larger than the camera's "
                       "images, as `correct`); the judge works only while a part is accepted: about 90 ms a "
                       "frame at 240x376 and 20 ms at 120x188 on two CPU cores")
    judge.add_argument("--no-judge", action="store_true",
                       help=f"{but}decide on the network's image size alone (no judge)")
    parser.add_argument("--realtime", type=float, nargs="?", const=OWN_TIMES, metavar="HZ",
                        help=f"{but}replay at the camera's rate: frame k is due k/HZ s after the first; "
                        "without HZ at the frames' own times (a recording's header stamps); report the "
                        "frames whose pose is written after the next one is due. The tests' measurement "
                        "then runs behind the poses: a pose is corrected with the decision of the pairs "
                        "measured before it, and a pair that comes while the measurement is busy is not "
                        "measured")


def correction_problem(args: argparse.Namespace, run_option: str, run: Path | None) -> str | None:
    """Why the live correction's options do not hold (``run``: the run given to ``run_option``, None:
    not given, in which case none of the options may be), or None. Standard library only."""
    given = [name for name, value in (("--select", args.select), ("--rotation-only", args.rotation_only),
                                      ("--force", args.force or None), ("--alpha", args.alpha),
                                      ("--no-mean-test", args.no_mean_test or None),
                                      ("--decision", args.decision),
                                      ("--judge-size", args.judge_size),
                                      ("--no-judge", args.no_judge or None),
                                      ("--realtime", args.realtime)) if value is not None]
    if run is None:
        if given:
            return (f"{', '.join(given)}: only used with {run_option} RUN (the live correction), which is "
                    "not given")
        return None
    if args.no_mean_test and args.decision is not None:
        return mean_options_problem(args.decision)
    if args.alpha is not None and not 0.0 < args.alpha < 1.0:
        return f"--alpha {args.alpha}: expected a level in (0, 1), such as {DEFAULT_ALPHA:g}"
    if args.realtime not in (None, OWN_TIMES) and not (math.isfinite(args.realtime)
                                                       and args.realtime >= MIN_RATE_HZ):
        return (f"--realtime {args.realtime}: expected the camera's rate in frames per second (> 0, at least "
                f"one frame an hour: {MIN_RATE_HZ:.3g}), such as 10")
    problem = input_problem(run, run_option, folder=True)
    if problem is None and not (run / "checkpoints" / "config.json").is_file():
        problem = (f"{run_option} {run}: not a training run (expected "
                   f"{run / 'checkpoints' / 'config.json'}, written by `dpc-jax train`)")
    return problem


def run_problem(args: argparse.Namespace, run: Path, run_option: str, images: tuple[int, int],
                where: str) -> tuple[str | None, Judge]:
    """Why the run's network cannot take the ``images`` (``(H, W)`` px) of ``where``, or None: its
    stored config unreadable, or its input larger than the images in either dimension (a frame is
    resized to the network's size as ``prepare`` does, which never upsamples), or the judge asked of it
    refused; and the judge of the options (``dpc_jax.correction.judge.judge_policy``, as ``correct``'s).
    Read without JAX."""
    from dpc_jax import config as config_lib
    from dpc_jax.training.train_config import TrainConfig

    try:
        config = config_lib.load_file(run / "checkpoints" / "config.json", TrainConfig)
    except (OSError, ValueError) as error:
        return f"{run_option} {run}: {error}", Judge()
    h, w = (int(v) for v in config.resolved_image_size)
    if h > images[0] or w > images[1]:
        size = f"{images[0]}x{images[1]}"
        return (f"{run_option} {run}: the network takes {h}x{w} images, larger than the {size} images of "
                f"{where}; a frame is never upsampled: use a run trained at {size} or smaller"), Judge()
    request = JudgeRequest(size=args.judge_size, off=args.no_judge, force=args.force)
    judge = judge_policy(config.method, (h, w), images, request, f"{run_option} {run}")
    return judge.problem, judge


def corrector(args: argparse.Namespace, run: Path, calibration: Calibration, judge: Judge, *,
              disparity_offset: float = 0.0) -> LiveCorrector:
    """The live corrector of the options and the ``judge`` (:func:`run_problem`; JAX imported, the network
    restored and compiled), its first pose the prior's first; the corrector's own defaults for the
    options not given; under ``--realtime`` measured behind the poses.
    ``CheckpointError`` for a run that cannot be restored."""
    import logging

    from dpc_jax.correction.live import LiveCorrector

    # Orbax logs a warning per read-only checkpoint manager; they say nothing useful here.
    logging.getLogger("absl").setLevel(logging.ERROR)
    given = {name: value for name, value in (("select", args.select), ("alpha", args.alpha))
             if value is not None}
    # Under a pace the tests' measurement runs behind the poses and skips the pairs it cannot keep up with,
    # so that every pose can meet its deadline, and every program is compiled before the first frame
    # (dpc_jax.correction.live); replayed as fast as possible, the decision is the synchronous one and a
    # measurement program is compiled when a pair first needs it.
    paced = args.realtime is not None
    return LiveCorrector(run, calibration, rotation_only=args.rotation_only, mean_test=not args.no_mean_test,
                         mean=MEAN_TESTS[args.decision or DEFAULT_MEAN_TEST],
                         force=args.force, disparity_offset=disparity_offset, judge_size=judge.size,
                         behind=paced, skip=paced, ahead=paced, **given)


def text_output_problem(path: Path | None, option: str, command: str) -> str | None:
    """Why ``path`` cannot take a pose text output: a name of a recording (``.mcap``, ``.bag``), which would
    receive KITTI pose rows no player opens; else None."""
    if path is None or recording_kind(path) is None:
        return None
    return (f"{option} {path}: {command} writes KITTI pose text, not a recording; name a .txt file (a "
            "recording of corrected odometry is what `dpc-jax correct --out OUT.mcap` writes)")


def beside_files(out: Path, csv: Path | None, csv_path: Path | None,
                 *summaries: Path | None) -> list[tuple[str, Path | None]]:
    """The live outputs named after ``out`` rather than by the user (the CSV when ``--csv`` is not given,
    the ``.json`` summaries), as ``(label, path)`` for ``dpc_jax._io.beside_problem``."""
    named = [(f"--out {out} (its .json summary)", path) for path in summaries]
    return [*([(f"--out {out} (its CSV; --csv names another)", csv_path)] if csv is None else []), *named]
