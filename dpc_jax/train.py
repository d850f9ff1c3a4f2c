"""Training: configuration, learning-rate schedule, the jitted train and evaluation steps, the loop.

Functional core (DESIGN §3, §5): the model and its optimizer are split once,
``graphdef, state = nnx.split((model, optimizer))``; ``state`` holds the parameters, the
BatchNorm statistics, the Adam moments and the step count. ``make_train_step`` returns ONE jitted
pure function ``train_step(graphdef, state, batch, key) -> (state, metrics)`` that merges,
differentiates the loss w.r.t. the ``nnx.Param`` variables only, applies the optimizer and splits
again; ``state`` is donated. Given a mesh (``dpc_jax.parallel``), the batch is sharded on
``data`` and the state replicated, so the same function runs on 1..N devices and hosts, with the
gradient mean and the BatchNorm batch statistics over the global batch.

Optimizer: Adam with *coupled* L2 weight decay, as PyTorch's ``Adam(weight_decay=wd)``: ``wd·θ``
is added to the gradient before the Adam moments (not AdamW's decoupled decay), on every
parameter (biases and BatchNorm scales included, as PyTorch does). The learning rate is halved
every ``lr_halving_epochs`` epochs, counted in optimizer steps from the epoch length: the update
with (0-based) index ``s`` uses ``lr · 0.5 ** floor(s / (lr_halving_epochs · steps_per_epoch))``.

The loop (``train``) and its files are described in its docstring.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import io
import itertools
import json
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import nnx
from jax.sharding import Mesh
from tqdm.auto import tqdm

from dpc_jax import config as config_lib
from dpc_jax import metrics as metrics_lib
from dpc_jax import parallel, trajectory
from dpc_jax.batch import Batch
from dpc_jax.checkpoints import Checkpoints
from dpc_jax.config import ConfigError, unknown_key_error
from dpc_jax.outputs import DPCOutputs
from dpc_jax.trajectory import atomic_write

METHODS = ("ss_dpc", "stereo_dpc")

LossFn = Callable[[DPCOutputs, Batch], tuple[jax.Array, dict[str, jax.Array]]]
GradientLossFn = Callable[[DPCOutputs, Batch], jax.Array]


@dataclass(frozen=True)
class TrainConfig:
    """One training run, as data (DESIGN §5 defaults are the Stereo DPC paper's).

    Model
        * ``method``: ``"ss_dpc"`` (ss-DPC-Net, mono + flow) or ``"stereo_dpc"`` (Zhang et al.).
        * ``preset``: a key of ``dpc_jax.models.PRESETS`` (``"reference"``, ``"small"``).
        * ``model``: overrides of ``ModelConfig`` fields on top of the preset.
        * ``image_size``: ``(H, W)`` of the cached images and the network input; None = the
          preset's.
        * ``dropout``: dropout rate of the pose head's FC layers.
        * ``learn_ssim_weight``: λ_s mode: True learns λ_s = sigmoid(s) (a model parameter),
          False uses the loss config's fixed value.
    Loss
        * ``loss``: overrides of the method's loss config (``SSDPCLossConfig`` or
          ``StereoDPCLossConfig``): term weights, fixed λ_s, rotation weighting γ and λ_rot, ...
        * ``rotation_only``: apply only the rotation part of ξ_corr when composing corrected
          trajectories (ss-DPC-Net with a stereo prior); passed to the loss config too when it
          has such a field.
    Optimisation
        * ``batch_size`` (global, over all devices and hosts), ``epochs``.
        * ``learning_rate``, ``lr_halving_epochs``: initial rate, halved every that many epochs.
        * ``weight_decay``: coupled L2 (PyTorch ``Adam(weight_decay=...)``).
        * ``steps_per_epoch``: cap on the optimizer steps per epoch; None = one full pass.
        * ``seed``: parameter initialisation and dropout; ``data_seed``: shuffling.
    Data (a preprocessing cache written by ``dpc-jax prepare``)
        * ``cache_root``: directory of the cache.
        * ``train_sequences``: empty = every cached sequence except validation and test ones.
        * ``validation_sequences``: used for epoch selection (no ground truth needed).
        * ``test_sequences``: held out, never loaded by training (recorded in the split).
        * ``frame_skip``: add a copy of each training sequence with every second frame.
        * ``reverse``: add reversed copies of the training sequences.
    Run
        * ``keep_checkpoints``: how many every-epoch checkpoints to keep (best ones are extra).
        * ``log_every``: steps between TensorBoard training scalars.
        * ``distributed``: call ``jax.distributed.initialize`` (several hosts; see
          ``dpc_jax.parallel``).
    """

    method: str = "stereo_dpc"
    preset: str = "reference"
    model: dict[str, Any] = field(default_factory=dict)
    image_size: tuple[int, int] | None = None
    dropout: float = 0.5
    learn_ssim_weight: bool = False
    loss: dict[str, Any] = field(default_factory=dict)
    rotation_only: bool = False
    batch_size: int = 32
    epochs: int = 30
    learning_rate: float = 6e-3
    lr_halving_epochs: int = 5
    weight_decay: float = 4e-6
    steps_per_epoch: int | None = None
    seed: int = 0
    data_seed: int = 0
    cache_root: str = ""
    train_sequences: tuple[str, ...] = ()
    validation_sequences: tuple[str, ...] = ()
    test_sequences: tuple[str, ...] = ()
    frame_skip: bool = True
    reverse: bool = False
    keep_checkpoints: int = 3
    log_every: int = 10
    distributed: bool = False

    def __post_init__(self) -> None:
        problems = []
        if self.method not in METHODS:
            problems.append(f"method must be one of {METHODS}, got {self.method!r}")
        for name in ("batch_size", "epochs", "lr_halving_epochs", "keep_checkpoints", "log_every"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.steps_per_epoch is not None and self.steps_per_epoch < 1:
            problems.append(f"steps_per_epoch must be >= 1 or None, got {self.steps_per_epoch}")
        if not self.learning_rate > 0 or not math.isfinite(self.learning_rate):
            problems.append(f"learning_rate must be > 0, got {self.learning_rate}")
        if not self.weight_decay >= 0:
            problems.append(f"weight_decay must be >= 0, got {self.weight_decay}")
        if not 0.0 <= self.dropout < 1.0:
            problems.append(f"dropout must be in [0, 1), got {self.dropout}")
        if self.image_size is not None and min(self.image_size) < 1:
            problems.append(f"image_size must be positive, got {self.image_size}")
        for key in ("image_size", "dropout", "learn_ssim_weight"):
            if key in self.model:
                problems.append(f"model.{key} duplicates the top-level key {key!r}; set it there")
        if not self.validation_sequences:
            problems.append("validation_sequences is empty; epoch selection needs at least one")
        for name in ("train_sequences", "validation_sequences", "test_sequences"):
            seqs = getattr(self, name)
            if len(set(seqs)) != len(seqs):
                problems.append(f"{name} lists a sequence twice: {list(seqs)}")
        for a, b in (("train", "validation"), ("train", "test"), ("validation", "test")):
            common = sorted(set(getattr(self, f"{a}_sequences")) & set(getattr(self, f"{b}_sequences")))
            if common:
                problems.append(f"sequence(s) {common} are both in {a}_sequences and {b}_sequences")
        if problems:
            raise ConfigError("invalid TrainConfig: " + "; ".join(problems))
        # Fail now, not after data loading, on bad model or loss overrides.
        self.model_config()
        self.loss_config()

    def model_config(self) -> Any:
        """The ``ModelConfig``: the preset, the ``model`` overrides and the top-level model keys."""
        from dpc_jax.models import PRESETS

        if self.preset not in PRESETS:
            raise ConfigError(f"preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        base = PRESETS[self.preset]
        overrides = dict(self.model, dropout=self.dropout, learn_ssim_weight=self.learn_ssim_weight)
        if self.image_size is not None:
            overrides["image_size"] = tuple(self.image_size)
        return _replace(base, overrides, "model")

    def loss_config(self) -> Any:
        """The method's loss config dataclass with the ``loss`` overrides (and ``rotation_only``)."""
        from dpc_jax import losses

        base = losses.SSDPCLossConfig() if self.method == "ss_dpc" else losses.StereoDPCLossConfig()
        overrides = dict(self.loss)
        if "rotation_only" in overrides:
            raise ConfigError("loss.rotation_only duplicates the top-level key 'rotation_only'; set it there")
        if any(f.name == "rotation_only" for f in dataclasses.fields(base)):
            overrides["rotation_only"] = self.rotation_only
        return _replace(base, overrides, "loss")

    @property
    def resolved_image_size(self) -> tuple[int, int]:
        return tuple(self.model_config().image_size)


