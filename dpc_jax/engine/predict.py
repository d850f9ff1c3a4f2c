"""The network over a cached sequence: ξ_corr, the loss and Δ of every consecutive pair; and Δ of any
correction there.

:func:`predict_sequence` evaluates a model (any ``graphdef, state``) on every consecutive pair
``(k, k+1)`` of a cached sequence in fixed-shape batches (the last one padded, its padding dropped),
so one compilation serves the sequence: ξ_corr, the training loss, and the paired photometric
effect Δ of the correction (``dpc_jax.nn.losses.correction_deltas``), with the network's depth or
an independent stereo depth (``dpc_jax.data.stereo_depth``). Validation during training and the
correction of a restored run (``dpc_jax.correction.inference``) both call it.

:func:`measure_effects` gives Δ of given corrections (``dpc_jax.nn.losses.candidate_deltas``) on the
pairs of a cached sequence, with its stereo depth (no network) or with a model's depth: the one
measurement under the acceptance test (``dpc_jax.correction.measure``). The step driver
(``dpc_jax.engine.driver``) runs both.
"""

from __future__ import annotations

import functools
import os
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.sharding import Mesh

from dpc_jax.data.pipeline import iterate_sequence
from dpc_jax.data.sequence_cache import SequenceCache, StereoDepth, load_cache
from dpc_jax.engine import backend, parallel
from dpc_jax.engine.driver import drive
from dpc_jax.geometry.pose_correction import check_finite
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.losses import candidate_deltas, correction_deltas, dpc_loss, with_stereo_depth
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs
from dpc_jax.runtime.progress import Progress

DELTAS = ("full", "rotation")


@dataclass(frozen=True)
class SequencePrediction:
    """The network over the ``N-1`` consecutive pairs of a sequence (arrays indexed by pair k).

    ``xi_corr [N-1, 6]``; ``photometric [N-1]``: ``L(0)``, the prior's gradient-masked
    photometric error; ``delta``: ``{name: [N-1]}``, ``L(ξ) − L(0)`` for each of :data:`DELTAS`
    (``dpc_jax.nn.losses.correction_deltas``);
    ``loss``: the training loss in evaluation mode, mean over pairs; ``measured``: with
    :func:`predict_sequence`'s ``candidates``, ``(candidates [C, N-1, 6] float32, Δ [C, N-1])``.
    """

    xi_corr: np.ndarray
    photometric: np.ndarray
    delta: dict[str, np.ndarray]
    loss: float
    measured: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def gradient_loss(self) -> float:
        """Mean over pairs of the corrected pose's gradient-masked photometric error (§IV-a)."""
        return float(np.mean(self.photometric + self.delta["full"]))


@functools.cache
def predict_step(
    mesh: Mesh | None, graphdef: nnx.GraphDef, treedef: Any, config: Any, keep: bool = False,
    loss: bool = True, deltas: tuple[str, ...] = DELTAS,
) -> Any:
    """The jitted ``step(leaves, batch) -> dict`` (evaluation mode) of the model
    ``graphdef`` with the loss ``config``, its state given as the flat list of arrays ``leaves``
    (``leaves, treedef = jax.tree.flatten(state)``), compiled with the backend's options
    (``dpc_jax.engine.backend``).

    The static parts are bound here, once per ``(mesh, graphdef, treedef, config)``, so a call
    neither hashes the graph definition nor walks the NNX state's Python tree. Δ is measured with
    ``batch.stereo_depth`` where the batch carries one
    (``dpc_jax.nn.losses.with_stereo_depth``), else with the network's depth. ``keep``: the step returns
    ``(dict, kept)``, ``kept`` the depth (and learned SSIM weight) Δ was measured with, left on the device
    for :func:`kept_effects_step`. ``loss``: False leaves the training loss out (NaN in its place);
    ``deltas``: which of :data:`DELTAS` Δ is measured of.
    """

    def step(leaves: list[jax.Array], batch: Batch) -> Any:
        model = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
        model.eval()
        outputs = model(batch)
        # The training loss (validation reads it; a correction does not): NaN where not asked for.
        value = dpc_loss(outputs, batch, config)[0] if loss else jnp.full((), jnp.nan)
        valid = None
        if batch.stereo_depth is not None:
            outputs, valid = with_stereo_depth(outputs, batch.stereo_depth)
        measured = correction_deltas(outputs, batch, config, valid, deltas)
        out = {"xi_corr": outputs.xi_corr, "loss": value, **measured}
        if not keep:
            return out
        # What Δ of other corrections on this batch reads of the outputs (no explainability mask).
        right = None if outputs.right is None else outputs.right.inv_depth
        return out, (outputs.left.inv_depth, right, outputs.ssim_weight, valid)

    kwargs: dict[str, Any] = {"compiler_options": backend.compiler_options(config.method, training=False)}
    if mesh is not None:
        kwargs["out_shardings"] = parallel.replicated(mesh)
    return jax.jit(step, **kwargs)


