"""Data parallelism: one device mesh with a ``data`` axis, the batch sharded on it, state replicated.

The same jitted train step runs on one CPU, one GPU, N local devices or N hosts: only the
shardings of its inputs change. XLA (GSPMD) inserts the cross-device reductions itself, so the
gradient mean and the BatchNorm batch statistics are taken over the *global* batch, exactly as
on one device.

Several hosts
-------------
Call ``initialize_distributed`` (the training loop does, when the config sets ``distributed``)
before anything else touches JAX, on every host, e.g. with::

    coordinator_address="10.0.0.1:1234", num_processes=4, process_id=<0..3>

or with no arguments on clusters JAX detects itself (SLURM, Cloud TPU, MPI via mpi4py). Every
process then builds the same global batch order from the shared seed and feeds only its slice
``process_slice(batch_size)``; ``shard_batch`` assembles the global array from the slices.
Checkpoints are written by orbax collectively (all processes call save/restore; the workdir must
be on a file system every host sees).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

DATA_AXIS = "data"


def initialize_distributed(
    coordinator_address: str | None = None, num_processes: int | None = None, process_id: int | None = None
) -> None:
    """Join a multi-host JAX job (``jax.distributed.initialize``); arguments None = auto-detect."""
    jax.distributed.initialize(
        coordinator_address=coordinator_address, num_processes=num_processes, process_id=process_id
    )


def make_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh over ``devices`` (default: every device of every process) named ``data``."""
    devices = list(jax.devices() if devices is None else devices)
    return Mesh(np.asarray(devices), (DATA_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading (batch) axis split over the ``data`` axis, the other axes whole."""
    return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    """Every device holds the whole array (parameters, optimizer state, keys)."""
    return NamedSharding(mesh, PartitionSpec())


def check_batch_size(batch_size: int, mesh: Mesh) -> None:
    """Raise ``ValueError`` unless the global batch splits evenly over devices and processes."""
    n = mesh.devices.size
    if batch_size % n:
        raise ValueError(f"batch_size {batch_size} is not divisible by the {n} devices of the mesh")
    if batch_size % jax.process_count():
        raise ValueError(f"batch_size {batch_size} is not divisible by the {jax.process_count()} processes")


def process_slice(batch_size: int) -> slice:
    """The samples of a global batch that this process loads (contiguous, equal shares)."""
    share = batch_size // jax.process_count()
    start = jax.process_index() * share
    return slice(start, start + share)


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Place every array of ``tree`` (identical on all processes) replicated on the mesh."""
    sharding = replicated(mesh)
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), tree)


def shard_batch(local_batch: Any, mesh: Mesh) -> Any:
    """Assemble global arrays, sharded on ``data``, from this process's slice of a batch.

    ``local_batch`` is a pytree (e.g. ``Batch``) of numpy arrays whose leading axis is this
    process's share of the global batch (the whole batch on one process). None leaves stay None.
    """
    sharding = batch_sharding(mesh)
    n = jax.process_count()

    def put(x: Any) -> jax.Array:
        x = np.asarray(x)
        return jax.make_array_from_process_local_data(sharding, x, (x.shape[0] * n, *x.shape[1:]))

    return jax.tree.map(put, local_batch)
