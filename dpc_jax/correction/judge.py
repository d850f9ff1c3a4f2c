"""The judge: Δ of a given correction on a larger copy of the frames, with its stereo depth and no
network, and what a correction that passed at the network's size keeps of it there.

The acceptance test (``dpc_jax.correction.acceptance``) judges a correction by its paired photometric effect
``Δ_k = L_k(ξ) − L_k(0)`` on the pairs ``(k, k+1)``. With the StereoSGBM depth the cache holds
(``dpc_jax.data.cache``), ``L`` (:func:`dpc_jax.nn.losses.temporal_pair_errors`: the temporal
reconstructions of both cameras, gradient-masked, no explainability mask) needs only the images,
the calibration, the prior's step and ξ: not the network that proposed ξ. So a correction
predicted at the network's input size can be judged on a copy of the sequence prepared at a
larger size (a *judge*): ξ is a pose, the same at every image size, and the photometric loss
resolves rotations better with more pixels (``docs/method.md`` §8). λ_s is the loss config's
fixed value (a network's learned one is the network's).

* :func:`correction_effects`: Δ of ``ξ ⊙ mask`` on every pair of a cache, for each named mask.
* :func:`judge_cache`: the judge of a cache, checked (the same frames, a stereo run).
* :func:`judged_correction`: the correction must pass the test at the judge's size too; then
  :func:`scale_correction` applies the scale of :data:`JUDGE_SCALES` with the lowest mean Δ there.
* :func:`judge_correction`: both for a decided correction of a run, from the measurement on.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dpc_jax.correction.acceptance import Acceptance, component_mask, component_test
from dpc_jax.correction.inference import TrainedRun
from dpc_jax.data.pipeline import iterate_sequence
from dpc_jax.data.sequence_cache import SequenceCache, load_cache
from dpc_jax.engine.driver import drive
from dpc_jax.engine.predict import stereo_depth_of
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.losses import temporal_pair_errors, with_stereo_depth
from dpc_jax.nn.model_config import SSDPCLossConfig, StereoDPCLossConfig
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs

# The scales of a passed correction the judge compares (:func:`scale_correction`).
JUDGE_SCALES = (0.25, 0.5, 0.75, 1.0)


@functools.partial(jax.jit, static_argnames="config")
def _effects(batch: Batch, xi: jax.Array, masks: jax.Array, config: StereoDPCLossConfig,
             none: jax.Array | None = None) -> jax.Array:
    """Δ ``[C, B]`` of ``xi [B, 6] ⊙ masks[c] [6]`` for each of the ``C`` masks (module docstring),
    with ``batch.stereo_depth``; ``none``: ``L(0)`` ``[B]`` if already measured, else measured here."""
    assert batch.stereo_depth is not None
    ones = jnp.ones(batch.stereo_depth[0].shape[:1] + batch.stereo_depth[0].shape[2:], jnp.float32)
    branch = BranchOutputs(ones, ones)
    outputs, valid = with_stereo_depth(DPCOutputs(jnp.zeros_like(xi), branch, branch), batch.stereo_depth)
    if none is None:
        none = temporal_pair_errors(outputs, batch, config, valid)
    return jnp.stack([temporal_pair_errors(outputs._replace(xi_corr=xi * masks[c]), batch, config, valid)
                      - none for c in range(masks.shape[0])])


def correction_effects(
    cache: SequenceCache,
    xi_corr: np.ndarray,
    masks: Mapping[str, np.ndarray],
    config: SSDPCLossConfig | StereoDPCLossConfig,
    batch_size: int = 8,
    none: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Δ of ``xi_corr ⊙ mask`` on every pair of ``cache`` for each named mask → ``{name: [N-1]}``.

    ``xi_corr``: ``[N-1, 6]`` corrections ``[ρ (m), φ (rad)]`` of the cache's consecutive pairs
    (e.g. predicted on another cache of the same frames); ``masks``: ``{name: [6]}`` weights of
    the entries of ξ (0/1 to select, or a scale); ``config``: the loss whose temporal error is
    measured. Depth: the cache's StereoSGBM depth (computed now if it holds none). ``none``:
    ``L(0)`` ``[N-1]`` of every pair when already measured on this cache with this depth (a
    prediction's ``photometric``), which spares its evaluation; else measured here.
    """
    if not isinstance(config, StereoDPCLossConfig):
        raise ValueError(f"{cache.path}: judging needs both cameras (Stereo DPC's loss), got "
                         f"{type(config).__name__}")
    xi_corr = np.asarray(xi_corr, np.float32)
    pairs = len(cache) - 1
    if xi_corr.shape != (pairs, 6):
        raise ValueError(f"{cache.path}: xi_corr must be [{pairs}, 6] for its {pairs + 1} frames, "
                         f"got {xi_corr.shape}")
    if not masks:
        raise ValueError("no mask to judge")
    if none is not None and np.shape(none) != (pairs,):
        raise ValueError(f"{cache.path}: L(0) must be [{pairs}], got {np.shape(none)}")
    names = list(masks)
    stacked = jnp.asarray(np.stack([np.asarray(masks[n], np.float32) for n in names]))
    stereo = stereo_depth_of(cache, "sgbm")
    assert stereo is not None  # "sgbm" always gives a depth
    size = max(1, min(batch_size, pairs))
    out: list[np.ndarray] = []
    known_none = None if none is None else np.asarray(none, np.float32)

    def put(batch: Batch) -> tuple[Batch, np.ndarray]:
        return jax.device_put(batch), np.asarray(batch.weight)

    def run(carry: None, item: tuple[Batch, np.ndarray], index: int) -> tuple[None, Any]:
        rows = np.minimum(np.arange(index * size, (index + 1) * size), pairs - 1)
        known = None if known_none is None else jnp.asarray(known_none[rows])
        return carry, _effects(item[0], jnp.asarray(xi_corr[rows]), stacked, config=config, none=known)

    def consume(index: int, effects: np.ndarray, item: tuple[Batch, np.ndarray]) -> int:
        real = item[1] > 0
        out.append(np.asarray(effects, np.float64)[:, real])
        return int(real.sum())

    # The step driver: batch k+1 is dispatched before the effects of batch k are fetched.
    batches = iterate_sequence(cache, size, flow=False, put=put, stereo_depth=stereo)
    drive(run, None, batches, total=pairs, desc=f"judge {cache.name}", unit="pair", consume=consume)
    merged = np.concatenate(out, axis=1)
    return {name: merged[i] for i, name in enumerate(names)}


