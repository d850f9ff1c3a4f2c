"""Adaptation to the corrected sequence: never reads the ground truth, learns a known bias, saves a run."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from flax import nnx

from dpc_jax.correction.adapt import AdaptConfig, adapt, save_adapted
from dpc_jax.correction.inference import TrainedRun, load_run, run_prediction
from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.holdout import adaptable_pairs, held_out_pairs
from dpc_jax.data.kitti import open_odometry
from dpc_jax.data.sequence_cache import load_cache
from dpc_jax.geometry.lie import se3_exp
from dpc_jax.geometry.poses import compose, relative_poses
from dpc_jax.nn.models import create_model
from dpc_jax.synth import SynthConfig
from dpc_jax.synth.writer import write_sequence
from dpc_jax.training.train_config import TrainConfig

SIZE = (32, 80)
YAW_BIAS = 4e-3  # rad per frame: the prior turns this much less than the truth
TINY = {"encoder_planes": [8, 16], "encoder_kernels": [3, 3], "decoder_planes": [16, 8],
        "mask_source_block": 1, "depth_scales": 1, "fc_planes": [16, 16]}


@pytest.fixture(scope="module")
def biased(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, TrainedRun]:
    """24 rendered frames (the size test_synth renders at), prior = truth with a constant yaw bias,
    and an untrained zero-start network (a run that was never trained)."""
    tmp = tmp_path_factory.mktemp("adapt")
    write_sequence(tmp / "kitti", "00", SynthConfig(frames=24, height=64, width=160, seed=3), overwrite=True)
    sequence = open_odometry(tmp / "kitti", "00")
    steps = relative_poses(sequence.poses)
    error = np.zeros((len(steps), 6))
    error[:, 4] = -YAW_BIAS
    prior = compose(np.asarray(se3_exp(error)) @ steps, sequence.poses[0])
    cache = prepare_sequence(sequence, prior, tmp / "cache", size=SIZE, progress=False, workers=1)
    # Image features in the pose head: with the prior-only head a constant bias is learned by the
    # output bias alone, at 1e-4 rad per unit far slower than 40 test steps allow.
    config = TrainConfig(method="stereo_dpc", preset="small", model=TINY, image_size=SIZE, batch_size=4,
                         learning_rate=2e-3, validation_sequences=("v",), pose_features="images_and_prior")
    model = create_model("stereo_dpc", config.model_config(), 0)
    model.eval()
    graphdef, state = nnx.split(model)
    return cache, TrainedRun(tmp, config, "last", 0, graphdef, state)


class _Untouchable:
    """Stands in for the ground truth: any use of it fails the test."""

    def __getattr__(self, name: str) -> object:
        raise AssertionError(f"adaptation touched the ground truth ({name})")

    def __getitem__(self, key: object) -> object:
        raise AssertionError("adaptation indexed the ground truth")

    def __array__(self, *args: object, **kwargs: object) -> np.ndarray:
        raise AssertionError("adaptation converted the ground truth to an array")


def test_held_out_pairs() -> None:
    np.testing.assert_array_equal(held_out_pairs(12, 5), [2, 7])
    np.testing.assert_array_equal(held_out_pairs(7, 2), [1, 3, 5])
    # Pairs 2 and 7 hold frames 2, 3, 7, 8: pairs 1, 3, 6 and 8 touch them.
    np.testing.assert_array_equal(adaptable_pairs(12, 5), [0, 4, 5, 9, 10, 11])
    np.testing.assert_array_equal(adaptable_pairs(4, 4), [0])
    assert held_out_pairs(2, 4).size == 0  # pair 2 does not exist: nothing to test on
    with pytest.raises(ValueError, match="holdout_every must be >= 4"):
        AdaptConfig(steps=3, holdout_every=3)
    with pytest.raises(ValueError, match="steps"):
        AdaptConfig(steps=0)


@pytest.mark.slow
def test_adaptation_learns_a_known_rotation_bias_without_the_ground_truth(biased, tmp_path: Path) -> None:
    cache_dir, run = biased
    cache = load_cache(cache_dir)
    before = run_prediction(run, cache)
    np.testing.assert_array_equal(before.delta["full"], 0.0)  # the zero start: no correction yet

    blind = dataclasses.replace(cache, gt=_Untouchable())
    result = adapt(run, blind, AdaptConfig(steps=40, holdout_every=4, batch_size=4))
    np.testing.assert_array_equal(result.held_out, [2, 6, 10, 14, 18, 22])
    assert len(result.log) == 40 and result.log[-1]["loss"] < result.log[0]["loss"]

    after = run_prediction(result.run, cache)
    held = result.held_out
    # On pairs it never fitted, the adapted correction explains the images better than the prior ...
    assert after.delta["full"][held].mean() < 0 and np.all(after.delta["full"][held] < 0)
    # ... and turns the biased prior the way the truth does.
    assert after.xi_corr[:, 4].mean() > 0.1 * YAW_BIAS
    # The source run is untouched (the adaptation trains a copy).
    np.testing.assert_array_equal(run_prediction(run, cache).xi_corr, before.xi_corr)

    folder = save_adapted(tmp_path / "adapted", result, {"delta": float(after.delta["full"][held].mean())})
    restored = load_run(folder, "last")
    np.testing.assert_allclose(run_prediction(restored, cache).xi_corr, after.xi_corr, atol=1e-7)
    assert load_run(folder, "delta").epoch == 1  # its held-out Δ is below zero
    assert (folder / "adapt.csv").read_text().count("\n") == 41
