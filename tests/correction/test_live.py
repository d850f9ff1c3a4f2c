"""``dpc_jax.correction.live``: the live corrector against ``correct`` on the same frames, and its sequential
test against the guarantees it states (false acceptances, withdrawal, memory)."""

from __future__ import annotations

import dataclasses
import gc
import math
import sys
import types
from typing import Any

import numpy as np
import pytest
from scipy import stats

from dpc_jax.correction.acceptance import SequentialTest
from dpc_jax.pipelines import protocol as dpc_protocol

FRAMES = 10
SIZE = dpc_protocol.SMOKE["image_size"]


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A fake odometry sequence, its cache at the run's size, and a stored (untrained) Stereo DPC run."""
    from support import write_fake_odometry, write_stored_run

    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.training.train_config import REFERENCE, TrainConfig

    tmp = tmp_path_factory.mktemp("live")
    kitti = write_fake_odometry(tmp / "kitti", ["05"], frames=FRAMES, prior_dir=tmp / "priors")
    sequence = open_odometry(kitti, "05")
    cache = prepare_sequence(sequence, tmp / "priors" / "stereo_05.mat", tmp / "cache", size=SIZE,
                             progress=False, workers=1)
    config = TrainConfig(method="stereo_dpc", **{**dpc_protocol.SMOKE, **REFERENCE},
                         cache_root=str(tmp / "cache"), train_sequences=("00",), validation_sequences=("05",))
    write_stored_run(tmp / "run", config, {1: (7, 0.5, 0, -1e-4)})
    return {"sequence": sequence, "cache": cache, "run": tmp / "run", "priors": tmp / "priors"}


@pytest.fixture(autouse=True, scope="module")
def _optimised() -> object:
    from support import optimised_programs

    with optimised_programs():
        yield


def _frames(sequence):
    from dpc_jax.data.kitti import load_image

    for left, right in zip(sequence.images.left_paths, sequence.images.right_paths, strict=True):
        yield load_image(left), load_image(right)


def test_forced_live_gives_the_poses_of_forced_correct(world: dict) -> None:
    """The same frames, prior and first pose: frame by frame as they arrive, or the prepared sequence at
    once: the same corrected poses, and before any test accepts, the prior's."""
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.live import Calibration, LiveCorrector
    from dpc_jax.data.poses_io import read_mat

    run = load_run(world["run"], "delta")
    gt, prior = read_mat(world["priors"] / "stereo_05.mat")
    offline = correct_cache(run, world["cache"], force=True, batch_size=1)  # the live programs, compiled once
    assert offline.acceptance.forced and np.abs(offline.corrected - offline.prior).max() > 1e-6
    calibration = Calibration.of(world["sequence"])
    live = LiveCorrector(run, calibration, force=True, first_pose=gt[0])
    frames = [live(left, right, prior[k]) for k, (left, right) in enumerate(_frames(world["sequence"]))]
    poses = np.stack([f.pose for f in frames])
    np.testing.assert_allclose(poses, offline.corrected, atol=1e-6)
    np.testing.assert_allclose(np.stack([f.proposal for f in frames[1:]]), offline.xi_corr, atol=1e-6)
    assert frames[0].part == "none" and {f.part for f in frames[1:]} == {"full"}
    assert all(f.forced for f in frames)
    # The tests' own decision, on nine pairs: no sequential test can accept so early (2^9 < 1 / α), so
    # every pose is the prior's, composed from the same first pose. Without a judge, which would compile
    # its own programs (the judge is tested below).
    tested = LiveCorrector(run, calibration, first_pose=gt[0], judge_size=None, ahead=False)
    frames = [tested(left, right, prior[k]) for k, (left, right) in enumerate(_frames(world["sequence"]))]
    np.testing.assert_allclose(np.stack([f.pose for f in frames]), offline.prior, atol=1e-9)
    assert {f.part for f in frames[1:]} == {"none"}
    np.testing.assert_allclose(np.stack([f.prior for f in frames]), offline.prior, atol=1e-9)
    with pytest.raises(ValueError, match="expected both 48x72"):
        tested(np.zeros((40, 72), np.uint8), np.zeros((40, 72), np.uint8), prior[0])


def _scripted(live, record: list | None = None):
    """``live`` with its measurement replaced by Δ that depend only on the pair's parts (the same in
    every mode): the rotation and its remainder help, the full correction hurts; ``record`` gets each
    measured pair's ``(pair, Δ at the network's size)``."""
    from dpc_jax.correction.live_measure import Measured

    def measure(frames, prior, needs, vectors, batch=None):
        wobble = 1.5 + np.sin(1e4 * vectors.sum(axis=1))
        network = {p: float(w * (1.0 if p.component == "full" else -0.5 if p.remainder else -1.0))
                   for (_, p), w in zip(needs, wobble, strict=True)}
        if record is not None:
            record.append(network)
        return Measured(network, {}, {})

    live._measure.deltas = measure
    return live


