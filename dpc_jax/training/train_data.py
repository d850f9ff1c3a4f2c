"""What the training loop consumes: the training loader over the cached sequences, the validation
sequences, the split record and the statistics of the training priors (:func:`open_data`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.config import ConfigError
from dpc_jax.data.sequence_cache import StereoDepth
from dpc_jax.engine.predict import stereo_depth_of
from dpc_jax.training.train_config import TrainConfig


@dataclass(frozen=True)
class ValidationSequence:
    """One validation sequence: its cache, prior trajectory, (optional) ground truth and, with
    ``acceptance_depth="sgbm"``, the stereo depth Δ is measured with."""

    name: str
    cache: Any
    prior: np.ndarray
    ground_truth: np.ndarray | None
    stereo_depth: StereoDepth | None = None


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
