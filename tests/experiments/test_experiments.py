"""The KITTI experiment entry points, end to end on a tiny fake KITTI odometry tree (dpc_jax.synth)."""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from support import write_fake_odometry

from dpc_jax.pipelines import protocol as dpc_protocol

ROOT = Path(__file__).resolve().parents[2]
PROTOCOLS = ROOT / "experiments" / "protocols"

FRAMES = 10


def _entry(name: str):
    spec = importlib.util.spec_from_file_location(f"experiment_{name}", PROTOCOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def kitti(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fake_kitti")
    return write_fake_odometry(
        root, ["00", "02", "05"], frames=FRAMES, prior_dir=root / "priors"
    )


def _rows(workdir: Path) -> list[dict[str, str]]:
    with (workdir / "results.csv").open() as f:
        return list(csv.DictReader(f))


def _split(workdir: Path, fold: str) -> dict:
    return json.loads((workdir / "runs" / fold / "checkpoints" / "split.json").read_text())


@pytest.mark.parametrize("name", ["kitti_stereo_dpc", "kitti_ss_dpc", "kitti_raw_excerpt",
                                  "kitti_raw_drives"])
def test_configs_are_train_configs_and_state_their_command(name: str) -> None:
    config, protocol = dpc_protocol.load_protocol(PROTOCOLS / "configs" / f"{name}.py")
    doc = (PROTOCOLS / "configs" / f"{name}.py").read_text().split('"""')[1]
    assert f"python experiments/protocols/{name}.py" in doc and "Produces" in doc
    assert protocol.select in ("delta", "gradient", "loop", "last")
    if name == "kitti_stereo_dpc":
        assert config.image_size == (240, 376) and config.epochs == 30 and config.learning_rate == 6e-3
        assert config.lr_halving_epochs == 5 and config.loss["alpha"] == (1.0, 1.0, 1.0, 0.08)
        assert not config.rotation_only and config.method == "stereo_dpc"
    if name in ("kitti_stereo_dpc", "kitti_ss_dpc"):  # the papers' correction head, every field of it
        from dpc_jax.training.train_config import REFERENCE

        assert {k: getattr(config, k) for k in REFERENCE} == REFERENCE
    if name == "kitti_ss_dpc":
        assert config.rotation_only and config.method == "ss_dpc"
        assert config.loss == {"exp_weight": 0.23, "rot_weight": 4.0, "rot_threshold": 0.005}
        folds = protocol.folds
        assert (folds["stereo_val05"].validation, folds["stereo_val05"].test) == ("05", ("00", "02"))
        assert (folds["stereo_val00"].validation, folds["stereo_val00"].test) == ("00", ("05",))
        assert folds["mono"].test == ("09", "10") and folds["mono"].prior == "mono"
        assert folds["mono"].overrides["rotation_only"] is False
    if name in ("kitti_raw_excerpt", "kitti_raw_drives"):  # every real-data protocol judges at 240×376
        assert protocol.judge_size == (240, 376)
    if name == "kitti_raw_drives":  # derived from the excerpt's config: its training and shared settings
        excerpt, shared = dpc_protocol.load_protocol(PROTOCOLS / "configs" / "kitti_raw_excerpt.py")
        assert config == dataclasses.replace(excerpt, cache_root="runs/kitti_raw_drives/cache",
                                             test_sequences=("test",))
        assert (protocol.select, protocol.adapt_steps, protocol.rotation_only, protocol.judge_size) == (
            shared.select, shared.adapt_steps, shared.rotation_only, shared.judge_size)
        assert protocol.drives["0005"].validation_frames == (68, 91)


def test_a_protocol_is_checked_like_a_config(tmp_path: Path) -> None:
    from dpc_jax.config import ConfigError

    path = tmp_path / "p.py"
    base = PROTOCOLS / "configs" / "kitti_stereo_dpc.py"
    config = f"import runpy\nCONFIG = runpy.run_path({str(base)!r})['CONFIG']\n"
    path.write_text(config + "PROTOCOL = {'selct': 'delta'}\n")
    with pytest.raises(ConfigError, match="PROTOCOL: unknown key 'selct'; did you mean 'select'"):
        dpc_protocol.load_protocol(path)
    path.write_text(config + "PROTOCOL = {'folds': {'a': {'prior': 'stereo', 'validation': '05', "
                    "'tests': []}}}\n")
    with pytest.raises(ConfigError, match=r"folds\.a: unknown key 'tests'; did you mean 'test'"):
        dpc_protocol.load_protocol(path)
    path.write_text(config + "PROTOCOL = {'adapt_steps': 'many'}\n")
    with pytest.raises(ConfigError, match="adapt_steps: expected an integer"):
        dpc_protocol.load_protocol(path)


def test_overrides_and_fold_config() -> None:
    assert dpc_protocol.parse_overrides(["epochs=2", "image_size=[64,96]", "preset=small"]) == {
        "epochs": 2, "image_size": [64, 96], "preset": "small"}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        dpc_protocol.parse_overrides(["epochs"])
    base, _ = dpc_protocol.load_protocol(PROTOCOLS / "configs" / "kitti_stereo_dpc.py")
    fold = dpc_protocol.Fold("f", ("02",), "05", ("00",))
    config = dpc_protocol.fold_config(base, fold, Path("/c"), {"epochs": 2})
    assert (config.train_sequences, config.validation_sequences, config.test_sequences) == (
        ("02",), ("05",), ("00",))
    assert config.epochs == 2 and config.cache_root == "/c"
    with pytest.raises(ValueError, match="did you mean 'epochs'"):
        dpc_protocol.fold_config(base, fold, Path("/c"), {"epoch": 2})


def test_bad_protocol_input_errors_before_compute(kitti: Path, tmp_path: Path, capsys) -> None:
    ss = _entry("kitti_ss_dpc")
    base = ["--kitti-odometry", str(kitti), "--priors", str(kitti / "priors"),
            "--sequences", "00", "02", "05",
            "--workdir", str(tmp_path / "w"), "--no-progress"]
    assert ss.main([*base, "--fold", "mono"]) == 2
    assert "fold mono needs sequence(s) ['09', '10']" in capsys.readouterr().err
    assert ss.main([*base, "--fold", "nope"]) == 2
    assert "stereo_val05, stereo_val00, mono" in capsys.readouterr().err
    stereo = _entry("kitti_stereo_dpc")
    assert stereo.main([*base, "--test", "07"]) == 2
    assert "--test 07 is not one of the sequences" in capsys.readouterr().err
    assert stereo.main([*base[:3], str(tmp_path), *base[4:], "--test", "00"]) == 2
    assert "no prior for sequence 00" in capsys.readouterr().err
    assert not (tmp_path / "w" / "runs").exists()


def _check_result_row(
    row: dict[str, str], workdir: Path, fold: str, sequence: str, kitti: Path
) -> np.ndarray:
    """The row's prior figures equal an independent evaluation; returns the corrected trajectory."""
    from dpc_jax.data.poses_io import read_mat, read_trajectory
    from dpc_jax.eval.evaluation import evaluate

    gt, prior = read_mat(kitti / "priors" / f"stereo_{sequence}.mat")
    expected = evaluate(gt, {"prior": prior})["estimates"]["prior"]
    assert float(row["prior_m_ate_trans_m"]) == pytest.approx(expected["m_ate_trans_m"], rel=1e-9)
    assert float(row["prior_ate_m"]) == pytest.approx(expected["ate_m"], rel=1e-9)
    corrected = read_trajectory(workdir / "corrected" / fold / f"{sequence}.txt", "kitti")
    assert corrected.shape == (FRAMES, 4, 4)
    np.testing.assert_allclose(corrected[0], gt[0], atol=1e-12)
    assert (workdir / "reports" / fold / sequence / "trained" / "report.md").is_file()
    return corrected


@pytest.mark.slow
def test_kitti_stereo_dpc_smoke(kitti: Path, tmp_path: Path, capsys) -> None:
    stereo = _entry("kitti_stereo_dpc")
    workdir = tmp_path / "stereo"
    argv = ["--kitti-odometry", str(kitti), "--priors", str(kitti / "priors"),
            "--sequences", "00", "02", "05",
            "--test", "00", "--workdir", str(workdir), "--smoke", "--no-progress"]
    assert stereo.main(argv) == 0
    assert "| test_00 | 00 |" in capsys.readouterr().out
    split = _split(workdir, "test_00")
    assert (split["train"], split["validation"], split["test"]) == (["02"], ["05"], ["00"])
    [row] = _rows(workdir)
    assert (row["fold"], row["sequence"], row["epoch"]) == ("test_00", "00", "1")
    _check_result_row(row, workdir, "test_00", "00", kitti)
    assert "SMOKE RUN" in (workdir / "results.md").read_text()


@pytest.mark.slow
def test_kitti_ss_dpc_smoke_corrects_rotation_only(kitti: Path, tmp_path: Path) -> None:
    from dpc_jax.data.poses_io import read_mat
    from dpc_jax.geometry.poses import relative_poses

    ss = _entry("kitti_ss_dpc")
    workdir = tmp_path / "ss"
    argv = ["--kitti-odometry", str(kitti), "--priors", str(kitti / "priors"),
            "--sequences", "00", "02", "05",
            "--fold", "stereo_val00", "--workdir", str(workdir), "--smoke", "--no-progress"]
    assert ss.main(argv) == 0
    split = _split(workdir, "stereo_val00")
    assert (split["train"], split["validation"], split["test"]) == (["02"], ["00"], ["05"])
    [row] = _rows(workdir)
    assert row["prior"] == "libviso2-s"
    corrected = _check_result_row(row, workdir, "stereo_val00", "05", kitti)
    # Rotation-only correction: every step keeps the prior's translation length, but rotations change.
    _, prior = read_mat(kitti / "priors" / "stereo_05.mat")
    steps, prior_steps = relative_poses(corrected), relative_poses(prior)
    np.testing.assert_allclose(np.linalg.norm(steps[:, :3, 3], axis=1),
                               np.linalg.norm(prior_steps[:, :3, 3], axis=1), rtol=1e-9)
    assert np.abs(steps[:, :3, :3] - prior_steps[:, :3, :3]).max() > 1e-7


def test_excerpt_ground_truth_step_geometry_round_trip() -> None:
    """Travel length, elevation and lateral angle of known camera motions (closed form), and back
    (``dpc_jax.experiments.steps``, what excerpt_ground_truth.py checks steps with)."""
    from scipy.spatial.transform import Rotation

    from dpc_jax.experiments import steps as check

    rng = np.random.default_rng(0)
    n = 6
    length = rng.uniform(0.5, 2.0, n)
    elevation = rng.uniform(-0.05, 0.05, n)
    lateral = rng.uniform(-0.1, 0.1, n)
    # Camera t moves by `travel` (its own frame: x right, y down, z forward) and turns by R_t_{t+1}.
    direction = [np.cos(elevation) * np.sin(lateral), -np.sin(elevation), np.cos(elevation) * np.cos(lateral)]
    travel = length[:, None] * np.stack(direction, axis=1)
    turn = Rotation.from_rotvec(rng.normal(0, 0.02, (n, 3))).as_matrix()
    step = np.tile(np.eye(4), (n, 1, 1))  # T_{t+1,t} = inv([turn | travel])
    step[:, :3, :3] = np.swapaxes(turn, 1, 2)
    step[:, :3, 3] = -np.einsum("nji,nj->ni", turn, travel)
    got = check.step_geometry(step)
    np.testing.assert_allclose(got[0], length, rtol=1e-12)
    np.testing.assert_allclose(got[1], elevation, atol=1e-12)
    np.testing.assert_allclose(got[2], lateral, atol=1e-12)
    np.testing.assert_allclose(check.with_travel(step, length, elevation, lateral), step, atol=1e-12)
    other = step.copy()
    other[:, :3, :3] = np.eye(3)
    swapped = check.exchange(other, step)  # identity rotation, the same travel in frame t
    np.testing.assert_allclose(swapped[:, :3, :3], np.tile(np.eye(3), (n, 1, 1)))
    np.testing.assert_allclose(-swapped[:, :3, 3], travel, atol=1e-12)
