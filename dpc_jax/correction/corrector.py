"""Correct a VO trajectory with a trained DPC network, only where the images support it (``dpc-jax correct``).

Pipeline (docs/method.md §1, §7, §8):

1. ``dpc_jax.correction.inference.load_run`` restores a run at the epoch of a selection criterion and
   ``dpc_jax.correction.inference.run_prediction`` runs it over every consecutive pair ``(k, k+1)`` of a
   prepared sequence: ξ_corr and L(0), the prior's photometric error on the sequence's own images.
2. The decision (``dpc_jax.correction.decision``) on the measured effects Δ of the correction's parts
   (``dpc_jax.correction.measure``, at the network's size and, with a judge, at a larger one): the
   full correction, its rotation, the rotation about some axes, each whole or without its mean over
   the sequence, or nothing — then the corrected trajectory *is* the prior (re-composed from its
   relative poses). ``force=True`` applies the network's correction whatever the tests say. The
   prediction's pass measures the first component whole and without its centred mean as the proposal
   arrives (each batch kept on the device until the mean of its pairs is known): a decision made there
   needs no second pass; a part it reaches later is measured then.
3. ``T*_{k+1,k} = Exp(ξ_k) · T_vo_{k+1,k}`` with the applied part ξ_k is composed from the first
   ground-truth pose when the cache has ground truth, else from the first prior pose
   (``dpc_jax.geometry.pose_correction.corrected_trajectory``, float64); the prior, the network's proposal and
   the final trajectory are evaluated against the ground truth when it exists.

:func:`correct_sequence` is the whole path a command, a protocol and the demo run: the network as
trained, optionally adapted to the sequence (``dpc_jax.correction.adapt``), and :func:`choose`.

Frames: a cache holds the frames it was prepared with (``indices``: their numbers in the source
sequence). When static frames were removed or a frame range was selected at prepare time, the
corrected trajectory has one pose per *cached* frame, and consecutive poses may be several
source frames apart; :attr:`Correction.frames` says which, and the CLI writes them beside the
trajectory.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax._io import atomic_write
from dpc_jax.correction.acceptance import DEFAULT_ALPHA, paired_test
from dpc_jax.correction.adapt import Adaptation, AdaptConfig
from dpc_jax.correction.adapt import adapt as adapt_network
from dpc_jax.correction.decision import DEFAULT_MEAN_TEST, MEAN_TESTS, MeanTest, decide, refused
from dpc_jax.correction.inference import TrainedRun, run_prediction
from dpc_jax.correction.measure import judge_measurement, measurement, remember, remembered
from dpc_jax.correction.parts import MEAN_WINDOW, Part, applied_correction
from dpc_jax.data.poses_io import WRITE_FORMATS, frames_path, write_kitti_poses, write_tum
from dpc_jax.data.priors import prior_for_cache
from dpc_jax.data.sequence_cache import SequenceCache, load_cache
from dpc_jax.results.acceptance import Acceptance
from dpc_jax.results.correction import AdaptationSummary, Correction
from dpc_jax.runtime.progress import Progress


def default_acceptance_depth(run: TrainedRun) -> str:
    """The depth the acceptance test measures Δ with when none is asked: ``sgbm`` for a stereo run.

    The network's own depth was trained together with the pose it judges, so on images unlike its
    training data (another camera, real images for a network trained on the synthetic world) both
    can be wrong together and the test passes what hurts; StereoSGBM on the cached pair is
    independent of the network. ``acceptance_depth="network"`` (``--acceptance-depth network``)
    gives the network's depth, the previous default; the run's ``acceptance_depth`` still sets
    its epoch selection. A monocular run has no stereo pair: its own setting is kept.
    """
    return "sgbm" if run.config.method == "stereo_dpc" else run.config.acceptance_depth


def correct_cache(
    run: TrainedRun,
    cache: SequenceCache | str | os.PathLike,
    prior: str | os.PathLike | np.ndarray | None = None,
    *,
    rotation_only: bool | None = None,
    prior_format: str | None = None,
    batch_size: int | None = None,
    acceptance_depth: str | None = None,
    alpha: float = DEFAULT_ALPHA,
    force: bool = False,
    mean_test: bool = True,
    window: int = MEAN_WINDOW,
    mean: MeanTest = MEAN_TESTS[DEFAULT_MEAN_TEST],
    held_out: np.ndarray | None = None,
    judge: SequenceCache | str | os.PathLike | None = None,
    proposal: np.ndarray | None = None,
    store: dict[str, dict[bytes, np.ndarray]] | None = None,
    progress: Progress = False,
) -> Correction:
    """Correct the prior of a cached sequence with ``run`` where the acceptance test allows it.

    ``prior``: None = the cache's own prior, else a replacement (see :func:`prior_for_cache`);
    ``rotation_only``: None = the run's ``config.rotation_only``; ``acceptance_depth``:
    ``network`` or ``sgbm`` (None = :func:`default_acceptance_depth`); ``alpha``: the tests' level;
    ``force``: apply the correction whatever the tests say; ``mean_test``: test the correction's
    mean (its moving mean over ``window`` pairs) on its own (``dpc_jax.correction.decision``; False:
    the earlier decision); ``mean``: where and how the mean is tested (``MEAN_TESTS``); ``held_out``:
    the pairs ``k`` the tests use (default all; after adaptation, the pairs it never saw). ``judge``: the
    same frames prepared at a larger size (a stereo run): what passes at the network's size must pass
    there too, with its StereoSGBM depth, and is applied at the
    scale its images support best. A run whose selection ``delta`` found no epoch better than "no
    correction" is never applied unless ``force``. ``proposal``: ``[N-1, 6]`` the run's corrections of
    this cache when already predicted (decided again, e.g. with other options; then the network does
    not run for them, and ``delta`` is empty). ``store``: Δ measured before on this cache with the
    same depth and judge, by size (``network``, ``judge``) and candidate, read and filled
    (``dpc_jax.correction.measure.remembered``): a proposal decided with several options measures each
    candidate once. The trajectories start at the first ground-truth pose
    when the cache has ground truth, else at the first prior pose (docs/method.md §1).
    """
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    if prior is not None:
        cache = dataclasses.replace(cache, prior=prior_for_cache(cache, prior, prior_format))
    rotation_only = run.config.rotation_only if rotation_only is None else bool(rotation_only)
    depth = acceptance_depth or default_acceptance_depth(run)
    components = ("rotation",) if rotation_only else ("full", "rotation")
    judged = None if judge is None else judge_measurement(run, cache, judge, batch_size, progress)
    store = {} if store is None else store
    if proposal is None:
        xi, none, delta = _predicted(run, cache, store.setdefault("network", {}), components, batch_size,
                                     depth, window if mean_test else None, progress)
    else:
        xi, none, delta = np.asarray(proposal, np.float64), None, {}
    measure = measurement(run, cache, depth=depth, batch_size=batch_size, none=none, progress=progress)
    measure = remembered(measure, store.setdefault("network", {}))
    judged = None if judged is None else remembered(judged, store.setdefault("judge", {}))
    acceptance = decide(xi, measure, components=components, alpha=alpha, tested=held_out, judge=judged,
                        mean_test=mean_test, window=window, mean=mean, force=force)
    if not (force or run.improves_on_prior):
        acceptance = refused(acceptance, "the run holds no epoch that lowered the validation Δ (selection "
                                         "delta, best_delta/)")
    correction = compose_correction(run, cache, xi, acceptance, rotation_only)
    return dataclasses.replace(correction, delta=delta,
                               tested=None if held_out is None else np.asarray(held_out, np.int64))


def _predicted(run: TrainedRun, cache: SequenceCache, store: dict[bytes, np.ndarray],
               components: tuple[str, ...], batch_size: int | None, depth: str, window: int | None,
               progress: Progress) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The run's proposal on ``cache`` → ``(ξ, L(0), {first component: Δ})``, and into ``store`` the Δ
    its pass measured of what the decision needs first: the first component whole and, with a mean test
    (``window``), its remainder, measured as the proposal arrives so that no second pass assembles the
    batches again (or, with the network's depth, runs the network again). Nothing else is measured
    there: a part the decision reaches later is measured then."""
    first = [Part(components[0], True, window=window)] if window is not None else []
    made = (lambda xi: np.stack([p.of(xi) for p in first])) if first else None
    prediction = run_prediction(run, cache, batch_size=batch_size, acceptance_depth=depth, candidates=made,
                                training_loss=False, deltas=components[:1], progress=progress)
    xi = prediction.xi_corr
    for component, measured_whole in prediction.delta.items():
        remember(store, Part(component).of(xi), measured_whole)
    if prediction.measured is not None:
        used, measured = prediction.measured
        for part, values, delta in zip(first, used, measured, strict=True):
            asked = part.of(xi)  # what the decision will ask for
            if np.array_equal(values, asked.astype(np.float32)):
                remember(store, asked, delta)
    return xi, prediction.photometric, dict(prediction.delta)