def judge_cache(
    run: TrainedRun, cache: SequenceCache, judge: SequenceCache | str | os.PathLike
) -> SequenceCache:
    """The judge of ``cache`` for ``run`` (a cache or its folder), checked: the same frames, a stereo
    run; its prior is replaced by ``cache``'s."""
    judged = judge if isinstance(judge, SequenceCache) else load_cache(judge)
    if run.config.method != "stereo_dpc":
        raise ValueError(f"{judged.path}: a judge measures Δ with stereo depth; the run is "
                         f"{run.config.method}")
    same_sequence = judged.manifest.get("sequence") == cache.manifest.get("sequence")
    if not same_sequence or not np.array_equal(np.asarray(judged.indices), np.asarray(cache.indices)):
        raise ValueError(f"{judged.path}: holds frames other than those of {cache.path}; a judge must be "
                         "the same frames prepared at another size")
    # Δ is measured around the prior being corrected, which may replace the caches' own.
    return dataclasses.replace(judged, prior=cache.prior)


def judged_correction(
    acceptance: Acceptance,
    delta: dict[str, np.ndarray],
    by_scale: dict[float, np.ndarray],
    pairs: np.ndarray | None = None,
) -> tuple[Acceptance, dict[str, np.ndarray]]:
    """A correction decided at the network's size, judged on a larger copy of the frames →
    ``(acceptance, delta)``.

    ``by_scale``: ``{s: Δ}`` at the judge of the decided correction times each of
    :data:`JUDGE_SCALES`. It must pass the test there at scale 1 too (else the
    prior is kept): a test at two sizes, with two depths, both of which must agree. Then
    :func:`scale_correction` picks its scale there; ``delta[decision]`` becomes
    the judge's Δ (what :func:`dpc_jax.correction.corrector.choose` compares).
    """
    chosen = slice(None) if pairs is None else np.asarray(pairs)
    decision = acceptance.decision
    name = f"{decision} (judge)"
    test = component_test(name, by_scale[1.0][chosen], acceptance.alpha)
    tests = {**acceptance.tests, name: test}
    if not test.passed:
        reason = (f"{acceptance.reason}; not at the judge's size (mean Δ {test.mean_delta:.3g}, "
                  f"p = {test.p_value:.3g}): the prior is kept")
        return dataclasses.replace(acceptance, tests=tests, decision="none", reason=reason), delta
    judged = dataclasses.replace(acceptance, tests=tests,
                                 reason=f"{acceptance.reason}; at the judge's size p = {test.p_value:.3g}")
    smaller = {s: d for s, d in by_scale.items() if s != 1.0}
    return scale_correction(judged, {**delta, decision: by_scale[1.0]}, smaller, pairs)


