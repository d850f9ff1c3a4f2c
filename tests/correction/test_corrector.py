"""``dpc_jax.correction.corrector`` and ``dpc-jax correct`` on a tiny stored run, against a float64 numpy
reference."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from dpc_jax.eval import reference_metrics as ref
from dpc_jax.pipelines import protocol as dpc_protocol

ROOT = Path(__file__).resolve().parents[2]

SIZE = dpc_protocol.SMOKE["image_size"]
FRAMES = 10


SEEDS = {1: 7, 2: 8}  # epoch -> seed of the stored (untrained) weights; config.seed stays 0
# epoch -> validation (gradient loss, loop closures, Δ): epoch 1 has the lower gradient loss and the only
# negative Δ, epoch 2 the more loop closures and is the newest.
FIGURES = {1: (0.5, 0, -1e-4), 2: (0.6, 3, 2e-4)}


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A fake odometry tree (00, 05), its caches, and a run folder with two stored epochs.

    The epochs hold differently initialised networks (seeds 7 and 8, not the config's seed 0; the
    reference initialisation, so their corrections are not zero), so a restore that re-initialised
    instead of loading would be caught. Writing the run directly (instead of training it) keeps the
    test free of the training step's compilation; training itself is tested in test_train.py and
    end to end in test_experiments.py. A second run ("flat") has no epoch with a negative Δ.
    """
    from support import write_fake_odometry, write_stored_run

    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.training.train_config import REFERENCE, TrainConfig

    tmp = tmp_path_factory.mktemp("correct")
    kitti = write_fake_odometry(tmp / "kitti", ["00", "05"], frames=FRAMES,
                                              prior_dir=tmp / "priors")
    cache = tmp / "cache"
    for name in ("00", "05"):
        prepare_sequence(open_odometry(kitti, name), tmp / "priors" / f"stereo_{name}.mat", cache,
                         size=SIZE, progress=False, workers=1)
    config = TrainConfig(method="stereo_dpc", **{**dpc_protocol.SMOKE, **REFERENCE}, cache_root=str(cache),
                         train_sequences=("00",), validation_sequences=("05",))
    models = write_stored_run(tmp / "run", config, {e: (SEEDS[e], *FIGURES[e]) for e in FIGURES})
    write_stored_run(tmp / "flat", config, {1: (SEEDS[1], 0.5, 0, 0.0)})
    return {"tmp": tmp, "kitti": kitti, "cache": cache, "run": tmp / "run", "flat": tmp / "flat",
            "priors": tmp / "priors", "models": models}


@pytest.fixture(scope="module")
def run(setup: dict):
    from dpc_jax.correction.inference import load_run

    return load_run(setup["run"], "gradient")


def test_selection_restores_the_chosen_epoch(setup: dict, run) -> None:
    from dpc_jax.correction.inference import load_run

    assert (run.epoch, run.selection, run.improves_on_prior) == (1, "gradient", True)
    assert load_run(setup["run"], "loop").epoch == 2
    assert load_run(setup["run"], "last").epoch == 2
    assert load_run(setup["run"], "delta").epoch == 1 and load_run(setup["run"], "delta").improves_on_prior
    # No epoch with a negative Δ: the newest epoch, flagged as not better than no correction.
    flat = load_run(setup["flat"], "delta")
    assert (flat.epoch, flat.improves_on_prior) == (1, False)
    with pytest.raises(ValueError, match="delta, gradient, loop, last"):
        load_run(setup["run"], "best")


def _reference_corrections(model, cache) -> np.ndarray:
    """The stored network applied to one pair at a time (BatchNorm uses its running statistics)."""
    from dpc_jax.nn.batch import Batch

    model.eval()
    out = []
    for k in range(len(cache) - 1):
        step = np.linalg.inv(cache.prior[k + 1]) @ cache.prior[k]
        batch = Batch(
            left=np.asarray(cache.left[k:k + 2])[None], right=np.asarray(cache.right[k:k + 2])[None],
            xi_vo=ref.se3_log(step)[None].astype(np.float32), intrinsics=cache.K[None].astype(np.float32),
            baseline=np.array([cache.baseline], np.float32), weight=np.ones(1, np.float32),
            flow=None, xi_gt=None,
        )
        out.append(np.asarray(model(batch).xi_corr, np.float64)[0])
    return np.stack(out)


def _compose(xi: np.ndarray, prior: np.ndarray, first: np.ndarray, rotation_only: bool) -> np.ndarray:
    poses = [first]
    for k in range(len(xi)):
        x = xi[k].copy()
        if rotation_only:
            x[:3] = 0.0
        corrected = ref.se3_exp(x) @ np.linalg.inv(prior[k + 1]) @ prior[k]
        poses.append(poses[-1] @ np.linalg.inv(corrected))
    return np.stack(poses)