@functools.cache
def xi_step(graphdef: nnx.GraphDef, treedef: Any, method: str) -> Any:
    """The jitted ``step(leaves, batch) -> xi_corr [B, 6]`` (evaluation mode) of the model ``graphdef``
    (its state the flat ``leaves``): the network's forward pass alone, compiled with the backend's
    options for ``method``. What a caller that measures Δ of its own corrections
    (:func:`effects_step`; the live corrector) needs of a prediction: :func:`predict_step` also
    computes the training loss and the Δ of ``DELTAS``, which at 64×96 on a CPU took a third of
    the live corrector's time."""

    def step(leaves: list[jax.Array], batch: Batch) -> jax.Array:
        model = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
        model.eval()
        return model(batch).xi_corr

    return jax.jit(step, compiler_options=backend.compiler_options(method, training=False))


class PreparedModel:
    """A model ``(graphdef, state)`` prepared once for the backend
    (``dpc_jax.engine.backend.prepare_for_backend``) and flattened, with its compiled steps bound to it:
    what :func:`predict_sequence` and :func:`measure_effects` take, so that a caller running them on
    many short sequences (the live corrector) prepares the model and looks its programs up once."""

    def __init__(self, graphdef: nnx.GraphDef, state: nnx.State) -> None:
        self.graphdef, self.state = backend.prepare_for_backend(graphdef, state)
        self.leaves, self.treedef = jax.tree.flatten(self.state)
        self._steps: dict[tuple[Any, ...], Any] = {}

    def predict_step(self, mesh: Mesh | None, config: Any, keep: bool = False, loss: bool = True,
                     deltas: tuple[str, ...] = DELTAS) -> Any:
        """:func:`predict_step` of this model."""
        key = ("predict", mesh, config, keep, loss, deltas)
        if key not in self._steps:
            self._steps[key] = predict_step(mesh, self.graphdef, self.treedef, config, keep, loss, deltas)
        return self._steps[key]

    def xi_step(self, method: str) -> Any:
        """:func:`xi_step` of this model."""
        key = ("xi", None, method)
        if key not in self._steps:
            self._steps[key] = xi_step(self.graphdef, self.treedef, method)
        return self._steps[key]

    def effects_step(self, config: Any) -> Any:
        """:func:`effects_step` of this model (its depth, or its learned SSIM weight, in Δ)."""
        key = ("effects", None, config)
        if key not in self._steps:
            self._steps[key] = effects_step(self.graphdef, self.treedef, config)
        return self._steps[key]


Model = PreparedModel | tuple[nnx.GraphDef, nnx.State]