def _replace(base: Any, overrides: dict[str, Any], where: str) -> Any:
    """``dataclasses.replace`` with unknown keys and the dataclass's own checks as ``ConfigError``."""
    names = [f.name for f in dataclasses.fields(base)]
    for key in overrides:
        if key not in names:
            raise unknown_key_error(key, names, where)
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    try:
        return dataclasses.replace(base, **values)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{where}: {error}") from None


# --------------------------------------------------------------------------- optimizer


def learning_rate_schedule(learning_rate: float, halving_epochs: int, steps_per_epoch: int) -> optax.Schedule:
    """``lr · 0.5 ** floor(step / (halving_epochs · steps_per_epoch))`` (staircase)."""
    return optax.exponential_decay(
        init_value=learning_rate,
        transition_steps=halving_epochs * steps_per_epoch,
        decay_rate=0.5,
        staircase=True,
    )


def make_optimizer(config: TrainConfig, steps_per_epoch: int) -> optax.GradientTransformation:
    """Adam with coupled L2 weight decay (PyTorch ``Adam(weight_decay)``) and the halving schedule."""
    schedule = learning_rate_schedule(config.learning_rate, config.lr_halving_epochs, steps_per_epoch)
    return optax.chain(
        optax.add_decayed_weights(config.weight_decay),
        optax.scale_by_adam(),
        optax.scale_by_learning_rate(schedule),
    )


