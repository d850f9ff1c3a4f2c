"""The jitted train step: one pure function from (state, batch, key) to (state, metrics).

The model and its optimizer (``dpc_jax.training.optim``) are split once,
``graphdef, state = nnx.split((model, optimizer))``; the loop (``dpc_jax.training.loop``) and the
test-time adaptation (``dpc_jax.correction.adapt``) both drive the step returned by :func:`make_train_step`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jax.sharding import Mesh

from dpc_jax.engine import backend, parallel
from dpc_jax.engine.driver import NonFiniteLossError as NonFiniteLossError
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.losses import dpc_loss

BoundStep = Callable[[list[jax.Array], Batch, jax.Array], tuple[list[jax.Array], dict[str, jax.Array]]]


class _CompiledStep:
    """The jitted step of one loss on one mesh, shared by every :class:`TrainStep` of them: ``jitted(graphdef,
    state, batch, key, warmup_steps)`` and, per ``(graphdef, treedef)``, the flat form of :meth:`flat`."""

    def __init__(self, function: Callable[..., tuple[nnx.State, dict[str, jax.Array]]],
                 jit_kwargs: dict[str, Any]) -> None:
        self._function = function
        self._jit_kwargs = jit_kwargs
        self.jitted = jax.jit(function, static_argnums=0, donate_argnums=1, **jit_kwargs)
        self._flat: dict[tuple[nnx.GraphDef, Any], Callable[..., Any]] = {}

    def flat(self, graphdef: nnx.GraphDef, treedef: Any) -> Callable[..., Any]:
        """``step(leaves, batch, key, warmup_steps) -> (leaves, metrics)`` (``leaves`` donated)."""
        if (graphdef, treedef) not in self._flat:
            function = self._function

            def flat(leaves: list[jax.Array], batch: Batch, key: jax.Array,
                     warmup_steps: jax.Array) -> tuple[list[jax.Array], dict[str, jax.Array]]:
                state = jax.tree.unflatten(treedef, leaves)
                state, metrics = function(graphdef, state, batch, key, warmup_steps)
                out, out_treedef = jax.tree.flatten(state)
                if out_treedef != treedef:
                    raise ValueError(f"the step changed the state's structure: {out_treedef} != {treedef}")
                return out, metrics

            self._flat[graphdef, treedef] = jax.jit(flat, donate_argnums=0, **self._jit_kwargs)
        return self._flat[graphdef, treedef]


class TrainStep:
    """The jitted train step of one loss: ``step(graphdef, state, batch, key) -> (state, metrics)``
    (``state`` donated), and :meth:`bind` for the drivers of many steps."""

    def __init__(self, compiled: _CompiledStep, warmup_steps: int) -> None:
        self._compiled = compiled
        # An argument of the compiled program, not a constant in it: runs that differ only in their
        # warm-up (a study's cells of other sizes) share one compilation.
        self._warmup = np.int32(warmup_steps)
        self._bound: dict[tuple[nnx.GraphDef, Any], BoundStep] = {}

    def __call__(self, graphdef: nnx.GraphDef, state: nnx.State, batch: Batch,
                 key: jax.Array) -> tuple[nnx.State, dict[str, jax.Array]]:
        return self._compiled.jitted(graphdef, state, batch, key, self._warmup)

    def bind(self, graphdef: nnx.GraphDef, treedef: Any) -> BoundStep:
        """``step(leaves, batch, key) -> (leaves, metrics)``: this step of the model ``graphdef``
        with the state carried as its flat list of arrays (``leaves, treedef =
        jax.tree.flatten(state)``; donated), compiled once per ``(graphdef, treedef)``.

        The same computation as a call. Per step the host then neither hashes and compares the
        graph definition (a static argument) nor walks the NNX state's Python tree in and out: host
        time an accelerator waits for when its step is shorter than the dispatch.
        """
        if (graphdef, treedef) not in self._bound:
            flat, warmup = self._compiled.flat(graphdef, treedef), self._warmup

            def bound(leaves: list[jax.Array], batch: Batch,
                      key: jax.Array) -> tuple[list[jax.Array], dict[str, jax.Array]]:
                return flat(leaves, batch, key, warmup)

            self._bound[graphdef, treedef] = bound
        return self._bound[graphdef, treedef]


def make_train_step(loss_config: Any, warmup_steps: int = 0, mesh: Mesh | None = None) -> TrainStep:
    """The jitted ``train_step(graphdef, state, batch, key) -> (state, metrics)``; ``state`` donated
    (:class:`TrainStep`; its :meth:`~TrainStep.bind` for a loop of steps).

    ``loss_config``: the method's loss config (``TrainConfig.loss_config()``); the loss sees
    ξ_corr = 0 while the optimizer's step count is below ``warmup_steps``.
    ``metrics``: ``loss``, the loss's named terms, ``grad_norm`` (global L2 norm of the gradient
    before weight decay) — scalars. ``key`` drives dropout. With ``mesh``, the outputs are
    replicated on it; put the state with ``parallel.replicate`` and the batch with
    ``parallel.shard_batch``.

    The program is compiled once per ``(loss_config, mesh)`` and model in a process, whatever the
    warm-up: a second run of the same network and optimizer (a study's next cell, a repeated run,
    the tests) reuses it.
    """
    return TrainStep(_compiled_step(loss_config, mesh), warmup_steps)


@functools.cache
def _compiled_step(loss_config: Any, mesh: Mesh | None) -> _CompiledStep:
    def step(
        graphdef: nnx.GraphDef, state: nnx.State, batch: Batch, key: jax.Array, warmup_steps: jax.Array
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
    return _CompiledStep(step, kwargs)
