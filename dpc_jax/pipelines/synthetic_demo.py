"""The synthetic end-to-end demo (``dpc-jax demo``): render, VO, train, correct, adapt, report.

:func:`run_demo` chains the library on data it makes itself, so it runs on a fresh machine:

1. **Render** (``dpc_jax.synth``) the training, validation and test sequences in the KITTI odometry
   layout under ``OUT/data`` at 240×376, with the nuisances a real rig has: moving cars, a slow
   illumination drift, image noise and a stereo calibration residual: the right camera's
   principal point 0.8 px off the written calibration (2.6 px at KITTI's 1242 px width, about twice
   the residual of KITTI's colour pair; ``disparity_offset=-0.36`` is KITTI's own level, at which
   the prior's rotation drift, ≈ 0.2 mrad per frame, is as small as the photometric loss's own
   rotation bias at 64×96 and the rotation gains vary in sign from seed to seed —
   docs/results/demo.md). Every sequence has its own seed (a different town and route).
2. **Prior**: our classical stereo VO (``dpc_jax.vo``) with its online disparity-offset estimate
   *off*, as libviso2, which ignores such a residual: its trajectory then carries a scale error
   and a slow rotation drift, systematic errors that a correction can learn (the report tabulates
   each sequence's prior error: mean per frame against spread). A prior that falls back to
   constant velocity on more than 5 % of the pairs is refused: it would not be VO.
3. **Calibrate and prepare**: the same VO with the estimate *on* measures the residual from the
   images (no ground truth); ``prepare`` rectifies the network's images by it, so the network sees
   a calibrated rig and its stereo depth is metric.
4. **Train** Stereo DPC (``dpc_jax.training.loop``, the improved settings of
   ``dpc_jax.training.train_config``) on the training sequences; the validation sequence selects
   the epoch by Δ (the correction's paired photometric effect, no ground truth). The test sequence
   is never read by training.
5. **Correct the test sequence twice**: with the network as trained (acceptance test on all its
   pairs), and after adapting the network to the test sequence's own images for ``adapt_steps``
   steps (``dpc_jax.correction.adapt``; every ``holdout_every``-th pair kept out, the acceptance test
   on those).
   The final trajectory (``corrected.txt``, ``summary.json``'s ``test.corrected``) is chosen by
   ``dpc_jax.correction.corrector.choose``: the adapted correction if its test passes *and* it beats
   the trained one on the kept-out pairs, else the trained one if its test passes, else the prior.
6. **Report** ``OUT/report.md``: the prior's error composition, the test table (prior, trained,
   adapted, final), plots, the training and adaptation records. The ground truth is read only here.

Re-running with the same ``OUT`` reuses what is already there and up to date: rendered sequences
whose ``synth.json`` matches, VO runs whose record matches, caches (by their input hash) and a
finished training run (resumed when interrupted; a run with a different config is refused).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dpc_jax import config as config_lib
from dpc_jax.pipelines.demo_config import DemoConfig
from dpc_jax.report.demo_report import decision_label, write_demo_report
from dpc_jax.report.tables import change_pct
from dpc_jax.results.demo import SUMMARY, DemoSummary
from dpc_jax.runtime.progress import Progress, progress_bar

if TYPE_CHECKING:
    from dpc_jax.correction.adapt import Adaptation
    from dpc_jax.data.kitti import StereoSequence
    from dpc_jax.data.sequence_cache import SequenceCache
    from dpc_jax.eval.evaluation import Evaluation
    from dpc_jax.results.correction import Correction
    from dpc_jax.training.train_config import TrainConfig

# The run and the caches inside OUT (the report lists them as `run/` and `cache/`).
_RUN_DIR, _CACHE_DIR = "run", "cache"


class DemoError(ValueError):
    """The demo cannot go on (e.g. its VO prior is not VO); the message says why and what to change."""


ProgressFn = Callable[[str], None]


def _render(config: DemoConfig, data_root: Path, name: str, progress: Progress) -> bool:
    """Render sequence ``name`` unless an identical one is there; whether it rendered."""
    from dpc_jax.synth import is_rendered, write_sequence

    synth = config.synth_config(name)
    if is_rendered(data_root, name, synth):
        return False
    with progress_bar(synth.frames, f"render {name}", progress) as bar:
        write_sequence(data_root, name, synth, overwrite=True, on_frame=lambda: bar.update(1))
    return True


def prior_error(gt: np.ndarray, prior: np.ndarray, focal_px: float | None = None) -> dict[str, Any]:
    """What a prior's error consists of (:func:`dpc_jax.eval.diagnosis.diagnose`, the same as
    ``dpc-jax evaluate --diagnose``): the mean per frame (systematic) and the standard deviation
    (``std``, random) of the correction each step needs, per axis, translation in mm and rotation in
    mrad; the share of the end-point drift the mean explains; the mean rotation's image shift."""
    from dpc_jax.eval.diagnosis import diagnose

    record = diagnose(gt, prior, focal_px).to_dict()
    record["std"] = record.pop("spread")
    return record