def scale_correction(
    acceptance: Acceptance,
    delta: dict[str, np.ndarray],
    scaled: dict[float, np.ndarray],
    pairs: np.ndarray | None = None,
) -> tuple[Acceptance, dict[str, np.ndarray]]:
    """The magnitude of a passed correction that the judge's images support → ``(acceptance, delta)``.

    ``delta[decision]``: Δ of the decided correction as proposed (scale 1); ``scaled``: ``{s: Δ}``
    of the same correction times each smaller scale of :data:`JUDGE_SCALES`. The scale with the
    lowest mean Δ on ``pairs`` (default all) is applied when it passes the test itself; its Δ
    replaces ``delta[decision]`` (what :func:`dpc_jax.correction.corrector.choose` compares). A
    network trained at a coarse input size can get the direction of a rotation right and its size
    wrong (docs/method.md §8).
    """
    chosen = slice(None) if pairs is None else np.asarray(pairs)
    decision = acceptance.decision
    means = {1.0: float(delta[decision][chosen].mean())}
    means.update({s: float(d[chosen].mean()) for s, d in scaled.items()})
    best = min(means, key=lambda s: means[s])
    listed = ", ".join(f"×{s:g} {means[s]:.3g}" for s in sorted(means))
    if best == 1.0:
        reason = f"{acceptance.reason}; mean Δ by scale: {listed}"
        return dataclasses.replace(acceptance, reason=reason), delta
    name = f"{decision} ×{best:g}"
    test = component_test(name, scaled[best][chosen], acceptance.alpha)
    tests = {**acceptance.tests, name: test}
    if not test.passed:
        reason = f"{acceptance.reason}; ×{best:g} did not pass (p = {test.p_value:.3g})"
        return dataclasses.replace(acceptance, tests=tests, reason=reason), delta
    return dataclasses.replace(
        acceptance, tests=tests, scale=best,
        reason=f"{acceptance.reason}; applied ×{best:g}, the scale with the lowest mean Δ ({listed})",
    ), {**delta, decision: scaled[best]}


def judge_correction(
    run: TrainedRun,
    judged: SequenceCache,
    xi_corr: np.ndarray,
    acceptance: Acceptance,
    delta: dict[str, np.ndarray],
    rotation_only: bool,
    pairs: np.ndarray | None = None,
    batch_size: int | None = None,
) -> tuple[Acceptance, dict[str, np.ndarray]]:
    """A decided correction ``xi_corr`` ``[N-1, 6]`` of ``run`` judged on ``judged`` (from
    :func:`judge_cache`) → ``(acceptance, delta)``: Δ of the decided part at each of
    :data:`JUDGE_SCALES` measured there (:func:`correction_effects`), then :func:`judged_correction`.
    A rejected or forced decision is returned as it is."""
    if acceptance.decision == "none" or acceptance.forced:
        return acceptance, delta
    decided = "rotation" if rotation_only and acceptance.decision == "full" else acceptance.decision
    mask = component_mask(decided)
    scales = {f"{s:g}": s * mask for s in JUDGE_SCALES}
    measured = correction_effects(judged, xi_corr, scales, run.config.loss_config(),
                                  batch_size or run.config.batch_size)
    by_scale = {s: measured[f"{s:g}"] for s in JUDGE_SCALES}
    return judged_correction(acceptance, delta, by_scale, pairs)
