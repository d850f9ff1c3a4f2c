"""The training loop: data, checkpoints, logging and validation each epoch around the jitted step.

Functional core (docs/method.md §3, §5): the model and its optimizer (``dpc_jax.training.optim``)
are split once, ``graphdef, state = nnx.split((model, optimizer))``; ``state`` holds the parameters, the
BatchNorm statistics, the prior statistics, the Adam moments and the step count.
``make_train_step`` returns ONE jitted pure function ``train_step(graphdef, state, batch, key) ->
(state, metrics)`` that merges, differentiates the loss w.r.t. the ``nnx.Param`` variables only,
applies the optimizer and splits again; ``state`` is donated. Given a mesh
(``dpc_jax.engine.parallel``), the batch is sharded on ``data`` and the state replicated, so the same
function runs on 1..N devices and hosts, with the gradient mean and the BatchNorm batch
statistics over the global batch.

Pose warm-up (``TrainConfig.pose_warmup_*``): while the optimizer's step count is below the
warm-up length the loss sees ξ_corr = 0, so depth, masks and λ_s learn first; the pose head's
updates are masked in the optimizer for the same steps.

Validation (each epoch, ``dpc_jax.engine.predict.predict_sequence``) gives the three selection
criteria of ``dpc_jax.training.checkpoints``: the gradient loss, the loop-closure count of the corrected
validation trajectory and the mean paired photometric effect Δ of the correction.

The loop (``train``) and its files are described in its docstring. The data it opens
(``dpc_jax.training.train_data``), its metrics log (``dpc_jax.training.metrics_log``), the validation
(``dpc_jax.training.validation``) and the workdir checks (``dpc_jax.training.workdir``) have their
own modules.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import orbax.checkpoint as ocp
from flax import nnx
from jax.sharding import Mesh

from dpc_jax import config as config_lib
from dpc_jax._io import InputWarning
from dpc_jax.config import ConfigError
from dpc_jax.engine import parallel
from dpc_jax.engine.driver import drive, step_key
from dpc_jax.runtime.progress import Progress
from dpc_jax.training.checkpoints import Checkpoints
from dpc_jax.training.metrics_log import MetricsLog
from dpc_jax.training.optim import create_train_state, learning_rate_schedule, make_optimizer
from dpc_jax.training.steps import NonFiniteLossError, TrainStep, make_train_step
from dpc_jax.training.train_config import TrainConfig
from dpc_jax.training.train_data import TrainData, open_data
from dpc_jax.training.validation import validate
from dpc_jax.training.workdir import check_split, check_workdir

if TYPE_CHECKING:
    import optax

    from dpc_jax.training.checkpoints import Record



def _train_epoch(
    epoch: int,
    graphdef: nnx.GraphDef,
    state: nnx.State,
    train_step: TrainStep,
    data: TrainData,
    config: TrainConfig,
    mesh: Mesh,
    first_step: int,
    log: MetricsLog,
    progress: Progress,
) -> tuple[nnx.State, dict[str, float]]:
    """One epoch of optimizer steps; returns the new state and the epoch means of the step metrics.

    The step driver (``dpc_jax.engine.driver``) runs it: the data threads put each batch (this
    process's slice) on the mesh ahead of its step, and the metrics of step i are fetched after
    step i+1 is dispatched, so the host never stalls the device; between steps the state travels
    as its flat list of arrays (``TrainStep.bind``); a non-finite loss raises
    ``NonFiniteLossError`` (the state is then discarded).
    """
    share = parallel.process_slice(config.batch_size)
    base_key = jax.random.key(config.seed)
    sums: dict[str, float] = {}
    timing = {"start": 0.0, "samples": 0, "rate": 0.0}

    def put(batch: Any) -> Any:
        return parallel.shard_batch(jax.tree.map(lambda x: x[share], batch), mesh)

    leaves, treedef = jax.tree.flatten(state)
    bound = train_step.bind(graphdef, treedef)

    def step(leaves: list[jax.Array], batch: Any, index: int) -> tuple[list[jax.Array], dict[str, jax.Array]]:
        return bound(leaves, batch, step_key(base_key, first_step + index))

    def consume(index: int, values: dict[str, Any], _: Any) -> None:
        for k, v in values.items():
            sums[k] = sums.get(k, 0.0) + float(v)
        now = time.perf_counter()
        if timing["start"] == 0.0:
            timing["start"] = now
        else:
            timing["samples"] += config.batch_size
            timing["rate"] = timing["samples"] / (now - timing["start"])
        if (first_step + index + 1) % config.log_every == 0:
            log.scalars(first_step + index + 1, {k: float(v) for k, v in values.items()}, "train")

    def nonfinite(index: int, value: float) -> str:
        return (
            f"non-finite training loss ({value}) at epoch {epoch}, step {first_step + index + 1}; stopping. "
            f"The last good checkpoint (epoch {epoch - 1}) is intact; lower learning_rate or check the "
            "data, then continue with --resume"
        )

    def postfix(values: dict[str, Any]) -> dict[str, str]:
        return {"loss": f"{float(values['loss']):.4f}", "samples_s": f"{timing['rate']:.1f}"}

    with contextlib.closing(data.loader.epoch(epoch, put=put)) as batches:
        leaves = drive(
            step, leaves, itertools.islice(batches, data.steps_per_epoch),
            total=data.steps_per_epoch, desc=f"epoch {epoch}/{config.epochs}", progress=progress,
            consume=consume, finite="loss", on_nonfinite=nonfinite, postfix=postfix,
        )
    state = jax.tree.unflatten(treedef, leaves)
    n = data.steps_per_epoch
    means = {f"train_{k}": v / n for k, v in sums.items()}
    means["samples_per_s"] = timing["rate"]
    return state, means


def _initial_state(
    config: TrainConfig, data: TrainData, mesh: Mesh
) -> tuple[nnx.GraphDef, nnx.GraphDef, nnx.State]:
    """A fresh model with the training prior statistics, split with its optimizer onto ``mesh``.

    Returns ``(model_graphdef, graphdef, state)``: ``state[0]`` of the train state is the model's
    and merges with ``model_graphdef`` (validation runs the model alone).
    """
    from dpc_jax.nn.models import create_model, set_prior_statistics

    model = create_model(config.method, config.model_config(), config.seed)
    set_prior_statistics(model, *data.prior_statistics)
    model_graphdef = nnx.graphdef(model)
    graphdef, state = create_train_state(model, make_optimizer(config, data.steps_per_epoch), mesh)
    return model_graphdef, graphdef, state


def _check_finite_validation(val: dict[str, Any], epoch: int) -> None:
    if not all(math.isfinite(val[k]) for k in ("val_loss", "val_gradient_loss", "val_delta")):
        raise NonFiniteLossError(
            f"non-finite validation loss at epoch {epoch} ({val['val_loss']}, gradient loss "
            f"{val['val_gradient_loss']}); stopping. "
            f"The last good checkpoint (epoch {epoch - 1}) is intact"
        )


@dataclass(frozen=True)
class _Run:
    """What the epochs of one ``train`` call share (the state, step and best records they advance are passed
    from one to the next)."""

    config: TrainConfig
    data: TrainData
    mesh: Mesh
    model_graphdef: nnx.GraphDef
    graphdef: nnx.GraphDef
    train_step: TrainStep
    schedule: optax.Schedule
    checkpoints: Checkpoints
    log: MetricsLog
    progress: Progress
    is_main: bool


def _open_run(
    config: TrainConfig,
    workdir: Path,
    resume: bool,
    distributed: dict[str, Any] | None,
    workers: int,
) -> tuple[bool, TrainData, Mesh]:
    """Check the workdir, join the distributed run, open the data and make the mesh; return whether
    there is a run to resume, the data and the mesh. Raises ``ConfigError`` before any compute."""
    has_run = check_workdir(config, workdir, resume)
    if config.distributed:
        parallel.initialize_distributed(**(distributed or {}))
    data = open_data(config, workers=workers)
    if has_run:
        check_split(workdir, data.split)
    mesh = parallel.make_mesh()
    try:
        parallel.check_batch_size(config.batch_size, mesh)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    return has_run, data, mesh


def _start_run(
    config: TrainConfig, workdir: Path, data: TrainData, mesh: Mesh, has_run: bool, progress: Progress
) -> tuple[_Run, nnx.State, dict[str, Any] | None]:
    """Build the model, optimizer and train state, restore the newest epoch checkpoint of a run being
    resumed (else record the new run's config and split), make the schedule and the train step and
    open the metrics log. Returns the run, the state and the restored checkpoint's meta (or None)."""
    is_main = jax.process_index() == 0
    model_graphdef, graphdef, state = _initial_state(config, data, mesh)
    checkpoints = Checkpoints(workdir, keep_last=config.keep_checkpoints)
    meta: dict[str, Any] | None = None
    if has_run and checkpoints.latest_epoch() is not None:
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, state)
        state, meta = checkpoints.restore(abstract)
    elif is_main:
        config_lib.save_json(checkpoints.root / "config.json", config)
        config_lib.save_json(checkpoints.root / "split.json", data.split)
    schedule = learning_rate_schedule(config.learning_rate, config.lr_halving_epochs, data.steps_per_epoch)
    from dpc_jax.nn.supervised_loss import with_target_precision

    # The supervised loss without a precision gets DPC-Net's, from the training pairs.
    table = data.loader.table
    loss_config = with_target_precision(config.train_loss_config(), table.xi_vo, table.xi_gt)
    train_step = make_train_step(loss_config, config.warmup_steps(data.steps_per_epoch), mesh)
    log = MetricsLog(workdir, meta["epoch"] if meta else 0, meta["step"] if meta else 0, enabled=is_main)
    run = _Run(config, data, mesh, model_graphdef, graphdef, train_step, schedule, checkpoints, log, progress,
               is_main)
    return run, state, meta


def _run_epoch(
    run: _Run, epoch: int, state: nnx.State, step: int, best: dict[str, Record]
) -> tuple[nnx.State, int, dict[str, Any], dict[str, Record]]:
    """Train epoch ``epoch`` from optimizer step ``step``, validate, log its metrics row, save its
    checkpoint and print its line; return the new state, step, row and best records."""
    config, data = run.config, run.data
    began = time.perf_counter()
    learning_rate = float(run.schedule(step))
    state, train_means = _train_epoch(
        epoch, run.graphdef, state, run.train_step, data, config, run.mesh, step, run.log, run.progress
    )
    step += data.steps_per_epoch
    val = validate(run.model_graphdef, state[0], data, config, run.mesh)
    _check_finite_validation(val, epoch)
    row = {
        "epoch": epoch,
        "step": step,
        "learning_rate": learning_rate,
        **train_means,
        **val,
        "epoch_time_s": time.perf_counter() - began,
    }
    run.log.epoch(row)
    # ``data`` is where a resume picks up: the next epoch, from its first batch, in the same order.
    meta = {
        "step": step,
        "metrics": row,
        "data": {
            "next_epoch": epoch + 1,
            "next_batch": 0,
            "data_seed": config.data_seed,
            "steps_per_epoch": data.steps_per_epoch,
        },
    }
    best = run.checkpoints.save(epoch, state, meta, best)
    if run.is_main:
        print(_epoch_line(row), file=sys.stderr if run.progress else sys.stdout, flush=True)
    return state, step, row, best


def train(
    config: TrainConfig,
    workdir: str | os.PathLike,
    resume: bool = False,
    *,
    progress: Progress = None,
    distributed: dict[str, Any] | None = None,
    workers: int = 2,
) -> dict[str, Any]:
    """Train ``config`` in ``workdir``; return a summary (epochs, steps, best epochs, last metrics).

    Files: ``WORKDIR/checkpoints/`` (see ``dpc_jax.training.checkpoints``: every epoch, the best by
    gradient loss, by loop closures and by Δ, ``config.json``, ``split.json``),
    ``WORKDIR/metrics.csv`` (one row per epoch: step, learning rate, training means, samples/s,
    validation figures), ``WORKDIR/tensorboard/`` (the same, plus training scalars every
    ``log_every`` steps).

    ``resume=True`` continues from the newest epoch checkpoint (same config required); an
    interrupted epoch is redone from its start with the same data order and dropout keys.
    ``progress``: bars, ``"lines"`` for a line every few seconds (``dpc_jax.runtime.progress``), or
    None: bars when stderr is a terminal. ``distributed``: keyword
    arguments of ``jax.distributed.initialize`` when ``config.distributed``.

    Errors before any compute: ``ConfigError`` for a bad split, missing cache, wrong image size,
    or a workdir holding another run. ``NonFiniteLossError`` when a loss becomes NaN/inf. A config
    whose pose warm-up lasts every epoch (``TrainConfig.pose_training_problem``) trains a network that
    corrects nothing: an ``InputWarning`` says so, with the epochs it needs.
    """
    workdir = Path(workdir).absolute()
    problem = config.pose_training_problem()
    if problem is not None:
        warnings.warn(InputWarning(problem), stacklevel=2)
    has_run, data, mesh = _open_run(config, workdir, resume, distributed, workers)
    progress = sys.stderr.isatty() if progress is None else progress
    run, state, meta = _start_run(config, workdir, data, mesh, has_run, progress)
    start_epoch = meta["epoch"] if meta else 0
    step = meta["step"] if meta else 0
    best = Checkpoints.best_records(meta)
    # A resumed run with no epoch left to do reports the metrics of its last checkpoint.
    row: dict[str, Any] = meta["metrics"] if meta else {}
    try:
        for epoch in range(start_epoch + 1, config.epochs + 1):
            state, step, row, best = _run_epoch(run, epoch, state, step, best)
    finally:
        run.log.close()
        run.checkpoints.close()
    return {
        "workdir": str(workdir),
        "epochs": config.epochs,
        "step": step,
        "best_epoch": {c: r.epoch for c, r in best.items()},
        "metrics": row,
    }


def _epoch_line(row: dict[str, Any]) -> str:
    text = (
        f"epoch {row['epoch']}: loss {row['train_loss']:.4f}, val loss {row['val_loss']:.4f}, "
        f"gradient loss {row['val_gradient_loss']:.4f}, Δ {row['val_delta']:.2e}, "
        f"loop closures {row['val_loop_closures']}, "
        f"{row['samples_per_s']:.1f} samples/s"
    )
    if math.isfinite(row["val_corrected_r_err"]):
        text += (
            f", r_err {row['val_prior_r_err']:.3f} → {row['val_corrected_r_err']:.3f} °/100m, "
            f"t_err {row['val_prior_t_err']:.2f} → {row['val_corrected_t_err']:.2f} %"
        )
    return text
