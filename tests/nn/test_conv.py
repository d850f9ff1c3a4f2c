"""dpc_jax.nn.conv against XLA's own convolutions (float64): values and both gradients, under jit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dpc_jax.engine.backend import compiler_options
from dpc_jax.nn.conv import (
    NHWC,
    conv3x3_few_outputs,
    conv3x3_planar,
    conv_s2,
    phase_kernel,
    upconv3x3_s2,
    upconv3x3_s2_phases,
)


def _reference_s2(x: jax.Array, kernel: jax.Array) -> jax.Array:
    pad = (kernel.shape[0] - 1) // 2
    return jax.lax.conv_general_dilated(x, kernel, (2, 2), ((pad, pad), (pad, pad)), dimension_numbers=NHWC)


def _reference_same3x3(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return jax.lax.conv_general_dilated(x, kernel, (1, 1), ((1, 1), (1, 1)), dimension_numbers=NHWC)


def _reference_up(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return jax.lax.conv_transpose(x, kernel, (2, 2), ((1, 2), (1, 2)), dimension_numbers=NHWC)


def _check(fn, reference, x_shape: tuple[int, ...], kernel_shape: tuple[int, ...], seed: int) -> None:
    """Value and the VJP (both arguments, a random cotangent) of ``fn`` equal ``reference``'s."""
    rng = np.random.default_rng(seed)
    x = jnp.asarray(rng.normal(size=x_shape))
    kernel = jnp.asarray(rng.normal(size=kernel_shape))
    want, want_vjp = jax.vjp(reference, x, kernel)
    got, got_vjp = jax.jit(lambda a, b: jax.vjp(fn, a, b))(x, kernel)
    assert got.shape == want.shape and got.dtype == jnp.float64
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    g = jnp.asarray(rng.normal(size=want.shape))
    for got_grad, want_grad in zip(got_vjp(g), want_vjp(g), strict=True):
        np.testing.assert_allclose(got_grad, want_grad, rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize(
    ("hw", "k", "cin", "cout"),
    [((9, 11), 7, 3, 4), ((8, 6), 5, 2, 3), ((7, 4), 3, 4, 2), ((1, 1), 3, 2, 2), ((2, 3), 7, 1, 1)],
)
def test_conv_s2_matches_strided_conv(hw: tuple[int, int], k: int, cin: int, cout: int) -> None:
    """Odd and even sizes, kernels larger than the image: ⌈n/2⌉ outputs and the same gradients."""
    _check(conv_s2, _reference_s2, (2, *hw, cin), (k, k, cin, cout), seed=k + hw[0])


@pytest.mark.parametrize(
    ("hw", "cin", "f"), [((6, 7), 8, 1), ((5, 4), 3, 2), ((1, 2), 2, 1), ((4, 4), 17, 2)]
)
def test_conv3x3_few_outputs_matches_conv(hw: tuple[int, int], cin: int, f: int) -> None:
    _check(conv3x3_few_outputs, _reference_same3x3, (2, *hw, cin), (3, 3, cin, f), seed=cin + f)


@pytest.mark.parametrize("hw", [(5, 7), (4, 6), (1, 1)])
def test_upconv3x3_s2_matches_conv_transpose(hw: tuple[int, int]) -> None:
    _check(upconv3x3_s2, _reference_up, (2, *hw, 3), (3, 3, 3, 4), seed=hw[1])


@pytest.mark.parametrize(
    ("hw", "cin", "f"), [((6, 7), 8, 2), ((5, 4), 10, 8), ((1, 2), 2, 1), ((3, 3), 1, 1)]
)
def test_conv3x3_planar_matches_conv(hw: tuple[int, int], cin: int, f: int) -> None:
    """Values only: inference is its one use (training differentiates the NHWC convolutions)."""
    rng = np.random.default_rng(cin * f)
    x, kernel = jnp.asarray(rng.normal(size=(2, *hw, cin))), jnp.asarray(rng.normal(size=(3, 3, cin, f)))
    planes = jnp.pad(jnp.moveaxis(x, -1, 1), ((0, 0), (0, 0), (1, 1), (1, 1)))
    got = jax.jit(conv3x3_planar)(planes, kernel)
    assert got.dtype == jnp.float64
    want = jnp.moveaxis(_reference_same3x3(x, kernel), -1, 1)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_conv3x3_planar_is_a_valid_convolution() -> None:
    """No padding of its own: [B, C, H, W] → [B, F, H − 2, W − 2], each output a 3×3 window."""
    rng = np.random.default_rng(3)
    x, kernel = rng.normal(size=(1, 2, 5, 6)), rng.normal(size=(3, 3, 2, 3))
    got = np.asarray(conv3x3_planar(jnp.asarray(x), jnp.asarray(kernel)))
    assert got.shape == (1, 3, 3, 4)
    i, j, f = 1, 2, 2
    window = x[0, :, i : i + 3, j : j + 3]  # [C, 3, 3]
    assert got[0, f, i, j] == pytest.approx(np.einsum("cab,abc->", window, kernel[..., f]), abs=1e-12)


@pytest.mark.parametrize("hw", [(5, 7), (1, 1)])
def test_upconv3x3_s2_channels_first_is_the_same_map(hw: tuple[int, int]) -> None:
    rng = np.random.default_rng(hw[1])
    x, kernel = jnp.asarray(rng.normal(size=(2, *hw, 3))), jnp.asarray(rng.normal(size=(3, 3, 3, 4)))
    want = jnp.moveaxis(_reference_up(x, kernel), -1, 1)
    np.testing.assert_allclose(upconv3x3_s2(x, kernel, channels_first=True), want, rtol=1e-12, atol=1e-12)


def test_phase_kernel_places_every_tap_once() -> None:
    """Each of the nine taps sits in exactly one (offset, phase) block; the seven others are zero.
    (That these are the right blocks, the transposed convolution tests check.)"""
    kernel = jnp.arange(9.0).reshape(3, 3, 1, 1) + 1.0
    phases = np.asarray(phase_kernel(kernel)).reshape(2, 2, 2, 2)  # [a, b, q, r]
    # Along one axis: phase 0 at offset 0 is tap 1; phase 1 at offsets 0 and 1 are taps 0 and 2.
    tap = {(0, 0): 1, (1, 0): 0, (1, 1): 2}
    for a, b, q, r in np.ndindex(2, 2, 2, 2):
        want = 0.0 if (q, a) not in tap or (r, b) not in tap else 3 * tap[q, a] + tap[r, b] + 1.0
        assert phases[a, b, q, r] == want, (a, b, q, r)
    assert sorted(phases[phases > 0].tolist()) == list(range(1, 10))


def test_upconv3x3_s2_phases_is_upconv3x3_s2_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=(2, 5, 7, 3)), jnp.float32)
    kernel = jnp.asarray(rng.normal(size=(3, 3, 3, 4)), jnp.float32)
    for channels_first in (False, True):
        np.testing.assert_array_equal(
            upconv3x3_s2_phases(x, phase_kernel(kernel), channels_first=channels_first),
            upconv3x3_s2(x, kernel, channels_first=channels_first),
        )
    with pytest.raises(ValueError, match="4\\*C_out"):
        upconv3x3_s2_phases(x, kernel)


