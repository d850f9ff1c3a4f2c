"""Tests of dpc_jax.nn.branch: the bilinear upsampling and the transposed convolution against
independent implementations (OpenCV, Flax's ConvTranspose)."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dpc_jax.nn.branch import UpConv, upsample2x_bilinear


def test_upsample2x_matches_opencv() -> None:
    x = np.random.default_rng(1).normal(size=(2, 5, 7, 3))
    got = np.asarray(upsample2x_bilinear(jnp.asarray(x)))
    for b in range(2):
        want = cv2.resize(x[b], (14, 10), interpolation=cv2.INTER_LINEAR)
        np.testing.assert_allclose(got[b], want, atol=1e-12)


@pytest.mark.parametrize("hw", [(5, 7), (4, 6), (1, 1)])
def test_upconv_is_transposed_conv(hw: tuple[int, int]) -> None:
    """The phase decomposition equals Flax's ConvTranspose (lax.conv_transpose) with that kernel."""
    up = UpConv(3, 4, nnx.Rngs(0))
    up.bias.set_value(jnp.asarray([0.1, -0.2, 0.3, 0.0], jnp.float32))
    x = jnp.asarray(np.random.default_rng(2).normal(size=(2, *hw, 3)), jnp.float32)
    reference = nnx.ConvTranspose(3, 4, (3, 3), strides=2, padding=((1, 2), (1, 2)), rngs=nnx.Rngs(1))
    reference.kernel.set_value(up.kernel[...])
    reference.bias.set_value(up.bias[...])
    want = jax.nn.relu(reference(x))
    got = up(x)
    assert got.shape == (2, 2 * hw[0], 2 * hw[1], 4)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
