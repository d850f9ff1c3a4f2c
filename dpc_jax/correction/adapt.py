"""Self-supervised adaptation of a trained network to the very sequence it corrects (``correct --adapt N``).

The training loss needs no ground truth, so a network can keep learning on the log being
corrected. :func:`adapt` fine-tunes a restored run for ``steps`` optimizer steps on the pairs of
one prepared sequence — its ground truth is dropped before anything reads the cache — with the
run's loss, a fresh Adam at a constant rate, and BatchNorm statistics updated. Every
``holdout_every``-th consecutive pair ``(k, k+1)`` is kept out of adaptation, with every pair of
any kind that reaches frame ``k`` or ``k+1`` (the neighbours share an image with it, a frame-skip
pair contains its motion), so the acceptance test (``dpc_jax.correction.acceptance``) judges the adapted
network on frames it has never seen.

:func:`save_adapted` writes the adapted network as a run folder (``checkpoints/config.json``,
``checkpoints/epochs/1``; usable with ``dpc-jax correct --checkpoint DIR --select last``) with its
log ``adapt.csv`` and record ``adapt.json``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import os
import time
from collections.abc import Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from dpc_jax._io import atomic_write
from dpc_jax.correction.inference import TrainedRun
from dpc_jax.data.holdout import DEFAULT_EVERY, MIN_EVERY, held_out_pairs
from dpc_jax.data.pipeline import TrainLoader
from dpc_jax.data.sequence_cache import SequenceCache
from dpc_jax.engine.driver import drive, step_key
from dpc_jax.report.tables import records_csv
from dpc_jax.runtime.progress import Progress
from dpc_jax.training.optim import create_train_state, make_optimizer
from dpc_jax.training.steps import make_train_step

if TYPE_CHECKING:
    from dpc_jax.results.correction import AdaptationSummary


@dataclass(frozen=True)
class AdaptConfig:
    """How to adapt (see the module docstring).

    * ``steps``: optimizer steps.
    * ``holdout_every``: every this-many-th consecutive pair is kept out with its frames (for the
      acceptance test); adaptation uses the pairs between them that touch none of their frames.
    * ``batch_size``, ``learning_rate``: None = the run's.
    * ``pose_warmup_steps``: first steps with ξ_corr = 0 in the loss (depth adapts first).
    * ``seed``: shuffling and dropout.
    """

    steps: int
    holdout_every: int = DEFAULT_EVERY
    batch_size: int | None = None
    learning_rate: float | None = None
    pose_warmup_steps: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        problems = []
        if self.steps < 1:
            problems.append(f"steps must be >= 1, got {self.steps}")
        if self.holdout_every < MIN_EVERY:
            problems.append(f"holdout_every must be >= {MIN_EVERY}, got {self.holdout_every}")
        if self.batch_size is not None and self.batch_size < 1:
            problems.append(f"batch_size must be >= 1, got {self.batch_size}")
        rate = self.learning_rate
        if rate is not None and not (rate > 0 and math.isfinite(rate)):
            problems.append(f"learning_rate must be > 0, got {self.learning_rate}")
        if not 0 <= self.pose_warmup_steps < self.steps:
            problems.append(f"pose_warmup_steps must be in [0, steps), got {self.pose_warmup_steps}")
        if problems:
            raise ValueError("invalid AdaptConfig: " + "; ".join(problems))


@dataclass(frozen=True)
class Adaptation:
    """An adapted network (``run``: same config, the adapted model state), the pairs it never saw
    (``held_out``), the per-step log and the seconds it took."""

    run: TrainedRun
    source: TrainedRun
    config: AdaptConfig
    held_out: np.ndarray
    log: list[dict[str, float]] = field(default_factory=list)
    seconds: float = 0.0

    def summary(self) -> AdaptationSummary:
        """What a report says of it (``dpc_jax.correction.corrector.Correction.adaptation``)."""
        return {"steps": self.config.steps, "seconds": self.seconds, "held_out": int(self.held_out.size),
                "holdout_every": self.config.holdout_every, "source_epoch": self.source.epoch}


def adapt(
    run: TrainedRun, cache: SequenceCache, config: AdaptConfig, *, progress: Progress = False
) -> Adaptation:
    """Fine-tune ``run``'s network on ``cache`` without its ground truth (module docstring)."""
    began = time.perf_counter()
    if cache.image_size != run.image_size:
        (h, w), (rh, rw) = cache.image_size, run.image_size
        raise ValueError(f"{cache.path}: images are {h}x{w}, but the run {run.workdir} expects {rh}x{rw}")
    blind = dataclasses.replace(cache, gt=None)  # adaptation never sees the ground truth
    held_out = held_out_pairs(len(blind) - 1, config.holdout_every)
    train_config = run.config
    batch_size = config.batch_size or train_config.batch_size
    loader = TrainLoader(
        [blind], batch_size, seed=config.seed, frame_skip=train_config.frame_skip,
        reverse=train_config.reverse, flow=train_config.use_flow, held_out=[held_out], workers=1,
    )
    # A constant rate: one "epoch" as long as the adaptation, so the schedule never halves.
    optimizer_config = dataclasses.replace(
        train_config, learning_rate=config.learning_rate or train_config.learning_rate, lr_halving_epochs=1,
        pose_warmup_epochs=0, pose_warmup_steps=config.pose_warmup_steps,
    )
    # A copy: the train step donates its state, and the source run stays usable.
    model = nnx.merge(run.graphdef, jax.tree.map(jnp.copy, run.state))
    graphdef, state = create_train_state(model, make_optimizer(optimizer_config, config.steps))
    step_fn = make_train_step(train_config.loss_config(), config.pose_warmup_steps)
    base_key = jax.random.key(config.seed)
    log: list[dict[str, float]] = []

    def batches() -> Generator[Any, None, None]:
        # Epoch after epoch of the loader, each closed (its threads stopped) when left.
        for epoch in itertools.count():
            with contextlib.closing(loader.epoch(epoch, put=jax.device_put)) as stream:
                yield from stream

    leaves, treedef = jax.tree.flatten(state)
    bound = step_fn.bind(graphdef, treedef)

    def step(leaves: list[jax.Array], batch: Any, index: int) -> tuple[list[jax.Array], dict[str, jax.Array]]:
        return bound(leaves, batch, step_key(base_key, index))

    def consume(index: int, values: dict[str, Any], _: Any) -> None:
        log.append({"step": index + 1, **{k: float(v) for k, v in values.items()}})

    stream = batches()
    with contextlib.closing(stream):
        leaves = drive(
            step, leaves, itertools.islice(stream, config.steps), total=config.steps,
            desc=f"adapt {cache.name}", progress=progress, consume=consume, finite="loss",
            on_nonfinite=lambda index, _: f"{cache.name}: non-finite loss, adaptation step {index + 1}",
            postfix=lambda values: {"loss": f"{float(values['loss']):.4f}"},
        )
    adapted, _ = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
    adapted.eval()
    model_graphdef, model_state = nnx.split(adapted)
    adapted_run = dataclasses.replace(run, selection=f"{run.selection}+adapted", graphdef=model_graphdef,
                                      state=model_state, improves_on_prior=True)
    return Adaptation(adapted_run, run, config, held_out, log, time.perf_counter() - began)


