"""experiments/studies/detection_limit.py: the answer's arithmetic on cells of known removal, and the
``--quick`` grid end to end (render, plant, prepare, train, correct, table, figure)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import load_script

from dpc_jax.experiments import detection
from dpc_jax.experiments import detection_answer as answer
from dpc_jax.experiments import detection_page as page
from dpc_jax.experiments import detection_rule as rule
from dpc_jax.pipelines.protocol import WORKDIR_MARKER

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "studies" / "detection_limit.py"


@pytest.fixture(scope="module")
def script():
    """The study's script (its main and its config)."""
    return load_script(SCRIPT)


def _cell(size, scale, pairs, removed, final_change=0.0, mate_change=0.0, earlier=None, world=0,
          matched=False, p_mean=1e-3, needed=None):
    earlier = removed if earlier is None else earlier
    test = {"sequence": "test0", "decision": "rotation", "earlier_decision": "rotation", "p_whole": 1e-3,
            "p_mean": p_mean, "p_remainder": None, "mean_pairs_needed": needed, "mean_test_pairs": 400,
            "found_axis_network": removed, "found_axis_final": removed, "found_seg_network": removed,
            "found_seg_final": removed, "found_axis_earlier": earlier, "found_seg_earlier": earlier,
            "final_r_change_pct": final_change, "final_mate_r_change_pct": mate_change,
            "earlier_r_change_pct": final_change, "earlier_mate_r_change_pct": mate_change}
    return {"size": list(size), "scale": scale, "pairs": pairs, "bias_mrad": 0.26 * scale, "train_s": 60.0,
            "tests": [test], "machine": "m", "key": f"{size}_{scale}_{pairs}", "world_seed": world,
            "matched": matched, "steps": 750}


def test_the_half_removal_scale_is_interpolated_in_log_s_and_extrapolated_in_log_n() -> None:
    """Cells whose removal is linear in log s, with s50 = 30 · (N / 1000)^-1/2: the fit finds the slope −1/2
    and N(s50 = 1) = 1000 · 30² = 900,000, beyond the papers' 46,000."""
    size = (64, 96)
    cells = []
    for pairs in (1000, 4000):
        s50 = 30.0 * (pairs / 1000) ** -0.5
        for scale in (1.0, 3.0, 10.0, 100.0):
            removed = 0.5 + 0.25 * (math.log(scale) - math.log(s50))
            cells.append(_cell(size, scale, pairs, removed))
    assert answer.half_scale(cells, size, 1000) == (pytest.approx(30.0), "=")
    assert answer.half_scale(cells, size, 4000) == (pytest.approx(15.0), "=")
    fit = answer.extrapolate(cells, size)
    assert fit["found_at"] is None and fit["slope"] == pytest.approx(-0.5)
    assert fit["pairs_at_x1"] == pytest.approx(900_000, rel=1e-6)
    assert "beyond the papers' 46,000" in page._extrapolation_text(fit, 46_000)
    assert answer.smallest_found(cells) == {(size, 1000): 100.0, (size, 4000): 100.0}
    assert answer.half_scale(cells, (120, 188), 1000) is None


def test_a_bias_found_at_x1_needs_no_extrapolation() -> None:
    size = (64, 96)
    cells = [_cell(size, 1.0, 1000, 0.3), _cell(size, 3.0, 1000, 0.8),
             _cell(size, 1.0, 4000, 0.6), _cell(size, 3.0, 4000, 0.9)]
    assert answer.half_scale(cells, size, 4000) == (1.0, "≤")
    fit = answer.extrapolate(cells, size)
    assert fit["found_at"] == 4000 and fit["slope"] is None
    assert "at ×1 with N = 4,000" in page._extrapolation_text(fit, 46_000)
    assert answer.smallest_found(cells) == {(size, 1000): 3.0, (size, 4000): 1.0}


def test_the_answer_reads_the_default_decisions_removal_where_every_option_decided() -> None:
    """A cell decided by the options answers with the default option's removal (the judge's decision), not
    the study's final at the network's size; a cell decided before the options, with its final."""
    from dpc_jax.correction.decision import DEFAULT_MEAN_TEST

    size = (64, 96)
    decided = _decided(_cell(size, 1.0, 1000, 0.1), **{DEFAULT_MEAN_TEST: (0.7, 3.0)})
    cells = [decided, _cell(size, 3.0, 1000, 0.9), _cell(size, 1.0, 4000, 0.2)]
    assert answer.cell_mean(decided, "found_axis_final") == pytest.approx(0.1)
    assert answer.cell_mean(decided, answer.DEFAULT_REMOVAL) == pytest.approx(0.7)
    assert answer.smallest_found(cells) == {(size, 1000): 1.0, (size, 4000): None}
    assert answer.extrapolate(cells, size)["found_at"] == 1000
    # The page's "never worse" is the default decision's too: its +3 % breaks the bar, the final's 0 % not.
    assert answer.test_value(decided["tests"][0], "r_change_pct_default") == 3.0
    assert "+3.00 % in the rotational segment error (**violated**)" in page.markdown(
        cells, {"sequences": {}, "mean": [0.0] * 3, "spread": [0.0] * 3}, 46_000, 1.0, False)
    assert [answer.percent(v) for v in (-0.001, -0.006, 0.41)] == ["0 %", "-1 %", "41 %"]  # no "-0 %"


