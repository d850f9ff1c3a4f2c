"""Checkpoints of a training run with orbax, and epoch selection without ground truth.

Layout under ``WORKDIR/checkpoints``::

    config.json            the TrainConfig of the run (a resumed run must match it)
    split.json             the data split: train / validation / test sequences and sample counts
    epochs/E/              after every epoch E (the last ``keep_last`` are kept)
    best_gradient_loss/E/  the epoch with the lowest validation gradient loss (ss-DPC-Net §IV-a)
    best_loop_closures/E/  the epoch with the most loop closures of the corrected validation
                           trajectory (ss-DPC-Net §IV-b); ties go to the lower gradient loss
    best_delta/E/          the epoch with the most negative mean Δ on the validation sequence
                           (the correction's paired photometric effect, ``dpc_jax.correction.acceptance``);
                           absent while no epoch has a negative Δ — none beats "no correction"

Each checkpoint holds two items: ``state`` (the pytree of model parameters, BatchNorm statistics,
optimizer state and step) and ``meta`` (JSON: epoch, global step, the position of the data
loader, the epoch's metrics and the best-so-far records). Orbax writes every checkpoint under a
temporary name and renames it when complete, so a killed process never leaves one that loads.

Order of writes for epoch E: the best-by-criterion checkpoints first, the epoch checkpoint last.
The epoch checkpoint is the commit point: a run killed before it redoes epoch E on resume (and
overwrites a best checkpoint E written before the kill), so at most the unfinished epoch is lost.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import orbax.checkpoint as ocp

CRITERIA = ("gradient_loss", "loop_closures", "delta")


class CheckpointError(RuntimeError):
    """A stored checkpoint under ``folder`` cannot be restored (damaged, incomplete, or written for
    another model); the restore's own exception is the ``__cause__``."""

    def __init__(self, folder: Path, error: BaseException):
        super().__init__(f"{folder}: cannot restore the checkpoint ({type(error).__name__})")
        self.folder = folder


@dataclass(frozen=True)
class Record:
    """The best epoch so far by one criterion (``epoch`` 0 = none yet; for ``delta``, "no correction",
    whose Δ is 0)."""

    epoch: int = 0
    gradient_loss: float = math.inf
    loop_closures: int = -1
    delta: float = 0.0

    def beaten_by(self, criterion: str, gradient_loss: float, loop_closures: int, delta: float) -> bool:
        """Whether an epoch with these validation figures becomes the new best by ``criterion``."""
        if criterion == "delta":
            return delta < self.delta
        if self.epoch == 0:
            return True
        if criterion == "gradient_loss":
            return gradient_loss < self.gradient_loss
        if loop_closures != self.loop_closures:
            return loop_closures > self.loop_closures
        return gradient_loss < self.gradient_loss


def _manager(directory: Path, max_to_keep: int | None, read_only: bool = False) -> ocp.CheckpointManager:
    if read_only:
        options = ocp.CheckpointManagerOptions(
            read_only=True, create=False, max_to_keep=None, save_interval_steps=0
        )
    else:
        options = ocp.CheckpointManagerOptions(
            max_to_keep=max_to_keep, enable_async_checkpointing=False, cleanup_tmp_directories=True
        )
    return ocp.CheckpointManager(directory, options=options, item_names=("state", "meta"))


