"""The optimizer of a run and its train state (docs/method.md §5), shared by training, adaptation and restore.

Adam with *coupled* L2 weight decay, as PyTorch's ``Adam(weight_decay=wd)``: ``wd·θ`` is added to
the gradient before the Adam moments (not AdamW's decoupled decay), on every parameter (biases
and BatchNorm scales included, as PyTorch does). The learning rate is halved every
``lr_halving_epochs`` epochs, counted in optimizer steps from the epoch length: the update with
(0-based) index ``s`` uses ``lr · 0.5 ** floor(s / (lr_halving_epochs · steps_per_epoch))``.
With ``pose_lr_multiplier ≠ 1`` or a pose warm-up the pose head (``dpc_jax.nn.models.POSE_HEAD``) gets
its own copy of the chain (``optax.multi_transform``): its rate multiplied, and during the warm-up
its updates masked *and its Adam state held* (``optax.transforms.conditionally_mask``), so that
its first real update is a proper first Adam step rather than one with a bias correction that
assumes hundreds of past steps (which would be up to 10× larger).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import optax
from flax import nnx
from jax.sharding import Mesh

from dpc_jax.engine import parallel
from dpc_jax.nn.models import POSE_HEAD


def learning_rate_schedule(learning_rate: float, halving_epochs: int, steps_per_epoch: int) -> optax.Schedule:
    """``lr · 0.5 ** floor(step / (halving_epochs · steps_per_epoch))`` (staircase)."""
    return optax.exponential_decay(
        init_value=learning_rate,
        transition_steps=halving_epochs * steps_per_epoch,
        decay_rate=0.5,
        staircase=True,
    )


def pose_head_labels(params: Any) -> Any:
    """``"pose"`` for the leaves of the pose head's modules, ``"rest"`` elsewhere (same tree)."""

    def label(path: tuple[Any, ...], _: Any) -> str:
        return "pose" if getattr(path[0], "key", None) in POSE_HEAD else "rest"

    return jax.tree_util.tree_map_with_path(label, params)


def make_optimizer(config: Any, steps_per_epoch: int) -> optax.GradientTransformation:
    """Adam with coupled L2 weight decay and the halving schedule for ``config`` (a TrainConfig).

    Equal settings give the same transformation object: the train state's graph definition holds
    it, so later runs of the same settings in a process (a second demo, a study's cells of equal
    settings) find their train step compiled."""
    return _optimizer(float(config.learning_rate), int(config.lr_halving_epochs), int(steps_per_epoch),
                      int(config.warmup_steps(steps_per_epoch)), float(config.weight_decay),
                      float(config.pose_lr_multiplier))


@functools.cache
def _optimizer(learning_rate: float, halving_epochs: int, steps_per_epoch: int, warmup: int,
               weight_decay: float, multiplier: float) -> optax.GradientTransformation:
    schedule = learning_rate_schedule(learning_rate, halving_epochs, steps_per_epoch)

    def adam(rate: optax.Schedule) -> optax.GradientTransformation:
        return optax.chain(
            optax.add_decayed_weights(weight_decay),
            optax.scale_by_adam(),
            optax.scale_by_learning_rate(rate),
        )

    if multiplier == 1.0 and warmup == 0:
        return adam(schedule)
    # The masked chain counts only its active steps: shift its schedule back onto the global step.
    pose = adam(lambda count: multiplier * schedule(count + warmup))
    if warmup:
        pose = optax.transforms.conditionally_mask(pose, lambda step: step >= warmup)
    return optax.multi_transform({"pose": pose, "rest": adam(schedule)}, pose_head_labels)


def create_train_state(
    model: nnx.Module, tx: optax.GradientTransformation, mesh: Mesh | None = None
) -> tuple[nnx.GraphDef, nnx.State]:
    """``nnx.split((model, optimizer))`` of ``model`` in training mode and its ``nnx.Optimizer``.

    ``state[0]`` is the model's state (it merges with ``nnx.graphdef(model)``), ``state[1]`` the
    optimizer's. With ``mesh`` the state is placed replicated on it. Build the model eagerly
    (``create_model``): every initializer compiles once per shape and process, which later runs
    in the same process reuse (one jitted initialisation would recompile as a whole every run).
    """
    model.train()
    graphdef, state = nnx.split((model, nnx.Optimizer(model, tx, wrt=nnx.Param)))
    return graphdef, state if mesh is None else parallel.replicate(state, mesh)
