"""The acceptance test: statistics against closed forms, Δ and decisions on rendered pairs with true depth
and on real pairs with StereoSGBM depth."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from support import OPTIMISED

from dpc_jax.correction.acceptance import paired_test
from dpc_jax.correction.decision import decide
from dpc_jax.data.priors import log_poses
from dpc_jax.geometry.lie import se3_exp
from dpc_jax.geometry.poses import relative_poses
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.losses import candidate_deltas, correction_deltas, temporal_pair_errors
from dpc_jax.nn.model_config import SSDPCLossConfig, StereoDPCLossConfig
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs
from dpc_jax.synth import SynthConfig, render_sequence


def test_wilcoxon_exact_p_values_in_closed_form() -> None:
    # All n differences negative: W+ = 0, exact one-sided p = 1 / 2^n.
    t = paired_test("full", -np.arange(1.0, 9.0))
    assert t.p_value == pytest.approx(2.0**-8) and t.statistic == 0 and t.passed
    assert t.improved_share == 1.0 and t.mean_delta == -4.5 and t.median_delta == -4.5
    # One positive difference with the smallest rank: W+ = 1, p = P(W+ <= 1) = 2 / 2^n.
    t = paired_test("full", np.array([0.5, -1, -2, -3, -4, -5, -6, -7]))
    assert t.p_value == pytest.approx(2 * 2.0**-8) and t.passed
    # Seven pairs cannot reach the 1 % level (1/128 < 0.01 < 2/128 with one positive).
    assert not paired_test("full", np.array([0.5, -1, -2, -3, -4, -5, -6])).passed
    # Every difference zero: nothing to rank.
    zero = paired_test("rotation", np.zeros(8))
    assert zero.p_value == 1.0 and math.isnan(zero.statistic) and not zero.passed
    # Significant but with a positive mean (a few large losses): not passed.
    skewed = np.array([-1e-5] * 15 + [1e-3])
    assert paired_test("full", skewed).p_value < 0.01 and not paired_test("full", skewed).passed
    with pytest.raises(ValueError, match="finite"):
        paired_test("full", np.array([np.nan, -1.0]))
    with pytest.raises(ValueError, match="alpha"):
        paired_test("full", -np.arange(1.0, 9.0), alpha=1.5)


_candidate_deltas = jax.jit(candidate_deltas, static_argnames="config", compiler_options=OPTIMISED)
# One program each, not JAX's operation-by-operation compilation of the same functions called eagerly.
_correction_deltas = jax.jit(correction_deltas, static_argnames="config")
_temporal_pair_errors = jax.jit(temporal_pair_errors, static_argnames="config")


def batch_measure(outputs: DPCOutputs, batch: Batch, config, valid):
    """The measurement of named corrections ``[n, 6]`` on one batch of pairs with the outputs' depth (one
    candidate at a time, so that one compilation serves every call)."""

    def measure(candidates):
        return {name: np.asarray(_candidate_deltas(outputs, batch, config, xi[None], valid)["delta"][0])
                for name, xi in candidates.items()}

    return measure


YAW = 2e-3
BIAS_MRAD = 0.5  # the planted per-step bias of the mean test on real frames


@pytest.fixture(scope="module")
def rendered() -> tuple[Batch, DPCOutputs, tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Nine rendered stereo frames as eight pairs, with the renderer's exact depth as the 'network' depth."""
    seq = render_sequence(SynthConfig(frames=9, height=64, width=160, seed=3))
    steps = relative_poses(seq.poses)
    n = len(steps)

    def pairs(a: np.ndarray) -> np.ndarray:
        return np.stack([a[:-1], a[1:]], axis=1)

    valid = (pairs(np.isfinite(seq.depth_left)), pairs(np.isfinite(seq.depth_right)))
    inverse = [np.where(v, 1.0 / np.where(v, pairs(d), 1.0), 1.0)
               for v, d in zip(valid, (seq.depth_left, seq.depth_right), strict=True)]
    batch = Batch(left=pairs(seq.left), right=pairs(seq.right), xi_vo=np.asarray(log_poses(steps)),
                  intrinsics=np.tile(seq.K, (n, 1, 1)), baseline=np.full(n, seq.baseline), weight=np.ones(n))
    outputs = DPCOutputs(np.zeros((n, 6)), BranchOutputs(inverse[0], np.ones_like(inverse[0])),
                         BranchOutputs(inverse[1], np.ones_like(inverse[1])))
    return batch, outputs, valid, steps


def _yaw(n: int) -> np.ndarray:
    xi = np.zeros((n, 6))
    xi[:, 4] = YAW
    return xi


