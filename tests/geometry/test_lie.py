"""Lie algebra against scipy, closed-form float64 numpy, and group properties (hypothesis).

Properties run over batch shapes (), (5,), (2, 3) and float32/float64. Float64 results are
compared to 1e-12; float32 to a few 1e-6 (rounding of 1e-7 amplified by a few operations).
"""

from __future__ import annotations

import math

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dpc_jax.data.poses_io import validate_poses
from dpc_jax.eval import reference_metrics as ref
from dpc_jax.geometry.lie import (
    project_to_so3,
    se3_exp,
    se3_inverse,
    se3_log,
    so3_exp,
    so3_hat,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    so3_vee,
    transform_points,
)

SHAPES = [(), (5,), (2, 3)]
DTYPES = [np.float32, np.float64]
TOL = {np.float32: 2e-5, np.float64: 1e-12}
PROPERTY = settings(max_examples=25, deadline=None)

# --- float64 numpy references ---------------------------------------------------------------------


def left_jacobian_series_np(phi: np.ndarray) -> np.ndarray:
    """J(φ) = Σ_n (φ^)^n / (n+1)!, summed to convergence (independent of the closed form)."""
    A = ref.so3_hat(phi)
    total, term = np.zeros((3, 3)), np.eye(3)
    for n in range(40):
        total += term / math.factorial(n + 1)
        term = term @ A
    return total


def loop(fn, x: np.ndarray, core: int) -> np.ndarray:
    """Apply a single-item numpy reference over the leading axes of ``x``."""
    lead = x.shape[: x.ndim - core]
    flat = x.reshape(-1, *x.shape[x.ndim - core :])
    out = np.stack([fn(item) for item in flat])
    return out.reshape(*lead, *out.shape[1:])


# --- strategies ---------------------------------------------------------------------------------


ANGLES = st.one_of(st.just(0.0), st.floats(0.0, 1e-5), st.floats(0.0, 0.02), st.floats(0.0, math.pi - 1e-2))


def draw_phi(data: st.DataObject, shape: tuple[int, ...], angles: st.SearchStrategy = ANGLES) -> np.ndarray:
    axis = data.draw(hnp.arrays(np.float64, (*shape, 3), elements=st.floats(-1.0, 1.0)))
    angle = data.draw(hnp.arrays(np.float64, shape, elements=angles))
    norm = np.linalg.norm(axis, axis=-1, keepdims=True)
    axis = np.where(norm > 1e-3, axis / np.maximum(norm, 1e-3), np.array([1.0, 0.0, 0.0]))
    return axis * angle[..., None]


def draw_xi(data: st.DataObject, shape: tuple[int, ...], angles: st.SearchStrategy = ANGLES) -> np.ndarray:
    rho = data.draw(hnp.arrays(np.float64, (*shape, 3), elements=st.floats(-2.0, 2.0)))
    return np.concatenate([rho, draw_phi(data, shape, angles)], axis=-1)


def close(actual: jax.Array, expected: np.ndarray, dtype: type) -> None:
    assert actual.dtype == dtype, (actual.dtype, dtype)
    np.testing.assert_allclose(np.asarray(actual, np.float64), expected, atol=TOL[dtype], rtol=0)


# --- jitted bundles: one compilation per shape and dtype, one dispatch per example ------------