def _vo_prior(config: DemoConfig, name: str, sequence: StereoSequence, first_pose: np.ndarray, vo_dir: Path,
              progress: Progress) -> tuple[dict[str, Any], float]:
    """Sequence ``name``'s VO prior (refused if it is not VO) and the disparity offset our VO measures."""
    from dpc_jax.vo import VOConfig
    from dpc_jax.vo.prior import write_vo_prior

    libviso2_like = VOConfig(estimate_offset=config.vo_estimate_offset)
    prior = write_vo_prior(sequence, vo_dir / f"{name}.txt", libviso2_like, first_pose=first_pose,
                     progress=progress)
    if prior["fallbacks"] > config.max_fallback_share * prior["pairs"]:
        raise DemoError(
            f"{name}: our VO fell back to constant velocity on {prior['fallbacks']} of {prior['pairs']} "
            f"pairs (more than {config.max_fallback_share:.0%}); a correction trained on such a prior "
            "shows nothing. Render larger images (render_size) or with less noise"
        )
    calibration = write_vo_prior(sequence, vo_dir / f"{name}.calibration.txt", VOConfig(estimate_offset=True),
                           first_pose=first_pose, progress=progress)
    return prior, calibration["disparity_offset_median_px"]


@dataclass(frozen=True)
class _Prepared:
    """Each sequence's prior record (fallbacks, pairs, offset in px, error composition) and length (m)."""

    records: dict[str, dict[str, Any]]
    lengths: dict[str, float]


def _prepare_sequences(config: DemoConfig, out: Path, size: tuple[int, int], seconds: dict[str, float],
                       progress: Progress, say: ProgressFn) -> _Prepared:
    """Render every sequence, run its VO prior and calibration, and prepare its cache, one sequence at a
    time."""
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.data.poses_io import read_kitti_poses

    data_root, vo_dir, cache_root = out / "data", out / "vo", out / _CACHE_DIR
    records: dict[str, dict[str, Any]] = {}
    lengths = {}
    for name in config.sequences:
        t = time.perf_counter()
        rendered = _render(config, data_root, name, progress)
        seconds["render"] += time.perf_counter() - t
        sequence = open_odometry(data_root, name)
        if sequence.poses is None:  # every rendered sequence has its poses; a reused folder might not
            raise DemoError(f"{name}: no ground-truth poses in {data_root}")
        t = time.perf_counter()
        prior, offset = _vo_prior(config, name, sequence, sequence.poses[0], vo_dir, progress)
        seconds["vo"] += time.perf_counter() - t
        t = time.perf_counter()
        prepare_sequence(sequence, prior["path"], cache_root, size=size,
                         disparity_offset=offset if config.rectify_offset else 0.0, progress=progress)
        seconds["prepare"] += time.perf_counter() - t
        records[name] = {"fallbacks": prior["fallbacks"], "pairs": prior["pairs"], "offset": offset,
                         "error": prior_error(sequence.poses, read_kitti_poses(prior["path"]),
                                              focal_px=float(sequence.K[0, 0]))}
        lengths[name] = float(np.linalg.norm(np.diff(sequence.poses[:, :3, 3], axis=0), axis=1).sum())
        say(f"{name}: {len(sequence)} frames, {lengths[name]:.0f} m"
            + (" (rendered)" if rendered else " (reused)")
            + f"; prior: {prior['fallbacks']} fallbacks, measured disparity offset {offset:+.3f} px")
    return _Prepared(records, lengths)


def _train(train_config: TrainConfig, run_dir: Path, seconds: dict[str, float], progress: Progress,
           say: ProgressFn) -> dict[str, Any]:
    """Train the network in ``run_dir`` (resuming an interrupted run, restoring a finished one)."""
    from dpc_jax.training.loop import train

    t = time.perf_counter()
    trained = train(train_config, run_dir, resume=True, progress=progress)
    seconds["train"] = time.perf_counter() - t
    say(f"trained: {trained['epochs']} epochs, {trained['step']} steps")
    return trained


@dataclass(frozen=True)
class _TestCorrections:
    """The test sequence's corrections (``trained``, ``adapted`` if adapted), the adaptation, and the
    final one (``result``, chosen as ``final``) with the epoch the network was restored at."""

    epoch: int
    cache: SequenceCache
    corrections: dict[str, Correction]
    adaptation: Adaptation | None
    final: str
    result: Correction


