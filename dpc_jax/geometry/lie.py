"""SO(3) and SE(3): exponential and logarithm maps, Jacobians, inverses.

Pure ``jnp`` functions, batched over any leading axes and dtype-preserving (float32 in,
float32 out; float64 in, float64 out). Conventions (docs/method.md §1):

* ``φ`` (phi) is an axis-angle vector in radians, shape ``[..., 3]``.
* ``ξ`` (xi) is an se(3) vector ``[ρ, φ]``: translation part first (metres), rotation second,
  shape ``[..., 6]``, as in Barfoot, *State Estimation for Robotics*.
* ``Exp(ξ) = [[Exp(φ), J(φ) ρ], [0, 1]]`` with ``J`` the left Jacobian of SO(3).

Every function is exact to rounding for rotation angles in ``[0, π)``. Each closed form that
divides by the angle has a Taylor branch near zero, selected with the *double-where* trick: the
unused branch is evaluated at a harmless argument, so neither its value nor its gradient can
produce NaN (``jax.grad`` at ξ = 0 is finite and equals the generators). ``so3_log`` switches to
an eigenvector construction for angles above π/2, where ``θ / sin θ`` is ill-conditioned, so that
rotations by exactly π return a vector of norm π.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from dpc_jax.geometry import rigid

# Below this squared angle (rad²) the Taylor branches are used. With the series truncated after
# the θ⁴ term the truncation error is below θ⁶/5040 ≈ 2e-16, float64 rounding.
_SMALL_ANGLE_SQ = 1e-4


def _check_last(x: Array, shape: tuple[int, ...], name: str) -> None:
    if tuple(x.shape[x.ndim - len(shape):]) != shape or x.ndim < len(shape):
        raise ValueError(f"{name} must have shape [..., {', '.join(map(str, shape))}], got {x.shape}")


def _float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _eye(dtype: jnp.dtype, n: int = 3) -> Array:
    return jnp.eye(n, dtype=dtype)


def so3_hat(phi: Array) -> Array:
    """Skew-symmetric matrix ``φ^`` with ``φ^ v = φ × v``. ``[..., 3] -> [..., 3, 3]``."""
    phi = _float(phi)
    _check_last(phi, (3,), "phi")
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


def so3_vee(matrix: Array) -> Array:
    """Inverse of :func:`so3_hat` (reads the skew part). ``[..., 3, 3] -> [..., 3]``."""
    matrix = _float(matrix)
    _check_last(matrix, (3, 3), "matrix")
    return jnp.stack([matrix[..., 2, 1], matrix[..., 0, 2], matrix[..., 1, 0]], -1)


def _angle_sq_and_safe_angle(phi: Array) -> tuple[Array, Array, Array]:
    """Squared angle, a small-angle mask, and an angle that is 1 wherever the mask is set."""
    theta_sq = jnp.sum(phi * phi, axis=-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    theta = jnp.sqrt(jnp.where(small, jnp.ones_like(theta_sq), theta_sq))
    return theta_sq, small, theta


def _exp_coefficients(phi: Array) -> tuple[Array, Array, Array]:
    """``sin θ / θ``, ``(1 − cos θ) / θ²`` and ``(θ − sin θ) / θ³``, each ``[...]``."""
    t2, small, theta = _angle_sq_and_safe_angle(phi)
    sin, half_sin = jnp.sin(theta), jnp.sin(0.5 * theta)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, sin / theta)
    # 2 sin²(θ/2) avoids the cancellation of 1 − cos θ at small angles.
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * half_sin * half_sin / (theta * theta))
    c = jnp.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (theta - sin) / (theta * theta * theta))
    return a, b, c


def so3_exp(phi: Array) -> Array:
    """Rotation matrix ``Exp(φ) = I + (sin θ/θ) φ^ + ((1 − cos θ)/θ²) φ^²``.

    ``phi``: ``[..., 3]`` axis-angle (rad) -> ``[..., 3, 3]``.
    """
    phi = _float(phi)
    _check_last(phi, (3,), "phi")
    a, b, _ = _exp_coefficients(phi)
    hat = so3_hat(phi)
    return _eye(phi.dtype) + a[..., None, None] * hat + b[..., None, None] * (hat @ hat)


def so3_left_jacobian(phi: Array) -> Array:
    """Left Jacobian ``J(φ) = I + ((1 − cos θ)/θ²) φ^ + ((θ − sin θ)/θ³) φ^²``.

    ``[..., 3] -> [..., 3, 3]``.
    """
    phi = _float(phi)
    _check_last(phi, (3,), "phi")
    _, b, c = _exp_coefficients(phi)
    hat = so3_hat(phi)
    return _eye(phi.dtype) + b[..., None, None] * hat + c[..., None, None] * (hat @ hat)


def so3_left_jacobian_inv(phi: Array) -> Array:
    """Inverse left Jacobian ``J⁻¹(φ) = I − ½ φ^ + (1/θ² − cot(θ/2)/(2θ)) φ^²``.

    Valid for ``θ < 2π``. ``[..., 3] -> [..., 3, 3]``.
    """
    phi = _float(phi)
    _check_last(phi, (3,), "phi")
    t2, small, theta = _angle_sq_and_safe_angle(phi)
    half = 0.5 * theta
    d = jnp.where(
        small,
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
        1.0 / (theta * theta) - jnp.cos(half) / (2.0 * theta * jnp.sin(half)),
    )
    hat = so3_hat(phi)
    return _eye(phi.dtype) - 0.5 * hat + d[..., None, None] * (hat @ hat)


def so3_log(rotation: Array) -> Array:
    """Axis-angle vector of a rotation matrix, with angle in ``[0, π]``.

    ``rotation``: ``[..., 3, 3]`` (assumed orthonormal, det +1) -> ``[..., 3]`` (rad).

    With ``w = vee(R − Rᵀ) = 2 sin θ · a`` and ``cos θ = (tr R − 1)/2`` the angle is
    ``atan2(|w|/2, cos θ)``, accurate at every angle. For ``θ ≤ π/2`` the vector is
    ``θ / (2 sin θ) · w`` (Taylor series in ``sin² θ`` near zero). Above π/2 the axis is read from
    the symmetric part ``(R + Rᵀ)/2 − cos θ I = (1 − cos θ) a aᵀ`` (its largest column) and its
    sign from ``w``; this stays exact up to and including θ = π.
    """
    rotation = _float(rotation)
    _check_last(rotation, (3, 3), "rotation")
    dtype = rotation.dtype
    w = so3_vee(rotation - jnp.swapaxes(rotation, -1, -2))
    cos = jnp.clip((jnp.trace(rotation, axis1=-2, axis2=-1) - 1.0) * 0.5, -1.0, 1.0)
    w_sq = jnp.sum(w * w, axis=-1)
    sin_sq = 0.25 * w_sq

    near_pi = cos < 0.0
    small = (w_sq < 4.0 * _SMALL_ANGLE_SQ) & ~near_pi
    general = ~small & ~near_pi

    # Small angles: θ/(2 sin θ) = asin(s)/(2s) = ½ (1 + s²/6 + 3 s⁴/40 + …), s = sin θ.
    coef_small = 0.5 * (1.0 + sin_sq / 6.0 + 3.0 * sin_sq * sin_sq / 40.0)
    # Angles above the Taylor range: evaluated at a safe argument where unused.
    # At θ = π exactly sin θ = 0; the floor keeps the gradient of the square root finite.
    tiny = jnp.finfo(dtype).tiny
    sin = jnp.sqrt(jnp.where(small, jnp.ones_like(w_sq), jnp.maximum(sin_sq, tiny)))
    theta = jnp.arctan2(sin, cos)
    coef_general = theta / (2.0 * jnp.where(general, sin, jnp.ones_like(sin)))
    phi_general = jnp.where(small, coef_small, coef_general)[..., None] * w

    sym = 0.5 * (rotation + jnp.swapaxes(rotation, -1, -2)) - cos[..., None, None] * _eye(dtype)
    k = jnp.argmax(jnp.diagonal(sym, axis1=-2, axis2=-1), axis=-1)
    column = jnp.take_along_axis(sym, k[..., None, None], axis=-1)[..., 0]
    col_sq = jnp.sum(column * column, axis=-1)
    axis = column / jnp.sqrt(jnp.where(near_pi, col_sq, jnp.ones_like(col_sq)))[..., None]
    sign = jnp.where(jnp.sum(axis * w, axis=-1) < 0.0, -1.0, 1.0).astype(dtype)
    phi_near_pi = (sign * theta)[..., None] * axis

    return jnp.where(near_pi[..., None], phi_near_pi, phi_general)


def se3_exp(xi: ArrayLike) -> Array:
    """4×4 transform ``Exp(ξ)``, ``ξ = [ρ, φ]`` (m, rad). ``[..., 6] -> [..., 4, 4]``."""
    xi = _float(xi)
    _check_last(xi, (6,), "xi")
    rho, phi = xi[..., :3], xi[..., 3:]
    rotation = so3_exp(phi)
    translation = jnp.einsum("...ij,...j->...i", so3_left_jacobian(phi), rho)
    return rigid.from_rotation_translation(rotation, translation, jnp)


def se3_log(transform: Array) -> Array:
    """se(3) vector ``[ρ, φ]`` of a 4×4 rigid transform (angle in ``[0, π]``).

    ``[..., 4, 4] -> [..., 6]``; the bottom row is not read.
    """
    transform = _float(transform)
    _check_last(transform, (4, 4), "transform")
    phi = so3_log(transform[..., :3, :3])
    rho = jnp.einsum("...ij,...j->...i", so3_left_jacobian_inv(phi), transform[..., :3, 3])
    return jnp.concatenate([rho, phi], axis=-1)


def se3_inverse(transform: Array) -> Array:
    """Inverse of a rigid transform, ``[[Rᵀ, −Rᵀ t], [0, 1]]``. ``[..., 4, 4] -> [..., 4, 4]``."""
    transform = _float(transform)
    _check_last(transform, (4, 4), "transform")
    return rigid.inverse(transform, jnp)


def transform_points(transform: Array, points: Array) -> Array:
    """Apply rigid transforms to points: ``R p + t``.

    ``transform``: ``[..., 4, 4]``; ``points``: ``[..., N, 3]`` whose leading axes broadcast
    against those of ``transform`` -> ``[..., N, 3]``.
    """
    transform, points = _float(transform), _float(points)
    _check_last(transform, (4, 4), "transform")
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape [..., N, 3], got {points.shape}")
    rotation = transform[..., None, :3, :3]
    return jnp.einsum("...ij,...j->...i", rotation, points) + transform[..., None, :3, 3]


def project_to_so3(matrix: Array) -> Array:
    """Nearest rotation (Frobenius norm) to a 3×3 matrix: ``U diag(1, 1, det(U Vᵀ)) Vᵀ``.

    ``[..., 3, 3] -> [..., 3, 3]``.
    """
    matrix = _float(matrix)
    _check_last(matrix, (3, 3), "matrix")
    u, _, vt = jnp.linalg.svd(matrix)
    det = jnp.linalg.det(u @ vt)
    fix = jnp.ones((*matrix.shape[:-2], 3), dtype=matrix.dtype).at[..., 2].set(det)
    return (u * fix[..., None, :]) @ vt