def create_train_state(
    model: nnx.Module, tx: optax.GradientTransformation, mesh: Mesh | None = None
) -> tuple[nnx.GraphDef, nnx.State]:
    """``nnx.split((model, optimizer))`` of ``model`` in training mode and its ``nnx.Optimizer``.

    With ``mesh`` the state is placed replicated on it. Build the model eagerly
    (``create_model``): every initializer compiles once per shape and process, which later runs
    in the same process reuse (one jitted initialisation would recompile as a whole every run).
    """
    model.train()
    graphdef, state = nnx.split((model, nnx.Optimizer(model, tx, wrt=nnx.Param)))
    return graphdef, state if mesh is None else parallel.replicate(state, mesh)


def state_step(state: nnx.State) -> int:
    """The optimizer step count stored in a train state."""
    return int(state[1]["step"][...])


# --------------------------------------------------------------------------- steps


def make_loss_functions(config: TrainConfig) -> tuple[LossFn, GradientLossFn]:
    """The method's training loss and the gradient loss (epoch selection), bound to the config."""
    from dpc_jax import losses

    loss_config = config.loss_config()
    loss = losses.ss_dpc_loss if config.method == "ss_dpc" else losses.stereo_dpc_loss

    def loss_fn(outputs: DPCOutputs, batch: Batch) -> tuple[jax.Array, dict[str, jax.Array]]:
        return loss(outputs, batch, loss_config)

    def gradient_loss_fn(outputs: DPCOutputs, batch: Batch) -> jax.Array:
        value = losses.gradient_loss(outputs, batch, loss_config)
        return value[0] if isinstance(value, tuple) else value

    return loss_fn, gradient_loss_fn