def test_float32_inputs_stay_float32() -> None:
    x = jnp.ones((1, 4, 4, 2), jnp.float32)
    assert conv_s2(x, jnp.ones((3, 3, 2, 3), jnp.float32)).dtype == jnp.float32
    assert conv3x3_few_outputs(x, jnp.ones((3, 3, 2, 1), jnp.float32)).dtype == jnp.float32
    assert upconv3x3_s2(x, jnp.ones((3, 3, 2, 3), jnp.float32)).dtype == jnp.float32
    assert conv3x3_planar(x, jnp.ones((3, 3, 4, 1), jnp.float32)).dtype == jnp.float32


def test_kernel_shape_errors() -> None:
    x = jnp.ones((1, 4, 4, 2))
    with pytest.raises(ValueError, match="odd size"):
        conv_s2(x, jnp.ones((4, 4, 2, 3)))
    with pytest.raises(ValueError, match="3x3 kernel"):
        conv3x3_few_outputs(x, jnp.ones((5, 5, 2, 1)))
    with pytest.raises(ValueError, match=r"\[3, 3, 4, F\] kernel"):
        conv3x3_planar(x, jnp.ones((3, 3, 2, 1)))


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the options concern XLA's CPU backend")
def test_compiler_options_move_convolutions_off_ynnpack() -> None:
    # 32 channels: a convolution XLA's default hands to YNNPACK. With the Eigen options (ss-DPC-Net's
    # training step, both networks' inference) it must compile (the option exists in this jaxlib),
    # run on another library, and give the same values; Stereo DPC's training step keeps the default.
    rng = np.random.default_rng(5)
    x = jnp.asarray(rng.normal(size=(2, 12, 10, 32)), jnp.float32)
    kernel = jnp.asarray(rng.normal(size=(3, 3, 32, 32)), jnp.float32)
    assert compiler_options("stereo_dpc", training=True) == {}
    options = compiler_options("ss_dpc", training=True)
    for method in ("ss_dpc", "stereo_dpc"):
        assert compiler_options(method, training=False) == options
    default = jax.jit(_reference_same3x3).lower(x, kernel).compile()
    eigen = jax.jit(_reference_same3x3, compiler_options=options).lower(x, kernel).compile()
    assert "ynn_fusion" in default.as_text()
    assert "ynn_fusion" not in eigen.as_text() and "convolution(" in eigen.as_text()
    np.testing.assert_allclose(eigen(x, kernel), default(x, kernel), rtol=1e-5, atol=1e-4)