def predict_sequence(
    model: Model,
    cache: SequenceCache | str | os.PathLike,
    loss_config: Any,
    *,
    batch_size: int,
    use_flow: bool,
    stereo_depth: StereoDepth | None = None,
    mesh: Mesh | None = None,
    candidates: Callable[[np.ndarray], np.ndarray] | None = None,
    training_loss: bool = True,
    deltas: tuple[str, ...] = DELTAS,
    progress: Progress = False,
) -> SequencePrediction:
    """Run ``model`` (``(graphdef, state)``, or a :class:`PreparedModel`) in evaluation mode over every
    pair of ``cache`` (prepared once for the backend: ``dpc_jax.engine.backend.prepare_for_backend``).

    ``loss_config``: the run's loss config (``TrainConfig.loss_config()``). ``stereo_depth``:
    ``(inverse depth, valid)`` ``[N, camera, H, W]`` of every frame (``dpc_jax.data.stereo_depth``)
    to measure Δ with instead of the network's depth (Stereo DPC only). Batches hold
    ``min(batch_size, N-1)`` samples; with ``mesh`` each is sharded on its ``data`` axis (the
    size must then divide over the devices). The batches, with their stereo depth, are assembled
    and moved to the device by the data threads; batch k+1 is dispatched before the results of
    batch k are fetched.

    ``candidates``: ``f(ξ) → [C, N-1, 6]``, corrections made from the proposal ``ξ`` ``[N-1, 6]`` (e.g. it
    without its centred moving mean) whose Δ are measured in the same pass, with the same depth
    (:attr:`SequencePrediction.measured`): ``f`` is called as the proposal arrives, its rows not yet
    predicted NaN, and a batch is measured once its rows of ``f`` are finite (its inputs and the
    network's depth kept on the device until then), so neither the batches nor the network run again.
    Not with ``mesh``. ``training_loss``: False spares the training loss (``loss`` is then NaN);
    ``deltas``: which of :data:`DELTAS` the prediction measures Δ of (``delta`` holds those).
    """
    if candidates is not None and mesh is not None:
        raise ValueError("predict_sequence measures candidates without a mesh only")
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    prepared = model if isinstance(model, PreparedModel) else PreparedModel(*model)
    pairs = len(cache) - 1
    size = max(1, min(batch_size, pairs)) if mesh is None else batch_size
    leaves = prepared.leaves
    keep = candidates is not None
    unknown = [d for d in deltas if d not in DELTAS]
    if unknown or not deltas:
        raise ValueError(f"deltas must be a non-empty part of {DELTAS}, got {deltas}")
    step = prepared.predict_step(mesh, loss_config, keep, training_loss, tuple(deltas))
    later = _Later(candidates, loss_config, pairs, size, str(cache.path)) if candidates is not None else None
    share = parallel.process_slice(size) if mesh is not None else slice(None)

    def place(tree: Any) -> Any:
        if mesh is None:
            return jax.device_put(tree)
        return parallel.shard_batch(jax.tree.map(lambda x: x[share], tree), mesh)

    def put(batch: Batch) -> tuple[Any, np.ndarray]:
        return place(batch), np.asarray(batch.weight)

    keys = ("xi_corr", "none", *deltas)
    results: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    totals = {"loss": 0.0, "samples": 0.0}

    def run(carry: None, item: tuple[Any, np.ndarray], index: int) -> tuple[None, Any]:
        out = step(leaves, item[0])
        if later is not None:
            out, kept = out
            later.keep(index, item[0], kept, item[1])
        return carry, out

    def consume(index: int, out: dict[str, np.ndarray], item: tuple[Any, np.ndarray]) -> int:
        real = item[1] > 0
        for k in keys:
            results[k].append(np.asarray(out[k], np.float64)[real])
        totals["loss"] += float(out["loss"]) * float(real.sum())
        totals["samples"] += float(real.sum())
        if later is not None:
            later.predicted(out["xi_corr"][real], out["none"][real])
        return int(real.sum())

    # No ground truth in the batches (the self-supervised losses never read it): a sequence with it and
    # one without run the same compiled program.
    batches = iterate_sequence(cache, size, flow=use_flow, put=put, stereo_depth=stereo_depth,
                               ground_truth=False)
    drive(run, None, batches, total=pairs, desc=f"predict {cache.name}", unit="pair", progress=progress,
          consume=consume)
    merged = {k: np.concatenate(v) for k, v in results.items()}
    if merged["xi_corr"].shape[0] != pairs:
        raise RuntimeError(f"{cache.path}: got {merged['xi_corr'].shape[0]} predictions for {pairs} pairs")
    return SequencePrediction(
        xi_corr=merged["xi_corr"],
        photometric=merged["none"],
        delta={k: merged[k] for k in deltas},
        loss=totals["loss"] / totals["samples"],
        measured=None if later is None else later.finish(),
    )


class _Later:
    """The candidates' Δ of :func:`predict_sequence`: each batch kept on the device, with the depth its
    prediction measured Δ with, until its rows of the candidates are known, then measured."""

    def __init__(self, candidates: Callable[[np.ndarray], np.ndarray], config: Any, pairs: int,
                 size: int, name: str) -> None:
        self.candidates, self.pairs, self.size, self.name = candidates, pairs, size, name
        self.step = kept_effects_step(config)
        self.xi = np.full((pairs, 6), np.nan)
        self.none = np.zeros(pairs, np.float32)
        self.known = 0
        self.waiting: deque[tuple[int, Any, Any, np.ndarray]] = deque()
        self.dispatched: list[tuple[jax.Array, np.ndarray]] = []
        self.used: np.ndarray | None = None

    def keep(self, index: int, batch: Any, kept: Any, weight: np.ndarray) -> None:
        self.waiting.append((index, batch, kept, weight))

    def predicted(self, xi: np.ndarray, none: np.ndarray) -> None:
        """The next rows' proposal and ``L(0)``: measure every kept batch whose candidates are known."""
        # A proposal that is not finite never makes finite candidates: said here, as the pairs arrive.
        check_finite(xi, f"{self.name}: the network's proposal", first=self.known)
        rows = slice(self.known, self.known + len(xi))
        self.xi[rows], self.none[rows] = xi, none
        self.known += len(xi)
        self._measure(final=self.known == self.pairs)

    def _measure(self, final: bool) -> None:
        made = np.asarray(self.candidates(self.xi), np.float64)
        while self.waiting:
            index, batch, kept, weight = self.waiting[0]
            rows = np.minimum(np.arange(index * self.size, (index + 1) * self.size), self.pairs - 1)
            if not np.isfinite(made[:, rows]).all():
                if final:
                    raise RuntimeError(f"candidates of pairs {rows[0]}..{rows[-1]} not finite with every "
                                       "pair predicted")
                break
            self.waiting.popleft()
            if self.used is None:
                self.used = np.full(made.shape, np.nan, np.float32)
            self.used[:, rows] = made[:, rows]
            delta = self.step(kept, batch, jnp.asarray(made[:, rows], jnp.float32),
                              jnp.asarray(self.none[rows]))
            self.dispatched.append((delta, weight > 0))

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """``(candidates [C, N-1, 6] as measured (float32), Δ [C, N-1])``."""
        if self.waiting or self.used is None:
            raise RuntimeError(f"{len(self.waiting)} batches left unmeasured")
        delta = np.concatenate([np.asarray(d, np.float64)[:, real] for d, real in self.dispatched], axis=1)
        return self.used, delta


