"""What the experiment entry points share: priors, caches, folds, training, correction (the results
table: :mod:`dpc_jax.report.protocol_report`; the scripts' runner: ``dpc_jax.experiments.folds``).

An experiment is a list of *folds*. A fold trains one network (``dpc_jax.training.loop.train``) on its
training sequences, selects the epoch on its validation sequence without ground truth, corrects
the prior of each of its test sequences (``dpc_jax.correction.corrector``) and evaluates prior and corrected
trajectories against the ground truth. Everything lives under one work folder::

    WORKDIR/cache/NAME/             prepared sequences (dpc-jax prepare), reused when up to date
    WORKDIR/priors/NAME.txt         priors computed with our classical VO (when asked)
    WORKDIR/runs/FOLD/              training runs (checkpoints, metrics.csv, TensorBoard)
    WORKDIR/corrected/FOLD/NAME.txt corrected trajectories (KITTI pose text)
    WORKDIR/reports/FOLD/NAME/      evaluation reports (report.md, CSV, plots)
    WORKDIR/results.md, results.csv the results table: prior vs corrected per test sequence
    WORKDIR/results.json            the results (dpc_jax.results.fold.FoldResult), read by other studies
    WORKDIR/.dpc-jax-workdir        the marker: an experiment script made this folder

Every script claims its work folder before any work (:func:`claim_workdir`): the output rule of the
commands (``dpc_jax._io``) applied to it and to the script's other outputs. Runs resume: an
interrupted experiment re-run with the same arguments continues each training from its newest epoch
and redoes only what is missing.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dpc_jax._io import (
    EMPTY_PATH,
    claim_folder,
    claim_problem,
    foreign_folder_problem,
    nonempty_path,
    output_problem,
    overlap_problem,
)
from dpc_jax.eval.evaluation import Metrics
from dpc_jax.results.fold import Final, FoldResult
from dpc_jax.runtime.progress import Progress

if TYPE_CHECKING:
    from dpc_jax.results.correction import Correction

# Odometry sequence ↔ raw drive (docs/method.md §6): raw drives that *are* an odometry sequence must not be
# used for training when that sequence is tested.
ODOMETRY_DRIVES = {
    "00": "2011_10_03_drive_0027", "01": "2011_10_03_drive_0042", "02": "2011_10_03_drive_0034",
    "04": "2011_09_30_drive_0016", "05": "2011_09_30_drive_0018", "06": "2011_09_30_drive_0020",
    "07": "2011_09_30_drive_0027", "08": "2011_09_30_drive_0028", "09": "2011_09_30_drive_0033",
    "10": "2011_09_30_drive_0034",
}

# --smoke: one epoch of two steps of a two-block network on tiny images, to check an experiment runs end
# to end (every part of the method runs; the network's depth only changes how long it compiles), the pose
# head trained from the first step (a warm-up as long as the run would leave it untrained). Lists, as a
# config read back from its JSON has them, so that a run's stored config equals the one it was given.
SMOKE = {"preset": "small", "image_size": (32, 48), "batch_size": 2, "epochs": 1, "steps_per_epoch": 2,
         "pose_warmup_epochs": 0,
         "model": {"encoder_planes": [4, 8], "encoder_kernels": [3, 3], "decoder_planes": [8, 4],
                   "mask_source_block": 1, "depth_scales": 1, "fc_planes": [8, 8]}}


@dataclass(frozen=True)
class Fold:
    """One trained network: its name, training/validation/test sequences and TrainConfig overrides."""

    name: str
    train: tuple[str, ...]
    validation: str
    test: tuple[str, ...]


@dataclass(frozen=True)
class DriveSpec:
    """One KITTI raw drive of a cross-drive protocol: its libviso2 ``.mat`` (relative to the raw root)
    and the frames ``[start, end)`` its networks train and validate on."""

    libviso2: str
    train_frames: tuple[int, int]
    validation_frames: tuple[int, int]


@dataclass(frozen=True)
class FoldSpec:
    """One named fold of a KITTI odometry protocol: the prior kind (``stereo`` or ``mono``), its
    validation and test sequences (it trains on the others) and TrainConfig overrides."""

    prior: str
    validation: str
    test: tuple[str, ...]
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ExperimentProtocol:
    """``PROTOCOL`` of an experiment config file: what the entry point does around the training
    (``CONFIG``). Built like ``CONFIG`` (``dpc_jax.config.from_dict``): unknown keys are refused with
    the closest known one, values are type-checked. Each entry point reads the fields of its kind;
    the others keep their defaults.

    Every kind: ``select`` (epoch selection, ``dpc_jax.training.train_config.SELECTIONS``), ``acceptance``
    (False: apply every correction, the papers' way), ``mean_test`` (test the correction's mean over
    the sequence on its own, ``dpc_jax.correction.decision``; False: the earlier decision),
    ``decisions`` (also decide every correction by each of these, from the same networks, and report
    each final trajectory beside the protocol's own: :data:`EARLIER`, the earlier decision, or an option
    of where the mean is tested, ``dpc_jax.correction.decision.MEAN_TESTS``; ``docs/method.md`` §8),
    ``rotation_only`` (None: the network's own),
    ``adapt_steps`` / ``holdout_every`` (``dpc_jax.correction.adapt``), ``rectify_offset`` (rectify the
    network's images by the disparity offset our VO measures), ``judge_size`` (measure every acceptance
    test on frames prepared at this size; None: the network's). KITTI odometry: ``sequences``, ``validation``
    (validation sequence per test sequence, ``default`` for the others) or ``folds``. KITTI raw:
    ``date`` and one ``drive`` (its ``libviso2`` file, ``train_frames``, ``validation_frames``) or
    ``drives`` with the (test prior, training prior) pairs of ``tests``."""

    select: str = "gradient"
    acceptance: bool = True
    rotation_only: bool | None = None
    mean_test: bool = True
    decisions: tuple[str, ...] = ()
    adapt_steps: int = 0
    holdout_every: int = 5
    rectify_offset: bool = False
    judge_size: tuple[int, int] | None = None
    sequences: tuple[str, ...] = ()
    validation: dict[str, str] = field(default_factory=dict)
    folds: dict[str, FoldSpec] = field(default_factory=dict)
    date: str = ""
    drive: str = ""
    libviso2: str = ""
    train_frames: tuple[int, int] | None = None
    validation_frames: tuple[int, int] | None = None
    drives: dict[str, DriveSpec] = field(default_factory=dict)
    tests: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        from dpc_jax import config as config_lib
        from dpc_jax.training.train_config import SELECTIONS

        if self.select not in SELECTIONS:
            raise config_lib.ConfigError(f"select: {self.select!r} is not one of {', '.join(SELECTIONS)}")
        for name in self.decisions:
            decision_options(name)
        # Nested specs come as dicts from a config file: checked the same way, naming where they sit.
        for name, cls in (("folds", FoldSpec), ("drives", DriveSpec)):
            specs = {key: spec if isinstance(spec, cls) else config_lib.from_dict(cls, spec, f"{name}.{key}")
                     for key, spec in getattr(self, name).items()}
            object.__setattr__(self, name, specs)


# The earlier decision among a protocol's ``decisions``: whole parts only, the mean never tested apart.
EARLIER = "earlier"


def decision_options(name: str) -> dict[str, Any]:
    """The options of ``dpc_jax.correction.corrector.correct_cache`` that decide by the decision ``name``:
    :data:`EARLIER` or an option of ``dpc_jax.correction.decision.MEAN_TESTS`` (else ``ConfigError``)."""
    from dpc_jax import config as config_lib
    from dpc_jax.correction.decision import MEAN_TESTS

    if name != EARLIER and name not in MEAN_TESTS:
        raise config_lib.ConfigError(f"decisions: {name!r} is not one of {', '.join((EARLIER, *MEAN_TESTS))}")
    return {"mean_test": False} if name == EARLIER else {"mean_test": True, "mean": MEAN_TESTS[name]}


def load_protocol(path: str | Path) -> tuple[Any, ExperimentProtocol]:
    """``(CONFIG, PROTOCOL)`` of an experiment config file: a TrainConfig and an
    :class:`ExperimentProtocol` (each given as the dataclass or a dict of its fields)."""
    from dpc_jax import config as config_lib
    from dpc_jax.training.train_config import TrainConfig

    return (config_lib.load_file(path, TrainConfig),
            config_lib.load_file(path, ExperimentProtocol, name="PROTOCOL"))


def parse_overrides(pairs: Sequence[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings → dict; VALUE is JSON (``epochs=2``, ``image_size=[64,96]``) or a string."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--set {pair!r}: expected KEY=VALUE, e.g. epochs=2")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def fold_config(base: Any, fold: Fold, cache_root: Path, overrides: dict[str, Any]) -> Any:
    """The fold's TrainConfig: ``base`` with its split, the cache root and the overrides."""
    from dpc_jax import config as config_lib
    from dpc_jax.training.train_config import TrainConfig

    data = config_lib.to_dict(base)
    unknown = [k for k in overrides if k not in data]
    if unknown:
        raise config_lib.unknown_key_error(unknown[0], list(data), "--set")
    data.update(overrides)
    data.update(
        cache_root=str(cache_root), train_sequences=list(fold.train),
        validation_sequences=[fold.validation], test_sequences=list(fold.test),
    )
    return config_lib.from_dict(TrainConfig, data, where=f"fold {fold.name}")


# --------------------------------------------------------------------------- priors and caches


def find_prior(directory: Path, name: str, kind: str = "stereo") -> Path:
    """The prior file of sequence ``name`` in ``directory``.

    Tried in order: ``{kind}_{name}.mat`` (the ss-DPC-Net libviso2 release), ``{name}.mat``,
    ``{name}.txt`` (KITTI pose text), ``{name}.tum``.
    """
    candidates = [f"{kind}_{name}.mat", f"{name}.mat", f"{name}.txt", f"{name}.tum"]
    for candidate in candidates:
        if (directory / candidate).is_file():
            return directory / candidate
    raise FileNotFoundError(f"{directory}: no prior for sequence {name} (looked for {', '.join(candidates)})")


def vo_prior(sequence: Any, out: Path, progress: Progress) -> dict[str, Any]:
    """Our classical stereo VO over ``sequence``, started at its first GT pose, as KITTI text ``out``
    (recomputed when its inputs change; ``dpc_jax.vo.prior``); the run's summary with ``path``."""
    from dpc_jax.vo.prior import write_vo_prior as run

    return run(sequence, out, first_pose=None if sequence.poses is None else sequence.poses[0],
               progress=progress)


def prepare(
    sequence: Any, prior: Path | np.ndarray, cache_root: Path, config: Any, *, name: str | None = None,
    frames: tuple[int, int] | None = None, ground_truth: Path | None = None, mono_rescale: bool = False,
    disparity_offset: float = 0.0, progress: Progress = False,
) -> Path:
    """Prepare (or find up to date) a sequence's cache at the config's image size.

    Flow (with the augmentation flows for frame-skip/reversed pairs) is stored when the network
    reads flow. Static frames are kept: the trajectories are corrected and evaluated on every
    frame, like the published tables. ``disparity_offset``: rectify the network's images by this
    calibration residual (``dpc_jax.data.cache.prepare_sequence``).
    """
    from dpc_jax.data.cache import prepare_sequence

    flow = config.use_flow
    return prepare_sequence(
        sequence, prior, cache_root, size=config.resolved_image_size, flow=flow,
        flow_augment=flow and (config.frame_skip or config.reverse), mono_rescale=mono_rescale,
        frames=frames, ground_truth=ground_truth, name=name, disparity_offset=disparity_offset,
        progress=progress,
    )


def prepare_judge(
    sequence: Any, prior: Path | np.ndarray, cache_root: Path, config: Any,
    judge_size: tuple[int, int] | None, *, name: str, frames: tuple[int, int] | None = None,
    disparity_offset: float = 0.0, progress: Progress = False,
) -> Path | None:
    """The judge of cache ``name``: the same frames prepared at ``judge_size`` as ``NAME_judge``
    (:func:`prepare` with the config's image size replaced), where :func:`correct_and_evaluate` measures
    every acceptance test (its ``judge``); None without a ``judge_size``."""
    import dataclasses

    if judge_size is None:
        return None
    judge_config = dataclasses.replace(config, image_size=tuple(judge_size))
    return prepare(sequence, prior, cache_root, judge_config, name=f"{name}_judge", frames=frames,
                   disparity_offset=disparity_offset, progress=progress)


# --------------------------------------------------------------------------- train and correct


def train_fold(config: Any, workdir: Path, progress: Progress) -> dict[str, Any]:
    """Train (or resume, or find finished) the fold's run in ``workdir``."""
    from dpc_jax.training.loop import train

    return train(config, workdir, resume=True, progress=progress)


def _estimates(correction: Correction) -> dict[str, Metrics]:
    """The per-estimate summaries of ``correction``'s evaluation (ValueError without ground truth)."""
    if correction.evaluation is None:
        raise ValueError(f"{correction.name}: no ground truth; the experiment needs it to evaluate")
    return correction.evaluation.estimates


def correct_and_evaluate(
    fold: str, run_dir: Path, cache: Path, out_root: Path, protocol: ExperimentProtocol, *,
    select: str | None = None, prior_label: str = "prior", adapt_steps: int | None = None,
    judge: Path | None = None, progress: Progress = False,
) -> FoldResult:
    """Correct the prior of ``cache`` with the run's epoch by ``select`` (None: the protocol's) as the
    ``protocol`` says (its ``acceptance``, ``mean_test``, ``rotation_only``, ``adapt_steps`` unless
    ``adapt_steps`` is given, ``holdout_every``, ``decisions``): behind the acceptance test and,
    adapting, also with the network adapted to ``cache``'s own pairs (``dpc_jax.correction.adapt``, the
    ground truth unread); the final trajectory is chosen by ``dpc_jax.correction.corrector.choose``
    (the adapted correction only if it passes its test and beats the trained one, else the trained one
    if it passes, else the prior). ``judge``: the same frames prepared at a larger size, where every
    acceptance test is measured too (``dpc_jax.correction.corrector.correct_sequence``). The same
    proposals (and adapted network) are decided again by each of the protocol's ``decisions``
    (``dpc_jax.correction.corrector.decided_again``: nothing retrains), each final recorded in the
    result's ``decided``; with the acceptance test off every decision is the same forced one, and none
    is made. Writes the final trajectory, the reports and (adapting) the adapted network."""
    from dpc_jax.correction.corrector import correct_sequence, decided_again
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.outputs import CorrectionOutputs, write_corrected
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.report.correction_report import write_correction_report

    select = select or protocol.select
    run = load_run(run_dir, select)
    name = Path(cache).name
    steps = protocol.adapt_steps if adapt_steps is None else adapt_steps
    how = None
    if steps:
        from dpc_jax.correction.adapt import AdaptConfig

        how = AdaptConfig(steps, holdout_every=protocol.holdout_every)
    loaded, judged = load_cache(cache), None if judge is None else load_cache(judge)
    options: dict[str, Any] = {"rotation_only": protocol.rotation_only, "force": not protocol.acceptance,
                               "judge": judged}
    done = correct_sequence(run, loaded, adapt=how, mean_test=protocol.mean_test, progress=progress,
                            **options)
    final, correction, corrections = done.final, done.result, done.corrections
    decided = {}
    for decision in protocol.decisions if protocol.acceptance else ():
        again = decided_again(run, loaded, done=done, **options, **decision_options(decision))
        decided[decision] = Final(applied_label(again.final, again.result.acceptance),
                                  _estimates(again.result)["corrected"])
    if correction.evaluation is None:
        raise ValueError(f"{cache}: no ground truth; the experiment needs it to evaluate")
    write_corrected(done, CorrectionOutputs(out_root / "corrected" / fold / f"{name}.txt",
                                            adapted=out_root / "adapted" / fold / name))
    for label, c in corrections.items():
        write_correction_report(
            out_root / "reports" / fold / name / label, c,
            f"{fold}: {name} ({prior_label} prior, epoch {run.epoch} by {select}, network {label})",
        )
    stages = {label: _estimates(c)["network"] for label, c in corrections.items()}
    decisions = {label: "forced" if c.acceptance.forced else c.acceptance.part
                 for label, c in corrections.items()}
    estimates = correction.evaluation.estimates
    return FoldResult(fold, name, prior_label, run.epoch, select, int(correction.corrected.shape[0]),
                      {"prior": estimates["prior"], "corrected": estimates["corrected"]},
                      applied_label(final, correction.acceptance), stages, decisions, decided)


def applied_label(final: str, acceptance: Any) -> str:
    """The results table's ``applied``: ``prior``, or the network whose correction the final trajectory
    holds with what its acceptance test let through (``trained (full)``), or with the test off what was
    applied regardless (``trained (full, test off: forced)``), which no test let through."""
    if final == "prior":
        return final
    return f"{final} ({acceptance.part}{', test off: forced' if acceptance.forced else ''})"


# --------------------------------------------------------------------------- entry-point plumbing


WORKDIR_MARKER = ".dpc-jax-workdir"
# An experiment's outputs and inputs, as (option, path) pairs; a None path was not given.
Named = tuple[str, str | os.PathLike[str] | None]


def path_argument(text: str) -> Path:
    """argparse type of the scripts' path options: ``Path(text)``, unless ``text`` is empty (``Path("")``
    is the current folder, where an unset shell variable would send the outputs)."""
    try:
        return Path(nonempty_path(text))
    except ValueError:
        raise argparse.ArgumentTypeError(EMPTY_PATH) from None


def claim_workdir(
    workdir: str | os.PathLike[str] | None, inputs: Sequence[Named] = (), *, option: str = "--workdir",
    files: Sequence[Named] = (), owner: str | None = None, shares: Sequence[str] = (),
) -> Path | None:
    """Check an experiment script's outputs by the commands' rule (``dpc_jax._io``), then make its work
    folder and mark it as one: call it once the inputs are checked, before any work.

    ``workdir``: the folder the script writes into (None: it has none), named ``option`` in messages;
    ``inputs``: ``(option, path)`` of every file or folder the script reads (data roots, prior folders,
    the config, other work folders); ``files``: ``(option, path)`` of file outputs outside the work folder
    (``--json``, ``--results-page``). Raises ``ValueError`` (one line, naming the option and the path) for
    an empty path, an output that cannot be written, an output that is, contains or lies inside an input
    or another output (after links, ``..`` and hard links), and a work folder that holds files but was not
    made by an experiment script (no :data:`WORKDIR_MARKER` in it; a work folder of an earlier version is
    taken by creating that empty file), and a work folder whose marker names other scripts than ``owner``
    (the script claiming it) and the scripts it ``shares`` a folder with (``dpc_jax._io.claim_problem``).
    Then creates the work folder with its marker, ``owner`` named in it, so that a rerun, or another
    script sharing the folder, is allowed. Returns ``workdir`` as a ``Path`` (None without one).
    """
    outputs = [(option, workdir), *files]
    for name, path in outputs:
        if path is not None and not os.fspath(path):
            raise ValueError(f"{name}: {EMPTY_PATH}")
    problem = (output_problem(workdir, option, folder=True)
               or next(filter(None, (output_problem(path, name) for name, path in files)), None)
               or overlap_problem(list(inputs), outputs))
    if problem is None and workdir is not None:
        problem = foreign_folder_problem(workdir, f"{option} {workdir}", marker=WORKDIR_MARKER,
                                         made_by="the work folder of an experiment script")
        if problem is not None:
            problem += f" (a work folder of an earlier version: create the empty file {WORKDIR_MARKER} in it)"
        elif owner is not None:
            problem = claim_problem(workdir, f"{option} {workdir}", marker=WORKDIR_MARKER, owner=owner,
                                    shares=shares)
    if problem is not None:
        raise ValueError(problem)
    if workdir is None:
        return None
    claim_folder(workdir, marker=WORKDIR_MARKER, owner=owner,
                 about="a work folder of dpc_jax's experiment scripts (experiments/), those below; they "
                 "write into it and resume from it")
    return Path(workdir)


def priors_argument(text: str) -> str:
    """argparse type of the protocols' ``--priors DIR|vo``: ``vo`` (our stereo VO) or a folder, never both
    at once: with a folder ``vo`` in the current folder (the README's chain makes one) the word is
    ambiguous, and taking either meaning silently would run the experiment on priors the user did not
    mean."""
    path = path_argument(text)
    if text == "vo" and path.exists():
        raise argparse.ArgumentTypeError(
            "'vo' means our stereo VO, and there is a folder ./vo here: give ./vo for the folder of priors, "
            "or run from another folder for our VO")
    return text


def prior_source(priors: str, directory_kind: str, sequence: Any, workdir: Path, progress: Progress) -> Path:
    """The prior file of ``sequence``: ``priors`` = a folder (see :func:`find_prior`) or ``vo`` (ours)."""
    if priors == "vo":
        if directory_kind != "stereo":
            raise ValueError(f"--priors vo gives stereo priors only; {directory_kind} priors need a folder")
        return Path(vo_prior(sequence, workdir / "priors" / f"{sequence.name}.txt", progress)["path"])
    return find_prior(Path(priors), sequence.name, directory_kind)
