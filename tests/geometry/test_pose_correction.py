"""Pose correction against scipy's matrix exponential of the se(3) twist."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from dpc_jax.geometry.pose_correction import apply_correction


def twist_exp(xi: np.ndarray) -> np.ndarray:
    """Exp of ξ = [ρ, φ] as the 4×4 matrix exponential of [[φ^, ρ], [0, 0]]."""
    rho, phi = xi[:3], xi[3:]
    twist = np.zeros((4, 4))
    twist[:3, :3] = [[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]]
    twist[:3, 3] = rho
    return expm(twist)


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return T


def test_apply_correction_matches_expm() -> None:
    rng = np.random.default_rng(0)
    xi = rng.normal(scale=0.3, size=(4, 6))
    T_vo = random_poses(rng, 4)
    out = np.asarray(jax.jit(apply_correction)(xi, T_vo))
    for i in range(4):
        np.testing.assert_allclose(out[i], twist_exp(xi[i]) @ T_vo[i], atol=1e-12)


def test_rotation_only_ignores_translation_part() -> None:
    rng = np.random.default_rng(1)
    xi = rng.normal(scale=0.3, size=(3, 6))
    T_vo = random_poses(rng, 3)
    out = np.asarray(apply_correction(xi, T_vo, rotation_only=True))
    for i in range(3):
        R = Rotation.from_rotvec(xi[i, 3:]).as_matrix()
        np.testing.assert_allclose(out[i, :3, :3], R @ T_vo[i, :3, :3], atol=1e-12)
        np.testing.assert_allclose(out[i, :3, 3], R @ T_vo[i, :3, 3], atol=1e-12)


def test_zero_correction_and_dtype_and_broadcast() -> None:
    rng = np.random.default_rng(2)
    T_vo = random_poses(rng, 5).astype(np.float32)
    out = apply_correction(np.zeros(6, np.float32), T_vo)
    assert out.dtype == jnp.float32 and out.shape == (5, 4, 4)
    np.testing.assert_allclose(np.asarray(out), T_vo, atol=1e-6)


def test_gradient_reaches_correction() -> None:
    T_vo = random_poses(np.random.default_rng(3), 1)[0]
    grad = jax.grad(lambda xi: apply_correction(xi, T_vo)[:3, 3].sum())(jnp.zeros(6))
    assert bool(jnp.isfinite(grad).all()) and float(jnp.abs(grad[:3]).sum()) > 0
    grad = jax.grad(lambda xi: apply_correction(xi, T_vo, rotation_only=True)[:3, 3].sum())(jnp.zeros(6))
    np.testing.assert_array_equal(np.asarray(grad[:3]), 0.0)


def test_shape_errors() -> None:
    with pytest.raises(ValueError, match=r"xi_corr must have shape \[\.\.\., 6\]"):
        apply_correction(np.zeros(5), np.eye(4))
    with pytest.raises(ValueError, match=r"T_vo must have shape"):
        apply_correction(np.zeros(6), np.eye(3))