def test_no_trend_is_claimed_without_two_crossings() -> None:
    cells = [_cell((64, 96), s, n, 0.1) for s in (1.0, 10.0) for n in (1000, 4000)]
    fit = answer.extrapolate(cells, (64, 96))
    assert fit["slope"] is None and fit["found_at"] is None
    assert "too few N" in page._extrapolation_text(fit, 46_000)
    assert answer.smallest_found(cells) == {((64, 96), 1000): None, ((64, 96), 4000): None}


def test_the_table_says_when_a_final_breaks_the_2_percent_bar() -> None:
    reference = {"sequences": {"00": {"mean": [0, 0, 0.24], "spread": [0.5, 0.8, 0.6]}},
                 "mean": [0.0, 0.0, 0.24], "spread": [0.5, 0.8, 0.6]}
    fine = page.markdown([_cell((64, 96), 1.0, 1000, 0.1, final_change=1.9)], reference, 46_000, 3.0, False)
    assert ("+1.90 % in the rotational segment error (holds) and +0.00 % in the rotational m-ATE (holds)"
            in fine)
    for broken in ({"final_change": 2.5}, {"mate_change": 2.1}):
        text = page.markdown([_cell((64, 96), 1.0, 1000, 0.1, **broken)], reference, 46_000, 3.0, False)
        assert "**violated**" in text


def test_refused_means_worlds_and_the_goal() -> None:
    """A ×1 cell whose earlier decision removed the bias and whose mean the new test refused is listed with
    the p and the pairs the test needs; cells measured in several worlds get their spread; the goal names
    the smallest N of pairs and whether only matched steps reached it."""
    size = (64, 96)
    lost = _cell(size, 1.0, 1000, 0.1, earlier=0.6, p_mean=0.3, needed=2600.0)
    kept = _cell(size, 1.0, 4000, 0.6)
    assert page.refused_means([lost, kept]) == [
        "- world 0, 64×96, N = 1000, ×1, test0: the earlier decision removed 60 %, now 10 %; the mean's p = "
        "0.3 on 400 pairs, about 2,600 pairs would pass it (80 % power)"]
    worlds = page.worlds_table([_cell(size, 3.0, 100, 0.2), _cell(size, 3.0, 100, 0.4, world=1), kept])
    assert "| 64×96 | 100 | ×3 | 20 % | 40 % | 30 % | 20 % – 40 % |" in worlds
    assert page.worlds_table([kept]) is None
    assert page._goal_text([kept]) == "N = 4,000 pairs"
    assert page._goal_text([_cell(size, 1.0, 100, 0.6, matched=True), kept]) == (
        "N = 100 pairs (with the steps of N = 1,000)")
    assert page._goal_text([]) == "not reached at any N of the grid"
    # A --world-seed work folder answers for its own world (its cells first), not for world 0's.
    other = [_cell(size, 1.0, 1000, 0.6, world=2), _cell(size, 1.0, 100, 0.7)]
    assert answer.own_world(other) == other[:1]
    assert "- 64×96: N = 1,000 pairs" in page.markdown(other, {"sequences": {}, "mean": [0.0] * 3,
                                                                "spread": [0.0] * 3}, 46_000, 1.0, False)
    test = type("T", (), {"mean_delta": -1e-5, "std_delta": 1e-4})()
    expected = ((detection.Z_ALPHA + detection.Z_POWER) * 10) ** 2 / detection.WILCOXON_EFFICIENCY
    assert detection.pairs_needed(test) == pytest.approx(expected)
    test.mean_delta = 1e-5
    assert detection.pairs_needed(test) == math.inf


def _decided(cell, **options):
    """``cell`` with each test sequence decided by ``options``: name → (removal, worst change %)."""
    for test in cell["tests"]:
        test["options"] = {name: {"decision": "rotation", "p_whole": 1e-3, "p_mean": None,
                                  "p_remainder": None, "p_whole_judge": 1e-3, "p_mean_judge": 0.02,
                                  "p_remainder_judge": None, "found_axis": removal, "found_seg": removal,
                                  "r_change_pct": change, "mate_r_change_pct": change - 1.0,
                                  "p": {"rotation (judge)": 1e-3, "mean of rotation (judge)": 0.02}}
                           for name, (removal, change) in options.items()}
    return cell


