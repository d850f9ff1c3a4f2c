"""Rigid transforms ``[[R, t], [0, 1]]``, written once for numpy and ``jax.numpy``.

Each function takes the array namespace ``xp`` (``numpy`` or ``jax.numpy``) and is dtype-preserving.
The trajectory algebra of :mod:`dpc_jax.geometry.poses` calls it with numpy, in float64 and without
importing JAX (the command line reads trajectories before it starts JAX); the SE(3) functions of
:mod:`dpc_jax.geometry.lie` trace the same code with ``jax.numpy``.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

# numpy.ndarray or jax.Array, matching ``xp``.
ArrayT = Any


def from_rotation_translation(rotation: ArrayT, translation: ArrayT, xp: ModuleType) -> ArrayT:
    """``[[R, t], [0, 1]]`` from ``rotation`` ``[..., 3, 3]`` and ``translation`` ``[..., 3]``.

    Returns ``[..., 4, 4]``.
    """
    top = xp.concatenate([rotation, translation[..., None]], axis=-1)
    bottom = xp.broadcast_to(xp.asarray([0.0, 0.0, 0.0, 1.0], dtype=rotation.dtype), (*top.shape[:-2], 1, 4))
    return xp.concatenate([top, bottom], axis=-2)


def inverse(transform: ArrayT, xp: ModuleType) -> ArrayT:
    """Closed-form inverse ``[[Rᵀ, −Rᵀ t], [0, 1]]`` of rigid transforms ``[..., 4, 4]`` -> ``[..., 4, 4]``.

    Exact for rigid transforms (the bottom row is not read), unlike a general matrix inverse.
    """
    rotation_t = xp.swapaxes(transform[..., :3, :3], -1, -2)
    translation = -xp.einsum("...ij,...j->...i", rotation_t, transform[..., :3, 3])
    return from_rotation_translation(rotation_t, translation, xp)
