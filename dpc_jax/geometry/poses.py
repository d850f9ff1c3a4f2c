"""Pose algebra on trajectories (numpy): inverses, relative poses, composition, se(3) logs, static frames.

A trajectory is a numpy array ``[N, 4, 4]`` of camera-to-world poses ``T_w_c`` ("Twv", docs/method.md §1).
Reading and writing trajectory files is :mod:`dpc_jax.data.poses_io`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from dpc_jax.geometry import rigid

# The ss-DPC-Net static-frame rule (docs/method.md §6): a frame pair moving less than this much in both
# translation (m, ‖ρ‖ of the se(3) log) and rotation (rad, ‖φ‖) counts as static.
STATIC_TRANSLATION_M = 1.5
STATIC_ROTATION_RAD = 0.007
# The fewest transforms a compiled Lie function is called with (:func:`_on_buckets`).
_MIN_BUCKET = 1024
# A jitted function of ``[M, 4, 4]`` transforms returning a tuple of ``[M, ...]`` arrays.
_Compiled = Callable[[np.ndarray], tuple[Any, ...]]


def validate_poses(
    poses: np.ndarray, source: str = "poses", tolerance: float = 1e-3
) -> np.ndarray:
    """Check and clean homogeneous poses (numpy, float64): those read from a file, and the poses
    every API function that takes a trajectory is given.

    ``poses``: ``[N, 4, 4]`` or ``[N, 3, 4]``. Returns ``[N, 4, 4]`` float64 whose rotation
    blocks are projected onto SO(3) and whose bottom rows are exactly ``[0, 0, 0, 1]``.

    Raises ``ValueError`` naming ``source`` and the pose index when a pose holds a non-finite
    value, when its rotation block deviates from orthonormality by more than ``tolerance``
    (max |RᵀR − I|), when its determinant is not positive, or when a given bottom row is not
    ``[0, 0, 0, 1]`` within ``tolerance``. Deviations below ``tolerance`` (rounding in text
    files) are silently projected away.
    """
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"{source}: expected poses of shape [N, 4, 4] or [N, 3, 4], got {arr.shape}")
    finite = np.isfinite(arr).all(axis=(1, 2))
    if not finite.all():
        i = int(np.argmin(finite))
        raise ValueError(f"{source}: pose {i} contains a non-finite value (NaN or inf)")
    if arr.shape[1] == 4:
        bottom_dev = np.abs(arr[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
        bad = np.flatnonzero(bottom_dev > tolerance)
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"{source}: pose {i} has bottom row {arr[i, 3].tolist()}, expected [0, 0, 0, 1]"
            )
    rotation = arr[:, :3, :3]
    gram = np.einsum("nji,njk->nik", rotation, rotation)
    deviation = np.abs(gram - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rotation)
    bad = np.flatnonzero((deviation > tolerance) | (det <= 0.0))
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{source}: pose {i} is not rigid: max |RᵀR − I| = {deviation[i]:.3g} "
            f"(tolerance {tolerance:g}), det R = {det[i]:.6g}"
        )
    u, _, vt = np.linalg.svd(rotation)
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, 2] *= d[:, None]
    out = np.zeros((arr.shape[0], 4, 4))
    out[:, :3, :3] = u @ vt
    out[:, :3, 3] = arr[:, :3, 3]
    out[:, 3, 3] = 1.0
    return out


def invert_poses(poses: np.ndarray) -> np.ndarray:
    """Closed-form inverse of rigid transforms ``[..., 4, 4]``: :func:`rigid.inverse` in numpy."""
    return rigid.inverse(np.asarray(poses), np)


def relative_poses(trajectory: np.ndarray) -> np.ndarray:
    """``[N, 4, 4]`` -> ``[N-1, 4, 4]`` with ``T_{t+1,t} = inv(T_w_{t+1}) @ T_w_t`` (docs/method.md §1).

    ``T_{t+1,t}`` maps a point expressed in frame t into frame t+1. Dtype-preserving numpy.
    """
    trajectory = np.asarray(trajectory)
    if trajectory.ndim != 3 or trajectory.shape[1:] != (4, 4) or trajectory.shape[0] < 1:
        raise ValueError(f"trajectory must have shape [N, 4, 4] with N ≥ 1, got {trajectory.shape}")
    return invert_poses(trajectory[1:]) @ trajectory[:-1]


def compose(relative: np.ndarray, first_pose: np.ndarray) -> np.ndarray:
    """Inverse of :func:`relative_poses`: ``T_w_{t+1} = T_w_t @ inv(T_{t+1,t})`` from ``T_w_0 = first_pose``.

    ``relative``: ``[N-1, 4, 4]``; ``first_pose``: ``[4, 4]`` -> ``[N, 4, 4]`` in the dtype of
    ``relative``. The product is accumulated sequentially, exactly as the papers compose VO.
    """
    relative = np.asarray(relative)
    if relative.ndim != 3 or relative.shape[1:] != (4, 4):
        raise ValueError(f"relative must have shape [N-1, 4, 4], got {relative.shape}")
    first = np.asarray(first_pose, dtype=relative.dtype)
    if first.shape != (4, 4):
        raise ValueError(f"first_pose must have shape [4, 4], got {first.shape}")
    steps = invert_poses(relative)
    out = np.empty((relative.shape[0] + 1, 4, 4), dtype=relative.dtype)
    out[0] = first
    for t in range(relative.shape[0]):
        out[t + 1] = out[t] @ steps[t]
    return out


# ----------------------------------------------------------------------------- se(3) logs of numpy poses

@functools.cache
def _compiled() -> tuple[_Compiled, _Compiled]:
    """Jitted ``se3_log`` and ``(‖ρ‖, ‖φ‖)`` of it, built on first use: importing this module needs no JAX."""
    import jax
    import jax.numpy as jnp

    from dpc_jax.geometry.lie import se3_log

    def log(transforms: jax.Array) -> tuple[jax.Array]:
        return (se3_log(transforms),)

    def norms(transforms: jax.Array) -> tuple[jax.Array, jax.Array]:
        xi = se3_log(transforms)
        return jnp.linalg.norm(xi[..., :3], axis=-1), jnp.linalg.norm(xi[..., 3:], axis=-1)

    return jax.jit(log), jax.jit(norms)


def _on_buckets(function: _Compiled, transforms: np.ndarray) -> list[np.ndarray]:
    """The numpy bridge to the compiled Lie functions: each output of ``function`` (one row per
    transform) for ``[M, 4, 4]`` numpy transforms, as numpy arrays of M rows.

    Evaluated once, on M padded with identities to a power of two of at least ``_MIN_BUCKET``, so
    that loaders, caches and the static-frame passes, which call it with many different lengths,
    reuse one or two compilations per process and dtype instead of tracing op by op.
    """
    m = transforms.shape[0]
    bucket = max(_MIN_BUCKET, 1 << max(m - 1, 1).bit_length())
    padded = np.concatenate([transforms, np.tile(np.eye(4), (bucket - m, 1, 1))])
    return [np.asarray(output)[:m] for output in function(padded)]


def log_poses(transforms: np.ndarray) -> np.ndarray:
    """:func:`dpc_jax.geometry.lie.se3_log` of ``[M, 4, 4]`` numpy transforms: numpy ``[M, 6]`` (m, rad).

    float64 with ``jax_enable_x64``, else float32.
    """
    (xi,) = _on_buckets(_compiled()[0], transforms)
    return xi


def _log_norms(transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(‖ρ‖ m, ‖φ‖ rad)`` float64 ``[M]`` of the se(3) logs of ``[M, 4, 4]`` transforms."""
    rho, phi = _on_buckets(_compiled()[1], transforms)
    return rho.astype(np.float64), phi.astype(np.float64)