def _correct_test(config: DemoConfig, out: Path, seconds: dict[str, float], progress: Progress,
                  say: ProgressFn) -> _TestCorrections:
    """Correct the test sequence with the network as trained and, unless ``adapt_steps`` is 0, adapted to
    it; choose the final correction and write it to ``corrected.txt``."""
    from dpc_jax.correction.adapt import AdaptConfig
    from dpc_jax.correction.corrector import correct_sequence
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.outputs import CorrectionOutputs, write_corrected
    from dpc_jax.data.sequence_cache import load_cache

    t = time.perf_counter()
    run = load_run(out / _RUN_DIR, config.select)
    test_cache = load_cache(out / _CACHE_DIR / "test")
    how = AdaptConfig(config.adapt_steps, holdout_every=config.holdout_every) if config.adapt_steps else None
    done = correct_sequence(run, test_cache, adapt=how, force=not config.acceptance,
                            mean_test=config.mean_test, progress=progress)
    seconds["correct"] = time.perf_counter() - t
    if done.adaptation is not None:
        # The adaptation's own time, out of the correction's.
        seconds["adapt"] = done.adaptation.seconds
        seconds["correct"] -= done.adaptation.seconds
    say(f"network as trained (epoch {run.epoch}): {decision_label(done.trained.acceptance)} on the test "
        "sequence")
    if done.adapted is not None and done.adaptation is not None:
        say(f"adapted ({config.adapt_steps} steps): {decision_label(done.adapted.acceptance)} on held-out "
            "pairs")
    final, result = done.final, done.result
    corrections = {"trained": done.trained, **({"adapted": done.adapted} if done.adapted is not None else {})}
    adaptation = done.adaptation
    write_corrected(done, CorrectionOutputs(out / "corrected.txt", adapted=out / "adapted"))
    return _TestCorrections(run.epoch, test_cache, corrections, adaptation, final, result)


def _evaluate_test(config: DemoConfig, tested: _TestCorrections, trained: dict[str, Any], prepared: _Prepared,
                   seconds: dict[str, float], began: float) -> tuple[Evaluation, DemoSummary]:
    """Evaluate the test trajectories against the ground truth (read here only); return the evaluation and
    the demo's summary (its report's wall time and path still to come)."""
    import jax

    from dpc_jax.eval.evaluation import evaluate

    gt = np.asarray(tested.cache.gt, np.float64)
    proposals = {k: c.proposed for k, c in tested.corrections.items()}
    estimates = {"prior": tested.result.prior, **proposals, "corrected": tested.result.corrected}
    evaluation = evaluate(gt, estimates)
    test_metrics = {label: dict(evaluation.estimates[label]) for label in estimates}
    change = {k: change_pct(test_metrics["prior"][k], test_metrics["corrected"][k])
              for k in ("seg_trans_pct", "seg_rot_deg_per_100m")}
    return evaluation, DemoSummary(
        test=test_metrics,
        decisions={k: decision_label(c.acceptance) for k, c in tested.corrections.items()},
        acceptance={k: c.acceptance for k, c in tested.corrections.items()},
        final=tested.final,
        choice=tested.result.choice,
        change_pct=change,
        corrected_better=all(v < 0 for v in change.values()),
        selected_epoch=tested.epoch,
        select=config.select,
        steps_per_epoch=trained["step"] // max(1, trained["epochs"]),
        sequences=prepared.records,
        lengths_m=prepared.lengths,
        seconds=seconds,
        devices=[str(d) for d in jax.devices()],
        config=config_lib.to_dict(config),
        adaptation=None if tested.adaptation is None else tested.adaptation.summary(),
        # The report states the wall time up to itself; the summary then gets the total with the report's.
        seconds_total=time.perf_counter() - began,
    )


def _overview(config: DemoConfig, train_config: TrainConfig, summary: DemoSummary) -> list[str]:
    """The report's title and its paragraph on the data, the prior and the network."""
    lengths = ", ".join(f"{n}: {summary.lengths_m[n]:.0f} m" for n in config.sequences)
    size = train_config.resolved_image_size
    return [
        "# dpc_jax synthetic demo: Stereo DPC corrects a classical stereo VO",
        "",
        f"Synthetic stereo sequences ({config.render_size[0]}×{config.render_size[1]}, 10 Hz) with moving "
        f"cars ({config.moving_objects}), an illumination drift (±{config.illumination_drift:g}), image "
        f"noise (σ = {config.noise:g}) and a stereo calibration residual of {config.disparity_offset:+g} px: "
        f"{config.train_sequences} for training, one for validation (epoch selection), one held-out test "
        f"sequence ({lengths}). Prior: our classical stereo VO with its online disparity-offset estimate "
        f"{'on' if config.vo_estimate_offset else 'off (as libviso2)'}. "
        + ("The network's images are rectified by the residual our VO measures with the estimate on. "
           if config.rectify_offset else "")
        + f"Network: Stereo DPC, `{train_config.preset}` preset, {size[0]}×{size[1]} input, "
        f"{train_config.epochs} epoch(s) of {summary.steps_per_epoch} steps (batch "
        f"{train_config.batch_size}); epoch {summary.selected_epoch} selected by `{config.select}`."
        + (" **Trained with DPC-Net's supervised loss: the training steps read the training sequences' "
           "ground truth** (`supervision: supervised`); validation, the acceptance test and the "
           "adaptation do not." if train_config.supervision == "supervised" else ""),
        "",
    ]


