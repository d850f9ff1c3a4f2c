"""``dpc_jax.correction.decision``: what is applied, from measured effects alone.

The reference is a closed-form photometric model: pair k's loss is a quadratic bowl around the step's
true correction ξ*_k, ``L_k(ξ) = ‖w ⊙ (ξ − ξ*_k)‖²``, so ``Δ_k(ξ) = L_k(ξ) − L_k(0)`` is known
exactly for any correction and the decision can be checked against what a correction does to the
steps (and so to the drift).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from dpc_jax.correction.acceptance import paired_test
from dpc_jax.correction.decision import JUDGE_SCALES, MEAN_TESTS, Decision, MeanTest, Outcome, decide
from dpc_jax.correction.parts import (
    MEAN_WINDOW,
    Part,
    applied_correction,
    component_mask,
    moving_mean,
    part_of,
    rotation_component,
)
from dpc_jax.results.acceptance import Acceptance

WEIGHT = np.array([1.0, 1.0, 1.0, 40.0, 40.0, 40.0])  # the images resolve a rotation better than a shift


def bowl(truth: np.ndarray, noise: float = 0.0, seed: int = 0):
    """The measurement of the quadratic model around ``truth`` ``[M, 6]``, with per-pair noise of the
    loss (the same draw for every correction of a pair, as the images are the same)."""
    jitter = np.random.default_rng(seed).normal(scale=noise, size=truth.shape[0])

    def loss(xi: np.ndarray) -> np.ndarray:
        return np.sum((WEIGHT * (xi - truth)) ** 2, axis=1) * (1.0 + jitter)

    asked: list[str] = []

    def measure(candidates):
        asked.extend(candidates)
        return {name: loss(xi) - loss(np.zeros_like(xi)) for name, xi in candidates.items()}

    measure.asked = asked  # type: ignore[attr-defined]
    return measure


def rotations(m: int, mrad: float, seed: int) -> np.ndarray:
    """``[m, 6]``: random rotations of about ``mrad`` per axis, no translation."""
    xi = np.zeros((m, 6))
    xi[:, 3:] = np.random.default_rng(seed).normal(scale=mrad * 1e-3, size=(m, 3))
    return xi


BIAS = np.array([0, 0, 0, 0.3e-3, -0.2e-3, 0.4e-3])  # a per-step rotation bias, the drift's cause


def test_a_proposal_right_per_step_and_right_in_the_mean_is_applied_whole() -> None:
    truth = BIAS + rotations(200, 1.0, 0)
    proposal = truth + rotations(200, 0.1, 1)
    result = decide(proposal, bowl(truth), components=("rotation",))
    assert result.component == "rotation" and not result.remainder and result.scale == 1.0
    assert result.tests["rotation"].passed and result.tests["mean of rotation"].passed
    np.testing.assert_allclose(applied_correction(proposal, result), proposal * component_mask("rotation"))


def test_a_wrong_mean_is_removed_and_the_per_step_part_kept() -> None:
    """The one harmful case the per-pair test let through: right about each step's noise, wrong about the
    mean. The whole passes, its mean fails, the remainder is applied: the drift is the prior's, not
    worse."""
    truth = BIAS + rotations(200, 1.0, 0)
    proposal = (truth - BIAS) - BIAS + rotations(200, 0.1, 1)  # the noise right, the bias reversed
    measure = bowl(truth)
    whole = paired_test("rotation", measure({"w": proposal})["w"])
    assert whole.passed  # what the earlier decision applied
    result = decide(proposal, measure, components=("rotation",))
    assert result.component == "rotation" and result.remainder, result.reason
    assert not result.tests["mean of rotation"].passed and result.tests["rotation − mean"].passed
    applied = applied_correction(proposal, result)
    np.testing.assert_allclose(applied, proposal - _moving_mean_loop(proposal, MEAN_WINDOW), atol=1e-15)
    np.testing.assert_allclose(result.mean, proposal.mean(axis=0), atol=1e-15)
    assert result.window == MEAN_WINDOW
    # The applied steps leave the drift (the mean error of the corrected steps) at the prior's, where the
    # whole proposal had doubled it.
    prior_drift = np.linalg.norm(truth.mean(axis=0))
    assert np.linalg.norm((truth - applied).mean(axis=0)) == pytest.approx(prior_drift, rel=0.05)
    assert np.linalg.norm((truth - proposal).mean(axis=0)) > 1.8 * prior_drift
    # The earlier decision applies it whole.
    assert not decide(proposal, measure, components=("rotation",), mean_test=False).remainder


def test_nothing_passes_nothing_is_applied_and_zero_effects_fail() -> None:
    truth = rotations(50, 1.0, 0)
    result = decide(rotations(50, 1.0, 5), bowl(truth))
    assert result.component == "none" and result.delta is None and "prior is kept" in result.reason
    assert np.all(applied_correction(np.ones((50, 6)), result) == 0)
    flat = decide(np.zeros((50, 6)), bowl(truth))
    assert flat.component == "none" and math.isnan(flat.tests["full"].statistic)


def test_the_full_correction_comes_before_its_rotation() -> None:
    truth = rotations(100, 1.0, 0)
    truth[:, :3] = np.random.default_rng(3).normal(scale=0.02, size=(100, 3))
    right = truth + rotations(100, 0.05, 1)
    assert decide(right, bowl(truth)).component == "full"
    wrong_shift = right.copy()
    wrong_shift[:, :3] = -3 * truth[:, :3]
    result = decide(wrong_shift, bowl(truth))
    assert result.component == "rotation" and not result.tests["full"].passed


def test_axes_that_fail_alone_are_dropped() -> None:
    """Pitch and roll right, yaw wrong: the rotation about x and z, with its own mean test."""
    truth = BIAS + rotations(200, 1.0, 0)
    proposal = truth.copy()
    proposal[:, 4] = -truth[:, 4] * 0.5  # a yaw that hurts on every pair
    measure = bowl(truth)
    result = decide(proposal, measure, components=("rotation",))
    assert result.component == "rotation_xz" and not result.remainder, result.reason
    assert {"rotation_x", "rotation_y", "rotation_z", "rotation_xz", "mean of rotation_xz"} <= set(
        result.tests)
    np.testing.assert_allclose(applied_correction(proposal, result), proposal * [0, 0, 0, 1, 0, 1])
    assert rotation_component("xz") == "rotation_xz" and rotation_component("xyz") == "rotation"
    with pytest.raises(ValueError, match="axes"):
        rotation_component("zx")


def test_the_judge_must_agree_and_picks_the_scale() -> None:
    truth = BIAS + rotations(200, 1.0, 0)
    proposal = truth / 0.75  # right direction, a third too large
    network = bowl(proposal)  # the coarse images ask for what the network proposes
    result = decide(proposal, network, components=("rotation",), judge=bowl(truth))
    assert result.component == "rotation" and result.scale == 0.75, result.reason
    assert "rotation ×0.75 (judge)" in result.tests and "mean of rotation (judge)" in result.tests
    np.testing.assert_allclose(applied_correction(proposal, result), truth * component_mask("rotation"))
    # The judge's Δ of what is applied is what choose compares.
    np.testing.assert_allclose(result.delta, bowl(truth)({"x": truth * component_mask("rotation")})["x"])
    # A judge that sees harm refuses what the network's size accepted.
    refused = decide(proposal, network, components=("rotation",), judge=bowl(-truth))
    assert refused.component == "none" and not refused.tests["rotation (judge)"].passed


def test_tested_pairs_and_forcing() -> None:
    truth = BIAS + rotations(100, 1.0, 0)
    proposal = truth.copy()
    proposal[::2] = -truth[::2]  # right on odd pairs, wrong on even ones
    measure = bowl(truth)
    assert decide(proposal, measure, components=("rotation",), tested=np.arange(1, 100, 2)).part != "none"
    assert decide(proposal, measure, components=("rotation",), tested=np.arange(0, 100, 2)).part == "none"
    forced = decide(proposal, measure, components=("rotation",), tested=np.arange(0, 100, 2), force=True)
    assert forced.forced and forced.component == "rotation" and not forced.remainder
    assert "rotation" in forced.tests and not forced.tests["rotation"].passed
    with pytest.raises(ValueError, match="components"):
        decide(proposal, measure, components=("translation",))
    with pytest.raises(ValueError, match="alpha"):
        decide(proposal, measure, alpha=0.0)


def test_each_candidate_is_measured_once_per_size() -> None:
    truth = BIAS + rotations(60, 1.0, 0)
    measure = bowl(truth)
    decide(truth, measure)
    assert len(measure.asked) == len(set(measure.asked))  # type: ignore[attr-defined]


def _moving_mean_loop(x: np.ndarray, window: int, trailing: bool = False) -> np.ndarray:
    """The reference: each row's mean over the rows within ⌊w/2⌋ before and ⌈w/2⌉ − 1 after it, or
    (``trailing``) over it and the w − 1 rows before it."""
    out = np.empty_like(x, dtype=np.float64)
    for k in range(x.shape[0]):
        first, last = (k - window + 1, k + 1) if trailing else (k - window // 2, k + window - window // 2)
        out[k] = x[max(0, first):min(x.shape[0], last)].mean(axis=0)
    return out


def test_the_moving_mean_is_a_windowed_average() -> None:
    x = np.random.default_rng(0).normal(size=(130, 6))
    for window in (1, 2, 7, 50, 400):
        np.testing.assert_allclose(moving_mean(x, window), _moving_mean_loop(x, window), atol=1e-12)
        np.testing.assert_allclose(moving_mean(x, window, trailing=True), _moving_mean_loop(x, window, True),
                                   atol=1e-12)
    np.testing.assert_allclose(moving_mean(x[:20], 50), np.broadcast_to(x[:20].mean(axis=0), (20, 6)),
                               atol=1e-12)  # shorter than half the window: the sequence's own mean
    np.testing.assert_allclose(moving_mean(x, 1), x, atol=1e-12)
    with pytest.raises(ValueError, match="window"):
        moving_mean(x, 0)


def test_parts_and_records() -> None:
    xi = np.arange(24, dtype=np.float64).reshape(4, 6)
    np.testing.assert_array_equal(part_of(xi, "rotation_xz"), xi * [0, 0, 0, 1, 0, 1])
    np.testing.assert_allclose(part_of(xi, "full", remainder=True, scale=0.5), 0.5 * (xi - xi.mean(axis=0)))
    np.testing.assert_allclose(part_of(xi, "full", remainder=True, window=1), np.zeros_like(xi))
    rotation = xi * component_mask("rotation")
    np.testing.assert_allclose(part_of(xi, "rotation", remainder=True, window=2, trailing=True),
                               rotation - np.concatenate([rotation[:1], (rotation[1:] + rotation[:-1]) / 2]))
    np.testing.assert_array_equal(component_mask("none"), np.zeros(6))
    record = Acceptance(0.01, {}, "rotation_xz", "why", scale=0.75, remainder=True, mean=(0.0,) * 6)
    assert record.part == "rotation_xz − mean ×0.75"
    assert record.to_dict()["part"] == record.part and record.to_dict()["remainder"]
    assert Acceptance(0.01).part == "none" and math.isnan(Acceptance(0.01).mean_delta)
    with pytest.raises(ValueError, match="xi must be"):
        part_of(np.zeros(6), "full")


# -- where and how the mean is tested (the options of docs/method.md §8) --------------------------------

def tabled(whole: np.ndarray, mean_differences: np.ndarray):
    """A measurement that returns given Δ: the whole rotation's (and each axis's alone, so no axis is
    dropped) and its remainder's, ``Δ(whole) − D`` for the mean's differences ``D``."""
    deltas = {"rotation": whole, "rotation − mean": whole - mean_differences}

    def measure(candidates):
        return {name: deltas.get(name, whole) for name in candidates}

    return measure


def _centred(seed: int, m: int = 200) -> np.ndarray:
    z = np.random.default_rng(seed).normal(size=m)
    return z - z.mean()


WHOLE = -10.0 + 0.1 * _centred(1)  # a whole rotation that helps every pair: its gain G = 10


def test_the_means_own_level() -> None:
    """D with a one-sided Wilcoxon p between 0.01 and 0.05 (scipy's, the reference): refused at the
    whole's level, passed at the mean's own 0.05."""
    differences = _centred(7) - 0.12
    p = stats.wilcoxon(differences, alternative="less").pvalue
    assert 0.01 < p < 0.05
    xi = BIAS + rotations(200, 1.0, 0)
    today = decide(xi, tabled(WHOLE, differences), components=("rotation",),
                   mean=MEAN_TESTS["mean-at-network"])
    assert today.remainder and today.tests["mean of rotation"].p_value == pytest.approx(p, rel=1e-12)
    apart = decide(xi, tabled(WHOLE, differences), components=("rotation",),
                   mean=MEAN_TESTS["mean-at-judge-a05"])  # no judge: at the network's size, at 0.05
    assert apart.component == "rotation" and not apart.remainder, apart.reason
    assert apart.tests["mean of rotation"].p_value == pytest.approx(p, rel=1e-12)


def test_the_means_harm_within_a_margin() -> None:
    """Non-inferiority: a mean that costs less than 5 % of the whole's gain passes, one that costs more
    does not; its p is scipy's of D − 0.05·G."""
    xi = BIAS + rotations(200, 1.0, 0)
    gain = -WHOLE.mean()
    for harm, passes in ((0.3, True), (0.7, False)):  # the margin: 0.05 · 10 = 0.5
        differences = _centred(7) + harm
        today = decide(xi, tabled(WHOLE, differences), components=("rotation",))
        assert today.remainder  # a mean that hurts never passes a test of its help
        bounded = decide(xi, tabled(WHOLE, differences), components=("rotation",),
                         mean=MEAN_TESTS["mean-noninferior"])
        p = stats.wilcoxon(differences - 0.05 * gain, alternative="less").pvalue
        assert bounded.tests["mean of rotation"].p_value == pytest.approx(p, rel=1e-12)
        assert bounded.remainder != passes, (harm, bounded.reason)
    with pytest.raises(ValueError, match="margin"):
        MeanTest(margin=1.0)
    with pytest.raises(ValueError, match="alpha"):
        MeanTest(alpha=0.0)


def test_the_mean_at_the_judges_size() -> None:
    """The network's images do not see the bias (its mean looks harmful there), the judge's do: today's
    decision refuses the mean at the network's size and never asks the judge; tested at the judge's size
    only, the whole is applied. The judge's p is scipy's on the closed-form model's differences."""
    truth = BIAS + rotations(200, 1.0, 0)
    proposal = truth + rotations(200, 0.1, 1)
    network, judge = bowl(truth - BIAS), bowl(truth)
    today = decide(proposal, network, components=("rotation",), judge=judge,
                   mean=MEAN_TESTS["mean-at-network"])
    assert today.remainder and not today.tests["mean of rotation"].passed, today.reason
    assert "mean of rotation (judge)" not in today.tests
    at_judge = decide(proposal, network, components=("rotation",), judge=judge,
                      mean=MEAN_TESTS["mean-at-judge"])
    assert at_judge.component == "rotation" and not at_judge.remainder, at_judge.reason
    assert "mean of rotation" not in at_judge.tests
    rotation = part_of(proposal, "rotation")
    rest = part_of(proposal, "rotation", remainder=True)
    measured = judge({"whole": rotation, "rest": rest})
    p = stats.wilcoxon(measured["whole"] - measured["rest"], alternative="less").pvalue
    assert at_judge.tests["mean of rotation (judge)"].p_value == pytest.approx(p, rel=1e-9)
    # Without a judge the option is today's decision.
    alone = decide(proposal, network, components=("rotation",), mean=MEAN_TESTS["mean-at-judge"])
    assert alone.remainder and "mean of rotation" in alone.tests


def test_one_proposal_decided_by_every_option_measures_each_candidate_once() -> None:
    """The detection study's way (``remembered`` stores): four options, each candidate measured once per
    size, and each decision the same as with a fresh measurement."""
    from dpc_jax.correction.measure import remembered

    truth = BIAS + rotations(120, 1.0, 0)
    proposal = truth + rotations(120, 0.1, 1)
    network, judge = bowl(truth - BIAS), bowl(truth)
    stores: dict[str, dict] = {"network": {}, "judge": {}}
    for option in MEAN_TESTS.values():
        shared = decide(proposal, remembered(network, stores["network"]), components=("rotation",),
                        judge=remembered(judge, stores["judge"]), mean=option)
        fresh = decide(proposal, bowl(truth - BIAS), components=("rotation",), judge=bowl(truth), mean=option)
        assert shared.part == fresh.part and shared.tests == fresh.tests
    for measure in (network, judge):
        assert len(measure.asked) == len(set(measure.asked))  # type: ignore[attr-defined]


# -- one decision, offline and live (issue 60) ----------------------------------------------------------

def _every_part(decision: Decision) -> list[Part]:
    """Every part a decision can consult: each component (and rotation about any axes), whole and
    remainder, at every scale the judge compares."""
    components = ["full", *(rotation_component(a) for a in ("x", "y", "z", "xy", "xz", "yz", "xyz"))]
    return [decision.part(c, r, s) for c in components for r in (False, True) for s in JUDGE_SCALES]


def _fed_pair_by_pair(xi: np.ndarray, network, judge, **options) -> Outcome:
    """The fixed-sample decision fed the pairs one by one, every part's Δ on each (measured on the
    whole sequence first: a remainder's centred mean needs all of ξ)."""
    decision = Decision(judge=judge is not None, **options)
    parts = _every_part(decision)
    at_network = network({p.name: p.of(xi) for p in parts})
    at_judge = None if judge is None else judge({p.name: p.of(xi) for p in parts})
    for k in range(xi.shape[0]):
        decision.update({p: at_network[p.name][k] for p in parts},
                        None if at_judge is None else {p: at_judge[p.name][k] for p in parts})
    assert not decision.needs()
    return decision.outcome


CASES = {  # (proposal, network's measurement, judge's, options): one case per way the decision goes
    "whole": lambda t: (t + rotations(200, 0.1, 1), bowl(t), None, {"components": ("rotation",)}),
    "remainder": lambda t: ((t - BIAS) - BIAS + rotations(200, 0.1, 1), bowl(t), None, {}),
    "axes": lambda t: (t * [1, 1, 1, 1, -0.5, 1], bowl(t), None, {"components": ("rotation",)}),
    "judge's scale": lambda t: (t / 0.75, bowl(t / 0.75), bowl(t), {"components": ("rotation",)}),
    "judge refuses": lambda t: (t, bowl(t), bowl(-t), {}),
    "nothing": lambda t: (rotations(200, 1.0, 5), bowl(t), None, {"alpha": 0.05}),
    "non-inferior mean": lambda t: (t + rotations(200, 0.1, 1), bowl(t - BIAS), bowl(t),
                                    {"mean": MEAN_TESTS["mean-noninferior"]}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_fed_pair_by_pair_the_decision_ends_as_the_offline_one(case: str) -> None:
    """The sequential decision (fixed-sample tests) fed every pair's Δ of every part, one pair at a time,
    ends with the offline decision on the same Δ: the same part, the same tests, the same reasons; and the
    offline one measured only what it needed. Each test's p is scipy's Wilcoxon on its Δ (the reference)."""
    truth = BIAS + rotations(200, 1.0, 0)
    xi, network, judge, options = CASES[case](truth)
    offline = decide(xi, network, judge=judge, **options)
    assert len(network.asked) < len(_every_part(Decision()))  # type: ignore[attr-defined]
    fed = _fed_pair_by_pair(xi, network, judge, **options)
    assert offline.part == ("none" if fed.part is None else fed.part.name), (offline.reason, fed.reason)
    assert offline.tests == fed.tests and offline.reason == fed.reason
    if offline.part != "none":
        applied = offline.tests[offline.part if judge is None else offline.part + " (judge)"]
        reference = stats.wilcoxon(offline.delta, alternative="less").pvalue
        assert applied.p_value == pytest.approx(reference, rel=1e-12)


def test_only_what_can_change_the_decision_is_measured() -> None:
    """A full correction that passes with its mean: its rotation and axes are never measured."""
    truth = rotations(100, 1.0, 0) + BIAS
    truth[:, :3] = np.random.default_rng(3).normal(scale=0.02, size=(100, 3))
    measure = bowl(truth)
    assert decide(truth + rotations(100, 0.05, 1), measure).part == "full"
    assert measure.asked == ["full", "full − mean"]  # type: ignore[attr-defined]


def test_an_axis_subset_is_applied_only_once_its_own_test_accepts() -> None:
    """Live, pair by pair (sequential tests): the rotation helps with its mean, its x and z alone help,
    but the rotation about x and z together hurts (Δ of a part is not the sum of its axes'). The old live
    rule applied ``rotation_xz`` as soon as the rotation's and the single axes' tests accepted; the one
    decision tests the subset itself, which never accepts, and applies the whole rotation."""
    decision = Decision(components=("rotation",), sequential=True)
    helps = {"rotation": -1.0, "rotation − mean": -0.5, "rotation_x": -1.0, "rotation_y": 1.0,
             "rotation_z": -1.0, "rotation_xz": 1.0}
    parts: list[str] = []
    for _ in range(120):
        needs = decision.needs()
        assert all(size == "network" for size, _ in needs)
        decision.update({p: helps.get(p.name, helps.get(p.name.replace(" − mean", ""), 0.0) - 0.1)
                         for _, p in needs})
        parts.append("none" if decision.outcome.part is None else decision.outcome.part.name)
    tests = decision.tests
    # What the old rule read: the rotation and x and z alone accepted.
    assert tests["rotation"].accepted and tests["mean of rotation"].accepted
    assert tests["rotation_x"].accepted and tests["rotation_z"].accepted and not tests["rotation_y"].accepted
    assert tests["rotation_xz"].pairs > 0 and not tests["rotation_xz"].accepted
    assert "rotation_xz" not in parts and parts[-1] == "rotation"


def test_a_sequential_decision_measures_what_it_consults_and_the_live_mean_trails() -> None:
    """Sequential: every part the walk consults is asked for each pair (the full correction and the
    rotation, whole and remainder, before anything is accepted); a remainder's mean is the trailing one."""
    decision = Decision(sequential=True, trailing=True)
    assert [p.name for _, p in decision.needs()] == ["full", "full − mean", "rotation", "rotation − mean"]
    assert all(p.trailing for _, p in decision.needs())
    xi = rotations(60, 1.0, 4)
    rotation = part_of(xi, "rotation")
    np.testing.assert_allclose(decision.part("rotation", True).of(xi),
                               rotation - _moving_mean_loop(rotation, MEAN_WINDOW, trailing=True), atol=1e-15)