# ----------------------------------------------------------------------------- static frames

def remove_static_frames(
    reference: np.ndarray,
    prior: np.ndarray | None = None,
    translation_m: float = STATIC_TRANSLATION_M,
    rotation_rad: float = STATIC_ROTATION_RAD,
) -> np.ndarray:
    """Indices of the frames kept by the ss-DPC-Net static-frame rule (docs/method.md §6).

    ``reference``: ``[N, 4, 4]``, the trajectory whose frames are kept or dropped (typically the
    ground truth); ``prior``: ``[N, 4, 4]``, the trajectory the rule reads (the VO prior, as in
    ss-DPC-Net), or None to read ``reference`` itself (sequences without a prior). Both lose the
    same frames. Returns sorted int64 indices into ``[0, N)``.

    The rule, on the current (already shortened) sequence: for each pair ``(i, i+1)`` with ``i``
    even, ``[ρ, φ] = Log(inv(T_{i+1}) T_i)`` of the prior; frame ``i`` is dropped when
    ``‖ρ‖ < translation_m`` (m) **and** ``‖φ‖ < rotation_rad`` (rad). Passes repeat until one
    drops nothing. The last frame is never dropped (it is never the first of a pair).
    """
    reference = np.asarray(reference)
    source = reference if prior is None else np.asarray(prior)
    if reference.ndim != 3 or reference.shape[1:] != (4, 4):
        raise ValueError(f"reference must have shape [N, 4, 4], got {reference.shape}")
    if source.shape != reference.shape:
        raise ValueError(
            f"prior has {source.shape[0]} poses but reference has {reference.shape[0]}; "
            "they must describe the same frames"
        )
    poses = source.astype(np.float64)
    kept = np.arange(poses.shape[0])
    while kept.size >= 2:
        first = kept[0 : kept.size - 1 : 2]
        second = kept[1 : kept.size : 2]
        rho, phi = _log_norms(invert_poses(poses[second]) @ poses[first])
        static = (rho < translation_m) & (phi < rotation_rad)
        if not static.any():
            break
        kept = np.setdiff1d(kept, first[static], assume_unique=True)
    return kept.astype(np.int64)
