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

The loop (``train``) and its files are described in its docstring.
"""

from __future__ import annotations

import contextlib
import csv
import io
import itertools
import json
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np
import orbax.checkpoint as ocp
from flax import nnx
from jax.sharding import Mesh

from dpc_jax import config as config_lib
from dpc_jax._io import atomic_write
from dpc_jax._progress import Progress
from dpc_jax.config import ConfigError
from dpc_jax.engine import parallel
from dpc_jax.engine.driver import drive, step_key
from dpc_jax.engine.predict import predict_sequence, stereo_depth_of
from dpc_jax.eval import metrics as metrics_lib
from dpc_jax.geometry.correction import corrected_trajectory
from dpc_jax.training.checkpoints import Checkpoints
from dpc_jax.training.config import TrainConfig
from dpc_jax.training.optim import create_train_state, learning_rate_schedule, make_optimizer
from dpc_jax.training.steps import NonFiniteLossError, make_train_step

if TYPE_CHECKING:
    import optax

    from dpc_jax.training.checkpoints import Record

# --------------------------------------------------------------------------- data


@dataclass(frozen=True)
class ValidationSequence:
    """One validation sequence: its cache, prior trajectory, (optional) ground truth and, with
    ``acceptance_depth="sgbm"``, the stereo depth Δ is measured with."""

    name: str
    cache: Any
    prior: np.ndarray
    ground_truth: np.ndarray | None
    stereo_depth: tuple[np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True)
class TrainData:
    """What the loop consumes: the training loader, the validation sequences, the split record and
    the per-component mean and scale of the training priors (``prior_statistics [2, 6]``)."""

    loader: Any
    steps_per_epoch: int
    validation: tuple[ValidationSequence, ...]
    use_flow: bool
    split: dict[str, Any]
    prior_statistics: np.ndarray


def open_data(config: TrainConfig, workers: int = 2) -> TrainData:
    """Open the cache of ``config``: check the split and the image size, build the loaders.

    Raises ``ConfigError`` for a sequence that is not cached, an empty training set or an image
    size different from the model's, before any compute.
    """
    from dpc_jax.data.pipeline import TrainLoader
    from dpc_jax.data.sequence_cache import load_cache, training_sequences

    try:
        # The command line checks the same caches before it starts JAX (dpc_jax.cli.train).
        train_names = training_sequences(
            config.cache_root, config.train_sequences, config.validation_sequences, config.test_sequences
        )
    except ValueError as error:
        raise ConfigError(str(error)) from None
    root = Path(config.cache_root)
    size = config.resolved_image_size
    caches = {name: load_cache(root / name) for name in [*train_names, *config.validation_sequences]}
    for name, cache in caches.items():
        if cache.image_size != size:
            raise ConfigError(
                f"{root / name}: images are {cache.image_size[0]}x{cache.image_size[1]}, the model expects "
                f"{size[0]}x{size[1]} (image_size); prepare the cache with --size {size[0]}x{size[1]}"
            )
    use_flow = config.use_flow
    loader = TrainLoader(
        [caches[n] for n in train_names],
        config.batch_size,
        seed=config.data_seed,
        frame_skip=config.frame_skip,
        reverse=config.reverse,
        flow=use_flow,
        # Ground truth reaches the training batches only for the supervised loss.
        ground_truth=config.supervision == "supervised",
        workers=workers,
    )
    steps = min(len(loader), config.steps_per_epoch or len(loader))
    validation = tuple(
        ValidationSequence(n, caches[n], np.asarray(caches[n].prior), caches[n].gt,
                           stereo_depth_of(caches[n], config.acceptance_depth))
        for n in config.validation_sequences
    )
    statistics = prior_statistics(loader.table.xi_vo, config.prior_normalization)
    split = {
        "cache_root": str(Path(config.cache_root).absolute()),
        "train": train_names,
        "validation": list(config.validation_sequences),
        "test": list(config.test_sequences),
        "train_samples": loader.num_samples,
        "steps_per_epoch": steps,
        "validation_pairs": {v.name: len(v.cache) - 1 for v in validation},
        "input_hashes": {n: c.manifest.get("input_hash") for n, c in caches.items()},
        "prior_statistics": statistics.tolist(),
    }
    return TrainData(loader, steps, validation, use_flow, split, statistics)


def prior_statistics(xi_vo: np.ndarray, normalization: str) -> np.ndarray:
    """``[2, 6]`` mean and scale of the prior input: those of ``xi_vo [S, 6]`` (the training pairs)
    for ``"train_statistics"``, else 0 and 1. A component that (nearly) never varies — standard
    deviation below 1e-6, float32 noise — keeps scale 1 rather than amplifying that noise."""
    if normalization == "none":
        return np.stack([np.zeros(6), np.ones(6)])
    xi = np.asarray(xi_vo, np.float64)
    scale = xi.std(axis=0)
    return np.stack([xi.mean(axis=0), np.where(scale > 1e-6, scale, 1.0)])


# --------------------------------------------------------------------------- logging


METRICS_CSV = "metrics.csv"


class MetricsLog:
    """``WORKDIR/metrics.csv`` (one row per epoch, rewritten atomically) and TensorBoard events.

    On resume from epoch E, rows after E are dropped and TensorBoard events after E's last
    step are purged, so a redone epoch appears once. Only process 0 writes.
    """

    def __init__(self, workdir: Path, resumed_epoch: int, resumed_step: int, enabled: bool = True):
        self.path = workdir / METRICS_CSV
        self.enabled = enabled
        self.rows: list[dict[str, Any]] = []
        self.writer = None
        if not enabled:
            return
        if resumed_epoch and self.path.is_file():
            with self.path.open(newline="") as f:
                self.rows = [r for r in csv.DictReader(f) if int(r["epoch"]) <= resumed_epoch]
        from tensorboardX import SummaryWriter

        self.writer = SummaryWriter(
            str(workdir / "tensorboard"), purge_step=resumed_step + 1 if resumed_epoch else None
        )

    def scalars(self, step: int, values: dict[str, float], prefix: str) -> None:
        if self.writer is not None:
            for name, value in values.items():
                self.writer.add_scalar(f"{prefix}/{name}", value, step)

    def epoch(self, row: dict[str, Any]) -> None:
        """Append one epoch's row to ``metrics.csv`` and its scalars to TensorBoard."""
        if not self.enabled:
            return
        self.rows.append(row)
        fields = list(dict.fromkeys(k for r in self.rows for k in r))
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.rows)
        atomic_write(self.path, buffer.getvalue())
        numbers = {k: float(v) for k, v in row.items() if k not in ("epoch", "step")}
        numbers = {k: v for k, v in numbers.items() if math.isfinite(v)}
        self.scalars(int(row["step"]), numbers, "epoch")
        if self.writer is not None:
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