@pytest.mark.parametrize("rotation_only", [False, True])
def test_corrected_trajectory_equals_float64_reference(setup: dict, run, rotation_only: bool) -> None:
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.data.sequence_cache import load_cache

    cache = load_cache(setup["cache"] / "05")
    # 9 pairs in batches of 2 (the run's, so the module's other tests share the compiled program): the
    # last batch is padded; the padding must be dropped.
    assert run.config.batch_size == 2
    result = correct_cache(run, cache, rotation_only=rotation_only, force=True)
    xi = _reference_corrections(setup["models"][run.epoch], cache)
    np.testing.assert_allclose(result.xi_corr, xi, atol=2e-6)
    assert np.abs(xi).max() > 1e-5  # a network's output, not zeros
    expected = _compose(result.xi_corr.astype(np.float64), cache.prior, cache.gt[0], rotation_only)
    np.testing.assert_allclose(result.corrected, expected, atol=1e-9)
    np.testing.assert_array_equal(result.corrected[0], cache.gt[0])  # composed from the first GT pose
    assert result.rotation_only is rotation_only
    summary = result.evaluation["estimates"]
    assert summary["prior"]["m_ate_trans_m"] > 0 and summary["corrected"]["m_ate_trans_m"] > 0


def test_rotation_only_keeps_the_prior_translation_steps(setup: dict, run) -> None:
    """T* = Exp([0, φ]) T_vo = [R_c R_vo, R_c t_vo]: each step keeps its length and t* = R* R_voᵀ t_vo."""
    from dpc_jax.correction.corrector import correct_cache

    rot = correct_cache(run, setup["cache"] / "05", rotation_only=True, force=True)
    full = correct_cache(run, setup["cache"] / "05", rotation_only=False, force=True)
    step_rot = np.linalg.inv(rot.corrected[1:]) @ rot.corrected[:-1]
    step_prior = np.linalg.inv(rot.prior[1:]) @ rot.prior[:-1]
    step_full = np.linalg.inv(full.corrected[1:]) @ full.corrected[:-1]
    t_rot, t_prior = step_rot[:, :3, 3], step_prior[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(t_rot, axis=1), np.linalg.norm(t_prior, axis=1), rtol=1e-10)
    r_c = step_rot[:, :3, :3] @ np.swapaxes(step_prior[:, :3, :3], 1, 2)
    np.testing.assert_allclose(t_rot, np.einsum("nij,nj->ni", r_c, t_prior), atol=1e-12)
    # Same rotations as the full correction, different translations.
    np.testing.assert_allclose(step_rot[:, :3, :3], step_full[:, :3, :3], atol=1e-12)
    assert np.abs(step_full[:, :3, 3] - t_rot).max() > 1e-5


def test_composes_from_the_first_prior_pose_without_ground_truth(setup: dict, run) -> None:
    import dataclasses

    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.data.sequence_cache import load_cache

    cache = load_cache(setup["cache"] / "05")
    shifted = cache.prior.copy()
    shifted[:, :3, 3] += np.array([5.0, -1.0, 2.0])  # the prior need not start at the GT pose
    no_gt = dataclasses.replace(cache, gt=None, prior=shifted)
    result = correct_cache(run, no_gt, force=True)
    assert result.evaluation is None
    np.testing.assert_array_equal(result.corrected[0], shifted[0])
    expected = _compose(result.xi_corr.astype(np.float64), shifted, shifted[0], run.config.rotation_only)
    np.testing.assert_allclose(result.corrected, expected, atol=1e-9)


