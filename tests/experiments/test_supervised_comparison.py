"""experiments/studies/supervised_comparison.py: its table (``dpc_jax.experiments.comparison``) from
hand-made demo summaries and drive results (no training), and its config."""

from __future__ import annotations

import csv
import dataclasses
import io
import runpy
from pathlib import Path

import pytest

from dpc_jax.experiments import comparison
from dpc_jax.experiments.demos import demo_config
from dpc_jax.pipelines import protocol as dpc_protocol
from dpc_jax.results.acceptance import Acceptance
from dpc_jax.results.demo import DemoSummary
from dpc_jax.results.fold import FoldResult

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "experiments" / "studies" / "configs" / "supervised_comparison.py"


def _values(t: float | None, r: float | None, ate: float) -> dict[str, float | None]:
    return {"seg_trans_pct": t, "seg_rot_deg_per_100m": r, "m_ate_trans_m": ate, "m_ate_rot_deg": ate / 2,
            "ate_m": ate * 1.5, "rpe_trans_m": 0.04, "rpe_rot_deg": 0.02, "loop_closures": 0}


def _demo(trained: float, adapted: float | None, final: str) -> DemoSummary:
    """A demo's summary: prior 10 % / 4 °/100 m, the network rows scaled by the given factors."""
    corrected = {"trained": trained, "adapted": adapted, "prior": 1.0}[final]
    test = {"prior": _values(10.0, 4.0, 2.0), "trained": _values(10 * trained, 4 * trained, 2 * trained),
            "corrected": _values(10 * corrected, 4 * corrected, 2 * corrected)}
    decisions = {"trained": "accepted (full 6-DoF)"}
    if adapted is not None:
        test["adapted"] = _values(10 * adapted, 4 * adapted, 2 * adapted)
        decisions["adapted"] = "rejected"
    return DemoSummary(test, decisions, {k: Acceptance(0.01) for k in decisions}, final, None, {}, False, 1,
                       "delta", 2, {}, {}, {}, [], {})


def _drive(drive: str, prior_t: float | None, scale: float, decision: str) -> FoldResult:
    """A ``kitti_raw_drives.py`` result of test drive ``drive`` with our VO's prior."""
    def values(factor: float) -> dict[str, float | None]:
        return _values(None if prior_t is None else prior_t * factor, None if prior_t is None else factor,
                       0.8 * factor)

    return FoldResult("train_x_vo", f"{drive}_vo", "vo", 3, "delta", 90,
                      {"prior": values(1.0), "corrected": values(scale)}, f"trained ({decision})",
                      {"trained": values(scale), "adapted": values(1.1)},
                      {"trained": decision, "adapted": "none"})


def _demo_rows(seed: int, supervised: DemoSummary, own: DemoSummary, baselines: dict,
               trained_on: str = "train0, train1") -> list[comparison.Row]:
    prior = comparison.metrics_of(own.test["prior"])
    return comparison.rows_of(f"demo seed {seed}", trained_on, prior, baselines,
                              {"supervised": comparison.demo_stages(supervised),
                               "self": comparison.demo_stages(own)})


def _drive_rows(drive: str, supervised: FoldResult, own: FoldResult, baselines: dict) -> list[comparison.Row]:
    return comparison.rows_of(f"drive {drive}", "drive 0001, frames 0–79",
                              comparison.metrics_of(own.metrics["prior"]), baselines,
                              {"supervised": comparison.fold_stages(supervised),
                               "self": comparison.fold_stages(own)})


BASELINES_0 = {"linear": _values(9.0, 1.0, 1.0), "constant": _values(9.5, 2.0, 1.0)}
BASELINES_1 = {"linear": _values(5.0, 2.0, 1.0), "constant": _values(9.5, 2.0, 1.0)}
SHORT = {"linear": _values(None, None, 0.7), "constant": _values(None, None, 0.75)}