def _write_results(out: Path, config: DemoConfig, train_config: TrainConfig, evaluation: Evaluation,
                   summary: DemoSummary, began: float) -> DemoSummary:
    """Write ``report.md`` (with its plots and metric files), then ``summary.json``; the summary written."""
    t = time.perf_counter()
    report = write_demo_report(out, _overview(config, train_config, summary), evaluation, summary,
                               out / _RUN_DIR)
    summary = dataclasses.replace(summary, seconds={**summary.seconds, "report": time.perf_counter() - t},
                                  seconds_total=time.perf_counter() - began, report=str(report))
    config_lib.save_json(out / SUMMARY, summary.to_dict())
    return summary


def run_demo(config: DemoConfig, out: str | os.PathLike, progress: Progress = False,
             log: ProgressFn | None = None) -> DemoSummary:
    """Run the demo into ``out`` (see the module docstring); return its summary (also ``OUT/summary.json``:
    :class:`dpc_jax.results.demo.DemoSummary`), which holds per sequence the prior's error composition;
    for the test sequence the metrics of ``prior``, ``trained``, ``adapted`` and the final ``corrected``
    trajectory, the acceptance ``decisions``, ``final`` (which one is in ``corrected.txt``) and
    ``change_pct`` (final against prior, %); the selected epoch, the seconds per stage and ``report``.
    ``progress``: bars for every stage; ``log``: called with one line per finished stage (e.g.
    ``print``). Raises :class:`DemoError` for a VO prior that is not VO.
    """
    say = log or (lambda line: None)
    out = Path(out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    train_config = config.train_config(out / _CACHE_DIR)
    size = train_config.resolved_image_size
    seconds = dict.fromkeys(("render", "vo", "prepare"), 0.0)
    began = time.perf_counter()

    prepared = _prepare_sequences(config, out, size, seconds, progress, say)
    trained = _train(train_config, out / _RUN_DIR, seconds, progress, say)
    tested = _correct_test(config, out, seconds, progress, say)
    evaluation, summary = _evaluate_test(config, tested, trained, prepared, seconds, began)
    return _write_results(out, config, train_config, evaluation, summary, began)


def decided_again_in(out: str | os.PathLike, config: DemoConfig, **options: Any) -> tuple[str, Correction]:
    """The test sequence of a finished demo in ``out`` corrected again from its networks (the run as
    trained and, when it adapted, the adapted network in ``adapted/`` with its kept-out pairs), decided
    with other ``options`` of ``dpc_jax.correction.corrector.correct_cache`` (e.g. ``mean_test=False``:
    the earlier decision) and chosen again → ``(final, correction)``; nothing is trained or adapted."""
    from dpc_jax.correction.corrector import decided_again
    from dpc_jax.correction.inference import load_run
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.data.sequence_cache import load_cache

    out = Path(out)
    # The test sequence prepared as the demo prepared it: the cache it left, rebuilt in place if this
    # dpc_jax writes caches of another format (the same arrays).
    record = json.loads((out / "vo" / "test.calibration.json").read_text())["summary"]
    offset = record["disparity_offset_median_px"] if config.rectify_offset else 0.0
    size = config.train_config(out / _CACHE_DIR).resolved_image_size
    cache = load_cache(prepare_sequence(open_odometry(out / "data", "test"), out / "vo" / "test.txt",
                                        out / _CACHE_DIR, size=size, disparity_offset=offset, progress=False))
    options = {"force": not config.acceptance, **options}
    adapted = None
    if config.adapt_steps:
        held_out = np.asarray(json.loads((out / "adapted" / "adapt.json").read_text())["held_out_pairs"])
        adapted = (load_run(out / "adapted", "last"), held_out)
    again = decided_again(load_run(out / _RUN_DIR, config.select), cache, adapted=adapted, **options)
    return again.final, again.result

