"""Builders the tests share: a stored training run without training it."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def write_stored_run(
    folder: Path, config: Any, epochs: dict[int, tuple[int, float, int, float]]
) -> dict[int, Any]:
    """A run folder as ``dpc-jax train`` writes it, with each epoch's network initialised from a seed instead
    of trained: ``epochs`` maps epoch → ``(seed, val gradient loss, val loop closures, val Δ)``. Returns the
    models by epoch. Writing the run directly keeps a test free of the training step's compilation."""
    from dpc_jax import config as config_lib
    from dpc_jax.nn.models import create_model
    from dpc_jax.training.checkpoints import Checkpoints
    from dpc_jax.training.optim import create_train_state, make_optimizer

    config_lib.save_json(folder / "checkpoints" / "config.json", config)
    models = {}
    with Checkpoints(folder) as checkpoints:
        best = Checkpoints.best_records(None)
        for epoch, (seed, gradient_loss, loops, delta) in epochs.items():
            models[epoch] = create_model(config.method, config.model_config(), seed)
            _, state = create_train_state(models[epoch], make_optimizer(config, 1))
            metrics = {"val_gradient_loss": gradient_loss, "val_loop_closures": loops, "val_delta": delta}
            best = checkpoints.save(epoch, state, {"step": epoch, "metrics": metrics}, best)
    return models