def test_measured_behind_the_poses_the_decision_is_the_synchronous_one_a_pair_later(world: dict) -> None:
    """Behind without skipping, each frame is corrected with the decision of the pairs before it: the
    synchronous corrector's states and tests' events one frame later, on the same measurements; forced,
    the same poses. Skipping while the measurement is busy, the tests are fed exactly the pairs measured
    (``LiveFrame.measured``)."""
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.live import Calibration, LiveCorrector
    from dpc_jax.data.poses_io import read_mat

    run = load_run(world["run"], "delta")
    _, prior = read_mat(world["priors"] / "stereo_05.mat")
    calibration = Calibration.of(world["sequence"])
    pairs = list(_frames(world["sequence"]))
    n = 6 * FRAMES

    def played(live):
        return [live(*pairs[k % FRAMES], prior[k % FRAMES]) for k in range(n)]

    options = {"judge_size": None, "ahead": False}
    synchronous = played(_scripted(LiveCorrector(run, calibration, **options)))
    behind = played(_scripted(LiveCorrector(run, calibration, behind=True, **options)))
    assert {f.part for f in synchronous} > {"none"}  # a part is accepted: the shift can show
    assert [f.part for f in behind[1:]] == [f.part for f in synchronous[:-1]]
    assert [f.events for f in behind[2:]] == [f.events for f in synchronous[1:-1]]
    assert all(f.measured for f in behind)
    forced = [played(LiveCorrector(run, calibration, force=True, behind=b, skip=b, **options))
              for b in (False, True)]
    np.testing.assert_allclose(np.stack([f.pose for f in forced[1]]), np.stack([f.pose for f in forced[0]]),
                               atol=1e-12)

    # Skipping, on a CPU the measurement runs in a child process: its tests are fed exactly the pairs it
    # measured (the first while it compiles, then those it keeps up with), with the Δ the corrector
    # measures itself on those pairs (float32 programs compiled apart: to 1e-3).
    inline = LiveCorrector(run, calibration, force=True, **options)
    own, measure = [], inline._measure.deltas
    inline._measure.deltas = lambda *a: own.append(measure(*a)) or own[-1]
    played(inline)
    child = LiveCorrector(run, calibration, force=True, behind=True, skip=True, **options)
    frames = played(child)
    child.finish()
    measured = [f.index for f in frames[1:] if f.measured]
    assert measured[0] == 1 and child.skipped == n - 1 - len(measured) > 0
    test = child.decision.tests["full"]
    expected = [next(v for p, v in own[k - 1].network.items() if p.name == "full") for k in measured]
    assert test.pairs == len(measured) and test.mean == pytest.approx(np.mean(expected), rel=1e-3)


def test_the_api_decides_as_the_command_line_and_takes_one_pose_shape_from_frame_0(world: dict) -> None:
    """``LiveCorrector`` judges by default as ``dpc-jax live`` does (``judge_rule``: the camera's 48x72 for
    a 32x48 Stereo DPC run; ``judge_size=None`` turns it off); a ``[3, 4]`` prior is one rule from frame 0
    (the poses equal those of ``[4, 4]`` priors, each ``[4, 4]``); a pose of another shape and a camera
    smaller than the network are one ``ValueError`` each."""
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.judge import judge_rule
    from dpc_jax.correction.live import Calibration, LiveCorrector
    from dpc_jax.data.poses_io import read_mat

    run = load_run(world["run"], "delta")
    _, prior = read_mat(world["priors"] / "stereo_05.mat")
    calibration = Calibration.of(world["sequence"])
    judged = LiveCorrector(run, calibration, ahead=False).judge_size
    assert judged == judge_rule("stereo_dpc", SIZE, (48, 72)) == (48, 72)
    pairs = list(_frames(world["sequence"]))[:3]
    rows, full = (LiveCorrector(run, calibration, force=True) for _ in range(2))
    by_rows = [rows(left, right, prior[k][:3]) for k, (left, right) in enumerate(pairs)]
    by_full = [full(left, right, prior[k]) for k, (left, right) in enumerate(pairs)]
    assert all(f.pose.shape == f.prior.shape == (4, 4) for f in by_rows)
    np.testing.assert_array_equal(np.stack([f.pose for f in by_rows]), np.stack([f.pose for f in by_full]))
    tested = LiveCorrector(run, calibration, judge_size=None, ahead=False)
    assert tested.judge_size is None
    with pytest.raises(ValueError, match=r"prior pose of frame 0: expected poses of shape \[N, 4, 4\] or"):
        tested(*pairs[0], prior[0][:2])
    with pytest.raises(ValueError, match="takes 32x48 images, larger than the camera's 24x40"):
        LiveCorrector(run, Calibration(calibration.K / 2, calibration.baseline, (24, 40)))