@functools.cache
def kept_effects_step(config: Any) -> Any:
    """The jitted ``step(kept, batch, candidates, none) -> Δ [C, B]`` of :func:`predict_sequence`'s
    candidates: :func:`dpc_jax.nn.losses.candidate_deltas` with the depth (and learned SSIM weight) a
    prediction step with ``keep`` measured its own Δ with, no network."""

    def step(kept: Any, batch: Batch, candidates: jax.Array, none: jax.Array) -> jax.Array:
        left, right, ssim_weight, valid = kept
        # The loss reads no explainability mask: the depth stands in for it.
        outputs = DPCOutputs(candidates[0], BranchOutputs(left, left),
                             None if right is None else BranchOutputs(right, right), ssim_weight)
        return candidate_deltas(outputs, batch, config, candidates, valid, none)["delta"]

    # The prediction step's options: its reconstructions are the same computation.
    return jax.jit(step, compiler_options=backend.compiler_options(config.method, training=False) or None)


@functools.cache
def effects_step(graphdef: nnx.GraphDef | None, treedef: Any, config: Any) -> Any:
    """The jitted ``step(leaves, batch, candidates, none) -> {"none", "delta"}``
    (``dpc_jax.nn.losses.candidate_deltas``): Δ ``[C, B]`` of the corrections ``candidates``
    ``[C, B, 6]``, with ``batch.stereo_depth`` when the batch has one, else with the depth of the
    model ``graphdef`` (its state the flat ``leaves``, evaluation mode); with ``graphdef`` None no
    network runs. ``none``: ``L(0)`` ``[B]`` when known, else None (measured)."""

    def step(leaves: list[jax.Array] | None, batch: Batch, candidates: jax.Array,
             none: jax.Array | None) -> dict[str, jax.Array]:
        valid = None
        if graphdef is None:
            assert batch.stereo_depth is not None
            ones = jnp.ones(batch.stereo_depth[0].shape[:1] + batch.stereo_depth[0].shape[2:], jnp.float32)
            branch = BranchOutputs(ones, ones)
            outputs, valid = with_stereo_depth(DPCOutputs(candidates[0], branch, branch), batch.stereo_depth)
        else:
            assert leaves is not None
            model = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
            model.eval()
            outputs = model(batch)
            if batch.stereo_depth is not None:
                outputs, valid = with_stereo_depth(outputs, batch.stereo_depth)
        return candidate_deltas(outputs, batch, config, candidates, valid, none)

    compiled = backend.compiler_options(config.method, training=False) if graphdef is not None else None
    return jax.jit(step, compiler_options=compiled) if compiled else jax.jit(step)