def compose_correction(
    run: TrainedRun, cache: SequenceCache, xi_corr: np.ndarray, acceptance: Acceptance, rotation_only: bool
) -> Correction:
    """The trajectories of a decided correction of ``cache`` and their evaluation (module docstring)."""
    from dpc_jax.eval.evaluation import evaluate
    from dpc_jax.geometry.pose_correction import corrected_trajectory

    prior = np.asarray(cache.prior, np.float64)
    gt = None if cache.gt is None else np.asarray(cache.gt, np.float64)
    first = gt[0] if gt is not None else prior[0]
    proposed = corrected_trajectory(xi_corr, prior, first, rotation_only)
    applied = corrected_trajectory(applied_correction(xi_corr, acceptance), prior, first)
    evaluation = None
    if gt is not None:
        evaluation = evaluate(gt, {"prior": prior, "network": proposed, "corrected": applied})
    return Correction(
        name=cache.name,
        frames=np.asarray(cache.indices, np.int64),
        times=np.asarray(cache.times, np.float64),
        prior=prior,
        proposed=proposed,
        corrected=applied,
        ground_truth=gt,
        xi_corr=xi_corr,
        rotation_only=rotation_only,
        acceptance=acceptance,
        epoch=run.epoch,
        evaluation=evaluation,
    )