def _held_bytes(root: object) -> int:
    """The bytes of the Python objects reachable from ``root``: its containers, numbers and numpy arrays, not
    modules, classes, functions or JAX's and Flax's objects (compiled programs and the network's state: fixed,
    and shared with caches of JAX's own that fill over the first thousand calls of any program)."""
    seen: set[int] = set()
    stack, total = [root], 0
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, (type, types.ModuleType, types.FunctionType,
                                               types.BuiltinFunctionType, types.MethodType)):
            continue
        seen.add(id(obj))
        if (type(obj).__module__ or "").split(".")[0] in ("jax", "jaxlib", "flax", "optax", "orbax"):
            continue
        total += sys.getsizeof(obj)
        stack.extend(gc.get_referents(obj))
    return total


@pytest.mark.slow
def test_memory_does_not_grow_with_the_frames(world: dict) -> None:
    """500 frames (the sequence's ten, over and over, the prior's poses continued): the memory the
    corrector holds after 500 frames is what it held after 200, when its windows are full (it varies by
    about 1.2 kB with the values held; a leak of one float a frame would add about 10 kB), and the
    objects alive in the process are as many."""
    from dpc_jax.correction.live import Calibration, LiveCorrector

    live = LiveCorrector(world["run"], Calibration.of(world["sequence"]), ahead=False)
    frames = list(_frames(world["sequence"]))
    step = np.eye(4)
    step[2, 3] = 1.0
    pose = np.eye(4)
    held = {}
    for k in range(1, 501):
        live(*frames[k % FRAMES], pose)
        pose = pose @ step
        if k in (200, 500):
            gc.collect()
            held[k] = (_held_bytes(live), len(gc.get_objects()))
    assert held[200][0] > 10_000, held  # the walk reaches the corrector's state
    assert held[500][0] - held[200][0] < 3 * 1024, held
    assert held[500][1] - held[200][1] < 50, held


def _signs(rng: np.random.Generator, n: int, helps: float) -> np.ndarray:
    """Paired differences that are below zero (the correction helps) with probability ``helps``."""
    magnitude = rng.exponential(1e-3, n)
    return np.where(rng.random(n) < helps, -magnitude, magnitude)


def test_the_sequential_test_keeps_its_level_under_continuous_monitoring() -> None:
    """Corrections that help on half the pairs (no better than none): checked after every one of 500 pairs,
    the sequential test accepts in at most α of 400 runs; a fixed-sample Wilcoxon test checked as often
    accepts far more often (the reason a live test must be sequential)."""
    rng = np.random.default_rng(0)
    alpha, runs, n = 0.05, 400, 500
    accepted = repeated = 0
    for _ in range(runs):
        d = _signs(rng, n, 0.5)
        test = SequentialTest("rotation", alpha)
        accepted += any(test.update(v) == "accepted" for v in d)
        repeated += any(stats.wilcoxon(d[:k], alternative="less").pvalue < alpha for k in range(20, n, 20))
    rate = accepted / runs
    # The binomial's 99.9 % upper bound at the level: the test's own guarantee, with sampling error.
    assert rate <= alpha + 3.1 * math.sqrt(alpha * (1 - alpha) / runs), rate
    assert repeated / runs > 2 * alpha


def test_a_harmful_correction_is_never_applied_and_a_scene_change_withdraws() -> None:
    rng = np.random.default_rng(1)
    harmful = SequentialTest("rotation")
    assert not any(harmful.update(v) for v in _signs(rng, 1000, 0.2)) and not harmful.accepted
    helpful = SequentialTest("rotation")
    events = [helpful.update(v) for v in _signs(rng, 60, 0.9)]
    first = events.index("accepted")
    assert first < 40 and helpful.accepted
    # The scene changes: the same correction now hurts on most pairs; it is withdrawn within a few.
    after = [helpful.update(v) for v in _signs(rng, 40, 0.2)]
    assert "withdrawn" in after and after.index("withdrawn") < 10 and not helpful.accepted
    # Accepted again only on new evidence, at a smaller level (α spent on the first acceptance).
    assert helpful.level < SequentialTest("x").level
    with pytest.raises(ValueError, match="not finite"):
        helpful.update(math.nan)