def measure_effects(
    cache: SequenceCache,
    candidates: np.ndarray,
    loss_config: Any,
    *,
    batch_size: int,
    stereo_depth: StereoDepth | None,
    model: Model | None = None,
    use_flow: bool = False,
    none: np.ndarray | None = None,
    progress: Progress = False,
) -> dict[str, np.ndarray]:
    """Δ of each of ``C`` corrections on every consecutive pair of ``cache`` →
    ``{"none": L(0) [N-1], "delta": [C, N-1]}`` (float64).

    ``candidates``: ``[C, N-1, 6]`` corrections ``[ρ (m), φ (rad)]`` of the pairs, e.g. parts of a
    network's proposal; ``loss_config``: the loss whose temporal error ``L`` is measured
    (``dpc_jax.nn.losses.temporal_pair_errors``). Depth: ``stereo_depth`` ``[N, camera, H, W]``
    (``dpc_jax.data.stereo_depth``) when given, else the depth of ``model``. ``model``:
    ``(graphdef, state)`` or a :class:`PreparedModel`, run in evaluation mode on every batch when
    given (``use_flow``: it reads flow): for its depth, or, with a stereo depth, for its learned SSIM
    weight; without a model the loss config's fixed weight is used and no network runs. ``none``:
    ``L(0)`` ``[N-1]`` when already measured with this depth (a prediction's ``photometric``), which
    spares its evaluation.
    """
    pairs = len(cache) - 1
    candidates = np.asarray(candidates, np.float32)
    if candidates.ndim != 3 or candidates.shape[1:] != (pairs, 6):
        raise ValueError(f"{cache.path}: candidates must be [C, {pairs}, 6] for its {pairs + 1} frames, got "
                         f"{candidates.shape}")
    if none is not None and np.shape(none) != (pairs,):
        raise ValueError(f"{cache.path}: L(0) must be [{pairs}], got {np.shape(none)}")
    if stereo_depth is None and model is None:
        raise ValueError("measure_effects needs a stereo depth or a model whose depth it uses")
    leaves: list[jax.Array] | None = None
    if model is None:
        step = effects_step(None, None, loss_config)
    else:
        prepared = model if isinstance(model, PreparedModel) else PreparedModel(*model)
        leaves, step = prepared.leaves, prepared.effects_step(loss_config)
    size = max(1, min(batch_size, pairs))
    known = None if none is None else np.asarray(none, np.float32)
    out: dict[str, list[np.ndarray]] = {"none": [], "delta": []}

    def put(batch: Batch) -> tuple[Batch, np.ndarray]:
        return jax.device_put(batch), np.asarray(batch.weight)

    def run(carry: None, item: tuple[Batch, np.ndarray], index: int) -> tuple[None, Any]:
        rows = np.minimum(np.arange(index * size, (index + 1) * size), pairs - 1)
        base = None if known is None else jnp.asarray(known[rows])
        return carry, step(leaves, item[0], jnp.asarray(candidates[:, rows]), base)

    def consume(index: int, effects: dict[str, np.ndarray], item: tuple[Batch, np.ndarray]) -> int:
        real = item[1] > 0
        out["none"].append(np.asarray(effects["none"], np.float64)[real])
        out["delta"].append(np.asarray(effects["delta"], np.float64)[:, real])
        return int(real.sum())

    # Batch k+1 is dispatched before the effects of batch k are fetched.
    batches = iterate_sequence(cache, size, flow=use_flow and model is not None, put=put,
                               stereo_depth=stereo_depth, ground_truth=False)
    drive(run, None, batches, total=pairs, desc=f"measure {cache.name}", unit="pair", progress=progress,
          consume=consume)
    return {"none": np.concatenate(out["none"]), "delta": np.concatenate(out["delta"], axis=1)}


def pair_batch(cache: SequenceCache, use_flow: bool, stereo_depth: StereoDepth | None) -> Batch:
    """The pair ``(0, 1)`` of a two-frame ``cache`` as :func:`predict_sequence` and :func:`measure_effects`
    assemble it (``dpc_jax.data.pipeline.iterate_sequence``: with its flow when ``use_flow``, its
    ``stereo_depth``), on the device: assembled and moved once for both steps of a live frame."""
    if len(cache) != 2:
        raise ValueError(f"{cache.path}: pair_batch takes a cache of two frames, got {len(cache)}")
    [batch] = iterate_sequence(cache, 1, flow=use_flow, put=jax.device_put, stereo_depth=stereo_depth,
                               ground_truth=False)
    return batch


def stereo_depth_of(cache: SequenceCache, acceptance_depth: str) -> StereoDepth | None:
    """The independent stereo depth of every frame of ``cache`` for ``acceptance_depth == "sgbm"``
    (the one prepared with the cache, else computed now), else None (the network's own depth)."""
    if acceptance_depth == "network":
        return None
    if acceptance_depth != "sgbm":
        raise ValueError(f"acceptance_depth must be 'network' or 'sgbm', got {acceptance_depth!r}")
    if cache.stereo_depth is not None:
        return cache.stereo_depth
    from dpc_jax.data.stereo_depth import sequence_inverse_depth

    return sequence_inverse_depth(np.asarray(cache.left), np.asarray(cache.right), float(cache.K[0, 0]),
                                  cache.baseline)