@pytest.mark.slow
def test_true_depth_rejects_a_spurious_yaw_and_accepts_the_true_correction(rendered) -> None:
    batch, outputs, valid, steps = rendered
    n = len(steps)
    config = StereoDPCLossConfig()
    # Exact prior: a constant 2 mrad yaw "correction" makes every pair worse.
    deltas = {k: np.asarray(v) for k, v in
              _correction_deltas(outputs._replace(xi_corr=_yaw(n)), batch, config, valid).items()}
    assert np.all(deltas["full"] > 0)
    assert decide(_yaw(n), batch_measure(outputs, batch, config, valid)).component == "none"
    # A prior with a known −2 mrad yaw error per step: the true correction (+2 mrad) is accepted, in full.
    biased = np.asarray(se3_exp(-_yaw(n))) @ steps
    batch = batch._replace(xi_vo=np.asarray(log_poses(biased)))
    deltas = {k: np.asarray(v) for k, v in
              _correction_deltas(outputs._replace(xi_corr=_yaw(n)), batch, config, valid).items()}
    result = decide(_yaw(n), batch_measure(outputs, batch, config, valid))
    assert np.all(deltas["full"] < 0) and result.component == "full" and not result.remainder
    assert result.tests["full"].p_value == pytest.approx(2.0**-8)
    # Its Δ is the measurement's, the per-sample Δ of correction_deltas.
    np.testing.assert_allclose(result.delta, deltas["full"], rtol=1e-4, atol=1e-7)  # float32
    # Δ is a paired difference: L(0) of the biased prior is what "none" reports (to float32 rounding: two
    # programs, whose code XLA generates its own way).
    baseline = _temporal_pair_errors(outputs, batch, config, valid)
    np.testing.assert_allclose(deltas["none"], np.asarray(baseline), rtol=2e-6)


def test_deltas_per_component_and_rotation_only(rendered) -> None:
    batch, outputs, valid, steps = rendered
    n = len(steps)
    xi = np.zeros((n, 6))
    xi[:, 2] = 0.05  # a translation-only correction: its rotation part is zero
    deltas = _correction_deltas(outputs._replace(xi_corr=xi), batch, StereoDPCLossConfig(), valid)
    np.testing.assert_array_equal(np.asarray(deltas["rotation"]), 0.0)
    assert np.all(np.asarray(deltas["full"]) > 0)
    # A rotation-only loss config applies only φ in "full" too.
    rotation_config = StereoDPCLossConfig(rotation_only=True)
    only = _correction_deltas(outputs._replace(xi_corr=xi), batch, rotation_config, valid)
    np.testing.assert_array_equal(np.asarray(only["full"]), 0.0)
    with pytest.raises(TypeError, match="SSDPCLossConfig or StereoDPCLossConfig"):
        temporal_pair_errors(outputs, batch, object())
    # ss-DPC-Net's assembly (frame t+1 from t, left camera, depth of t+1). Its one-directional L1 error
    # at this size is not monotonic below a pixel (bilinear resampling blurs less at some sub-pixel
    # offsets), so the spurious yaw here is 1 cm-rad ≈ 0.9 px.
    mono = outputs._replace(left=BranchOutputs(outputs.left.inv_depth[:, 1:], outputs.left.mask[:, 1:]),
                            right=None, xi_corr=5 * _yaw(n))
    mono_deltas = _correction_deltas(mono, batch, SSDPCLossConfig(), (valid[0][:, 1:], None))
    assert np.all(np.asarray(mono_deltas["full"]) > 0)


REAL_SIZE = (96, 320)  # H, W: about the aspect of KITTI's 375 × 1242
REAL_FRAMES = 20  # the harmful command of issue 30 corrected frames 0:20 of drive 0001


