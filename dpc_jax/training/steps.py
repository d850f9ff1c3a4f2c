"""The jitted train step: one pure function from (state, batch, key) to (state, metrics).

The model and its optimizer (``dpc_jax.training.optim``) are split once,
``graphdef, state = nnx.split((model, optimizer))``; the loop (``dpc_jax.training.loop``) and the
test-time adaptation (``dpc_jax.adapt``) both drive the step returned by :func:`make_train_step`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import nnx
from jax.sharding import Mesh

from dpc_jax.engine import backend, parallel
from dpc_jax.engine.driver import NonFiniteLossError as NonFiniteLossError
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.losses import dpc_loss

TrainStep = Callable[[nnx.GraphDef, nnx.State, Batch, jax.Array], tuple[nnx.State, dict[str, jax.Array]]]


def make_train_step(loss_config: Any, warmup_steps: int = 0, mesh: Mesh | None = None) -> TrainStep:
    """The jitted ``train_step(graphdef, state, batch, key) -> (state, metrics)``; ``state`` donated.

    ``loss_config``: the method's loss config (``TrainConfig.loss_config()``); the loss sees
    ξ_corr = 0 while the optimizer's step count is below ``warmup_steps``.
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
        pose_on = optimizer.step[...] >= warmup_steps

        def objective(model: nnx.Module) -> tuple[jax.Array, dict[str, jax.Array]]:
            outputs = model(batch, key=key)
            outputs = outputs._replace(xi_corr=jnp.where(pose_on, outputs.xi_corr, 0.0))
            return dpc_loss(outputs, batch, loss_config)

        (loss, terms), grads = nnx.value_and_grad(objective, has_aux=True)(model)
        optimizer.update(model, grads)
        metrics = {"loss": loss, **terms, "grad_norm": optax.tree.norm(grads)}
        return nnx.state((model, optimizer)), metrics

    kwargs: dict[str, Any] = {"compiler_options": backend.compiler_options(loss_config.method, training=True)}
    if mesh is not None:
        kwargs["out_shardings"] = parallel.replicated(mesh)
    return jax.jit(step, static_argnums=0, donate_argnums=1, **kwargs)