def test_cli_writes_trajectory_that_reads_back_and_a_report(setup: dict, tmp_path: Path, capsys) -> None:
    from dpc_jax.cli import main
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.inference import load_run
    from dpc_jax.data.poses_io import read_trajectory, read_tum

    expected = correct_cache(load_run(setup["run"], "gradient"), setup["cache"] / "05", force=True).corrected
    out = tmp_path / "corrected.txt"
    argv = ["correct", "--checkpoint", str(setup["run"]), "--data", str(setup["cache"] / "05"),
            "--out", str(out), "--report", str(tmp_path / "report"), "--no-progress", "--select", "gradient",
            "--force"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "| corrected |" in printed and "| prior |" in printed
    np.testing.assert_allclose(read_trajectory(out, "kitti"), expected, atol=1e-12)
    assert not (tmp_path / "corrected.frames.txt").exists()  # every source frame is there
    for name in ("report.md", "metrics.json", "trajectory.png", "summary.json"):
        assert (tmp_path / "report" / name).is_file()

    tum = tmp_path / "corrected.tum"
    assert main([*argv[:5], "--out", str(tum), "--format", "tum", "--no-progress", "--select", "gradient",
                 "--force"]) == 0
    stamps, poses = read_tum(tum)
    np.testing.assert_allclose(poses, expected, atol=1e-9)
    np.testing.assert_allclose(stamps, np.arange(FRAMES) * 0.1, atol=1e-9)
    # A recording written from a cache says that its stamps are the cache's frame times.
    capsys.readouterr()
    assert main([*argv[:5], "--out", str(tmp_path / "c.mcap"), "--no-progress", "--force"]) == 0
    assert "c.mcap is stamped from 0 s at the cache's frame times" in capsys.readouterr().out


def test_cli_prepares_raw_input_and_writes_kept_frames(setup: dict, tmp_path: Path, capsys) -> None:
    """Odometry input with static-frame removal: the trajectory has the kept frames, listed beside it.
    The stereo run is smaller than 240x376, so its acceptance test is judged at a larger size by default:
    the same kept frames, prepared as ``05_judge`` at the largest size of 240x376 that the 48x72 source
    images give without upsampling; a --judge-size larger than the source is refused."""
    from dpc_jax.cli import main
    from dpc_jax.data.poses_io import read_trajectory
    from dpc_jax.data.sequence_cache import load_cache

    out = tmp_path / "corrected.txt"
    argv = ["correct", "--checkpoint", str(setup["run"]), "--kitti-odometry", str(setup["kitti"]),
            "--sequence", "05", "--prior", str(setup["priors"] / "stereo_05.mat"), "--remove-static",
            "--cache", str(tmp_path / "cache"), "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    cache = load_cache(tmp_path / "cache" / "05")
    assert 2 <= len(cache) < FRAMES  # ~1 m steps: the static rule drops frames
    assert cache.image_size == SIZE  # prepared at the run's image size
    judge = load_cache(tmp_path / "cache" / "05_judge")  # the default judge, at the source's size
    assert judge.image_size == (48, 72)
    np.testing.assert_array_equal(judge.indices, cache.indices)
    out_text = capsys.readouterr().out
    assert "acceptance test: measured at 48x72 (the default judge" in out_text
    assert "the largest the 48x72 source images allow of 240x376" in out_text
    larger = [*argv[:-5], "--judge-size", "96x144", "--out", str(tmp_path / "larger.txt"), "--no-progress"]
    assert main(larger) == 2 and not (tmp_path / "larger.txt").exists()
    assert "--judge-size 96x144: larger than the source images (48x72)" in capsys.readouterr().err
    frames = np.loadtxt(tmp_path / "corrected.frames.txt", dtype=int)
    np.testing.assert_array_equal(frames, cache.indices)
    poses = read_trajectory(out, "kitti")
    assert poses.shape == (len(cache), 4, 4)
    np.testing.assert_allclose(poses[0], cache.gt[0], atol=1e-12)

    # A full-length prior is accepted for a cache with fewer frames: the cached frames are taken.
    from dpc_jax.data.poses_io import read_mat
    from dpc_jax.data.priors import prior_for_cache

    _, full = read_mat(setup["priors"] / "stereo_05.mat")
    np.testing.assert_allclose(prior_for_cache(cache, full), full[cache.indices], atol=1e-12)


def _error(capsys, argv: list[str]) -> str:
    from dpc_jax.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_bad_input_errors_name_what_was_expected(setup: dict, tmp_path: Path, capsys) -> None:
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.data.poses_io import read_trajectory, write_kitti_poses

    base = ["correct", "--checkpoint", str(setup["run"]), "--out", str(tmp_path / "c.txt"), "--no-progress"]
    data = ["--data", str(setup["cache"] / "05")]

    err = _error(capsys, ["correct", "--checkpoint", str(tmp_path / "nowhere"), *data, "--out",
                          str(tmp_path / "c.txt")])
    assert "not a training run" in err and "config.json" in err

    short = tmp_path / "short.txt"
    write_kitti_poses(short, read_trajectory(setup["kitti"] / "poses" / "05.txt")[:5])
    err = _error(capsys, [*base, *data, "--prior", str(short)])
    assert "5 prior poses" in err and f"expected {FRAMES}" in err

    other = tmp_path / "other_size"
    prepare_sequence(open_odometry(setup["kitti"], "05"), setup["priors"] / "stereo_05.mat", other,
                     size=(24, 40), progress=False, workers=1)
    err = _error(capsys, [*base, "--data", str(other / "05")])
    size = f"{SIZE[0]}x{SIZE[1]}"
    assert "24x40" in err and f"trained at {size}" in err and f"--size {size}" in err

    err = _error(capsys, [*base, "--kitti-odometry", str(setup["kitti"]), "--sequence", "05"])
    assert "--prior FILE is required" in err
    err = _error(capsys, [*base, *data, "--remove-static"])
    assert "only apply to raw inputs" in err
    err = _error(capsys, [*base, "--data", str(tmp_path)])
    assert "not a prepared cache" in err
    assert not (tmp_path / "c.txt").exists()


def test_an_untrained_network_leaves_the_prior_unchanged(setup: dict) -> None:
    """Zero-initialised output layer (the default): ξ_corr = 0 exactly, corrected trajectory = prior."""
    from flax import nnx

    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.engine.predict import predict_sequence
    from dpc_jax.geometry.pose_correction import corrected_trajectory
    from dpc_jax.nn.models import create_model, set_prior_statistics
    from dpc_jax.training.train_config import TrainConfig

    config = TrainConfig(method="stereo_dpc", **dpc_protocol.SMOKE, validation_sequences=("05",))
    cache = load_cache(setup["cache"] / "05")
    for seed in (0, 1, 2):
        model = create_model("stereo_dpc", config.model_config(), seed)
        set_prior_statistics(model, np.full(6, 0.1), np.full(6, 0.01))
        model.eval()  # as a restored run is: the module's network-depth predictions share one program
        graphdef, state = nnx.split(model)
        prediction = predict_sequence((graphdef, state), cache, config.loss_config(), batch_size=2,
                                      use_flow=False)
        np.testing.assert_array_equal(prediction.xi_corr, 0.0)
        np.testing.assert_array_equal(prediction.delta["full"], 0.0)
        corrected = corrected_trajectory(prediction.xi_corr, cache.prior, cache.prior[0])
        np.testing.assert_allclose(corrected, cache.prior, atol=1e-12)


def test_a_proposal_that_is_not_finite_is_named_not_measured(setup: dict, run) -> None:
    """A network whose weights went NaN proposes NaN: ``correct`` says so by the first pair (a ValueError,
    the command line's one-line error), instead of failing later on candidates that never become finite."""
    import jax

    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.data.sequence_cache import load_cache

    broken = dataclasses.replace(run, state=jax.tree.map(lambda x: x * np.nan, run.state))
    cache = load_cache(setup["cache"] / "05")
    with pytest.raises(ValueError, match=rf"^{re.escape(str(cache.path))}: the network's proposal: the "
                       r"correction of pair 0 is not finite \(NaN or inf\); \d+ of pairs 0–\d+ are$"):
        correct_cache(broken, cache)


def test_cli_keeps_the_prior_when_no_epoch_beats_it_and_applies_with_force(
    setup: dict, tmp_path: Path, capsys
) -> None:
    import json

    from dpc_jax.cli import main
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.inference import load_run
    from dpc_jax.data.poses_io import read_trajectory
    from dpc_jax.data.sequence_cache import load_cache

    cache = load_cache(setup["cache"] / "05")
    base = ["correct", "--checkpoint", str(setup["flat"]), "--data", str(setup["cache"] / "05"),
            "--no-progress"]
    kept = tmp_path / "kept.txt"
    assert main([*base, "--out", str(kept), "--report", str(tmp_path / "kept")]) == 0
    out = capsys.readouterr().out
    assert "correction NOT applied, the prior is written unchanged" in out and "--force" in out
    # A cache holds no frames larger than the run's: the summary says where the test was measured.
    assert f"measured at the cache's {SIZE[0]}x{SIZE[1]} only" in out and "--judge CACHE" in out
    np.testing.assert_allclose(read_trajectory(kept, "kitti"), cache.prior, atol=1e-9)
    summary = json.loads((tmp_path / "kept" / "summary.json").read_text())
    assert summary["part"] == "none" and "selection delta" in summary["acceptance"]["reason"]
    assert {"full", "rotation"} <= set(summary["acceptance"]["tests"])
    assert "Applied: nothing" in (tmp_path / "kept" / "report.md").read_text()

    forced = tmp_path / "forced.txt"
    assert main([*base, "--out", str(forced), "--force"]) == 0
    expected = _compose(correct_cache(load_run(setup["flat"], "delta"), cache, force=True).xi_corr,
                        cache.prior, cache.gt[0], False)
    np.testing.assert_allclose(read_trajectory(forced, "kitti"), expected, atol=1e-9)
    assert np.abs(expected - cache.prior).max() > 1e-6


def test_the_decision_follows_the_test_on_the_sequence(setup: dict, run) -> None:
    """Whatever the tests decide, the final trajectory is the prior with what they let through."""
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.parts import applied_correction
    from dpc_jax.data.sequence_cache import load_cache

    cache = load_cache(setup["cache"] / "05")
    for alpha in (1e-9, 0.999):
        result = correct_cache(run, cache, alpha=alpha)
        tests = result.acceptance.tests
        if result.part == "none":
            assert not any(t.passed for name, t in tests.items() if name in ("full", "rotation"))
        else:
            assert tests[result.part].passed
        xi = applied_correction(result.xi_corr, result.acceptance)
        np.testing.assert_allclose(result.corrected, _compose(xi, cache.prior, cache.gt[0], False), atol=1e-9)
        np.testing.assert_allclose(result.proposed, _compose(result.xi_corr, cache.prior, cache.gt[0], False),
                                   atol=1e-9)
    assert correct_cache(run, cache, alpha=1e-9).part == "none"  # 9 pairs cannot reach p < 1e-9


@pytest.mark.slow
def test_cli_adapt_writes_the_adapted_network_that_made_the_trajectory(setup: dict, tmp_path: Path) -> None:
    from dpc_jax.cli import main
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.inference import load_run
    from dpc_jax.data.holdout import held_out_pairs
    from dpc_jax.data.poses_io import read_trajectory

    out = tmp_path / "c.txt"
    assert main(["correct", "--checkpoint", str(setup["run"]), "--data", str(setup["cache"] / "05"),
                 "--out", str(out), "--select", "gradient", "--adapt", "3", "--holdout-every", "4",
                 "--force", "--no-progress"]) == 0
    folder = tmp_path / "c.adapted"
    assert (folder / "adapt.csv").read_text().count("\n") == 4  # header and one line per step
    # The saved network, restored, gives the written trajectory.
    held = held_out_pairs(FRAMES - 1, 4)
    again = correct_cache(load_run(folder, "last"), setup["cache"] / "05", force=True, held_out=held)
    np.testing.assert_allclose(read_trajectory(out, "kitti"), again.corrected, atol=1e-9)


def _candidate(delta: np.ndarray, tested: np.ndarray | None, label: float):
    """A Correction whose full correction was decided on ``delta[tested]``; its trajectories are filled
    with ``label`` so the chosen one can be told apart."""
    from dpc_jax.correction.decision import decide
    from dpc_jax.results.correction import Correction

    acceptance = decide(np.ones((delta.size, 6)), lambda candidates: {name: delta for name in candidates},
                        tested=tested, mean_test=False)
    poses = np.full((delta.size + 1, 4, 4), label)
    return Correction(name="s", frames=np.arange(delta.size + 1), times=np.zeros(delta.size + 1), prior=poses,
                      proposed=poses, corrected=poses, ground_truth=None, xi_corr=np.zeros((delta.size, 6)),
                      rotation_only=False, acceptance=acceptance, epoch=1, evaluation=None,
                      delta={"full": delta}, tested=tested)


def test_choose_takes_the_adapted_correction_only_when_it_beats_the_trained_one() -> None:
    """Reference: scipy's one-sided Wilcoxon on the paired differences of Δ on the kept-out pairs."""
    from scipy import stats

    from dpc_jax.correction.corrector import choose

    rng = np.random.default_rng(0)
    n, held = 120, np.arange(2, 120, 3)
    trained = _candidate(-1e-3 + 1e-4 * rng.standard_normal(n), None, 1.0)
    assert trained.part == "full"
    better = _candidate(trained.delta["full"] - 5e-4 + 1e-4 * rng.standard_normal(n), held, 2.0)
    as_good = _candidate(trained.delta["full"] + 1e-4 * rng.standard_normal(n), held, 3.0)
    for adapted, expected in ((better, "adapted"), (as_good, "trained")):
        assert adapted.part == "full"
        difference = adapted.delta["full"][held] - trained.delta["full"][held]
        p = stats.wilcoxon(difference, alternative="less").pvalue
        assert (p < 0.01) == (expected == "adapted")
        name, final = choose(trained, adapted)
        assert name == expected and final.choice is not None and final.choice["final"] == expected
        assert final.choice["comparison"]["pairs"] == held.size
        np.testing.assert_allclose(final.choice["comparison"]["p_value"], p)
        assert final.corrected[0, 0, 0] == (2.0 if expected == "adapted" else 1.0)


def test_choose_falls_back_in_order_adapted_trained_prior() -> None:
    from dpc_jax.correction.corrector import choose

    rng = np.random.default_rng(1)
    n, held = 60, np.arange(2, 60, 5)
    good = -1e-3 + 1e-4 * rng.standard_normal(n)
    bad = 1e-3 + 1e-4 * rng.standard_normal(n)
    trained_good, trained_bad = _candidate(good, None, 1.0), _candidate(bad, None, 1.0)
    adapted_good, adapted_bad = _candidate(good, held, 2.0), _candidate(bad, held, 2.0)
    assert choose(trained_good)[0] == "trained"
    assert choose(trained_bad)[0] == "prior"
    assert choose(trained_good, adapted_bad)[0] == "trained"
    assert choose(trained_bad, adapted_good)[0] == "adapted"
    name, final = choose(trained_bad, adapted_bad)
    assert name == "prior" and final.part == "none" and final.choice is not None
    assert "prior is kept" in str(final.choice["reason"])


def test_cli_corrects_a_grey_raw_drive(setup: dict, tmp_path: Path, capsys) -> None:
    """The grey pair of real drive 0005 through `correct`: prepared as replicated grey at the run's size.
    ``--no-judge`` turns the default judge at 240x376 off."""
    from conftest import DATA

    from dpc_jax.cli import main
    from dpc_jax.data.poses_io import read_mat, read_trajectory, write_kitti_poses
    from dpc_jax.data.sequence_cache import load_cache

    raw = DATA / "kitti-raw"
    gt, est = read_mat(raw / "libviso2" / "stereo_2011_09_26_drive_0005.mat")
    write_kitti_poses(tmp_path / "prior.txt", est[:91])  # the first 91 of 154 poses belong to the images
    write_kitti_poses(tmp_path / "gt.txt", gt[:91])
    out = tmp_path / "corrected.txt"
    argv = ["correct", "--checkpoint", str(setup["run"]), "--kitti-raw", str(raw), "--date", "2011_09_26",
            "--drive", "5", "--prior", str(tmp_path / "prior.txt"), "--gt", str(tmp_path / "gt.txt"),
            "--frames", "0:8", "--cache", str(tmp_path / "cache"), "--out", str(out), "--no-progress",
            "--no-judge"]
    assert main(argv) == 0
    assert not (tmp_path / "cache" / "2011_09_26_drive_0005_judge").exists()  # --no-judge: none prepared
    assert "240x376" not in capsys.readouterr().out
    cache = load_cache(tmp_path / "cache" / "2011_09_26_drive_0005")
    assert len(cache) == 8 and cache.image_size == SIZE
    left = np.asarray(cache.left)
    assert left.shape[-1] == 3
    np.testing.assert_array_equal(left[..., 0], left[..., 1])  # grey, replicated to three channels
    np.testing.assert_array_equal(left[..., 0], left[..., 2])
    # P_rect_00 scaled to the cached width; the grey pair's baseline, not the colour pair's.
    assert cache.K[0, 0] == pytest.approx(721.5377 * SIZE[1] / 1242, rel=1e-6)
    assert cache.baseline == pytest.approx(387.5744 / 721.5377, rel=1e-6)
    poses = read_trajectory(out, "kitti")
    assert poses.shape == (8, 4, 4)
    np.testing.assert_allclose(poses[0], gt[0], atol=1e-9)


def test_a_stereo_run_measures_delta_with_stereo_sgbm_unless_asked_otherwise(setup: dict, run) -> None:
    """The default acceptance depth of a stereo run is the independent StereoSGBM one, whatever the run's
    ``acceptance_depth`` (here the config's default, ``network``); ``network`` stays reachable."""
    from dpc_jax.correction.corrector import correct_cache, default_acceptance_depth
    from dpc_jax.data.sequence_cache import load_cache

    assert run.config.acceptance_depth == "network" and default_acceptance_depth(run) == "sgbm"
    cache = load_cache(setup["cache"] / "05")
    default = correct_cache(run, cache)
    sgbm = correct_cache(run, cache, acceptance_depth="sgbm")
    network = correct_cache(run, cache, acceptance_depth="network")
    np.testing.assert_array_equal(default.delta["full"], sgbm.delta["full"])
    assert not np.allclose(default.delta["full"], network.delta["full"])
    np.testing.assert_array_equal(default.xi_corr, network.xi_corr)  # the depth changes Δ, not ξ_corr
    # The depth prepared with the cache is the one computed from its images when a cache lacks it.
    assert cache.stereo_depth is not None
    computed = correct_cache(run, dataclasses.replace(cache, stereo_depth=None))
    np.testing.assert_array_equal(computed.delta["full"], default.delta["full"])


def test_the_measurement_without_the_network_is_the_prediction_with_stereo_depth(setup: dict, run) -> None:
    """On the cache the network ran on, Δ measured with StereoSGBM depth and no network (what a judge
    does) is the Δ of the prediction with that depth: the temporal error needs only images, depth,
    prior and ξ. Measured with the network's depth it is the network-depth prediction's."""
    from dpc_jax.correction.inference import run_prediction
    from dpc_jax.correction.measure import judge_measurement, measurement
    from dpc_jax.correction.parts import Part
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.engine.predict import measure_effects

    cache = load_cache(setup["cache"] / "05")
    rotation = np.array([0, 0, 0, 1, 1, 1.0])
    # Remainders whose centred means reach past the batch of 2 pairs being predicted: measured in the
    # prediction's own pass, each batch once the pairs its means need have arrived.
    parts = [Part("full", True, window=4), Part("rotation", True, window=7)]
    for depth in ("network", "sgbm"):
        prediction = run_prediction(run, cache, acceptance_depth=depth, batch_size=2,
                                    candidates=lambda xi: np.stack([p.of(xi) for p in parts]))
        candidates = {"full": prediction.xi_corr, "rotation": prediction.xi_corr * rotation}
        candidates |= {p.name: p.of(prediction.xi_corr) for p in parts}
        measured = measurement(run, cache, depth=depth, batch_size=3)(candidates)
        for name in ("full", "rotation"):
            np.testing.assert_allclose(measured[name], prediction.delta[name], rtol=1e-4, atol=1e-7)
        assert prediction.measured is not None
        used, delta = prediction.measured
        expected = np.stack([p.of(prediction.xi_corr) for p in parts]).astype(np.float32)
        np.testing.assert_array_equal(used, expected)
        # Δ is a difference of two float32 losses summed over pixels in programs that differ: equal to
        # 3e-7, far below how much removing the mean moves it.
        for part, values in zip(parts, delta, strict=True):
            np.testing.assert_allclose(values, measured[part.name], rtol=1e-4, atol=3e-7)
            assert np.abs(measured[part.name] - measured[part.component]).max() > 1e-5
    # The last prediction is the StereoSGBM one: a judge of the very same frames measures its Δ.
    judged = judge_measurement(run, cache, cache, batch_size=2)(candidates)
    np.testing.assert_allclose(judged["rotation"], prediction.delta["rotation"], rtol=1e-4, atol=1e-7)
    # With the prediction's L(0) given, the same Δ without measuring L(0) again.
    stereo, config = cache.stereo_depth, run.config.loss_config()
    both = np.stack([prediction.xi_corr, 0.5 * prediction.xi_corr])
    known = prediction.photometric
    reused = measure_effects(cache, both, config, batch_size=2, stereo_depth=stereo, none=known)
    fresh = measure_effects(cache, both, config, batch_size=3, stereo_depth=stereo)
    np.testing.assert_allclose(reused["delta"], fresh["delta"], rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(fresh["none"], known, rtol=1e-4, atol=1e-7)
    with pytest.raises(ValueError, match=r"L\(0\) must be \[9\]"):
        measure_effects(cache, both, config, batch_size=4, stereo_depth=stereo, none=known[:-1])
    with pytest.raises(ValueError, match=r"candidates must be \[C, 9, 6\]"):
        measure_effects(cache, both[:, :-1], config, batch_size=4, stereo_depth=stereo)


def test_a_scaled_part_is_composed_as_decided(setup: dict, run) -> None:
    from dpc_jax.correction.corrector import compose_correction
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.geometry.pose_correction import corrected_trajectory
    from dpc_jax.results.acceptance import Acceptance

    cache = load_cache(setup["cache"] / "05")
    xi = np.random.default_rng(0).normal(scale=1e-3, size=(len(cache) - 1, 6))
    applied = compose_correction(run, cache, xi, Acceptance(0.01, {}, "rotation_xz", "", scale=0.5), False)
    expected = corrected_trajectory(0.5 * xi * np.array([0, 0, 0, 1, 0, 1]), cache.prior, cache.gt[0])
    np.testing.assert_allclose(applied.corrected, expected, atol=1e-12)
    proposed = corrected_trajectory(xi, cache.prior, cache.gt[0])
    np.testing.assert_allclose(applied.proposed, proposed, atol=1e-12)
    mean = (xi * [1, 1, 1, 1, 1, 1]).mean(axis=0)
    without = compose_correction(run, cache, xi, Acceptance(0.01, {}, "full", "", remainder=True,
                                                            mean=tuple(mean)), False)
    np.testing.assert_allclose(without.corrected, corrected_trajectory(xi - mean, cache.prior, cache.gt[0]),
                               atol=1e-12)


def test_cli_judge_measures_the_test_on_another_cache_of_the_same_frames(setup: dict, tmp_path: Path) -> None:
    import json

    from dpc_jax.cli import main

    cache = str(setup["cache"] / "05")
    out = tmp_path / "c.txt"
    assert main(["correct", "--checkpoint", str(setup["run"]), "--data", cache, "--judge", cache,
                 "--out", str(out), "--report", str(tmp_path / "r"), "--no-progress"]) == 0
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["acceptance"]["scale"] in (0.25, 0.5, 0.75, 1.0)
    # Another sequence's frames cannot judge this one.
    assert main(["correct", "--checkpoint", str(setup["run"]), "--data", cache, "--judge",
                 str(setup["cache"] / "00"), "--out", str(tmp_path / "d.txt"), "--no-progress"]) == 2
    assert not (tmp_path / "d.txt").exists()




def test_cli_corrects_a_recording_as_its_kitti_layout(setup: dict, tmp_path: Path, capsys) -> None:
    """Sequence 05 as a recording written by rosbags (PNG-compressed images, CameraInfo, the prior as
    nav_msgs/Odometry): `correct --bag` writes the trajectory `correct --kitti-odometry` writes, byte for
    byte with the same prior file; and with --prior-topic, --out OUT.mcap holds one nav_msgs/Odometry per
    frame at the frames' stamps, corrected and prior, that the bag library reads back."""
    from recordings import CAMERA_FRAME, stamps_of, write_recording
    from rosbags.highlevel import AnyReader
    from scipy.spatial.transform import Rotation

    from dpc_jax.cli import main
    from dpc_jax.data.poses_io import read_mat, read_trajectory
    from dpc_jax.sources.bag import read_pose_topic

    prior_file = setup["priors"] / "stereo_05.mat"
    _, prior = read_mat(prior_file)
    recording = write_recording(tmp_path / "05.mcap", setup["kitti"], "05", compressed=True,
                                poses={"/vo": prior})
    common = ["correct", "--checkpoint", str(setup["run"]), "--force", "--no-progress"]
    assert main([*common, "--kitti-odometry", str(setup["kitti"]), "--sequence", "05", "--prior",
                 str(prior_file), "--out", str(tmp_path / "files.txt")]) == 0
    assert main([*common, "--bag", str(recording), "--prior", str(prior_file),
                 "--out", str(tmp_path / "bag.txt")]) == 0
    assert (tmp_path / "files.txt").read_bytes() == (tmp_path / "bag.txt").read_bytes()
    assert main([*common, "--bag", str(recording), "--prior-topic", "/vo", "--out",
                 str(tmp_path / "c.mcap")]) == 0
    capsys.readouterr()
    expected = {"/dpc/odometry": read_trajectory(tmp_path / "files.txt", "kitti"), "/dpc/prior": prior}
    times = [float(t) for t in (setup["kitti"] / "sequences" / "05" / "times.txt").read_text().split()]
    with AnyReader([tmp_path / "c.mcap"]) as reader:
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == {
            topic: ("nav_msgs/msg/Odometry", FRAMES) for topic in expected}
        read: dict[str, list] = {topic: [] for topic in expected}
        for connection, stamp, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
            assert (msg.header.frame_id, msg.child_frame_id) == ("odom", CAMERA_FRAME)
            pose = np.eye(4)
            q, p = msg.pose.pose.orientation, msg.pose.pose.position
            pose[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            pose[:3, 3] = [p.x, p.y, p.z]
            read[connection.topic].append((stamp, pose))
    for topic, poses in expected.items():
        assert [s for s, _ in read[topic]] == stamps_of(times)
        np.testing.assert_allclose(np.stack([p for _, p in read[topic]]), poses, atol=1e-9)
    assert not np.allclose(expected["/dpc/odometry"], prior, atol=1e-6)  # --force: the network's correction
    # A ROS 1 bag and a ROS 2 bag folder hold the same messages; the folder's data file is named as the
    # folder (not hidden) and its metadata is version 8 (the QoS as a string, which older ROS 2 reads).
    for out, more in ((tmp_path / "c.bag", []), (tmp_path / "c_ros2", ["--format", "rosbag2"])):
        assert main([*common, "--bag", str(recording), "--prior-topic", "/vo", "--out", str(out), *more]) == 0
        with AnyReader([out]) as reader:
            stamps = [stamp for connection, stamp, _ in reader.messages()
                      if connection.topic == "/dpc/odometry"]
            assert stamps == stamps_of(times) and len(reader.connections) == 2
    assert sorted(p.name for p in (tmp_path / "c_ros2").iterdir()) == ["c_ros2.mcap", "metadata.yaml"]
    assert "  version: 8" in (tmp_path / "c_ros2" / "metadata.yaml").read_text()
    # Run again, the bag it wrote is replaced; a folder of someone else's files is not written over.
    ros2 = [*common, "--bag", str(recording), "--prior-topic", "/vo", "--format", "rosbag2", "--out"]
    assert main([*ros2, str(tmp_path / "c_ros2")]) == 0
    assert sorted(p.name for p in (tmp_path / "c_ros2").iterdir()) == ["c_ros2.mcap", "metadata.yaml"]
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main([*ros2, str(tmp_path / "theirs")]) == 2
    assert "theirs: holds files but is not a ROS 2 bag that `correct` wrote" in capsys.readouterr().err
    assert [p.name for p in (tmp_path / "theirs").iterdir()] == ["notes.txt"]
    (tmp_path / "theirs" / "notes.txt").unlink()
    (tmp_path / "theirs").rmdir()
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("05")) == [
        "bag.txt", "c.bag", "c.mcap", "c_ros2", "files.txt"]  # nothing else left beside the outputs
    # Ground truth elsewhere than the prior's first pose: the text output starts at it, the recording's
    # corrected topic where the prior starts (both its topics are in the prior's frame), the same steps.
    moved = np.eye(4)
    moved[:3, :3], moved[:3, 3] = Rotation.from_rotvec([0.0, 0.3, 0.0]).as_matrix(), [5.0, 0.0, -2.0]
    gt = moved @ read_trajectory(setup["kitti"] / "poses" / "05.txt", "kitti")
    with_gt = write_recording(tmp_path / "05gt.mcap", setup["kitti"], "05", compressed=True,
                              poses={"/vo": prior, "/gt": gt})
    assert main([*common, "--bag", str(with_gt), "--prior-topic", "/vo", "--gt-topic", "/gt", "--out",
                 str(tmp_path / "gt.txt")]) == 0
    assert main([*common, "--bag", str(with_gt), "--prior-topic", "/vo", "--gt-topic", "/gt", "--out",
                 str(tmp_path / "gt.mcap")]) == 0
    text = read_trajectory(tmp_path / "gt.txt", "kitti")
    np.testing.assert_allclose(text[0], gt[0], atol=1e-9)
    written = read_pose_topic(tmp_path / "gt.mcap", "/dpc/odometry")[1]
    np.testing.assert_allclose(written[0], prior[0], atol=1e-9)
    np.testing.assert_allclose(np.linalg.inv(written[:-1]) @ written[1:], np.linalg.inv(text[:-1]) @ text[1:],
                               atol=1e-9)