def test_the_judge_measures_what_corrects_judge_does_and_gates_what_is_applied(world: dict,
                                                                                 tmp_path) -> None:
    """With a judge (the camera's 48x72 frames; the network's are 32x48), once the tests at the network's
    size accept the rotation (its measurement there replaced by one that favours it): the rotation is
    measured on the pair at the judge's size, the same Δ as ``correct``'s judge on the same frames
    prepared there; it is applied only once the judge's own tests have accepted: never while the judge
    says it hurts, from the judge's acceptance on while it says it helps."""
    from dpc_jax.correction.decision import MEAN_TESTS
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.live import Calibration, LiveCorrector
    from dpc_jax.correction.measure import judge_measurement
    from dpc_jax.correction.parts import part_of
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.poses_io import read_mat
    from dpc_jax.data.sequence_cache import load_cache

    run = load_run(world["run"], "delta")
    gt, prior = read_mat(world["priors"] / "stereo_05.mat")
    calibration = Calibration.of(world["sequence"])
    with pytest.raises(ValueError, match=r"larger than the source images \(48x72\)"):
        LiveCorrector(run, calibration, judge_size=(64, 96))

    def favoured(live: LiveCorrector) -> LiveCorrector:
        """The network's size measures the rotation helping (its mean too) and the full correction
        hurting, whatever the images say."""
        measured = live._measure.deltas

        def measure(*args):
            done = measured(*args)
            return dataclasses.replace(done, network={p: 1.0 if p.component == "full" else -0.5 if p.remainder
                                                      else -1.0 for p in done.network})

        live._measure.deltas = measure  # type: ignore[method-assign]
        return live

    frames_list = list(_frames(world["sequence"]))
    live = favoured(LiveCorrector(run, calibration, first_pose=gt[0], judge_size=(48, 72), ahead=False))
    judged: list[tuple[int, float]] = []
    at_judge = live._measure._at_judge

    def recorded(frames, prior, corrections):
        values = at_judge(frames, prior, corrections)
        judged.append((live._pairs, float(values[0])))  # the first part consulted there: the rotation
        return values

    live._measure._at_judge = recorded  # type: ignore[method-assign]
    frames = [live(*frames_list[k % FRAMES], prior[k % FRAMES]) for k in range(3 * FRAMES)]
    assert judged and all(f.part == "none" for f in frames[:judged[0][0] + 1])
    judge = prepare_sequence(world["sequence"], world["priors"] / "stereo_05.mat", tmp_path / "judge",
                             size=(48, 72), progress=False, workers=1)
    xi = np.stack([f.proposal for f in frames[1:FRAMES]])
    offline = judge_measurement(run, load_cache(world["cache"]), judge)({"rotation": part_of(xi, "rotation")})
    # Pair k joins frames k and k + 1 of the sequence, each pass (those from its last frame to its first:
    # no such pair offline).
    within = [(k % FRAMES, value) for k, value in judged if (k + 1) % FRAMES]
    assert within
    np.testing.assert_allclose([v for _, v in within], offline["rotation"][[k for k, _ in within]], atol=1e-6)
    step = np.eye(4)
    step[2, 3] = 1.0

    def played(sign: float, frames: int = 80, **options: Any) -> tuple[LiveCorrector, list[str]]:
        gated = favoured(LiveCorrector(run, calibration, judge_size=(48, 72), ahead=False, **options))
        gated._measure._at_judge = lambda *a: sign * 1e-3 * np.where(  # type: ignore[method-assign]
            np.arange(len(a[2])) == 1, 0.5, 1.0)  # its remainder helps half as much: the mean helps too
        pose, out = np.eye(4), []
        for k in range(frames):
            out.append(gated(*frames_list[k % FRAMES], pose))
            pose = pose @ step
        return gated, [f.part for f in out[1:]]

    def parts(sign: float) -> list[str]:
        return played(sign)[1]

    assert set(parts(+1.0)) == {"none"}  # the judge says it hurts on every pair: never applied
    helped = parts(-1.0)
    first = next(k for k, p in enumerate(helped) if p != "none")
    assert helped[first].startswith("rotation") and set(helped[:first]) == {"none"}
    assert set(helped[first:]) <= {"rotation", "rotation ×0.25", "rotation ×0.5", "rotation ×0.75"}
    # The live corrector takes correct's --decision: with mean-at-judge the whole rotation's mean is not
    # tested at the network's size (at the judge's only, docs/method.md §8); with mean-at-network it is.
    for name, at_network in (("mean-at-network", True), ("mean-at-judge", False)):
        tests = played(-1.0, 12, mean=MEAN_TESTS[name])[0].decision.tests
        assert "rotation" in tests and ("mean of rotation" in tests) is at_network, name
