"""Inference: restore a trained run and run its network over a sequence (ξ_corr and Δ per pair).

The one path from a model to corrections, used by validation during training, ``dpc-jax correct``,
adaptation, the demo and the experiments. It imports neither the training loop nor its logging.

* :func:`load_run` restores a run written by ``dpc-jax train`` at the epoch chosen by a
  selection criterion (:data:`SELECTIONS`).
* :func:`predict_sequence` evaluates a model (any ``graphdef, state``) on every consecutive pair
  ``(k, k+1)`` of a cached sequence in fixed-shape batches (the last one padded, its padding
  dropped), so one compilation serves the sequence: ξ_corr, the training loss, and the paired
  photometric effect Δ of the correction (``dpc_jax.nn.losses.correction_deltas``), with the
  network's depth or an independent stereo depth (``dpc_jax.data.stereo_depth``).
* Composing the corrected trajectory is ``dpc_jax.geometry.correction.corrected_trajectory``.
"""

from __future__ import annotations

import contextlib
import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.sharding import Mesh
from tqdm.auto import tqdm

from dpc_jax.data.pipeline import iterate_sequence
from dpc_jax.data.sequence_cache import SequenceCache, load_cache
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.conv import compiler_options
from dpc_jax.nn.losses import correction_deltas, dpc_loss
from dpc_jax.nn.models import prepare_inference
from dpc_jax.training import parallel
from dpc_jax.training.config import SELECTIONS, TrainConfig