@functools.lru_cache(maxsize=8)
def make_train_step(
    loss_fn: LossFn, mesh: Mesh | None = None
) -> Callable[[nnx.GraphDef, nnx.State, Batch, jax.Array], tuple[nnx.State, dict[str, jax.Array]]]:
    """The jitted ``train_step(graphdef, state, batch, key) -> (state, metrics)``; ``state`` donated.

    Cached per ``(loss_fn, mesh)``, so runs that share both share the compiled program.

    ``metrics``: ``loss``, the loss's named terms, ``grad_norm`` (global L2 norm of the gradient
    before weight decay) — scalars. ``key`` drives dropout. With ``mesh``, the outputs are
    replicated on it; put the state with ``parallel.replicate`` and the batch with
    ``parallel.shard_batch``.
    """

    def step(
        graphdef: nnx.GraphDef, state: nnx.State, batch: Batch, key: jax.Array
    ) -> tuple[nnx.State, dict[str, jax.Array]]:
        model, optimizer = nnx.merge(graphdef, state)
        model.train()

        def objective(model: nnx.Module) -> tuple[jax.Array, dict[str, jax.Array]]:
            return loss_fn(model(batch, key=key), batch)

        (loss, terms), grads = nnx.value_and_grad(objective, has_aux=True)(model)
        optimizer.update(model, grads)
        metrics = {"loss": loss, **terms, "grad_norm": optax.tree.norm(grads)}
        return nnx.state((model, optimizer)), metrics

    kwargs: dict[str, Any] = {}
    if mesh is not None:
        from dpc_jax.parallel import replicated

        kwargs["out_shardings"] = replicated(mesh)
    return jax.jit(step, static_argnums=0, donate_argnums=1, **kwargs)


@functools.lru_cache(maxsize=8)
def make_eval_step(
    loss_fn: LossFn, gradient_loss_fn: GradientLossFn, mesh: Mesh | None = None
) -> Callable[[nnx.GraphDef, nnx.State, Batch], dict[str, jax.Array]]:
    """The jitted ``eval_step(graphdef, state, batch) -> metrics`` in evaluation mode.

    ``metrics``: ``loss`` (the training loss, photometric terms included), ``gradient_loss``,
    ``samples`` (Σ batch.weight, the real samples) — scalars — and ``xi_corr [B, 6]`` per sample
    (padding rows included; drop them with ``weight``). The state is not changed.
    """

    def step(graphdef: nnx.GraphDef, state: nnx.State, batch: Batch) -> dict[str, jax.Array]:
        model, _ = nnx.merge(graphdef, state)
        model.eval()
        outputs = model(batch)
        loss, _ = loss_fn(outputs, batch)
        return {
            "loss": loss,
            "gradient_loss": gradient_loss_fn(outputs, batch),
            "samples": jnp.sum(batch.weight),
            "xi_corr": outputs.xi_corr,
        }

    kwargs: dict[str, Any] = {}
    if mesh is not None:
        from dpc_jax.parallel import replicated

        kwargs["out_shardings"] = replicated(mesh)
    return jax.jit(step, static_argnums=0, **kwargs)


# --------------------------------------------------------------------------- data


@dataclass(frozen=True)
class ValidationSequence:
    """One validation sequence: its cache, prior trajectory and (optional) ground truth, in order."""

    name: str
    cache: Any
    prior: np.ndarray
    ground_truth: np.ndarray | None


@dataclass(frozen=True)
class TrainData:
    """What the loop consumes: the training loader, the validation sequences, the split record."""

    loader: Any
    steps_per_epoch: int
    validation: tuple[ValidationSequence, ...]
    use_flow: bool
    split: dict[str, Any]


def cached_sequences(cache_root: str | os.PathLike) -> list[str]:
    """Names of the prepared sequences (folders with a manifest) under ``cache_root``."""
    from dpc_jax.data.cache import MANIFEST

    root = Path(cache_root)
    if not root.is_dir():
        raise ConfigError(
            f"cache_root {str(root)!r} is not a directory; prepare the data with `dpc-jax prepare`"
        )
    return sorted(d.name for d in root.iterdir() if (d / MANIFEST).is_file())