@pytest.fixture(scope="module")
def real_pairs() -> tuple[Batch, DPCOutputs, tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Frames 0–19 of real drive 0001 as 19 pairs, resized here with OpenCV, with StereoSGBM depth as the
    depth Δ is measured with, and libviso2-s's steps (the images' best motion known without a network)."""
    import cv2
    from conftest import DATA

    from dpc_jax.data.kitti import load_image, open_raw
    from dpc_jax.data.poses_io import read_trajectory
    from dpc_jax.data.stereo_depth import sgbm_inverse_depth

    raw = DATA / "kitti-raw"
    seq = open_raw(raw, "2011_09_26", 1).select(0, REAL_FRAMES)
    libviso2 = read_trajectory(raw / "libviso2" / "stereo_2011_09_26_drive_0001.mat")
    steps = relative_poses(libviso2[:REAL_FRAMES])
    h, w = REAL_SIZE
    scale = np.diag([w / seq.image_size[1], h / seq.image_size[0], 1.0])
    K = scale @ seq.K
    # The pixel-centre convention of a resize: u' = (u + 0.5)·s − 0.5.
    K[0, 2] = (seq.K[0, 2] + 0.5) * w / seq.image_size[1] - 0.5
    K[1, 2] = (seq.K[1, 2] + 0.5) * h / seq.image_size[0] - 0.5
    left, right = ([cv2.resize(load_image(p), (w, h), interpolation=cv2.INTER_AREA) for p in paths]
                   for paths in (seq.images.left_paths, seq.images.right_paths))
    depth = [sgbm_inverse_depth(a, b, K[0, 0], seq.baseline) for a, b in zip(left, right, strict=True)]
    left_arr, right_arr = np.stack(left), np.stack(right)
    inv_l, ok_l = np.stack([d[0] for d in depth]), np.stack([d[1] for d in depth])
    inv_r, ok_r = np.stack([d[2] for d in depth]), np.stack([d[3] for d in depth])
    n = REAL_FRAMES - 1

    def pairs(a: np.ndarray) -> np.ndarray:
        return np.stack([a[:-1], a[1:]], axis=1)

    valid = (pairs(ok_l), pairs(ok_r))
    inverse = [np.where(v, pairs(i), 1.0) for v, i in zip(valid, (inv_l, inv_r), strict=True)]
    batch = Batch(left=pairs(left_arr), right=pairs(right_arr), xi_vo=np.asarray(log_poses(steps)),
                  intrinsics=np.tile(K, (n, 1, 1)), baseline=np.full(n, seq.baseline), weight=np.ones(n))
    outputs = DPCOutputs(np.zeros((n, 6)), BranchOutputs(inverse[0], np.ones_like(inverse[0])),
                         BranchOutputs(inverse[1], np.ones_like(inverse[1])))
    return batch, outputs, valid, steps


def _planted_rotations(n: int, mrad: float, seed: int = 0) -> np.ndarray:
    """``[n, 6]`` corrections: rotations of ``mrad`` about random axes, no translation."""
    axes = np.random.default_rng(seed).normal(size=(n, 3))
    xi = np.zeros((n, 6))
    xi[:, 3:] = mrad * 1e-3 * axes / np.linalg.norm(axes, axis=1, keepdims=True)
    return xi


@pytest.mark.parametrize("mrad", [1.0, 3.0])
def test_on_real_frames_a_planted_correction_is_accepted_when_it_helps_and_refused_when_it_hurts(
    real_pairs, mrad: float
) -> None:
    """19 real pairs, SGBM depth: the short sequence of the harmful command has the power to accept a
    correction that undoes a planted rotation error, and refuses the same rotations planted on a prior
    that lacks them (what a network from another domain proposing spurious rotations does)."""
    batch, outputs, valid, steps = real_pairs
    n = len(steps)
    config = StereoDPCLossConfig()
    xi = _planted_rotations(n, mrad)
    refused = decide(xi, batch_measure(outputs, batch, config, valid))
    assert refused.component == "none", refused.reason
    biased = np.asarray(se3_exp(-xi)) @ steps  # a prior with the planted error; ξ undoes it exactly
    helped_batch = batch._replace(xi_vo=np.asarray(log_poses(biased)))
    accepted = decide(xi, batch_measure(outputs, helped_batch, config, valid))
    assert accepted.component == "full", accepted.reason


def test_on_real_frames_a_wrong_mean_is_removed_and_a_right_one_kept(real_pairs) -> None:
    """19 real pairs, SGBM depth: a prior whose steps carry a planted error, a per-step part and a bias
    (the drift). A proposal that undoes the per-step part but reverses the bias passes the per-pair test
    as a whole (the earlier decision applied it, doubling the drift); its mean fails its own test and
    only the remainder is applied. The same proposal with the bias right is applied whole."""
    batch, outputs, valid, steps = real_pairs
    n = len(steps)
    config = StereoDPCLossConfig()
    per_step = _planted_rotations(n, 2.0, seed=4)
    per_step -= per_step.mean(axis=0)
    bias = np.array([0, 0, 0, 0, BIAS_MRAD * 1e-3, 0])
    planted = per_step + bias
    batch = batch._replace(xi_vo=np.asarray(log_poses(np.asarray(se3_exp(-planted)) @ steps)))
    measure = batch_measure(outputs, batch, config, valid)
    wrong = decide(per_step - bias, measure, components=("rotation",))
    assert wrong.tests["rotation"].passed and not wrong.tests["mean of rotation"].passed
    assert wrong.component.startswith("rotation") and wrong.remainder, wrong.reason
    assert not decide(per_step - bias, measure, components=("rotation",), mean_test=False).remainder
    right = decide(per_step + bias, measure, components=("rotation",))
    assert right.tests["mean of rotation"].passed
    assert right.component.startswith("rotation") and not right.remainder, right.reason


def test_on_real_frames_a_spurious_axis_is_dropped_and_the_helpful_one_kept(real_pairs) -> None:
    """19 real pairs, SGBM depth: a prior with a planted 2 mrad yaw error per pair, and a proposal that
    undoes it but adds a spurious 1 mrad pitch (alternating): the rotation as a whole passes, and only
    the rotation about y is applied."""
    batch, outputs, valid, steps = real_pairs
    n = len(steps)
    config = StereoDPCLossConfig()
    undo = np.zeros((n, 6))
    undo[:, 4] = 2e-3
    spurious = undo.copy()
    spurious[:, 3] = 1e-3 * np.where(np.arange(n) % 2, 1.0, -1.0)
    biased = np.asarray(se3_exp(-undo)) @ steps
    batch = batch._replace(xi_vo=np.asarray(log_poses(biased)))
    result = decide(spurious, batch_measure(outputs, batch, config, valid), components=("rotation",),
                    mean_test=False)
    assert result.tests["rotation_y"].passed and not result.tests["rotation_x"].passed
    assert result.component == "rotation_y", result.reason