class Checkpoints:
    """The checkpoints of one run: every epoch plus the best epoch by each selection criterion."""

    def __init__(self, workdir: str | os.PathLike, keep_last: int | None = 3, read_only: bool = False):
        self.root = Path(workdir).absolute() / "checkpoints"
        self.managers = {
            "epochs": _manager(self.root / "epochs", keep_last, read_only),
            **{f"best_{c}": _manager(self.root / f"best_{c}", 1, read_only) for c in CRITERIA},
        }

    def latest_epoch(self, which: str = "epochs") -> int | None:
        """The newest completed epoch in ``which`` (``epochs`` or ``best_<criterion>``), or None."""
        return self.managers[which].latest_step()

    def all_epochs(self, which: str = "epochs") -> list[int]:
        return list(self.managers[which].all_steps())

    def save(
        self, epoch: int, state: Any, meta: dict[str, Any], best: dict[str, Record]
    ) -> dict[str, Record]:
        """Save epoch ``epoch``; return the updated best records.

        ``meta`` must hold ``metrics`` with ``val_gradient_loss``, ``val_loop_closures`` and
        ``val_delta``; ``best`` is the record per criterion from the previous epoch's ``meta``.
        """
        metrics = meta["metrics"]
        figures = (float(metrics["val_gradient_loss"]), int(metrics["val_loop_closures"]),
                   float(metrics["val_delta"]))
        best = dict(best)
        for criterion in CRITERIA:
            if best[criterion].beaten_by(criterion, *figures):
                best[criterion] = Record(epoch, *figures)
        meta = {**meta, "epoch": epoch, "best": {c: vars(r) for c, r in best.items()}}
        for criterion in CRITERIA:
            if best[criterion].epoch == epoch:
                self._save(f"best_{criterion}", epoch, state, meta)
        self._save("epochs", epoch, state, meta)
        return best

    def _save(self, which: str, epoch: int, state: Any, meta: dict[str, Any]) -> None:
        manager = self.managers[which]
        if epoch in manager.all_steps():
            manager.delete(epoch)
        manager.save(
            epoch, args=ocp.args.Composite(state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta))
        )
        manager.wait_until_finished()

    def restore(
        self, abstract_state: Any, which: str = "epochs", epoch: int | None = None
    ) -> tuple[Any, dict]:
        """Restore ``(state, meta)`` of ``epoch`` (default the newest) from ``which``.

        ``abstract_state`` gives the structure, shapes, dtypes and shardings to restore into
        (e.g. ``jax.tree.map(ocp.utils.to_shape_dtype_struct, state)``).
        Raises ``FileNotFoundError`` when there is none and :class:`CheckpointError` when it cannot
        be read into ``abstract_state``.
        """
        manager = self.managers[which]
        epoch = manager.latest_step() if epoch is None else epoch
        if epoch is None:
            raise FileNotFoundError(f"{manager.directory}: no checkpoint to restore")
        try:
            restored = manager.restore(
                epoch,
                args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(abstract_state), meta=ocp.args.JsonRestore()
                ),
            )
        except Exception as error:  # orbax and tensorstore raise bare Exceptions for damaged data
            raise CheckpointError(self.root, error) from error
        return restored["state"], restored["meta"]

    def restore_model(self, abstract_model: Any, which: str = "epochs", epoch: int | None = None) -> Any:
        """Restore only the model's part (``state[0]``) of ``epoch`` (default the newest) from ``which``,
        without building an optimizer: for inference and adaptation.

        ``abstract_model`` gives the model state's structure, shapes and dtypes (e.g.
        ``jax.tree.map(ocp.utils.to_shape_dtype_struct, nnx.state(model))``). Raises like
        :meth:`restore`.
        """
        from flax import nnx

        manager = self.managers[which]
        epoch = manager.latest_step() if epoch is None else epoch
        if epoch is None:
            raise FileNotFoundError(f"{manager.directory}: no checkpoint to restore")
        item = nnx.State({0: abstract_model})
        try:
            restored = manager.restore(
                epoch,
                args=ocp.args.Composite(state=ocp.args.PyTreeRestore(
                    item=item, restore_args=ocp.checkpoint_utils.construct_restore_args(item),
                    partial_restore=True,
                )),
            )
        except Exception as error:  # orbax and tensorstore raise bare Exceptions for damaged data
            raise CheckpointError(self.root, error) from error
        return restored["state"][0]

    @staticmethod
    def best_records(meta: dict[str, Any] | None) -> dict[str, Record]:
        """The best-so-far records stored in a checkpoint's ``meta`` (empty records for a new run)."""
        stored = (meta or {}).get("best", {})
        return {c: Record(**stored[c]) if c in stored else Record() for c in CRITERIA}

    def close(self) -> None:
        for manager in self.managers.values():
            manager.close()

    def __enter__(self) -> Checkpoints:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
