"""The reporting layer: shared table helpers, the experiment results table, the correction report."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dpc_jax.report.correction_report import acceptance_markdown, choice_markdown, write_correction_report
from dpc_jax.report.demo_report import decision_label
from dpc_jax.report.pages import read_block, replace_block, write_results
from dpc_jax.report.protocol_report import results_csv, results_markdown
from dpc_jax.report.tables import EMPTY, change_pct, csv_text, number, records_csv, table
from dpc_jax.results.acceptance import Acceptance, PairedTest
from dpc_jax.results.correction import Correction
from dpc_jax.results.fold import Final, FoldResult, read_fold_results, write_fold_results

METRICS = {"seg_trans_pct": 2.5, "seg_rot_deg_per_100m": None, "m_ate_trans_m": 12345.678,
           "m_ate_rot_deg": math.nan, "ate_m": 0.125}


def test_table_and_csv_text() -> None:
    assert table(["a", "b"], [["1", ""], ["x", "y"]]) == "| a | b |\n|---|---|\n| 1 |  |\n| x | y |\n"
    assert csv_text(["a", "b"], [[1, None], ["x,y", 2.5]]) == 'a,b\n1,\n"x,y",2.5\n'
    assert records_csv([{"a": 1, "b": None}, {"a": 2, "c": "z"}]) == "a,b,c\n1,,\n2,,z\n"


def test_cells_and_the_change_against_the_prior() -> None:
    cells = [number(v) for v in (None, math.nan, math.inf, 2, 0.123456)]
    assert cells == [EMPTY, EMPTY, EMPTY, "2", "0.1235"]
    assert number(-1.25, "+.1f") == "-1.2"
    assert change_pct(2.0, 1.0) == -50.0 and change_pct(4.0, 5.0) == 25.0
    undefined = ((0.0, 1.0), (None, 1.0), (1.0, None), (math.nan, 1.0))
    assert all(math.isnan(change_pct(p, v)) for p, v in undefined)


def test_a_page_block_is_replaced_and_nothing_else(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("# title\n<!-- results:begin -->\nold\n<!-- results:end -->\nkept\n")
    replace_block(page, "results", "| a |\n|---|\n")
    assert page.read_text() == "# title\n<!-- results:begin -->\n| a |\n|---|\n<!-- results:end -->\nkept\n"
    assert read_block(page, "results") == "\n| a |\n|---|\n"
    with pytest.raises(ValueError, match="no <!-- other:begin -->"):
        replace_block(page, "other", "x")
    write_results(page, "# An experiment\n\nits note\n\n| b |\n|---|\n", Path(__file__))
    block = read_block(page, "results")
    assert block.startswith(f"\nWritten by `{Path(__file__).name}` at commit ")
    assert block.endswith(".\n\nits note\n\n| b |\n|---|\n") and "An experiment" not in block


def test_results_table_and_csv() -> None:
    corrected = {**METRICS, "seg_trans_pct": 2.0}
    results = [
        FoldResult("f", "00", "libviso2", 3, "delta", 100, {"prior": METRICS, "corrected": corrected},
                   "trained (full)", {"trained": METRICS}, {"trained": "full"}),
        FoldResult("g", "05", "vo", 1, "last", 7, {"prior": METRICS, "corrected": METRICS}, "prior"),
    ]
    text = results_markdown(results, "Title", ["a note"], tolerance_pct=2.0)
    lines = text.splitlines()
    assert lines[:4] == ["# Title", "", "a note", ""]
    assert lines[4] == ("| fold | sequence | prior | epoch | applied | frames | seg. t (%) | "
                        "seg. r (°/100 m) | m-ATE (m) | m-ATE (°) | ATE (m) |")
    assert lines[5] == "|---|---|---|---|---|---|---|---|---|---|---|"
    assert lines[6] == ("| f | 00 | libviso2 | 3 (delta) | trained (full) | 100 | 2.5 → 2 | n/a → n/a | "
                        "1.235e+04 → 1.235e+04 | n/a → n/a | 0.125 → 0.125 |")
    # Only the staged result has per-network rows: prior, each network, final.
    assert lines[-5] == ("| sequence | prior | estimate | acceptance test | seg. t (%) | seg. r (°/100 m) | "
                         "m-ATE (m) | m-ATE (°) | ATE (m) |")
    assert lines[-3] == "| 00 | libviso2 | prior |  | 2.5 | n/a | 1.235e+04 | n/a | 0.125 |"
    assert lines[-2] == "| 00 | libviso2 | network trained | full | 2.5 | n/a | 1.235e+04 | n/a | 0.125 |"
    assert lines[-1] == "| 00 | libviso2 | final (trained (full)) |  | 2 | n/a | 1.235e+04 | n/a | 0.125 |"
    assert text.endswith("\n")
    assert "# Title\n\n| fold" in results_markdown(results, "Title", tolerance_pct=2.0)

    csv_lines = results_csv(results).splitlines()
    assert csv_lines[0] == ("fold,sequence,prior,epoch,selection,applied,frames," + ",".join(
        f"{which}_{k}" for which in ("prior", "corrected") for k in METRICS))
    assert csv_lines[1] == ("f,00,libviso2,3,delta,trained (full),100,"
                            "2.5,,12345.678,nan,0.125,2.0,,12345.678,nan,0.125")
    assert results_csv([]) == "fold,sequence,prior,epoch,selection,applied,frames\n"


def _test(component: str, passed: bool) -> PairedTest:
    return PairedTest(component, 12, -1.5e-3, -2e-4, 0.75, 10.0, 0.0123, passed, 3e-3)


def test_acceptance_and_choice_markdown() -> None:
    acceptance = Acceptance(0.05, {"full": _test("full", True)}, "full", "full: passed")
    lines = acceptance_markdown(acceptance).splitlines()
    assert lines[0] == ("| component | pairs | mean Δ | median Δ | pairs improved | Wilcoxon W "
                        "| p (one-sided) | passed |")
    assert lines[1] == "|---|---|---|---|---|---|---|---|"
    assert lines[2] == "| full | 12 | -1.500e-03 | -2.000e-04 | 75.0 % | 10 | 0.0123 | yes |"
    assert "**Applied: full 6-DoF** (full: passed)." in lines
    without = Acceptance(0.05, {}, "rotation_xz", "r", scale=0.5, remainder=True,
                         mean=(0, 0, 0, 1e-4, 0, -2e-4), window=50)
    assert ("**Applied: rotation about x, z only, without its mean over 50 pairs (on average +0.100, +0.000, "
            "-0.200 mrad per step), "
            "×0.5**") in acceptance_markdown(without)
    assert decision_label(without).startswith("accepted (rotation about x, z only, without its mean")
    comparison = dataclasses.asdict(_test("adapted − trained", False))
    choice = {"final": "trained", "reason": "because", "comparison": comparison}
    lines = choice_markdown(choice).splitlines()
    assert lines[2] == "**trained**: because."
    assert lines[4].startswith("| comparison | pairs |")
    assert lines[6] == "| adapted − trained | 12 | -1.500e-03 | -2.000e-04 | 75.0 % | 10 | 0.0123 | no |"
    assert choice_markdown({"final": "prior", "reason": "r"}).count("|") == 0
    assert decision_label(acceptance) == "accepted (full 6-DoF)"
    assert decision_label(Acceptance(0.05, component="none")) == "rejected"
    assert decision_label(Acceptance(0.05, component="rotation", forced=True)) == "not tested (applied)"


def test_correction_report_without_ground_truth(tmp_path: Path) -> None:
    acceptance = Acceptance(0.05, {"rotation": _test("rotation", False)}, "none", "rotation: failed")
    adaptation = {"steps": 30, "seconds": 90.0, "held_out": 6, "holdout_every": 5, "source_epoch": 2}
    poses = np.tile(np.eye(4), (3, 1, 1))
    correction = Correction("05", np.arange(3), np.arange(3) / 10, poses, poses, poses, None,
                            np.zeros((2, 6)), True, acceptance, 2, None, adaptation=adaptation)
    written = write_correction_report(tmp_path / "r", correction, "T")
    assert [p.name for p in written] == ["report.md", "summary.json"]
    text = (tmp_path / "r" / "report.md").read_text()
    assert text.startswith("# T\n\nNo ground truth: nothing to evaluate.\n\n"
                           "## Adaptation (no ground truth used)\n\n30 steps on this sequence's own pairs in "
                           "1.5 min; 6 pairs kept out for the acceptance test (every 5th).\n\n"
                           "## Acceptance test (no ground truth used)\n\n")
    assert "**Applied: nothing: the corrected trajectory is the prior** (rotation: failed)." in text
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary == {"sequence": "05", "epoch": 2, "part": "none", "rotation_only": True,
                       "acceptance": acceptance.to_dict(), "adaptation": adaptation}


def test_results_read_back_as_they_were_written(tmp_path: Path) -> None:
    """An acceptance test and a fold's result read back from their JSON equal what was written (an
    acceptance's Δ is not written: it reads back as None)."""
    tests = {"rotation": _test("rotation", True), "mean of rotation": _test("mean of rotation", False)}
    acceptance = Acceptance(0.01, tests, "rotation", "r", scale=0.5, remainder=True,
                            mean=(0, 0, 0, 1e-4, 0, 0), delta=np.ones(3))
    again = Acceptance.from_dict(json.loads(json.dumps(acceptance.to_dict())))
    assert again == acceptance and again.delta is None and again.part == "rotation − mean ×0.5"
    metrics = {**METRICS, "m_ate_rot_deg": 1.5}  # an evaluation's summary holds None, never NaN
    results = [FoldResult("f", "00", "vo", 3, "delta", 10, {"prior": metrics, "corrected": metrics},
                          "trained (rotation)", {"trained": metrics}, {"trained": "rotation"},
                          {"earlier": Final("prior", metrics),
                           "mean-at-judge": Final("trained (rotation)", {**metrics, "ate_m": 0.5})}),
               FoldResult("f", "02", "vo", 3, "delta", 10, {"prior": metrics, "corrected": metrics}, "prior")]
    write_fold_results(tmp_path / "results.json", results)
    read = read_fold_results(tmp_path / "results.json")
    assert [r.decided for r in read] == [results[0].decided, {}]
    assert [r.to_dict() for r in read] == json.loads(json.dumps([r.to_dict() for r in results]))
    # Results of an earlier version hold the earlier decision alone, under its own key.
    old = {k: v for k, v in results[0].to_dict().items() if k != "decided"}
    legacy = FoldResult.from_dict({**old, "earlier": {"applied": "prior", "metrics": metrics}})
    assert legacy.decided == {"earlier": Final("prior", metrics)}
    assert FoldResult.from_dict({**old, "earlier": None}).decided == {}


def test_table_reports_do_not_import_matplotlib() -> None:
    # The command line prints tables without drawing: matplotlib is imported only to write figures.
    code = "import sys, dpc_jax.report.evaluation_report; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False"]


def test_the_demo_summary_names_the_network_its_final_holds() -> None:
    from dpc_jax.results.demo import DemoSummary

    def summary(final: str, networks: tuple[str, ...]) -> DemoSummary:
        return DemoSummary({}, {}, {n: Acceptance(0.01) for n in networks}, final, None, {}, False, 1,
                           "delta", 2, {}, {}, {}, [], {})

    # Read back from summary.json the networks come sorted: the last tried is still the adapted one.
    assert summary("prior", ("adapted", "trained")).final_network == "adapted"
    assert summary("trained", ("trained", "adapted")).final_network == "trained"
    assert summary("prior", ("trained",)).final_network == "trained"
