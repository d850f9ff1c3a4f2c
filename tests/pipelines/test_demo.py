"""The synthetic demo end to end at a tiny size: outputs, report, reuse on a second run, config errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dpc_jax import config as config_lib
from dpc_jax.cli import main as cli_main
from dpc_jax.data.poses_io import read_trajectory
from dpc_jax.pipelines.protocol import SMOKE
from dpc_jax.pipelines.synthetic_demo import DemoConfig, DemoError, run_demo
from dpc_jax.results.demo import DemoSummary

ROOT = Path(__file__).resolve().parents[2]
# At 48×80 the VO falls back on most pairs; the tiny demo accepts that (the refusal is tested below).
TINY = {
    "train_sequences": 1, "train_frames": 7, "validation_frames": 7, "test_frames": 7,
    "render_size": (48, 80), "moving_objects": 1, "max_fallback_share": 1.0, "adapt_steps": 2,
    "holdout_every": 4,
    "training": {"image_size": (32, 48), "batch_size": 2, "epochs": 1, "steps_per_epoch": 2,
                 "model": SMOKE["model"]},
}


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, DemoSummary, list[str]]:
    out = tmp_path_factory.mktemp("demo")
    lines: list[str] = []
    summary = run_demo(config_lib.from_dict(DemoConfig, TINY), out, log=lines.append)
    return out, summary, lines


@pytest.mark.slow
def test_outputs_and_report(demo: tuple[Path, DemoSummary, list[str]]) -> None:
    out, summary, lines = demo
    assert [line.split(":")[0] for line in lines[:3]] == ["train0", "val", "test"]
    assert all("(rendered)" in line for line in lines[:3])
    for name in ("train0", "val", "test"):
        assert (out / "data" / "sequences" / name / "image_2" / "000000.png").is_file()
        assert (out / "cache" / name / "manifest.json").is_file()
        assert read_trajectory(out / "vo" / f"{name}.txt").shape[0] == TINY[
            {"train0": "train_frames", "val": "validation_frames", "test": "test_frames"}[name]]
    corrected = read_trajectory(out / "corrected.txt")
    gt = read_trajectory(out / "data" / "poses" / "test.txt")
    assert corrected.shape == (TINY["test_frames"], 4, 4)
    np.testing.assert_allclose(corrected[0], gt[0], atol=1e-9)  # composed from the first GT pose

    report = (out / "report.md").read_text()
    for label in ("| prior (our VO) |", "| network as trained", "| network adapted to the test sequence",
                  "| **final:"):
        assert label in report, label
    assert "What the prior's error consists of" in report and "| train0 |" in report
    for image in ("trajectory.png", "segment_errors.png", "c_ate.png"):
        assert f"]({image})" in report
        assert (out / image).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    stored = json.loads((out / "summary.json").read_text())
    assert stored["report"] == str(out / "report.md") == summary.report
    # The summary reads back as it was written.
    text = (out / "summary.json").read_text()
    assert json.dumps(DemoSummary.from_dict(stored).to_dict(), indent=2, sort_keys=True) + "\n" == text
    assert set(stored["test"]) == {"prior", "trained", "adapted", "corrected"}
    assert set(stored["decisions"]) == {"trained", "adapted"}
    # The final trajectory is the adapted correction if accepted, else the trained one, else the prior.
    accepted = [k for k in ("adapted", "trained") if stored["decisions"][k].startswith("accepted")]
    assert stored["final"] == (accepted[0] if accepted else "prior")
    if stored["final"] == "prior":
        prior = read_trajectory(out / "vo" / "test.txt")
        np.testing.assert_allclose(corrected, gt[0] @ np.linalg.inv(prior[0]) @ prior, atol=1e-9)
    # The sequences are shorter than 100 m: no segment errors, so no claim of improvement.
    assert stored["test"]["prior"]["seg_trans_pct"] is None and stored["corrected_better"] is False
    assert stored["test"]["prior"]["m_ate_trans_m"] > 0
    assert stored["steps_per_epoch"] == 2 and stored["adaptation"]["steps"] == 2
    assert (out / "adapted" / "adapt.csv").is_file()
    assert (out / "adapted" / "checkpoints" / "config.json").is_file()
    composition = stored["sequences"]["test"]
    assert len(composition["error"]["mean"]) == 6 and composition["pairs"] == TINY["test_frames"] - 1


@pytest.mark.slow
def test_second_run_reuses_everything(demo: tuple[Path, DemoSummary, list[str]]) -> None:
    out, summary, _ = demo
    files = [out / "vo" / "test.txt", out / "cache" / "test" / "left.npy",
             out / "data" / "sequences" / "val" / "image_2" / "000000.png"]
    stamps = {p: p.stat().st_mtime_ns for p in files}
    lines: list[str] = []
    again = run_demo(config_lib.from_dict(DemoConfig, TINY), out, log=lines.append)
    assert all("(reused)" in line for line in lines[:3])
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert again.test == summary.test  # the finished run is restored, not retrained
    assert again.seconds["train"] < summary.seconds["train"]


@pytest.mark.slow
def test_a_prior_that_is_not_vo_is_refused(demo: tuple[Path, DemoSummary, list[str]]) -> None:
    out, summary, _ = demo
    fallbacks = summary.sequences["train0"]["fallbacks"]
    assert fallbacks > 0.05 * summary.sequences["train0"]["pairs"]  # 48×80 is too small for the VO
    strict = config_lib.from_dict(DemoConfig, {**TINY, "max_fallback_share": 0.05})
    with pytest.raises(DemoError, match=rf"train0: our VO fell back to constant velocity on {fallbacks} of"):
        run_demo(strict, out)


def test_config_checks() -> None:
    with pytest.raises(config_lib.ConfigError, match="train_sequences must be >= 1"):
        DemoConfig(train_sequences=0)
    with pytest.raises(config_lib.ConfigError, match="cache_root"):
        DemoConfig(training={"cache_root": "/elsewhere"})
    with pytest.raises(config_lib.ConfigError, match="select must be one of"):
        DemoConfig(select="best")
    with pytest.raises(config_lib.ConfigError, match="learning_rate"):
        DemoConfig(training={"learning_rate": -1.0})
    with pytest.raises(config_lib.ConfigError, match="unknown key 'epoch'"):
        DemoConfig(training={"epoch": 3})
    config = DemoConfig(train_sequences=3, seed=5)
    assert list(config.sequences) == ["train0", "train1", "train2", "val", "test"]
    assert [config.synth_config(n).seed for n in config.sequences] == [5, 6, 7, 105, 205]
    train = config.train_config("/cache")
    assert train.train_sequences == ("train0", "train1", "train2")
    assert (train.validation_sequences, train.test_sequences) == (("val",), ("test",))


def test_experiment_config_is_the_default() -> None:
    path = ROOT / "experiments" / "studies" / "configs" / "synthetic_demo.py"
    assert config_lib.load_file(path, DemoConfig) == DemoConfig()


def test_cli_reports_a_bad_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("CONFIG = {'train_frames': 1}\n")
    assert cli_main(["demo", "--config", str(bad), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "dpc-jax demo: error:" in err and "train_frames must be >= 3" in err
    assert not (tmp_path / "out").exists()