def test_the_rule_picks_the_safe_option_that_removes_most() -> None:
    """docs/method.md §8: an unsafe option is out however much it removes; of two within a point of
    each other the one with the smaller worst change; world 3 only checks, and a failed check keeps
    today's decision; incomplete data choose nothing."""
    size = (64, 96)
    options = {"mean-at-network": (0.30, 0.5), "mean-at-judge": (0.600, 1.0),
               "mean-at-judge-a05": (0.80, 3.0), "mean-noninferior": (0.605, 0.2)}
    cells = [_decided(_cell(size, 1.0, 1000, 0.3, world=w), **options) for w in (0, 1, 2)]
    checked = _decided(_cell(size, 1.0, 1000, 0.3, world=3), **{**options, "mean-noninferior": (0.6, 2.5)})
    expected = {w: {cells[0]["key"]} for w in (0, 1, 2, 3)}
    rows, verdict = rule.apply_rule([*cells, checked], list(options), expected)
    assert verdict.startswith("Chosen on worlds 0–2: mean-noninferior (median removal 60 %), but on world 3 "
                              "its final is +2.50 % above") and "mean-at-network stays the default" in verdict
    passed = _decided(_cell(size, 1.0, 1000, 0.3, world=3), **options)
    verdict = rule.apply_rule([*cells, passed], list(options), expected)[1]
    assert "mean-noninferior" in verdict and "on world 3 at most +0.20 % above the prior" in verdict
    waiting = rule.apply_rule(cells, list(options), expected)[1]
    assert "its check on world 3 waits for 1 of its 1 cells: mean-at-network stays" in waiting
    unlisted = {w: keys for w, keys in expected.items() if w != 3}  # no grid of world 3 given
    assert "its check on world 3 waits for its cells" in rule.apply_rule(cells, list(options), unlisted)[1]
    # The best safe option is more than a point above today's: today's does not stay, even where the tied
    # option with the smaller worst change is within a point of today's.
    near = {"mean-at-network": (0.500, 0.5), "mean-at-judge": (0.515, 1.5), "mean-at-judge-a05": (0.508, 0.5)}
    close_cells = [_decided(_cell(size, 1.0, 1000, 0.3, world=w), **near) for w in (0, 1, 2, 3)]
    assert "Chosen on worlds 0–2: mean-at-judge-a05" in rule.apply_rule(close_cells, list(near), expected)[1]
    by_option = {row[0]: row for row in rows}
    assert by_option["mean-at-judge-a05"][3] == "no" and by_option["mean-at-judge"][3] == "yes"
    assert by_option["mean-noninferior"][2] == "+0.20 %" and by_option["mean-noninferior"][5] == "+2.50 %"
    assert by_option["mean-at-network"][4] == "30 % (of 3)"
    # No option more than a point above today's: today's stays.
    close = {"mean-at-network": (0.60, 0.5), "mean-at-judge": (0.605, 0.1)}
    same = [_decided(_cell(size, 1.0, 1000, 0.3, world=w), **close) for w in (0, 1, 2)]
    assert "than mean-at-network (median 60 %, the largest 60 %): it stays the default" in (
        rule.apply_rule(same, list(close), expected)[1])
    # A cell of a choosing world's grid not decided: the rule waits.
    wider = {**expected, 2: {cells[0]["key"], "64x96_s3_n100"}}
    rows, verdict = rule.apply_rule(cells, list(options), wider)
    assert verdict.startswith("The rule is not applied: 3 of the 4 cells")
    assert "world 2 64x96_s3_n100" in verdict
    text = page.markdown(cells, {"sequences": {}, "mean": [0.0] * 3, "spread": [0.0] * 3}, 46_000, 1.0,
                          False, expected)
    assert "options side by side" in text and "60 %, worst +1.0 / +0.0 %: rotation (mean p 0.02 / –)" in text


def test_the_grid_names_its_training_sequences(script) -> None:
    grid, _ = detection.load_study(script.CONFIG, "cpu", quick=False)
    assert grid.scales == (1.0, 3.0, 10.0) and grid.pairs == (100, 300, 1000, 4000)
    assert grid.train_names(4000) == ("train0", "train1", "train2", "train3")
    assert grid.train_names(100) == ("train0_first100",)
    assert grid.prefixes() == {"train0_first100": 101, "train0_first300": 301}
    # Matched cells train as many steps as N = 1,000 (4 epochs): 40 epochs of 100 pairs, the halving and
    # the warm-up at the same fractions.
    assert grid.matched == (100, 300) and grid.steps_of == 1000
    matched = grid.training_for(100, True)
    assert (matched["epochs"], matched["lr_halving_epochs"], matched["pose_warmup_epochs"]) == (40, 20, 10)
    assert grid.training_for(100, False) == grid.training
    cells = grid.cells()
    assert len(cells) == 2 * 3 * (4 + 2) and cells[0] == ((64, 96), 10.0, 100, False)
    assert cells[1] == ((64, 96), 10.0, 100, True) and detection.cell_key(*cells[1]) == "64x96_s10_n100_steps"
    other, _ = detection.load_study(script.CONFIG, "worlds", quick=False, world_seed=2)
    assert other.seed == grid.seed + 2000 and other.pairs == (100, 1000) and other.matched == ()
    assert list(grid.sequences()) == ["train0", "train1", "train2", "train3", "val", "test0", "test1"]
    with pytest.raises(ValueError, match="neither below nor a multiple"):
        grid.train_names(1500)


