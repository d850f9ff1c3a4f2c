"""Orbax checkpoints of a run: every epoch, best by each criterion, restore, interrupted saves."""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np
import optax
import orbax.checkpoint as ocp
import pytest
from flax import nnx

from dpc_jax.training.checkpoints import Checkpoints, Record


class _Net(nnx.Module):
    def __init__(self) -> None:
        rngs = nnx.Rngs(0)
        self.linear = nnx.Linear(3, 4, rngs=rngs)
        self.norm = nnx.BatchNorm(4, rngs=rngs)


def _state(seed: int) -> nnx.State:
    """A model + optimizer state whose every leaf depends on ``seed``."""
    net = _Net()
    optimizer = nnx.Optimizer(net, optax.adam(1e-3), wrt=nnx.Param)
    _, state = nnx.split((net, optimizer))
    leaves, tree = jax.tree.flatten(state)
    rng = np.random.default_rng(seed)
    return jax.tree.unflatten(tree, [np.asarray(rng.integers(0, 100, x.shape), x.dtype) for x in leaves])


def _meta(gradient_loss: float, closures: int, delta: float = 0.0) -> dict:
    metrics = {"val_gradient_loss": gradient_loss, "val_loop_closures": closures, "val_delta": delta}
    return {"step": 10, "metrics": metrics}


def _equal(a: nnx.State, b: nnx.State) -> bool:
    return all(jax.tree.leaves(jax.tree.map(lambda x, y: np.array_equal(np.asarray(x), np.asarray(y)), a, b)))


def test_best_record_rules() -> None:
    assert Record().beaten_by("gradient_loss", 5.0, 0, 0.0)
    r = Record(epoch=2, gradient_loss=1.0, loop_closures=3, delta=-1e-4)
    assert r.beaten_by("gradient_loss", 0.9, 0, 0.0) and not r.beaten_by("gradient_loss", 1.0, 9, -1.0)
    assert r.beaten_by("loop_closures", 5.0, 4, 0.0) and not r.beaten_by("loop_closures", 0.1, 2, -1.0)
    assert r.beaten_by("loop_closures", 0.9, 3, 0.0) and not r.beaten_by("loop_closures", 1.1, 3, -1.0)
    assert r.beaten_by("delta", 5.0, 0, -2e-4) and not r.beaten_by("delta", 0.1, 9, -1e-4)
    # "No correction" (Δ = 0) is the record to beat: an epoch whose Δ is not negative never is.
    assert not Record().beaten_by("delta", 0.1, 9, 0.0) and not Record().beaten_by("delta", 0.1, 9, 1e-6)
    assert Record().beaten_by("delta", 5.0, 0, -1e-9)


def test_delta_selection_keeps_the_most_negative_epoch_and_none_without_one(tmp_path: Path) -> None:
    states = [_state(e) for e in range(1, 5)]
    with Checkpoints(tmp_path / "a") as ckpt:
        best = Checkpoints.best_records(None)
        for epoch, (delta, s) in enumerate(zip([2e-4, -1e-4, -3e-4, -2e-4], states, strict=True), start=1):
            best = ckpt.save(epoch, s, _meta(1.0 / epoch, 0, delta), best)
        assert ckpt.all_epochs("best_delta") == [3] and best["delta"].epoch == 3
        restored, meta = ckpt.restore(jax.tree.map(ocp.utils.to_shape_dtype_struct, states[0]), "best_delta")
        assert meta["epoch"] == 3 and _equal(restored, states[2])
    with Checkpoints(tmp_path / "b") as ckpt:
        best = Checkpoints.best_records(None)
        for epoch, s in enumerate(states[:2], start=1):
            best = ckpt.save(epoch, s, _meta(1.0, 0, 1e-5 * epoch), best)
        assert ckpt.latest_epoch("best_delta") is None and best["delta"].epoch == 0


def test_every_epoch_and_best_by_criterion(tmp_path: Path) -> None:
    # (gradient loss, loop closures) per epoch → best gradient loss: epoch 3; most closures: 4 at
    # epochs 2 and 5, tie broken by the lower gradient loss → epoch 5.
    figures = [(1.0, 1), (0.8, 4), (0.5, 2), (0.7, 0), (0.6, 4)]
    states = [_state(e) for e in range(1, 6)]
    with Checkpoints(tmp_path, keep_last=2) as ckpt:
        best = Checkpoints.best_records(None)
        for epoch, ((g, c), s) in enumerate(zip(figures, states, strict=True), start=1):
            best = ckpt.save(epoch, s, _meta(g, c), best)
        assert ckpt.all_epochs() == [4, 5]
        assert ckpt.all_epochs("best_gradient_loss") == [3]
        assert ckpt.all_epochs("best_loop_closures") == [5]
        assert best["gradient_loss"] == Record(3, 0.5, 2, 0.0)
        assert best["loop_closures"] == Record(5, 0.6, 4, 0.0)
    # A new manager (as after a restart) restores the newest epoch, its meta and the records.
    with Checkpoints(tmp_path, keep_last=2) as ckpt:
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, states[0])
        restored, meta = ckpt.restore(abstract)
        assert meta["epoch"] == 5 and meta["step"] == 10
        assert _equal(restored, states[4]) and not _equal(restored, states[3])
        assert Checkpoints.best_records(meta) == best
        restored, meta = ckpt.restore(abstract, "best_gradient_loss")
        assert meta["epoch"] == 3 and _equal(restored, states[2])


def test_redone_epoch_overwrites_its_best_checkpoint(tmp_path: Path) -> None:
    """A run killed after the best checkpoint of epoch E but before the epoch checkpoint redoes E."""
    with Checkpoints(tmp_path) as ckpt:
        best = ckpt.save(1, _state(1), _meta(1.0, 0), Checkpoints.best_records(None))
        ckpt._save("best_gradient_loss", 2, _state(99), {"epoch": 2})  # the interrupted epoch 2
        assert ckpt.latest_epoch() == 1
        best = ckpt.save(2, _state(2), _meta(0.5, 0), best)
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _state(0))
        restored, meta = ckpt.restore(abstract, "best_gradient_loss")
        assert meta["epoch"] == 2 and _equal(restored, _state(2))


def test_unfinished_save_is_ignored(tmp_path: Path) -> None:
    with Checkpoints(tmp_path) as ckpt:
        ckpt.save(1, _state(1), _meta(1.0, 0), Checkpoints.best_records(None))
    # What a process killed mid-save leaves: a temporary folder orbax never renamed.
    partial = tmp_path / "checkpoints" / "epochs" / "2.orbax-checkpoint-tmp-123"
    (partial / "state").mkdir(parents=True)
    with Checkpoints(tmp_path) as ckpt:
        assert ckpt.latest_epoch() == 1
        # orbax removes such folders in a background task: wait for it (bounded) rather than race it.
        deadline = time.monotonic() + 30
        while partial.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not partial.exists()
        _, meta = ckpt.restore(jax.tree.map(ocp.utils.to_shape_dtype_struct, _state(0)))
        assert meta["epoch"] == 1
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        Checkpoints(tmp_path / "empty").restore({})