def choose(trained: Correction, adapted: Correction | None = None) -> tuple[str, Correction]:
    """The final correction of a sequence corrected by a network as trained and, optionally, by the
    same network adapted to the sequence (``dpc_jax.correction.adapt``) → ``(name, correction)`` with ``name``
    ``adapted``, ``trained`` or ``prior`` (then the trajectory is the prior re-composed).

    Each candidate has passed or failed its own acceptance test against the prior. The adapted
    network is the more flexible model, fitted to the very images it is judged on (its test pairs
    are kept out of adaptation, but their neighbours were fitted), so it must also beat the trained
    network's applied correction on the kept-out pairs: the paired differences of the two applied
    corrections' effects, ``Δ_adapted,i − Δ_trained,i``, significantly below 0 (the same one-sided
    Wilcoxon test at the adapted test's level). Failing that, the trained network's accepted
    correction is kept — a nested comparison, prior ⊂ trained ⊂ adapted, each step taken only on
    significant evidence. With one depth for both (``acceptance_depth="sgbm"``) the difference is
    exactly ``L(ξ_adapted) − L(ξ_trained)``; with each network's own depth it compares the two
    effects. Forced corrections (``force``) are not compared: the adapted one is applied. The
    returned correction's ``choice`` records the comparison.
    """
    if adapted is None or adapted.part == "none":
        name = "trained" if trained.part != "none" else "prior"
        first = "no adapted correction" if adapted is None else "the adapted correction failed its test"
        reason = first + ("; the trained correction passed its test" if name == "trained"
                          else "; the trained correction failed its test: the prior is kept")
        return name, dataclasses.replace(trained, choice={"final": name, "reason": reason})
    if trained.part == "none" or adapted.acceptance.forced:
        reason = ("forced" if adapted.acceptance.forced
                  else "the adapted correction passed its test, the trained one did not")
        return "adapted", dataclasses.replace(adapted, choice={"final": "adapted", "reason": reason})
    pairs = slice(None) if adapted.tested is None else adapted.tested
    assert adapted.acceptance.delta is not None and trained.acceptance.delta is not None  # both applied
    difference = adapted.acceptance.delta[pairs] - trained.acceptance.delta[pairs]
    test = paired_test("adapted − trained", difference, adapted.acceptance.alpha)
    name = "adapted" if test.passed else "trained"
    verdict = "beats" if test.passed else "does not significantly beat"
    reason = (f"both passed their tests; the adapted correction {verdict} the trained one on the "
              f"{test.pairs} kept-out pairs (mean difference of Δ {test.mean_delta:.3g}, "
              f"p = {test.p_value:.3g})")
    chosen = adapted if test.passed else trained
    return name, dataclasses.replace(chosen, choice={"final": name, "reason": reason,
                                                     "comparison": dataclasses.asdict(test)})