def test_restricting_the_grid(script) -> None:
    grid, _ = detection.load_study(script.CONFIG, "cpu", quick=False)
    small = grid.restricted([100, 4000], [(64, 96)], None)
    assert small.pairs == (100, 4000) and small.sizes == ((64, 96),) and small.scales == grid.scales
    assert grid.restricted(None, None, None) == grid
    with pytest.raises(ValueError, match=r"--pairs 1500: not in the grid \(100, 300, 1000, 4000\)"):
        grid.restricted([1500], None, None)
    with pytest.raises(ValueError, match="--sizes 32x48: not in the grid"):
        grid.restricted(None, [(32, 48)], None)


@pytest.mark.slow
def test_the_quick_grid_runs_end_to_end(script, tmp_path: Path, capsys) -> None:
    """The wiring: one cell trained on planted priors, its test corrected, the table, CSV and figure
    written; a rerun reuses the cell; a folder that is not the study's is refused."""
    workdir = tmp_path / "dl"
    workdir.mkdir()
    reference = {"source": "test", "sequences": {"00": {"mean": [0.0, 0.0, 0.25], "spread": [0.5, 0.8, 0.6]}},
                 "mean": [0.0, 0.0, 0.25], "spread": [0.5, 0.8, 0.6]}
    (workdir / "reference.json").write_text(json.dumps(reference))
    (workdir / WORKDIR_MARKER).write_text("")  # the folder is the study's (reference.json made here)
    assert script.main(["--quick", "--workdir", str(workdir)]) == 0
    cell_file, matched_file = sorted((workdir / "cells").glob("*.json"))
    cell, matched = json.loads(cell_file.read_text()), json.loads(matched_file.read_text())
    assert cell["scale"] == 10.0 and cell["pairs"] == 10 and cell["size"] == [32, 80]
    assert cell["bias_mrad"] == pytest.approx(2.5)
    # The matched cell trained as long as 20 pairs would: twice the fixed-epoch cell's steps.
    assert matched["matched"] and matched["steps"] == 2 * cell["steps"]
    [test] = cell["tests"]
    assert test["p_whole"] is not None
    assert test["earlier_decision"] == "none" or test["earlier_decision"].startswith("rotation")
    # The planted prior carries the bias: its mean rotation error is ×10 the reference's, up to the
    # planted noise's sampling error over 8 steps.
    assert test["prior_axis_mrad"] == pytest.approx(2.5, abs=3 * 10 * 0.8 / math.sqrt(8))
    assert test["decision"] in ("none", "full", "rotation") or test["decision"].startswith("rotation_")
    # Every option decided the same proposal with the judge rendered and prepared again (at 32×80).
    assert list(test["options"]) == cell["correction"]["decisions"]
    assert cell["correction"]["judge"] == [32, 80]
    assert all(o["decision"] == "none" or any(n.endswith("(judge)") for n in o["p"])
               for o in test["options"].values())
    assert (workdir / "cache" / "judge_32x80" / "s10" / "test0" / "manifest.json").is_file()
    assert "options side by side" in (workdir / "detection_limit.md").read_text()
    for name in ("detection_limit.md", "detection_limit.csv", "detection_limit.png"):
        assert (workdir / name).stat().st_size > 0
    assert np.loadtxt(workdir / "detection_limit.csv", delimiter=",", skiprows=1, usecols=1).size == 2
    mtime = cell_file.stat().st_mtime_ns
    assert script.main(["--quick", "--workdir", str(workdir)]) == 0
    assert cell_file.stat().st_mtime_ns == mtime
    # Measured with another correction: measured again, its training kept (not retrained).
    cell_file.write_text(json.dumps({**cell, "correction": {"rotation_only": True}}))
    assert script.main(["--quick", "--workdir", str(workdir)]) == 0
    again = json.loads(cell_file.read_text())
    assert again["correction"] == cell["correction"] and again["train_s"] == cell["train_s"]
    assert again["tests"] == cell["tests"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert script.main(["--quick", "--workdir", str(other)]) == 2
    assert "is not the work folder of an experiment script" in capsys.readouterr().err