@jax.jit
def _hat_vee(phi: jax.Array, v: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    hat = so3_hat(phi)
    return so3_vee(hat), jnp.einsum("...ij,...j->...i", hat, v), hat


_so3_exp = jax.jit(so3_exp)
_so3_log = jax.jit(so3_log)
_se3_exp = jax.jit(se3_exp)
_se3_log = jax.jit(se3_log)
_transform_points = jax.jit(transform_points)


@jax.jit
def _so3_properties(phi: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    R = so3_exp(phi)
    return jnp.swapaxes(R, -1, -2) @ R, jnp.linalg.det(R), so3_log(R)


@jax.jit
def _jacobians(phi: jax.Array) -> tuple[jax.Array, jax.Array]:
    J = so3_left_jacobian(phi)
    return J, so3_left_jacobian_inv(phi) @ J


@jax.jit
def _se3_properties(xi: jax.Array, a: jax.Array, b: jax.Array) -> dict[str, jax.Array]:
    T = se3_exp(xi)
    R = T[..., :3, :3]
    inverse = se3_inverse(T)
    return {
        "T": T,
        "gram": jnp.swapaxes(R, -1, -2) @ R,
        "det": jnp.linalg.det(R),
        "log": se3_log(T),
        "exp_log": se3_exp(se3_log(T)),
        "exp_neg": se3_exp(-xi),
        "inverse": inverse,
        "T_inv_T": T @ inverse,
        "exp_a_exp_b": se3_exp(a * xi) @ se3_exp(b * xi),
        "exp_a_plus_b": se3_exp((a + b) * xi),
    }


# --- hat / vee / SO(3) --------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", DTYPES)
@PROPERTY
@given(data=st.data())
def test_hat_vee_roundtrip_and_cross_product(
    shape: tuple[int, ...], dtype: type, data: st.DataObject
) -> None:
    phi = draw_phi(data, shape).astype(dtype)
    v = draw_phi(data, shape).astype(dtype)
    vee, cross, hat = _hat_vee(phi, v)
    close(vee, phi.astype(np.float64), dtype)
    close(cross, np.cross(phi, v).astype(np.float64), dtype)
    close(hat + jnp.swapaxes(hat, -1, -2), np.zeros((*shape, 3, 3)), dtype)


@pytest.mark.parametrize("shape", SHAPES)
@PROPERTY
@given(data=st.data())
def test_so3_exp_log_match_scipy_float64(shape: tuple[int, ...], data: st.DataObject) -> None:
    phi = draw_phi(data, shape)
    R = _so3_exp(phi)
    close(R, loop(lambda p: Rotation.from_rotvec(p).as_matrix(), phi, 1), np.float64)
    R_np = loop(lambda p: Rotation.from_rotvec(p).as_matrix(), phi, 1)
    close(_so3_log(R_np), loop(lambda m: Rotation.from_matrix(m).as_rotvec(), R_np, 2), np.float64)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", DTYPES)
@PROPERTY
@given(data=st.data())
def test_so3_exp_is_rotation_and_log_inverts(
    shape: tuple[int, ...], dtype: type, data: st.DataObject
) -> None:
    phi = draw_phi(data, shape).astype(dtype)
    gram, det, log = _so3_properties(phi)
    close(gram, np.broadcast_to(np.eye(3), (*shape, 3, 3)), dtype)
    close(det, np.ones(shape), dtype)
    close(log, phi.astype(np.float64), dtype)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", DTYPES)
@PROPERTY
@given(data=st.data())
def test_left_jacobian_series_and_inverse(shape: tuple[int, ...], dtype: type, data: st.DataObject) -> None:
    phi = draw_phi(data, shape).astype(dtype)
    J, product = _jacobians(phi)
    close(J, loop(left_jacobian_series_np, phi.astype(np.float64), 1), dtype)
    close(product, np.broadcast_to(np.eye(3), (*shape, 3, 3)), dtype)


def test_left_jacobian_is_derivative_of_exp() -> None:
    # Exp(φ + δ) ≈ Exp(J(φ) δ) Exp(φ) to first order.
    phi = np.array([0.3, -1.2, 0.8])
    delta = 1e-7 * np.array([0.4, 0.1, -0.7])
    lhs = np.asarray(so3_exp(phi + delta))
    rhs = np.asarray(so3_exp(np.asarray(so3_left_jacobian(phi)) @ delta) @ so3_exp(phi))
    np.testing.assert_allclose(lhs, rhs, atol=1e-13)


@pytest.mark.parametrize("dtype", DTYPES)
def test_so3_log_at_exactly_pi(dtype: type) -> None:
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    axes[:3] = np.eye(3)
    R = 2.0 * np.einsum("ni,nj->nij", axes, axes) - np.eye(3)  # rotation by π about each axis
    phi = _so3_log(R.astype(dtype))
    close(jnp.linalg.norm(phi, axis=-1), np.full(20, np.pi), dtype)
    close(_so3_exp(phi), R, dtype)
    grad = jax.jit(jax.jacfwd(so3_log))(jnp.asarray(R[5], dtype))
    assert bool(jnp.isfinite(grad).all())


# --- SE(3) --------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
@PROPERTY
@given(data=st.data())
def test_se3_exp_log_match_closed_form_float64(shape: tuple[int, ...], data: st.DataObject) -> None:
    xi = draw_xi(data, shape)
    T_np = loop(ref.se3_exp, xi, 1)
    close(_se3_exp(xi), T_np, np.float64)
    close(_se3_log(T_np), loop(ref.se3_log, T_np, 2), np.float64)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", DTYPES)
@PROPERTY
@given(data=st.data())
def test_se3_group_properties(shape: tuple[int, ...], dtype: type, data: st.DataObject) -> None:
    xi = draw_xi(data, shape).astype(dtype)
    a, b = data.draw(st.floats(-1.0, 1.0)), data.draw(st.floats(-1.0, 1.0))
    p = _se3_properties(xi, dtype(a), dtype(b))
    T = np.asarray(p["T"], np.float64)
    close(p["gram"], np.broadcast_to(np.eye(3), (*shape, 3, 3)), dtype)
    close(p["det"], np.ones(shape), dtype)
    close(p["T"][..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (*shape, 4)), dtype)
    close(p["log"], xi.astype(np.float64), dtype)
    close(p["exp_log"], T, dtype)
    close(p["exp_neg"], np.asarray(p["inverse"], np.float64), dtype)
    close(p["T_inv_T"], np.broadcast_to(np.eye(4), (*shape, 4, 4)), dtype)
    close(p["exp_a_exp_b"], np.asarray(p["exp_a_plus_b"], np.float64), dtype)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", DTYPES)
@PROPERTY
@given(data=st.data())
def test_transform_points(shape: tuple[int, ...], dtype: type, data: st.DataObject) -> None:
    xi = draw_xi(data, shape)
    points = data.draw(hnp.arrays(np.float64, (*shape, 4, 3), elements=st.floats(-10.0, 10.0)))
    T = loop(ref.se3_exp, xi, 1)
    expected = np.einsum("...ij,...nj->...ni", T[..., :3, :3], points) + T[..., None, :3, 3]
    out = _transform_points(T.astype(dtype), points.astype(dtype))
    assert out.dtype == dtype
    np.testing.assert_allclose(np.asarray(out, np.float64), expected, atol=20 * TOL[dtype])


def test_se3_log_near_pi_and_exp_at_pi() -> None:
    for angle in (np.pi - 1e-3, np.pi - 1e-6, np.pi):
        xi = np.array([0.5, -1.0, 2.0, *(angle * np.array([2.0, -1.0, 2.0]) / 3.0)])
        T = se3_exp(xi)
        np.testing.assert_allclose(np.asarray(se3_exp(se3_log(T))), np.asarray(T), atol=1e-9)
        assert abs(float(jnp.linalg.norm(se3_log(T)[3:])) - angle) < 1e-9


# --- derivatives --------------------------------------------------------------------------------


def generators() -> np.ndarray:
    """The six se(3) generators ∂Exp/∂ξ_i at 0, stacked on the last axis: [4, 4, 6]."""
    G = np.zeros((4, 4, 6))
    for i in range(3):
        G[i, 3, i] = 1.0
        G[:3, :3, 3 + i] = ref.so3_hat(np.eye(3)[i])
    return G


@pytest.mark.parametrize("dtype", DTYPES)
def test_jacobian_of_exp_at_zero_is_generators(dtype: type) -> None:
    @jax.jit
    def derivatives(xi: jax.Array) -> dict[str, jax.Array]:
        return {
            "fwd": jax.jacfwd(se3_exp)(xi),
            "rev": jax.jacrev(se3_exp)(xi),
            "log_exp": jax.jacfwd(_log_exp)(xi),
            "log_at_identity": jax.grad(lambda T: jnp.sum(se3_log(T)))(se3_exp(xi)),
            "so3": jnp.stack([jax.jacfwd(fn)(xi[3:]) for fn in (so3_left_jacobian, so3_left_jacobian_inv,
                                                                 so3_exp)]),
        }

    d = derivatives(jnp.zeros(6, dtype))
    close(d["fwd"], generators(), dtype)
    close(d["rev"], generators(), dtype)
    # Log is the local inverse: d(Log ∘ Exp)/dξ = I at 0, and Log's gradient at I is finite.
    close(d["log_exp"], np.eye(6), dtype)
    assert bool(jnp.isfinite(d["log_at_identity"]).all()) and bool(jnp.isfinite(d["so3"]).all())


def _log_exp(xi: jax.Array) -> jax.Array:
    return se3_log(se3_exp(xi))


_jac_exp = jax.jit(jax.jacfwd(se3_exp))
_jac_log_exp = jax.jit(jax.jacfwd(_log_exp))
_log_exp_jit = jax.jit(_log_exp)


def finite_difference(fn, x: np.ndarray, step: float = 1e-6) -> np.ndarray:
    columns = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = step
        columns.append((np.asarray(fn(x + e)) - np.asarray(fn(x - e))) / (2 * step))
    return np.stack(columns, axis=-1)


@pytest.mark.parametrize("small", [0.0, 1e-6, 3e-3])
def test_gradients_at_small_angles_match_finite_differences(small: float) -> None:
    xi = np.array([0.3, -0.2, 0.5, small, -small, 0.5 * small])
    for jac, fn in ((_jac_exp, _se3_exp), (_jac_log_exp, _log_exp_jit)):
        np.testing.assert_allclose(np.asarray(jac(xi)), finite_difference(fn, xi), atol=1e-8)


def test_gradients_near_pi_are_finite_and_correct() -> None:
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    xi = np.concatenate([[0.4, 0.1, -0.3], (np.pi - 1e-3) * axis])
    for jac_fn, fn in ((_jac_exp, _se3_exp), (_jac_log_exp, _log_exp_jit)):
        jac = np.asarray(jac_fn(xi))
        assert np.isfinite(jac).all()
        np.testing.assert_allclose(jac, finite_difference(fn, xi), atol=1e-6)
    np.testing.assert_allclose(np.asarray(_jac_log_exp(xi)), np.eye(6), atol=1e-7)
    grad = jax.jit(jax.grad(lambda x: jnp.sum(_log_exp(x) ** 2)))(jnp.asarray(xi))
    assert bool(jnp.isfinite(grad).all())
    np.testing.assert_allclose(np.asarray(grad), 2 * xi, atol=1e-6)


# --- jit and vmap -------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_jit_and_vmap_equal_python_loop(dtype: type) -> None:
    rng = np.random.default_rng(1)
    xi = np.concatenate([rng.normal(size=(5, 3)), rng.normal(size=(5, 3))], axis=1).astype(dtype)
    xi[0, 3:] = 0.0
    xi[1, 3:] = 1e-6
    cases = ((se3_exp, xi), (se3_log, np.asarray(se3_exp(xi))), (so3_log, np.asarray(so3_exp(xi[:, 3:]))))
    for fn, args in cases:
        single = jax.jit(fn)  # compiled for one unbatched item, then called in a Python loop
        looped = np.stack([np.asarray(single(item)) for item in args])
        np.testing.assert_allclose(np.asarray(jax.jit(fn)(args)), looped, atol=TOL[dtype], rtol=0)
        np.testing.assert_allclose(np.asarray(jax.vmap(fn)(args)), looped, atol=TOL[dtype], rtol=0)


# --- projection and file validation -------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_project_to_so3_matches_scipy_nearest_rotation(dtype: type) -> None:
    rng = np.random.default_rng(2)
    R = Rotation.random(6, random_state=3).as_matrix()
    noisy = R + 1e-3 * rng.normal(size=R.shape)
    out = project_to_so3(noisy.astype(dtype))
    assert out.dtype == dtype
    tol = 1e-6 if dtype == np.float32 else 1e-10
    np.testing.assert_allclose(np.asarray(out, np.float64), Rotation.from_matrix(noisy).as_matrix(), atol=tol)
    np.testing.assert_allclose(np.asarray(project_to_so3(R)), R, atol=1e-12)
    # A reflection is mapped to a proper rotation.
    assert float(jnp.linalg.det(project_to_so3(np.diag([1.0, 1.0, -1.0])))) == pytest.approx(1.0)


def test_validate_poses_projects_near_rotations() -> None:
    rng = np.random.default_rng(4)
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, :3, :3] = Rotation.random(4, random_state=5).as_matrix()
    T[:, :3, 3] = rng.normal(size=(4, 3))
    noisy = T.copy()
    noisy[:, :3, :3] += 1e-5 * rng.normal(size=(4, 3, 3))
    out = validate_poses(noisy[:, :3, :], source="poses.txt")
    assert out.shape == (4, 4, 4) and out.dtype == np.float64
    gram = np.einsum("nji,njk->nik", out[:, :3, :3], out[:, :3, :3])
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-12)
    np.testing.assert_allclose(out, T, atol=1e-4)
    np.testing.assert_array_equal(out[:, 3], np.broadcast_to([0, 0, 0, 1.0], (4, 4)))