def test_demo_rows_keep_every_stage_its_decision_and_the_prior() -> None:
    rows = _demo_rows(3, _demo(0.5, 0.4, "adapted"), _demo(0.8, 1.2, "trained"), BASELINES_0)
    assert [r.kind for r in rows] == list(comparison.KINDS)
    by_kind = {r.kind: r for r in rows}
    assert {r.test for r in rows} == {"demo seed 3"} and {r.trained_on for r in rows} == {"train0, train1"}
    assert by_kind["prior"].metrics["seg_trans_pct"] == 10.0 and by_kind["prior"].decision == ""
    assert by_kind["linear"].metrics["seg_rot_deg_per_100m"] == 1.0
    assert by_kind["supervised_trained"].metrics["seg_trans_pct"] == pytest.approx(5.0)
    assert by_kind["supervised_adapted"].decision == "rejected"
    assert by_kind["supervised_final"].decision == "adapted: rejected"
    assert by_kind["supervised_final"].metrics["m_ate_trans_m"] == pytest.approx(0.8)
    assert by_kind["self_final"].decision == "trained: accepted (full 6-DoF)"
    assert by_kind["self_adapted"].metrics["seg_rot_deg_per_100m"] == pytest.approx(4.8)
    assert "loop_closures" not in by_kind["self_trained"].metrics


def test_a_demo_without_adaptation_and_kept_prior() -> None:
    summary = _demo(1.1, None, "prior")
    rows = _demo_rows(0, summary, summary, {"linear": _values(None, None, 1.0),
                                            "constant": _values(None, None, 1.0)}, "train0")
    kinds = [r.kind for r in rows]
    assert "self_adapted" not in kinds and "supervised_adapted" not in kinds
    assert {r.decision for r in rows if r.kind.endswith("_final")} == {"prior"}
    assert next(r for r in rows if r.kind == "linear").metrics["seg_trans_pct"] is None


def test_drive_rows_from_the_fold_results() -> None:
    rows = _drive_rows("0005", _drive("0005", None, 0.9, "rotation_xz"), _drive("0005", None, 0.95, "none"),
                       SHORT)
    assert [r.kind for r in rows] == list(comparison.KINDS)
    by_kind = {r.kind: r for r in rows}
    assert by_kind["prior"].metrics["m_ate_trans_m"] == pytest.approx(0.8)
    assert by_kind["prior"].metrics["seg_trans_pct"] is None  # shorter than 100 m: no segments
    assert by_kind["supervised_trained"].decision == "rotation_xz"
    assert by_kind["supervised_trained"].metrics["m_ate_trans_m"] == pytest.approx(0.72)
    assert by_kind["self_final"].decision == "trained (none)"
    assert by_kind["self_trained"].metrics["m_ate_trans_m"] == pytest.approx(0.76)
    assert by_kind["linear"].metrics["m_ate_trans_m"] == 0.7