def open_data(config: TrainConfig, workers: int = 2) -> TrainData:
    """Open the cache of ``config``: check the split and the image size, build the loaders.

    Raises ``ConfigError`` for a sequence that is not cached, an empty training set or an image
    size different from the model's, before any compute.
    """
    from dpc_jax.data.pipeline import TrainLoader, load_cache

    available = cached_sequences(config.cache_root)
    for role in ("train", "validation", "test"):
        missing = [s for s in getattr(config, f"{role}_sequences") if s not in available]
        if missing:
            raise ConfigError(
                f"{role}_sequences {missing} are not prepared under {config.cache_root} (found {available})"
            )
    held_out = set(config.validation_sequences) | set(config.test_sequences)
    train_names = list(config.train_sequences) or [s for s in available if s not in held_out]
    if not train_names:
        raise ConfigError(
            f"no training sequence under {config.cache_root} besides the validation and test ones"
        )
    root = Path(config.cache_root)
    size = config.resolved_image_size
    caches = {name: load_cache(root / name) for name in [*train_names, *config.validation_sequences]}
    for name, cache in caches.items():
        if cache.image_size != size:
            raise ConfigError(
                f"{root / name}: images are {cache.image_size[0]}x{cache.image_size[1]}, the model expects "
                f"{size[0]}x{size[1]} (image_size); prepare the cache with --size {size[0]}x{size[1]}"
            )
    model_config = config.model_config()
    use_flow = model_config.flow if model_config.flow is not None else config.method == "ss_dpc"
    loader = TrainLoader(
        [caches[n] for n in train_names],
        config.batch_size,
        seed=config.data_seed,
        frame_skip=config.frame_skip,
        reverse=config.reverse,
        flow=use_flow,
        workers=workers,
    )
    steps = min(len(loader), config.steps_per_epoch or len(loader))
    validation = tuple(
        ValidationSequence(n, caches[n], np.asarray(caches[n].prior), caches[n].gt)
        for n in config.validation_sequences
    )
    split = {
        "cache_root": str(Path(config.cache_root).absolute()),
        "train": train_names,
        "validation": list(config.validation_sequences),
        "test": list(config.test_sequences),
        "train_samples": loader.num_samples,
        "steps_per_epoch": steps,
        "validation_pairs": {v.name: len(v.cache) - 1 for v in validation},
        "input_hashes": {n: c.manifest.get("input_hash") for n, c in caches.items()},
    }
    return TrainData(loader, steps, validation, use_flow, split)


# --------------------------------------------------------------------------- logging


class NonFiniteLossError(RuntimeError):
    """Training produced a NaN or infinite loss; the run stopped without saving that state."""


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
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


# --------------------------------------------------------------------------- validation


def corrected_trajectory(
    xi_corr: np.ndarray, prior: np.ndarray, first_pose: np.ndarray, rotation_only: bool = False
) -> np.ndarray:
    """Compose ``T*_{t+1,t} = Exp(ξ_corr,t) · T_vo_{t+1,t}`` from ``first_pose`` → ``[N, 4, 4]`` float64.

    ``xi_corr``: ``[N-1, 6]`` corrections of the consecutive pairs; ``prior``: ``[N, 4, 4]``
    camera-to-world VO trajectory.
    """
    from dpc_jax.correction import apply_correction

    relative = trajectory.relative_poses(prior)
    corrected = np.asarray(apply_correction(xi_corr, relative, rotation_only), np.float64)
    return trajectory.compose(corrected, first_pose)