@dataclass(frozen=True)
class TrainedRun:
    """A restored training run: its config, the chosen epoch and the model split for inference.

    ``improves_on_prior`` is False when the selection ``delta`` found no epoch whose validation
    Δ was below zero; the state is then the newest epoch's (what ``--force`` or adaptation use).
    """

    workdir: Path
    config: TrainConfig
    selection: str
    epoch: int
    graphdef: nnx.GraphDef
    state: nnx.State
    improves_on_prior: bool = True

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` the network expects."""
        height, width = self.config.resolved_image_size
        return height, width

    @property
    def use_flow(self) -> bool:
        """Whether the network reads optical flow."""
        return self.config.use_flow


def load_run(workdir: str | os.PathLike, select: str = "delta") -> TrainedRun:
    """Restore the run in ``workdir`` (written by ``dpc-jax train``) at the epoch chosen by ``select``.

    ``select``: ``delta`` (most negative validation Δ; no epoch if none is below 0), ``gradient``
    (lowest validation gradient loss), ``loop`` (most loop closures) or ``last`` (newest epoch).
    Raises ``FileNotFoundError`` when ``workdir`` holds no run or no checkpoint, ``ValueError``
    for an unknown ``select``.
    """
    import orbax.checkpoint as ocp

    from dpc_jax import config as config_lib
    from dpc_jax.nn.models import create_model
    from dpc_jax.training.checkpoints import Checkpoints
    from dpc_jax.training.optim import create_train_state, make_optimizer

    if select not in SELECTIONS:
        raise ValueError(f"select must be one of {', '.join(SELECTIONS)}, got {select!r}")
    workdir = Path(workdir).absolute()
    config_path = workdir / "checkpoints" / "config.json"
    if not config_path.is_file():
        raise FileNotFoundError(
            f"{workdir}: not a training run (expected {config_path}, written by `dpc-jax train`)"
        )
    config = config_lib.load_file(config_path, TrainConfig)
    which = SELECTIONS[select]
    checkpoints = Checkpoints(workdir, keep_last=None, read_only=True)
    try:
        epoch = checkpoints.latest_epoch(which)
        improves = True
        if epoch is None and select == "delta":
            which, epoch, improves = "epochs", checkpoints.latest_epoch("epochs"), False
        if epoch is None:
            raise FileNotFoundError(
                f"{checkpoints.root / which}: no checkpoint to restore (--select {select}); "
                "has the run finished an epoch?"
            )
        # The stored state holds the optimizer too; its schedule does not change the state's layout.
        model = create_model(config.method, config.model_config(), config.seed)
        graphdef, initial = create_train_state(model, make_optimizer(config, 1))
        del model
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, initial)
        state, _ = checkpoints.restore(abstract, which=which, epoch=epoch)
    finally:
        checkpoints.close()
    model, _ = nnx.merge(graphdef, state)
    model.eval()
    model_graphdef, model_state = nnx.split(model)
    return TrainedRun(workdir, config, select, int(epoch), model_graphdef, model_state, improves)


@dataclass(frozen=True)
class SequencePrediction:
    """The network over the ``N-1`` consecutive pairs of a sequence (arrays indexed by pair k).

    ``xi_corr [N-1, 6]``; ``photometric [N-1]``: ``L(0)``, the prior's gradient-masked
    photometric error; ``delta``: ``{"full", "rotation"}: [N-1]``, ``L(ξ) − L(0)``;
    ``loss``: the training loss in evaluation mode, mean over pairs.
    """

    xi_corr: np.ndarray
    photometric: np.ndarray
    delta: dict[str, np.ndarray]
    loss: float

    @property
    def gradient_loss(self) -> float:
        """Mean over pairs of the corrected pose's gradient-masked photometric error (§IV-a)."""
        return float(np.mean(self.photometric + self.delta["full"]))


@functools.cache
def _predict_step(mesh: Mesh | None, method: str) -> Any:
    """The jitted ``step(graphdef, state, batch, config, depth) -> dict`` (evaluation mode) for
    ``method``'s network."""

    def step(graphdef: nnx.GraphDef, state: nnx.State, batch: Batch, config: Any,
             depth: tuple[jax.Array, jax.Array] | None) -> dict[str, jax.Array]:
        model = nnx.merge(graphdef, state)
        model.eval()
        outputs = model(batch)
        loss, _ = dpc_loss(outputs, batch, config)
        valid = None
        if depth is not None:
            # [B, camera, frame, H, W]: the independent depth replaces the network's; holes are
            # filled with 1 m and left out through ``valid``.
            inverse, ok = depth
            left = outputs.left._replace(inv_depth=jnp.where(ok[:, 0], inverse[:, 0], 1.0))
            right = outputs.right._replace(inv_depth=jnp.where(ok[:, 1], inverse[:, 1], 1.0))
            outputs, valid = outputs._replace(left=left, right=right), (ok[:, 0], ok[:, 1])
        deltas = correction_deltas(outputs, batch, config, valid)
        return {"xi_corr": outputs.xi_corr, "loss": loss, **deltas}

    kwargs: dict[str, Any] = {"compiler_options": compiler_options(method, training=False)}
    if mesh is not None:
        kwargs["out_shardings"] = parallel.replicated(mesh)
    return jax.jit(step, static_argnums=(0, 3), **kwargs)


def _pair_depths(stereo: tuple[np.ndarray, np.ndarray], size: int, n_pairs: int) -> list[tuple[Any, Any]]:
    """Per batch of ``size`` pairs: the stereo depth of frames ``(k, k+1)`` → ``[B, camera, frame, H, W]``."""
    inverse, valid = stereo
    out = []
    for start in range(0, n_pairs, size):
        k = np.minimum(np.arange(start, start + size), n_pairs - 1)  # padding repeats the last pair
        frames = np.stack([k, k + 1], axis=1)
        out.append((np.moveaxis(inverse[frames], 1, 2), np.moveaxis(valid[frames], 1, 2)))
    return out


def predict_sequence(
    graphdef: nnx.GraphDef,
    state: nnx.State,
    cache: SequenceCache | str | os.PathLike,
    loss_config: Any,
    *,
    batch_size: int,
    use_flow: bool,
    stereo_depth: tuple[np.ndarray, np.ndarray] | None = None,
    mesh: Mesh | None = None,
    progress: bool = False,
) -> SequencePrediction:
    """Run the model ``(graphdef, state)`` in evaluation mode over every pair of ``cache``
    (prepared once: ``dpc_jax.nn.models.prepare_inference``).

    ``loss_config``: the run's loss config (``TrainConfig.loss_config()``). ``stereo_depth``:
    ``(inverse depth, valid)`` ``[N, camera, H, W]`` of every frame (``dpc_jax.data.stereo_depth``)
    to measure Δ with instead of the network's depth (Stereo DPC only). Batches hold
    ``min(batch_size, N-1)`` samples; with ``mesh`` each is sharded on its ``data`` axis (the
    size must then divide over the devices). Batch k+1 is dispatched before the results of
    batch k are fetched.
    """
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    graphdef, state = prepare_inference(graphdef, state)
    pairs = len(cache) - 1
    size = max(1, min(batch_size, pairs)) if mesh is None else batch_size
    step = _predict_step(mesh, loss_config.method)
    depths = _pair_depths(stereo_depth, size, pairs) if stereo_depth is not None else None
    share = parallel.process_slice(size) if mesh is not None else slice(None)
    keys = ("xi_corr", "none", "full", "rotation")
    results: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    totals = {"loss": 0.0, "samples": 0.0}

    def fetch(out: dict[str, jax.Array], weight: np.ndarray) -> None:
        out = jax.device_get(out)
        real = weight > 0
        for k in keys:
            results[k].append(np.asarray(out[k], np.float64)[real])
        totals["loss"] += float(out["loss"]) * float(real.sum())
        totals["samples"] += float(real.sum())
        bar.update(int(real.sum()))

    pending: tuple[dict[str, jax.Array], np.ndarray] | None = None
    with contextlib.closing(iterate_sequence(cache, size, flow=use_flow)) as batches, tqdm(
        total=pairs, unit="pair", desc=f"predict {cache.name}", disable=not progress, leave=False
    ) as bar:
        for b, batch in enumerate(batches):
            depth = None if depths is None else depths[b]
            weight = np.asarray(batch.weight)
            if mesh is not None:
                batch = parallel.shard_batch(jax.tree.map(lambda x: x[share], batch), mesh)
                if depth is not None:
                    depth = parallel.shard_batch(jax.tree.map(lambda x: x[share], depth), mesh)
            out = step(graphdef, state, batch, loss_config, depth)
            if pending is not None:
                fetch(*pending)
            pending = (out, weight)
        if pending is not None:
            fetch(*pending)
    merged = {k: np.concatenate(v) for k, v in results.items()}
    if merged["xi_corr"].shape[0] != pairs:
        raise RuntimeError(f"{cache.path}: got {merged['xi_corr'].shape[0]} predictions for {pairs} pairs")
    return SequencePrediction(
        xi_corr=merged["xi_corr"],
        photometric=merged["none"],
        delta={"full": merged["full"], "rotation": merged["rotation"]},
        loss=totals["loss"] / totals["samples"],
    )


def run_prediction(
    run: TrainedRun,
    cache: SequenceCache,
    *,
    batch_size: int | None = None,
    acceptance_depth: str | None = None,
    progress: bool = False,
) -> SequencePrediction:
    """:func:`predict_sequence` with a restored run's model, loss and settings.

    ``acceptance_depth``: ``network`` or ``sgbm`` (default: the run's ``acceptance_depth``).
    """
    if cache.image_size != run.image_size:
        (h, w), (rh, rw) = cache.image_size, run.image_size
        raise ValueError(
            f"{cache.path}: images are {h}x{w}, but the run {run.workdir} expects {rh}x{rw}; "
            f"prepare the sequence with --size {rh}x{rw}"
        )
    return predict_sequence(
        run.graphdef, run.state, cache, run.config.loss_config(),
        batch_size=batch_size or run.config.batch_size, use_flow=run.config.use_flow,
        stereo_depth=stereo_depth_of(cache, acceptance_depth or run.config.acceptance_depth),
        progress=progress,
    )


def predict_corrections(
    run: TrainedRun,
    cache: SequenceCache | str | os.PathLike,
    batch_size: int | None = None,
    progress: bool = False,
) -> np.ndarray:
    """``ξ_corr [N-1, 6]`` of the consecutive pairs of a cached sequence (:func:`run_prediction`)."""
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    return run_prediction(
        run, cache, batch_size=batch_size, acceptance_depth="network", progress=progress
    ).xi_corr


def stereo_depth_of(cache: SequenceCache, acceptance_depth: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The independent stereo depth of every frame of ``cache`` for ``acceptance_depth == "sgbm"``,
    else None (the network's own depth)."""
    if acceptance_depth == "network":
        return None
    if acceptance_depth != "sgbm":
        raise ValueError(f"acceptance_depth must be 'network' or 'sgbm', got {acceptance_depth!r}")
    from dpc_jax.data.stereo_depth import sequence_inverse_depth

    return sequence_inverse_depth(np.asarray(cache.left), np.asarray(cache.right), float(cache.K[0, 0]),
                                  cache.baseline)
