"""The planted prior: `evaluate --diagnose`'s decomposition reads back the bias and noise planted."""

from __future__ import annotations

import numpy as np
import pytest

from dpc_jax.eval.diagnosis import diagnose
from dpc_jax.synth.planted_prior import planted_prior
from dpc_jax.synth.sequence import SynthConfig, sequence_poses


@pytest.fixture(scope="module")
def ground_truth() -> np.ndarray:
    return sequence_poses(SynthConfig(frames=400, height=24, width=40, seed=3))[0]


def test_diagnosis_reads_back_a_planted_bias_exactly(ground_truth: np.ndarray) -> None:
    bias = np.array([0.1e-3, -0.25e-3, 0.24e-3])  # rad per step, the size of libviso2-s's
    prior = planted_prior(ground_truth, bias)
    result = diagnose(ground_truth, prior)
    np.testing.assert_allclose(result.mean[3:], bias * 1e3, atol=1e-9)  # mrad
    np.testing.assert_allclose(result.mean[:3], 0.0, atol=1e-9)  # mm: no translation error planted
    np.testing.assert_allclose(result.spread, 0.0, atol=1e-9)
    np.testing.assert_array_equal(prior[0], ground_truth[0])
    # Step lengths are kept: the error rotates a step, it does not stretch it.
    length = lambda poses: np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(length(prior), length(ground_truth), rtol=1e-12)


def test_planted_noise_is_the_diagnosed_spread(ground_truth: np.ndarray) -> None:
    noise = np.array([0.05e-3, 0.1e-3, 0.02e-3])
    prior = planted_prior(ground_truth, (0.0, 0.0, 0.0), noise, seed=1)
    result = diagnose(ground_truth, prior)
    steps = len(ground_truth) - 1
    # Sample standard deviation of 399 normal draws: within 4 standard errors (σ / √(2(M-1))).
    np.testing.assert_allclose(result.spread[3:], noise * 1e3, rtol=4 / np.sqrt(2 * (steps - 1)))
    assert np.all(np.abs(result.mean[3:]) < 4 * noise * 1e3 / np.sqrt(steps))
    np.testing.assert_array_equal(prior, planted_prior(ground_truth, (0.0, 0.0, 0.0), noise, seed=1))


def test_bad_arguments_are_refused(ground_truth: np.ndarray) -> None:
    with pytest.raises(ValueError, match="N >= 2"):
        planted_prior(ground_truth[:1], (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="finite"):
        planted_prior(ground_truth, (np.nan, 0.0, 0.0))