def test_markdown_csv_and_the_change_over_seeds() -> None:
    rows = [*_demo_rows(0, _demo(0.5, 0.4, "adapted"), _demo(0.8, 1.2, "trained"), BASELINES_0),
            *_demo_rows(1, _demo(0.9, 1.1, "trained"), _demo(0.3, 0.6, "trained"), BASELINES_1),
            *_drive_rows("0005", _drive("0005", None, 0.9, "none"), _drive("0005", None, 0.95, "none"),
                         SHORT)]
    text = comparison.comparison_markdown(rows, ["a note"])
    lines = text.splitlines()
    assert lines[2] == "a note"
    table = [line for line in lines if line.startswith("| demo seed") or line.startswith("| drive")]
    assert len(table) == len(rows) == 2 * 9 + 9
    assert "| drive 0005 | drive 0001, frames 0–79 | prior (our VO) |  | n/a | n/a | 0.8 |" in text
    linear_row = ("| demo seed 0 | train0, train1 | linear baseline, **supervised** (rotation) | "
                  "applied (no test) |")
    assert linear_row + " 9 | 1 |" in text
    # Over the two seeds (not the drive): linear seg. t 9 and 5 against 10 → -10 % (seed 0) … -50 % (seed 1).
    linear = next(line for line in lines if line.startswith("| linear baseline") and "…" in line)
    assert "-50.0 % (1) … -10.0 % (0)" in linear
    supervised_trained = next(line for line in lines
                              if line.startswith("| network, **supervised**: trained |"))
    assert supervised_trained.split(" | ")[1] == "-50.0 % (0) … -10.0 % (1)"
    self_adapted = next(line for line in lines if line.startswith("| network, self-supervised: adapted |"))
    assert self_adapted.split(" | ")[1] == "-40.0 % (1) … +20.0 % (0)"
    assert "over the demo seeds (0, 1)" in text

    parsed = list(csv.DictReader(io.StringIO(comparison.comparison_csv(rows))))
    assert [r["row"] for r in parsed[:9]] == list(comparison.KINDS)
    assert parsed[0]["test"] == "demo seed 0" and float(parsed[0]["seg_trans_pct"]) == 10.0
    assert parsed[-1]["seg_trans_pct"] == ""
    assert float(parsed[-1]["m_ate_trans_m"]) == pytest.approx(0.8 * 0.95)


def test_no_seed_no_summary_and_a_missing_metric_is_na() -> None:
    drive = _drive_rows("0001", _drive("0001", 0.6, 0.9, "none"), _drive("0001", 0.6, 0.95, "none"),
                        {"linear": _values(0.5, 0.5, 0.7), "constant": _values(0.5, 0.5, 0.7)})
    assert comparison.change_summary(drive) == []
    short = _demo_rows(0, _demo(0.5, 0.4, "adapted"), _demo(0.8, 1.2, "trained"),
                       {"linear": _values(None, None, 1.0), "constant": _values(None, None, 1.0)}, "train0")
    for row in short:
        row.metrics["seg_trans_pct"] = None
    summary = comparison.change_summary(short)
    assert all(line.split(" | ")[1] == "n/a" for line in summary[4:])


def test_the_config_states_its_command_and_narrows_the_drives_to_our_vo() -> None:
    doc = CONFIG.read_text().split('"""')[1]
    assert "python experiments/studies/supervised_comparison.py --workdir" in doc and "Produces" in doc
    config, protocol = dpc_protocol.load_protocol(CONFIG)
    drives_config, drives_protocol = dpc_protocol.load_protocol(ROOT / "experiments" / "protocols" / "configs"
                                                                / "kitti_raw_drives.py")
    assert config == drives_config and config.supervision == "self"
    assert protocol.tests == (("vo", "vo"),)
    assert dataclasses.replace(protocol, tests=()) == dataclasses.replace(drives_protocol, tests=())
    namespace = runpy.run_path(str(CONFIG))
    supervised = dpc_protocol.fold_config(config, dpc_protocol.Fold("f", ("a",), "b", ()), Path("c"),
                                          namespace["SUPERVISED"])
    assert supervised.supervision == "supervised" and supervised.precision is not None


def test_smoke_keeps_the_supervised_demo_supervised() -> None:
    namespace = runpy.run_path(str(CONFIG))
    smoke = namespace["SMOKE_DEMO"]
    configs = {kind: demo_config(Path(path), 7, smoke) for kind, path in namespace["DEMO"].items()}
    assert configs["supervised"].train_config("c").supervision == "supervised"
    assert configs["self"].train_config("c").supervision == "self"
    for config in configs.values():
        assert config.seed == 7 and config.train_frames == smoke["train_frames"]
        assert config.train_config("c").image_size == smoke["training"]["image_size"]
    full = demo_config(Path(namespace["DEMO"]["supervised"]), 0)
    assert full.train_config("c").precision == configs["supervised"].train_config("c").precision