def test_validate_poses_errors_name_index_and_deviation() -> None:
    good = np.tile(np.eye(4), (5, 1, 1))
    bad = good.copy()
    bad[3, :3, :3] *= 1.1
    with pytest.raises(ValueError, match=r"poses\.txt: pose 3 is not rigid: max \|RᵀR − I\| = 0\.21"):
        validate_poses(bad, source="poses.txt")
    reflection = good.copy()
    reflection[2, 0, 0] = -1.0
    with pytest.raises(ValueError, match=r"pose 2 is not rigid.*det R = -1"):
        validate_poses(reflection, source="poses.txt")
    nan = good.copy()
    nan[4, 1, 3] = np.nan
    with pytest.raises(ValueError, match=r"traj\.mat: pose 4 contains a non-finite value"):
        validate_poses(nan, source="traj.mat")
    bottom = good.copy()
    bottom[1, 3, 0] = 0.5
    with pytest.raises(ValueError, match=r"pose 1 has bottom row"):
        validate_poses(bottom)
    with pytest.raises(ValueError, match=r"expected poses of shape \[N, 4, 4\] or \[N, 3, 4\], got \(5, 4\)"):
        validate_poses(np.zeros((5, 4)))


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: so3_hat(np.zeros(4)), r"phi must have shape \[\.\.\., 3\], got \(4,\)"),
        (lambda: so3_log(np.zeros((3, 4))), r"rotation must have shape \[\.\.\., 3, 3\]"),
        (lambda: se3_exp(np.zeros((2, 5))), r"xi must have shape \[\.\.\., 6\], got \(2, 5\)"),
        (lambda: se3_log(np.zeros((3, 4))), r"transform must have shape \[\.\.\., 4, 4\]"),
        (lambda: transform_points(np.eye(4), np.zeros((4, 2))), r"points must have shape \[\.\.\., N, 3\]"),
    ],
)
def test_shape_errors_name_shapes(call, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call()