@dataclass(frozen=True)
class CorrectedSequence:
    """A sequence corrected by :func:`correct_sequence`: the network as trained (``trained``), adapted
    (``adapted``, with ``adaptation``; None without adaptation), which :func:`choose` picked
    (``final``: ``trained``, ``adapted`` or ``prior``) and that correction (``result``, its
    ``choice`` recorded)."""

    trained: Correction
    adapted: Correction | None
    adaptation: Adaptation | None
    final: str
    result: Correction

    @property
    def corrections(self) -> dict[str, Correction]:
        """``trained`` (and ``adapted``), the chosen one with its choice recorded."""
        out = {"trained": self.trained, **({"adapted": self.adapted} if self.adapted is not None else {})}
        out[self.final if self.final != "prior" else "trained"] = self.result
        return out


def correct_sequence(
    run: TrainedRun,
    cache: SequenceCache | str | os.PathLike,
    prior: str | os.PathLike | np.ndarray | None = None,
    *,
    adapt: AdaptConfig | None = None,
    prior_format: str | None = None,
    progress: Progress = False,
    **options: Any,
) -> CorrectedSequence:
    """Correct ``cache`` with ``run`` as trained (:func:`correct_cache` with ``options``) and, with
    ``adapt``, with the network adapted to the sequence's own pairs (``dpc_jax.correction.adapt``, its
    tests on the kept-out pairs); :func:`choose` picks the final correction."""
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    if prior is not None:
        cache = dataclasses.replace(cache, prior=prior_for_cache(cache, prior, prior_format))
    trained = correct_cache(run, cache, progress=progress, **options)
    adaptation = adapted = None
    if adapt is not None:
        adaptation = adapt_network(run, cache, adapt, progress=progress)
        adapted = correct_adapted(adaptation.run, cache, adaptation.held_out, adaptation.summary(),
                                  progress=progress, **options)
    final, result = choose(trained, adapted)
    return CorrectedSequence(trained, adapted, adaptation, final, result)


def correct_adapted(run: TrainedRun, cache: SequenceCache, held_out: np.ndarray,
                    summary: AdaptationSummary | None = None, **options: Any) -> Correction:
    """``cache`` corrected by an adapted network ``run`` (:func:`correct_cache` with ``options``), its
    tests on the pairs ``held_out`` of adaptation only; the correction carries the adaptation's
    ``summary``."""
    correction = correct_cache(run, cache, held_out=held_out, **options)
    return dataclasses.replace(correction, adaptation=summary)


def decided_again(
    run: TrainedRun, cache: SequenceCache | str | os.PathLike, *, done: CorrectedSequence | None = None,
    adapted: tuple[TrainedRun, np.ndarray] | None = None, **options: Any
) -> CorrectedSequence:
    """``cache`` corrected again by the network as trained (``run``) and, when there is one, by the
    adapted network on the pairs it never saw, decided with ``options`` of :func:`correct_cache` (e.g.
    ``mean_test=False``, the earlier decision) and chosen again (:func:`choose`); nothing is trained or
    adapted. ``done``: the sequence corrected before by :func:`correct_sequence`: its proposals are
    decided again with its adapted network (with StereoSGBM depth no network runs); else ``adapted``:
    ``(run, held_out)``, an adapted network and its kept-out pairs (the networks run)."""
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    adaptation = None if done is None else done.adaptation
    if adaptation is not None:
        adapted = (adaptation.run, adaptation.held_out)
    trained = correct_cache(run, cache, proposal=None if done is None else done.trained.xi_corr, **options)
    again = None
    if adapted is not None:
        proposal = None if done is None or done.adapted is None else done.adapted.xi_corr
        summary = None if adaptation is None else adaptation.summary()
        again = correct_adapted(adapted[0], cache, adapted[1], summary, proposal=proposal, **options)
    final, result = choose(trained, again)
    return CorrectedSequence(trained, again, adaptation, final, result)


def write_trajectory(path: str | os.PathLike, correction: Correction, format: str = "kitti") -> list[Path]:
    """Write the corrected trajectory atomically as KITTI pose text or TUM (timestamps = frame times).

    When the trajectory lacks source frames (static frames removed or a frame range at prepare
    time), the source frame number of every pose is written too, one per line, to
    :func:`frames_path`. Returns the written paths.
    """
    if format not in WRITE_FORMATS:
        raise ValueError(f"format must be one of {WRITE_FORMATS}, got {format!r}")
    path = Path(path)
    if format == "kitti":
        write_kitti_poses(path, correction.corrected)
    else:
        write_tum(path, correction.corrected, correction.times)
    written = [path]
    if not correction.all_source_frames:
        atomic_write(frames_path(path), "".join(f"{int(i)}\n" for i in correction.frames))
        written.append(frames_path(path))
    return written