def _segment_errors(ground_truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """Mean segment errors (t_err %, r_err °/100 m) over the lengths the sequence covers (NaN if none)."""
    result = metrics_lib.segment_errors(ground_truth, estimate)
    return float(result.trans_pct), float(result.rot_deg_per_100m)


def validate(
    graphdef: nnx.GraphDef,
    state: nnx.State,
    eval_step: Callable[[nnx.GraphDef, nnx.State, Batch], dict[str, jax.Array]],
    data: TrainData,
    config: TrainConfig,
    mesh: Mesh,
) -> dict[str, float]:
    """Validation figures of one epoch (DESIGN §5).

    * ``val_loss``: the training loss in evaluation mode, mean over validation pairs;
    * ``val_gradient_loss``: the photometric loss restricted to the gradient mask (selection a);
    * ``val_loop_closures``: loop closures of the corrected validation trajectories (selection b),
      summed over the validation sequences;
    * ``val_{prior,corrected}_{t,r}_err``: segment errors against ground truth, averaged over the
      sequences that have it (reporting only; NaN without ground truth).
    """
    from dpc_jax.data.pipeline import iterate_sequence

    share = parallel.process_slice(config.batch_size)
    totals = {"loss": 0.0, "gradient_loss": 0.0, "samples": 0.0}
    closures = 0
    errors: list[tuple[float, float, float, float]] = []
    for seq in data.validation:
        corrections = []
        with contextlib.closing(
            iterate_sequence(seq.cache, config.batch_size, flow=data.use_flow)
        ) as batches:
            for batch in batches:
                local = jax.tree.map(lambda x: x[share], batch)
                out = jax.device_get(eval_step(graphdef, state, parallel.shard_batch(local, mesh)))
                n = float(out["samples"])
                totals["loss"] += float(out["loss"]) * n
                totals["gradient_loss"] += float(out["gradient_loss"]) * n
                totals["samples"] += n
                corrections.append(np.asarray(out["xi_corr"], np.float64)[np.asarray(batch.weight) > 0])
        first = seq.ground_truth[0] if seq.ground_truth is not None else seq.prior[0]
        corrected = corrected_trajectory(np.concatenate(corrections), seq.prior, first, config.rotation_only)
        closures += int(metrics_lib.count_loop_closures(corrected))
        if seq.ground_truth is not None:
            errors.append(
                (*_segment_errors(seq.ground_truth, seq.prior), *_segment_errors(seq.ground_truth, corrected))
            )
    mean_errors = np.mean(errors, axis=0) if errors else np.full(4, np.nan)
    return {
        "val_loss": totals["loss"] / totals["samples"],
        "val_gradient_loss": totals["gradient_loss"] / totals["samples"],
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
    progress: bool,
) -> tuple[nnx.State, dict[str, float]]:
    """One epoch of optimizer steps; returns the new state and the epoch means of the step metrics.

    The metrics of step i are fetched after step i+1 is dispatched, so the host never stalls the
    device; a non-finite loss raises ``NonFiniteLossError`` (the state is then discarded).
    """
    share = parallel.process_slice(config.batch_size)
    base_key = jax.random.key(config.seed)
    sums: dict[str, float] = {}
    timing = {"start": 0.0, "samples": 0}
    bar = tqdm(
        total=data.steps_per_epoch,
        desc=f"epoch {epoch}/{config.epochs}",
        unit="step",
        disable=not progress,
        leave=False,
        dynamic_ncols=True,
    )

    def consume(step: int, metrics: dict[str, jax.Array]) -> None:
        values = {k: float(v) for k, v in jax.device_get(metrics).items()}
        if not math.isfinite(values["loss"]):
            raise NonFiniteLossError(
                f"non-finite training loss ({values['loss']}) at epoch {epoch}, step {step}; stopping. "
                f"The last good checkpoint (epoch {epoch - 1}) is intact; lower learning_rate or check the "
                "data, then continue with --resume"
            )
        for k, v in values.items():
            sums[k] = sums.get(k, 0.0) + v
        now = time.perf_counter()
        if timing["start"] == 0.0:
            timing["start"] = now
        else:
            timing["samples"] += config.batch_size
        rate = timing["samples"] / (now - timing["start"]) if timing["samples"] else 0.0
        bar.update(1)
        bar.set_postfix(loss=f"{values['loss']:.4f}", samples_s=f"{rate:.1f}")
        if step % config.log_every == 0:
            log.scalars(step, values, "train")
        timing["rate"] = rate

    pending: tuple[int, dict[str, jax.Array]] | None = None
    step = first_step
    try:
        with contextlib.closing(data.loader.epoch(epoch)) as batches:
            for batch in itertools.islice(batches, data.steps_per_epoch):
                local = jax.tree.map(lambda x: x[share], batch)
                key = jax.random.fold_in(base_key, step)
                state, metrics = train_step(graphdef, state, parallel.shard_batch(local, mesh), key)
                step += 1
                if pending is not None:
                    consume(*pending)
                pending = (step, metrics)
        if pending is not None:
            consume(*pending)
    finally:
        bar.close()
    n = data.steps_per_epoch
    means = {f"train_{k}": v / n for k, v in sums.items()}
    means["samples_per_s"] = timing.get("rate", 0.0)
    return state, means


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

    Files: ``WORKDIR/checkpoints/`` (see ``dpc_jax.checkpoints``: every epoch, the best by
    gradient loss and by loop closures, ``config.json``, ``split.json``),
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
    from dpc_jax.models import create_model

    workdir = Path(workdir).absolute()
    has_run = check_workdir(config, workdir, resume)
    if config.distributed:
        parallel.initialize_distributed(**(distributed or {}))
    progress = sys.stderr.isatty() if progress is None else progress
    data = open_data(config, workers=workers)
    if has_run:
        _check_split(workdir, data.split)
    mesh = parallel.make_mesh()
    try:
        parallel.check_batch_size(config.batch_size, mesh)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    is_main = jax.process_index() == 0

    graphdef, state = create_train_state(
        create_model(config.method, config.model_config(), config.seed),
        make_optimizer(config, data.steps_per_epoch),
        mesh,
    )
    checkpoints = Checkpoints(workdir, keep_last=config.keep_checkpoints)
    meta: dict[str, Any] | None = None
    if has_run and checkpoints.latest_epoch() is not None:
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, state)
        try:
            state, meta = checkpoints.restore(abstract)
        except ValueError as error:
            raise ConfigError(
                f"{checkpoints.root}: the stored state does not fit the model this code builds from the "
                f"config (did the model code change since the run started?): {str(error)[:300]}"
            ) from None
    elif is_main:
        config_lib.save_json(checkpoints.root / "config.json", config)
        config_lib.save_json(checkpoints.root / "split.json", data.split)
    start_epoch = meta["epoch"] if meta else 0
    step = meta["step"] if meta else 0
    best = Checkpoints.best_records(meta)
    schedule = learning_rate_schedule(config.learning_rate, config.lr_halving_epochs, data.steps_per_epoch)

    loss_fn, gradient_loss_fn = make_loss_functions(config)
    train_step = make_train_step(loss_fn, mesh)
    eval_step = make_eval_step(loss_fn, gradient_loss_fn, mesh)
    log = MetricsLog(workdir, start_epoch, step, enabled=is_main)
    row: dict[str, Any] = meta["metrics"] if meta else {}
    try:
        for epoch in range(start_epoch + 1, config.epochs + 1):
            began = time.perf_counter()
            learning_rate = float(schedule(step))
            state, train_means = _train_epoch(
                epoch, graphdef, state, train_step, data, config, mesh, step, log, progress
            )
            step += data.steps_per_epoch
            val = validate(graphdef, state, eval_step, data, config, mesh)
            if not all(math.isfinite(val[k]) for k in ("val_loss", "val_gradient_loss")):
                raise NonFiniteLossError(
                    f"non-finite validation loss at epoch {epoch} ({val['val_loss']}, gradient loss "
                    f"{val['val_gradient_loss']}); stopping. "
                    f"The last good checkpoint (epoch {epoch - 1}) is intact"
                )
            row = {
                "epoch": epoch,
                "step": step,
                "learning_rate": learning_rate,
                **train_means,
                **val,
                "epoch_time_s": time.perf_counter() - began,
            }
            log.epoch(row)
            best = checkpoints.save(
                epoch,
                state,
                {
                    "step": step,
                    "metrics": row,
                    "data": {
                        "next_epoch": epoch + 1,
                        "next_batch": 0,
                        "data_seed": config.data_seed,
                        "steps_per_epoch": data.steps_per_epoch,
                    },
                },
                best,
            )
            if is_main:
                print(_epoch_line(row), file=sys.stderr if progress else sys.stdout, flush=True)
    finally:
        log.close()
        checkpoints.close()
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
        f"gradient loss {row['val_gradient_loss']:.4f}, loop closures {row['val_loop_closures']}, "
        f"{row['samples_per_s']:.1f} samples/s"
    )
    if math.isfinite(row["val_corrected_r_err"]):
        text += (
            f", r_err {row['val_prior_r_err']:.3f} → {row['val_corrected_r_err']:.3f} °/100m, "
            f"t_err {row['val_prior_t_err']:.2f} → {row['val_corrected_t_err']:.2f} %"
        )
    return text