# --------------------------------------------------------------------------- validation


def _segment_errors(ground_truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """Mean segment errors (t_err %, r_err °/100 m) over the lengths the sequence covers (NaN if none)."""
    with jax.enable_x64(True):
        result = metrics_lib.segment_errors(ground_truth, estimate)
        return float(result.trans_pct), float(result.rot_deg_per_100m)


def validate(
    model_graphdef: nnx.GraphDef, model_state: nnx.State, data: TrainData, config: TrainConfig, mesh: Mesh
) -> dict[str, float]:
    """Validation figures of one epoch (docs/method.md §5), means over the validation pairs.

    * ``val_loss``: the training loss in evaluation mode;
    * ``val_gradient_loss``: the photometric loss on high-gradient pixels (selection a);
    * ``val_loop_closures``: loop closures of the corrected validation trajectories, summed
      (selection b);
    * ``val_delta``, ``val_delta_rotation``: mean Δ of the full / rotation-only correction
      (selection ``delta``; ``dpc_jax.acceptance``);
    * ``val_{prior,corrected}_{t,r}_err``: segment errors against ground truth, averaged over the
      sequences that have it (reporting only; NaN without ground truth).
    """
    loss_config = config.loss_config()
    weighted = {"loss": 0.0, "gradient_loss": 0.0, "delta": 0.0, "delta_rotation": 0.0}
    pairs = 0
    closures = 0
    errors: list[tuple[float, float, float, float]] = []
    for seq in data.validation:
        prediction = predict_sequence(
            model_graphdef, model_state, seq.cache, loss_config, batch_size=config.batch_size,
            use_flow=data.use_flow, stereo_depth=seq.stereo_depth, mesh=mesh,
        )
        n = prediction.xi_corr.shape[0]
        weighted["loss"] += prediction.loss * n
        weighted["gradient_loss"] += prediction.gradient_loss * n
        weighted["delta"] += float(prediction.delta["full"].sum())
        weighted["delta_rotation"] += float(prediction.delta["rotation"].sum())
        pairs += n
        first = seq.ground_truth[0] if seq.ground_truth is not None else seq.prior[0]
        corrected = corrected_trajectory(prediction.xi_corr, seq.prior, first, config.rotation_only)
        closures += int(metrics_lib.count_loop_closures(corrected))
        if seq.ground_truth is not None:
            errors.append(
                (*_segment_errors(seq.ground_truth, seq.prior), *_segment_errors(seq.ground_truth, corrected))
            )
    mean_errors = np.mean(errors, axis=0) if errors else np.full(4, np.nan)
    return {
        **{f"val_{k}": v / pairs for k, v in weighted.items()},
        "val_loop_closures": closures,
        "val_prior_t_err": float(mean_errors[0]),
        "val_prior_r_err": float(mean_errors[1]),
        "val_corrected_t_err": float(mean_errors[2]),
        "val_corrected_r_err": float(mean_errors[3]),
    }


# --------------------------------------------------------------------------- the loop


def check_workdir(config: TrainConfig, workdir: str | os.PathLike, resume: bool) -> bool:
    """Refuse a workdir that holds another run; return whether there is a run to resume.

    A workdir with a stored config needs ``resume=True`` and the same config (the error lists
    the differing keys). ``resume=True`` on a workdir without a run starts a new one.
    """
    stored_path = Path(workdir) / "checkpoints" / "config.json"
    if not stored_path.is_file():
        return False
    stored = config_lib.load_file(stored_path, TrainConfig)
    if not resume:
        raise ConfigError(
            f"{workdir} already holds a training run ({stored_path}); pass --resume to continue it "
            "or choose another --workdir"
        )
    differences = config_lib.diff(stored, config)
    if differences:
        raise ConfigError(
            f"{workdir} holds a run with a different config ({stored_path}); cannot resume with: "
            + "; ".join(differences)
        )
    return True


def _check_split(workdir: Path, split: dict[str, Any]) -> None:
    """Refuse to resume on data that differ from the run's stored split (re-prepared cache, ...)."""
    path = workdir / "checkpoints" / "split.json"
    if not path.is_file():
        return
    stored = json.loads(path.read_text())
    changes = [f"{k}: {stored.get(k)!r} → {split.get(k)!r}" for k in sorted(set(stored) | set(split))
               if stored.get(k) != split.get(k)]
    if changes:
        message = "; ".join(changes)
        raise ConfigError(f"{path}: the data changed since the run started, cannot resume: {message}")


def _train_epoch(
    epoch: int,
    graphdef: nnx.GraphDef,
    state: nnx.State,
    train_step: Callable[..., tuple[nnx.State, dict[str, jax.Array]]],
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
    step i+1 is dispatched, so the host never stalls the device; a non-finite loss raises
    ``NonFiniteLossError`` (the state is then discarded).
    """
    share = parallel.process_slice(config.batch_size)
    base_key = jax.random.key(config.seed)
    sums: dict[str, float] = {}
    timing = {"start": 0.0, "samples": 0, "rate": 0.0}

    def put(batch: Any) -> Any:
        return parallel.shard_batch(jax.tree.map(lambda x: x[share], batch), mesh)

    def step(state: nnx.State, batch: Any, index: int) -> tuple[nnx.State, dict[str, jax.Array]]:
        return train_step(graphdef, state, batch, step_key(base_key, first_step + index))

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
        state = drive(
            step, state, itertools.islice(batches, data.steps_per_epoch),
            total=data.steps_per_epoch, desc=f"epoch {epoch}/{config.epochs}", progress=progress,
            consume=consume, finite="loss", on_nonfinite=nonfinite, postfix=postfix,
        )
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
    train_step: Callable[..., tuple[nnx.State, dict[str, jax.Array]]]
    schedule: optax.Schedule
    checkpoints: Checkpoints
    log: MetricsLog
    progress: bool
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
        _check_split(workdir, data.split)
    mesh = parallel.make_mesh()
    try:
        parallel.check_batch_size(config.batch_size, mesh)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    return has_run, data, mesh


def _start_run(
    config: TrainConfig, workdir: Path, data: TrainData, mesh: Mesh, has_run: bool, progress: bool
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
    progress: bool | None = None,
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
    ``progress``: tqdm bars (default: when stderr is a terminal). ``distributed``: keyword
    arguments of ``jax.distributed.initialize`` when ``config.distributed``.

    Errors before any compute: ``ConfigError`` for a bad split, missing cache, wrong image size,
    or a workdir holding another run. ``NonFiniteLossError`` when a loss becomes NaN/inf.
    """
    workdir = Path(workdir).absolute()
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
