"""dpc_jax.nn.loss_terms: the loss building blocks against numpy and OpenCV references."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dpc_jax.geometry.ssim import ssim_loss
from dpc_jax.nn.loss_terms import (
    explainability_loss,
    gradient_mask,
    masked_mean,
    photometric_error,
    rotation_weights,
)


def test_photometric_error_reference_and_learned_weight() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.random((2, 5, 6, 3)), rng.random((2, 5, 6, 3))
    l1 = np.abs(a - b).mean(-1)
    structural = np.asarray(ssim_loss(a, b)).mean(-1)
    np.testing.assert_allclose(np.asarray(photometric_error(a, b, 0.0)), l1, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(photometric_error(a, b)), 0.85 * structural + 0.15 * l1, rtol=1e-12)
    learned = photometric_error(a, b, jnp.asarray(0.3))
    np.testing.assert_allclose(np.asarray(learned), 0.3 * structural + 0.7 * l1, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(photometric_error(a, a)), 0.0, atol=1e-12)


def test_photometric_error_ignores_invalid_neighbours_in_ssim() -> None:
    rng = np.random.default_rng(1)
    target = rng.random((6, 8, 3))
    recon = target.copy()
    recon[:, :2] = 0.0  # what the sampler returns outside the source
    valid = np.ones((6, 8), bool)
    valid[:, :2] = False
    error = np.asarray(photometric_error(target, recon, 0.85, valid))
    np.testing.assert_allclose(error[valid], 0.0, atol=1e-12)
    assert np.asarray(photometric_error(target, recon, 0.85))[:, 2].min() > 1e-3


def test_masked_mean_reference_invalid_and_padding() -> None:
    rng = np.random.default_rng(2)
    values = rng.random((3, 4, 5))
    valid = rng.random((3, 4, 5)) > 0.3
    weight = np.array([1.0, 0.5, 0.0])
    scale = np.array([5.0, 1.0, 7.0])
    w = weight[:, None, None] * valid
    expected = (w * scale[:, None, None] * values).sum() / w.sum()
    np.testing.assert_allclose(float(masked_mean(values, valid, weight, scale)), expected, rtol=1e-13)
    # Invalid pixels and padding samples neither count nor dilute, whatever they hold.
    changed = values.copy()
    changed[~valid] = np.inf
    changed[2] = np.nan
    np.testing.assert_allclose(float(masked_mean(changed, valid, weight, scale)), expected, rtol=1e-13)
    assert float(masked_mean(values, np.zeros_like(valid), weight)) == 0.0


def test_explainability_loss_and_clamp() -> None:
    mask = np.array([[[0.5, 1.0]], [[0.25, 0.25]]])
    weight = np.array([1.0, 0.0])
    np.testing.assert_allclose(float(explainability_loss(mask, weight)), np.log(2) / 2, rtol=1e-13)
    clamped = explainability_loss(np.zeros((1, 2, 2)), np.ones(1), floor=1e-3)
    assert float(clamped) == pytest.approx(-np.log(1e-3))
    grad = jax.grad(lambda m: explainability_loss(m, jnp.ones(1)))(jnp.zeros((1, 2, 2)))
    assert bool(jnp.isfinite(grad).all())


def test_rotation_weights_switch_at_gamma() -> None:
    gamma = 0.005
    xi = np.zeros((4, 6))
    xi[:, 3] = [0.0, gamma * (1 - 1e-9), gamma, gamma * 1.5]
    xi[:, 0] = 5.0  # translation is irrelevant
    np.testing.assert_array_equal(np.asarray(rotation_weights(xi, gamma, 4.0)), [1.0, 1.0, 5.0, 5.0])


def test_gradient_mask_against_cv2_grey_and_numpy() -> None:
    rng = np.random.default_rng(3)
    image = rng.random((2, 7, 9, 3)).astype(np.float32) * 0.2
    mask = np.asarray(gradient_mask(image, 0.03))
    for b in range(2):
        grey = cv2.cvtColor(image[b], cv2.COLOR_RGB2GRAY).astype(np.float64)
        dx = np.zeros_like(grey)
        dy = np.zeros_like(grey)
        dx[:, :-1] = np.abs(grey[:, 1:] - grey[:, :-1])
        dy[:-1, :] = np.abs(grey[1:, :] - grey[:-1, :])
        expected = (dx + dy) / 2 > 0.03
        # Ignore pixels within float32 rounding of the threshold.
        close = np.abs((dx + dy) / 2 - 0.03) < 1e-5
        np.testing.assert_array_equal(mask[b][~close], expected[~close])
        assert 0.05 < expected.mean() < 0.95
