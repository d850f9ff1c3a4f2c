"""The leave-one-out rule: which sequences a network trains on.

A network trains on the ``train`` sequences when they are named, else on every available sequence
that is held out neither for validation (epoch selection) nor for test, in the order the sequences
are available. :func:`dpc_jax.data.pipeline.leave_one_out`,
:func:`dpc_jax.data.sequence_cache.training_sequences` (``TrainConfig.train_sequences``) and the
experiments' folds all choose their training sequences with :func:`training_names`; each checks
the names against its own source (a list, the prepared caches, the protocol) and reports in its
own terms.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence


def training_names(
    available: Sequence[str], held_out: Iterable[str], train: Sequence[str] | None = None
) -> tuple[str, ...]:
    """``train`` when given, else the names of ``available`` not in ``held_out`` (in their order)."""
    if train is not None:
        return tuple(train)
    held = set(held_out)
    return tuple(name for name in available if name not in held)
