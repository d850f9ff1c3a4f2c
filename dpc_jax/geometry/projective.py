"""The pinhole projection's division, written once for numpy and ``jax.numpy``.

Every projection of the package ends in :func:`perspective_divide`: :func:`dpc_jax.geometry.camera.project`,
the temporal warp :func:`dpc_jax.geometry.warp.inverse_warp` (under ``jit``, on per-coordinate arrays:
XLA's CPU backend runs elementwise arithmetic on separate coordinates many times faster than
reductions over a minor axis of 3) and the stereo VO's reprojection
(:func:`dpc_jax.vo.motion.project`, float64 numpy, without importing JAX). It takes the array
namespace ``xp`` (``numpy`` or ``jax.numpy``) and is dtype-preserving.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

# numpy.ndarray or jax.Array, matching ``xp``.
ArrayT = Any


def perspective_divide(
    px: ArrayT, py: ArrayT, pz: ArrayT, eps: float, xp: ModuleType
) -> tuple[ArrayT, ArrayT, ArrayT]:
    """``(px / pz, py / pz)`` and the mask ``pz > eps`` of points in front of the camera.

    ``px, py, pz``: the homogeneous pixel coordinates ``K P`` of camera-frame points ``P``, any
    (equal) shape; with ``K = [[fu, 0, cu], [0, fv, cv], [0, 0, 1]]`` the principal point may
    instead be added after the division (``px = fu x``, ``pz = z``). Where ``pz ≤ eps`` the division
    uses 1 instead of ``pz``, so the result and its gradient stay finite there; such points must be
    discarded through the mask. Returns ``(u, v, in_front)``, ``in_front`` bool.
    """
    in_front = pz > eps
    safe_z = xp.where(in_front, pz, xp.ones_like(pz))
    return px / safe_z, py / safe_z, in_front