def save_adapted(directory: str | os.PathLike, adaptation: Adaptation, metrics: dict[str, Any]) -> Path:
    """Write the adapted network as a run folder in ``directory`` (module docstring); ``metrics``
    (e.g. the held-out Δ) go into the checkpoint's record and ``adapt.json``. Returns the folder."""
    from dpc_jax import config as config_lib
    from dpc_jax.training.checkpoints import Checkpoints

    directory = Path(directory).absolute()
    run = adaptation.run
    model = nnx.merge(run.graphdef, run.state)
    # The optimizer part is a fresh one of the run's config: what ``load_run`` expects to find.
    _, state = create_train_state(model, make_optimizer(run.config, 1))
    config_lib.save_json(directory / "checkpoints" / "config.json", run.config)
    record = {
        "val_gradient_loss": float(metrics.get("gradient_loss", math.nan)),
        "val_loop_closures": 0,
        "val_delta": float(metrics.get("delta", 0.0)),
    }
    with Checkpoints(directory, keep_last=1) as checkpoints:
        checkpoints.save(1, state, {"step": adaptation.config.steps, "metrics": record},
                         Checkpoints.best_records(None))
    atomic_write(directory / "adapt.csv", records_csv(adaptation.log))
    summary = {
        "source": {"workdir": str(adaptation.source.workdir), "selection": adaptation.source.selection,
                   "epoch": adaptation.source.epoch},
        "config": dataclasses.asdict(adaptation.config),
        "held_out_pairs": adaptation.held_out.tolist(),
        "seconds": adaptation.seconds,
        "metrics": metrics,
    }
    atomic_write(directory / "adapt.json", json.dumps(summary, indent=2) + "\n")
    return directory
