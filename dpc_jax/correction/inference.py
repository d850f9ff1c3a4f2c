"""Inference: restore a trained run and run its network over a sequence (ξ_corr and Δ per pair).

The path from a trained run to corrections, used by ``dpc-jax correct``, adaptation, the demo and
the experiments. Of the training package it imports only the run's config and its checkpoint
format (``dpc_jax.training.train_config``, ``dpc_jax.training.checkpoints``): never the loop, the step or
the optimizer (the import contracts in ``pyproject.toml`` say so).

* :func:`load_run` restores the model of a run written by ``dpc-jax train`` at the epoch chosen by
  a selection criterion (:data:`SELECTIONS`); the optimizer's part of the checkpoint is not read.
* :func:`run_prediction` runs a restored run's network through
  :func:`dpc_jax.engine.predict.predict_sequence` (also what validation during training runs) on
  every consecutive pair ``(k, k+1)`` of a cached sequence: ξ_corr, the training loss, and the
  paired photometric effect Δ of the correction.
* Composing the corrected trajectory is ``dpc_jax.geometry.pose_correction.corrected_trajectory``.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import nnx

from dpc_jax.data.sequence_cache import SequenceCache, load_cache
from dpc_jax.engine.predict import (
    DELTAS,
    PreparedModel,
    SequencePrediction,
    predict_sequence,
    stereo_depth_of,
)
from dpc_jax.runtime.progress import Progress
from dpc_jax.training.train_config import DEFAULT_SELECTION, SELECTIONS, TrainConfig


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

    @functools.cached_property
    def prepared(self) -> PreparedModel:
        """The model prepared once for the backend, its compiled steps bound to it: every pass of this run
        (prediction, measurement) shares it instead of preparing the model again."""
        return PreparedModel(self.graphdef, self.state)

    def __getstate__(self) -> dict[str, Any]:
        # The prepared model holds compiled programs: a copy sent to another process prepares its own.
        return {k: v for k, v in self.__dict__.items() if k != "prepared"}

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` the network expects."""
        height, width = self.config.resolved_image_size
        return height, width

    @property
    def use_flow(self) -> bool:
        """Whether the network reads optical flow."""
        return self.config.use_flow


def load_run(workdir: str | os.PathLike, select: str = DEFAULT_SELECTION) -> TrainedRun:
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
        # The model alone: its abstract state gives the structure to read from the checkpoint.
        graphdef, initial = nnx.split(nnx.eval_shape(
            lambda: create_model(config.method, config.model_config(), config.seed)
        ))
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, initial)
        state = checkpoints.restore_model(abstract, which=which, epoch=epoch)
    finally:
        checkpoints.close()
    model = nnx.merge(graphdef, state)
    model.eval()
    model_graphdef, model_state = nnx.split(model)
    return TrainedRun(workdir, config, select, int(epoch), model_graphdef, model_state, improves)


def run_prediction(
    run: TrainedRun,
    cache: SequenceCache,
    *,
    batch_size: int | None = None,
    acceptance_depth: str | None = None,
    candidates: Callable[[np.ndarray], np.ndarray] | None = None,
    training_loss: bool = True,
    deltas: tuple[str, ...] = DELTAS,
    progress: Progress = False,
) -> SequencePrediction:
    """:func:`dpc_jax.engine.predict.predict_sequence` with a restored run's model, loss and settings.

    ``acceptance_depth``: ``network`` or ``sgbm`` (default: the run's ``acceptance_depth``);
    ``candidates``: corrections made from the proposal, measured in the same pass; ``training_loss``: False
    spares the training loss (``loss`` NaN), which a correction never reads; ``deltas``: which of
    ``DELTAS`` Δ is measured of.
    """
    if cache.image_size != run.image_size:
        (h, w), (rh, rw) = cache.image_size, run.image_size
        raise ValueError(
            f"{cache.path}: images are {h}x{w}, but the run {run.workdir} expects {rh}x{rw}; "
            f"prepare the sequence with --size {rh}x{rw}"
        )
    return predict_sequence(
        run.prepared, cache, run.config.loss_config(),
        batch_size=batch_size or run.config.batch_size, use_flow=run.config.use_flow,
        stereo_depth=stereo_depth_of(cache, acceptance_depth or run.config.acceptance_depth),
        candidates=candidates, training_loss=training_loss, deltas=deltas, progress=progress,
    )


def predict_corrections(
    run: TrainedRun,
    cache: SequenceCache | str | os.PathLike,
    batch_size: int | None = None,
    progress: Progress = False,
) -> np.ndarray:
    """``ξ_corr [N-1, 6]`` of the consecutive pairs of a cached sequence (:func:`run_prediction`)."""
    cache = cache if isinstance(cache, SequenceCache) else load_cache(cache)
    return run_prediction(
        run, cache, batch_size=batch_size, acceptance_depth="network", progress=progress
    ).xi_corr
