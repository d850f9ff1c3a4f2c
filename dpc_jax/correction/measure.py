"""The measurement under the acceptance test: Δ of any correction on the pairs of a cached sequence.

``Δ_k(ξ) = L_k(ξ) − L_k(0)`` on each consecutive pair ``(k, k+1)``
(``dpc_jax.engine.predict.measure_effects``): what ``dpc_jax.correction.decision`` decides on. A
:data:`~dpc_jax.correction.decision.Measure` is bound to one cache and one depth:

* :func:`measurement`: at the network's size, with StereoSGBM depth (the default for a stereo run; no
  network runs unless it learned its SSIM weight) or with the network's own depth (it runs again).
* :func:`judge_measurement`: on a *judge*, the same frames prepared at a larger size, with its
  StereoSGBM depth and no network. ξ is a pose, the same at every image size, and the photometric
  loss resolves rotations better with more pixels (``docs/method.md`` §8).
* :func:`pair_deltas`: the same measurement on the one pair of a batch (the live corrector's, at the
  network's size or the judge's).
* :func:`remembered`: a measurement that measures each candidate once into a store kept by the caller,
  so one proposal decided with several options (``docs/method.md`` §8) measures nothing twice;
  :func:`remember` puts there what the prediction's pass measured already.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Mapping

import numpy as np

from dpc_jax.correction.decision import Measure
from dpc_jax.correction.inference import TrainedRun
from dpc_jax.correction.judge import judge_frames_problem
from dpc_jax.data.sequence_cache import SequenceCache, load_cache
from dpc_jax.engine.predict import PreparedModel, effects_step, measure_effects, stereo_depth_of
from dpc_jax.nn.batch import Batch
from dpc_jax.runtime.progress import Progress


def measurement(
    run: TrainedRun,
    cache: SequenceCache,
    *,
    depth: str,
    batch_size: int | None = None,
    none: np.ndarray | None = None,
    progress: Progress = False,
) -> Measure:
    """Δ of named corrections ``{name: [N-1, 6]}`` on the pairs of ``cache`` → ``{name: [N-1]}``.

    ``depth``: ``sgbm`` (StereoSGBM on the cached pair) or ``network`` (the run's own depth);
    ``none``: ``L(0)`` ``[N-1]`` already measured with that depth (a prediction's ``photometric``).
    The loss is the run's, with its learned SSIM weight if it learned one.
    """
    stereo = stereo_depth_of(cache, depth)
    model = run.prepared if _model_needed(run, stereo) else None
    return _bound(cache, run.config.loss_config(), batch_size or run.config.batch_size, stereo, model,
                  run.use_flow, none, progress)


def _model_needed(run: TrainedRun, stereo: object) -> bool:
    """Whether measuring Δ runs the network: for its depth (``stereo`` None: no stereo depth), or with a
    stereo depth for its learned SSIM weight."""
    return stereo is None or run.config.learn_ssim_weight


# The numbers of corrections one pair is measured for (:func:`pair_deltas` pads to the next): each is a
# program of its own, compiled once; two for a whole part and its remainder, up to the rotation's axes
# and their subset, and the judge's scales.
PADDED = (2, 4, 8, 16)


def pair_deltas(run: TrainedRun, batch: Batch, corrections: np.ndarray, *,
                model: PreparedModel | None = None) -> np.ndarray:
    """Δ ``[K]`` of ``corrections`` ``[K, 6]`` on the one pair of ``batch`` (``pair_batch``): the
    measurement of :func:`measurement` (with ``model``, the run prepared, where it needs the network), or
    of :func:`judge_measurement` without it (the batch's stereo depth and the loss config's SSIM weight).
    The corrections are padded to a count of :data:`PADDED`."""
    import jax.numpy as jnp

    count = len(corrections)
    fits = [n for n in PADDED if n >= count]
    if not fits:
        raise ValueError(f"{count} corrections to measure on one pair, more than the {PADDED[-1]} compiled")
    padded = np.zeros((fits[0], 1, 6))
    padded[:count, 0] = corrections
    candidates = jnp.asarray(padded, jnp.float32)
    config = run.config.loss_config()
    if model is None or not _model_needed(run, batch.stereo_depth):
        effects = effects_step(None, None, config)(None, batch, candidates, None)
    else:
        effects = model.effects_step(config)(model.leaves, batch, candidates, None)
    return np.asarray(effects["delta"], np.float64)[:count, 0]


def judge_cache(
    run: TrainedRun, cache: SequenceCache, judge: SequenceCache | str | os.PathLike
) -> SequenceCache:
    """The judge of ``cache`` for ``run`` (a cache or its folder), checked: a stereo run, and the same
    frames at least as large (``dpc_jax.correction.judge.judge_frames_problem``, the command line's
    check); its prior is replaced by ``cache``'s (Δ is measured around the prior being corrected)."""
    judged = judge if isinstance(judge, SequenceCache) else load_cache(judge)
    if run.config.method != "stereo_dpc":
        raise ValueError(f"{judged.path}: a judge measures Δ with stereo depth; the run is "
                         f"{run.config.method}")
    problem = judge_frames_problem(judged, cache, str(judged.path), str(cache.path))
    if problem is not None:
        raise ValueError(problem)
    same_sequence = judged.manifest.get("sequence") == cache.manifest.get("sequence")
    if not same_sequence or not np.array_equal(np.asarray(judged.indices), np.asarray(cache.indices)):
        raise ValueError(f"{judged.path}: holds frames other than those of {cache.path}; a judge must be "
                         "the same frames prepared at another size")
    return dataclasses.replace(judged, prior=cache.prior)


def judge_measurement(
    run: TrainedRun, cache: SequenceCache, judge: SequenceCache | str | os.PathLike,
    batch_size: int | None = None, progress: Progress = False,
) -> Measure:
    """Δ of named corrections on the pairs of ``judge`` (:func:`judge_cache`), with its StereoSGBM depth
    and the loss config's fixed SSIM weight (a learned one belongs to the network's size)."""
    judged = judge_cache(run, cache, judge)
    return _bound(judged, run.config.loss_config(), batch_size or run.config.batch_size,
                  stereo_depth_of(judged, "sgbm"), None, False, None, progress)


def _bound(cache: SequenceCache, config: object, batch_size: int, stereo: object, model: object,
           use_flow: bool, none: np.ndarray | None, progress: Progress) -> Measure:
    def measure(candidates: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        names = list(candidates)
        effects = measure_effects(cache, np.stack([candidates[n] for n in names]), config,
                                  batch_size=batch_size, stereo_depth=stereo, model=model,  # type: ignore[arg-type]
                                  use_flow=use_flow, none=none, progress=progress)
        return dict(zip(names, effects["delta"], strict=True))

    return measure


def remembered(measure: Measure, store: dict[bytes, np.ndarray]) -> Measure:
    """``measure``, with each candidate's Δ kept in ``store`` by the candidate's values (``[M, 6]``) and
    read from there when asked again. The store belongs to one measurement (one cache, depth and
    size): the caller keeps one per size."""

    def measured(candidates: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        keys = {name: _key(xi) for name, xi in candidates.items()}
        todo = {name: xi for name, xi in candidates.items() if keys[name] not in store}
        if todo:
            got = measure(todo)
            store.update({keys[name]: np.asarray(got[name], np.float64) for name in todo})
        return {name: store[keys[name]] for name in candidates}

    return measured


def remember(store: dict[bytes, np.ndarray], xi: np.ndarray, delta: np.ndarray) -> None:
    """Put Δ ``[M]`` of the correction ``xi`` ``[M, 6]``, measured with the store's cache, depth and size
    elsewhere (a prediction's pass), into a :func:`remembered` store."""
    store[_key(xi)] = np.asarray(delta, np.float64)


def _key(xi: np.ndarray) -> bytes:
    values = np.ascontiguousarray(xi, np.float64)
    return hashlib.sha256(repr(values.shape).encode() + values.tobytes()).digest()
