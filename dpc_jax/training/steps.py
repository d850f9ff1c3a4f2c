"""The jitted train step: one pure function from (state, batch, key) to (state, metrics).

The model and its optimizer (``dpc_jax.training.optim``) are split once,
``graphdef, state = nnx.split((model, optimizer))``; the loop (``dpc_jax.training.loop``) and the
test-time adaptation (``dpc_jax.correction.adapt``) both drive the step returned by :func:`make_train_step`.
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

BoundStep = Callable[[list[jax.Array], Batch, jax.Array], tuple[list[jax.Array], dict[str, jax.Array]]]


class TrainStep:
    """The jitted train step of one loss: ``step(graphdef, state, batch, key) -> (state, metrics)``
    (``state`` donated), and :meth:`bind` for the drivers of many steps."""

    def __init__(self, function: Callable[..., tuple[nnx.State, dict[str, jax.Array]]],
                 jit_kwargs: dict[str, Any]) -> None:
        self._function = function
        self._jit_kwargs = jit_kwargs
        self._jitted = jax.jit(function, static_argnums=0, donate_argnums=1, **jit_kwargs)
        self._bound: dict[tuple[nnx.GraphDef, Any], BoundStep] = {}

    def __call__(self, graphdef: nnx.GraphDef, state: nnx.State, batch: Batch,
                 key: jax.Array) -> tuple[nnx.State, dict[str, jax.Array]]:
        return self._jitted(graphdef, state, batch, key)

    def bind(self, graphdef: nnx.GraphDef, treedef: Any) -> BoundStep:
        """``step(leaves, batch, key) -> (leaves, metrics)``: this step of the model ``graphdef``
        with the state carried as its flat list of arrays (``leaves, treedef =
        jax.tree.flatten(state)``; donated), compiled once per ``(graphdef, treedef)``.

        The same computation as a call. Per step the host then neither hashes and compares the
        graph definition (a static argument) nor walks the NNX state's Python tree in and out: host
        time an accelerator waits for when its step is shorter than the dispatch.
        """
        key = (graphdef, treedef)
        if key not in self._bound:
            function = self._function

            def flat(leaves: list[jax.Array], batch: Batch,
                     key: jax.Array) -> tuple[list[jax.Array], dict[str, jax.Array]]:
                state, metrics = function(graphdef, jax.tree.unflatten(treedef, leaves), batch, key)
                out, out_treedef = jax.tree.flatten(state)
                if out_treedef != treedef:
                    raise ValueError(f"the step changed the state's structure: {out_treedef} != {treedef}")
                return out, metrics

            self._bound[key] = jax.jit(flat, donate_argnums=0, **self._jit_kwargs)
        return self._bound[key]


def make_train_step(loss_config: Any, warmup_steps: int = 0, mesh: Mesh | None = None) -> TrainStep:
    """The jitted ``train_step(graphdef, state, batch, key) -> (state, metrics)``; ``state`` donated
    (:class:`TrainStep`; its :meth:`~TrainStep.bind` for a loop of steps).

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
    return TrainStep(step, kwargs)
