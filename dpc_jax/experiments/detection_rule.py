"""Where the correction's mean is tested: the options side by side over the detection-limit study's cells,
and the rule of ``docs/method.md`` §8 (stated before the options' results) that chooses among them."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from dpc_jax.correction.decision import MEAN_TESTS
from dpc_jax.experiments.detection_answer import TOLERANCE_PCT, cell_order, change_text, p_text, percent
from dpc_jax.report.tables import table

# Per option of where the mean is tested (``options`` of a test's record), ``OPTION:FIELD`` columns.
OPTION_FIELDS = ("decision", "p_whole", "p_mean", "p_remainder", "p_whole_judge", "p_mean_judge",
                 "p_remainder_judge", "found_axis", "found_seg", "r_change_pct", "mate_r_change_pct")
OPTION_COLUMNS = tuple(f"{option}:{field}" for option in MEAN_TESTS for field in OPTION_FIELDS)
# The rule of docs/method.md §8 (stated before the options' results): the worlds it chooses on, the one
# that checks the choice, the cells whose median removal it compares, and a tie.
CHOOSING_WORLDS, CHECKING_WORLD = (0, 1, 2), 3
RULE_CELLS = {"size": (64, 96), "scale": 1.0, "pairs": 1000}
TIE_POINTS = 1.0
# Option (a), today's decision when the rule was stated: what stays unless another option wins.
BASELINE = "mean-at-network"


def _worst(records: Sequence[dict[str, Any]], field: str) -> float:
    """The largest finite ``field`` of ``records`` (−inf when none has one: a sequence shorter than 100 m
    has no segment error, and raises nothing)."""
    return max((r[field] for r in records if r[field] is not None and math.isfinite(r[field])),
               default=-math.inf)


def _finite_mean(values: Sequence[float]) -> float:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def decided_by(cells: Sequence[dict[str, Any]], option: str) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(cell, the option's record of one test sequence) for every test sequence ``option`` decided."""
    return [(c, t["options"][option]) for c in cells for t in c["tests"] if option in t.get("options", {})]


def _applied_mean_p(decided: dict[str, Any], suffix: str) -> str:
    """The p of the mean's test of the applied component (the whole rotation's when nothing is applied)
    at one size (``suffix``: " (judge)" or ""), – where it was not tested there."""
    component = decided["decision"].split(" ")[0]
    name = "mean of " + ("rotation" if component == "none" else component) + suffix
    return p_text(decided["p"].get(name))


def options_table(cells: Sequence[dict[str, Any]], options: Sequence[str]) -> str:
    """One row per cell decided by the options: per option the removal (axis, mean over the test
    sequences), the largest change of the rotational segment error and m-ATE against the prior, and per
    test sequence what was applied with the p of the mean at the judge's size (and at the network's)."""
    def entry(c: dict[str, Any], option: str) -> str:
        decided = [t["options"][option] for t in c["tests"] if option in t.get("options", {})]
        if not decided:
            return "–"
        axis = _finite_mean([d["found_axis"] for d in decided])
        worst = _worst(decided, "r_change_pct"), _worst(decided, "mate_r_change_pct")
        parts = "; ".join(f"{d['decision']} (mean p {_applied_mean_p(d, ' (judge)')} / "
                          f"{_applied_mean_p(d, '')})" for d in decided)
        return f"{percent(axis)}, worst {worst[0]:+.1f} / {worst[1]:+.1f} %: {parts}"

    rows = [c for c in sorted(cells, key=cell_order) if any(t.get("options") for t in c["tests"])]
    return table(["world", "size", "N pairs", "steps", "bias ×", *options],
                 ([str(c.get("world_seed", 0)), f"{c['size'][0]}×{c['size'][1]}", str(c["pairs"]),
                   f"{c.get('steps', '?')}" + (" (matched)" if c.get("matched") else ""), f"×{c['scale']:g}",
                   *(entry(c, o) for o in options)] for c in rows))


def apply_rule(cells: Sequence[dict[str, Any]], options: Sequence[str],
               expected: dict[int, set[str]]) -> tuple[list[list[str]], str]:
    """The rule of ``docs/method.md`` §8 on ``cells``: per option its worst final change (rotational
    segment error, rotational m-ATE) over the choosing worlds, whether that is within
    :data:`TOLERANCE_PCT`, the median removal of its :data:`RULE_CELLS`, the worst change on the checking
    world; and the verdict: the option chosen and whether its check on world 3 holds, or why none is
    chosen yet (``expected``: per world the keys of its grid's cells, every one of which must be decided
    by every option of ``options``)."""
    choosing = [c for c in cells if c.get("world_seed", 0) in CHOOSING_WORLDS]
    checking = [c for c in cells if c.get("world_seed", 0) == CHECKING_WORLD]
    rows, measured = [], {}
    for option in options:
        decided = decided_by(choosing, option)
        records = [d for _, d in decided]
        worst = max(_worst(records, "r_change_pct"), _worst(records, "mate_r_change_pct"))
        removal = [d["found_axis"] for c, d in decided
                   if tuple(c["size"]) == RULE_CELLS["size"] and c["scale"] == RULE_CELLS["scale"]
                   and c["pairs"] == RULE_CELLS["pairs"] and not c.get("matched")]
        median = float(np.median(removal)) if removal else math.nan
        checked = [d for _, d in decided_by(checking, option)]
        check = max(_worst(checked, "r_change_pct"), _worst(checked, "mate_r_change_pct"))
        measured[option] = (worst, median, check)
        rows.append([option, str(len(decided)), change_text(worst), "yes" if worst <= TOLERANCE_PCT else "no",
                     f"{percent(median)} (of {len(removal)})", change_text(check)])
    missing = _undecided(cells, options, expected, CHOOSING_WORLDS)
    if missing:
        total = sum(len(expected.get(w, ())) for w in CHOOSING_WORLDS)
        return rows, (f"The rule is not applied: {total - len(missing)} of the {total} cells of worlds "
                      f"{', '.join(map(str, CHOOSING_WORLDS))} are decided by every option (missing: "
                      + ", ".join(f"world {w} {k}" for w, k in missing[:8])
                      + (", …" if len(missing) > 8 else "") + f"); {BASELINE} stays the default.")
    safe = {o: v for o, v in measured.items() if v[0] <= TOLERANCE_PCT and math.isfinite(v[1])}
    if not safe:
        return rows, f"No option is safe on worlds 0–2; {BASELINE} stays the default."
    best = max(v[1] for v in safe.values())
    if BASELINE in safe and 100 * (best - safe[BASELINE][1]) <= TIE_POINTS:
        return rows, (f"No safe option removes more than {TIE_POINTS:g} point more than {BASELINE} (median "
                      f"{percent(safe[BASELINE][1])}, the largest {percent(best)}): it stays the default.")
    tied = [o for o, v in safe.items() if 100 * (best - v[1]) <= TIE_POINTS]
    chosen = min(tied, key=lambda o: safe[o][0])
    said = f"Chosen on worlds 0–2: {chosen} (median removal {percent(safe[chosen][1])})"
    unchecked = _undecided(cells, [chosen], expected, (CHECKING_WORLD,))
    check = safe[chosen][2]
    if unchecked or not math.isfinite(check):
        waits = (f"{len(unchecked)} of its {len(expected.get(CHECKING_WORLD, ()))} cells" if unchecked
                 else "its cells")
        return rows, (f"{said}; its check on world {CHECKING_WORLD} waits for {waits}: {BASELINE} stays the "
                      "default until then.")
    if not check <= TOLERANCE_PCT:
        return rows, (f"{said}, but on world {CHECKING_WORLD} its final is {change_text(check)} above the "
                      f"prior's (the bar: +{TOLERANCE_PCT:g} %): not adopted, {BASELINE} stays the default.")
    return rows, (f"{said}; on world {CHECKING_WORLD} at most {change_text(check)} above the prior "
                  f"(within +{TOLERANCE_PCT:g} %): adopted if the real drives and the excerpt hold too (the "
                  "rule's check on their pages).")


def _undecided(cells: Sequence[dict[str, Any]], options: Sequence[str], expected: dict[int, set[str]],
               worlds: Sequence[int]) -> list[tuple[int, str]]:
    """``(world, key)`` of the cells of ``expected``'s grids of ``worlds`` not decided by every option."""
    have = {(c.get("world_seed", 0), c["key"]) for c in cells
            if all(o in t.get("options", {}) for t in c["tests"] for o in options)}
    return [(w, k) for w in worlds for k in sorted(expected.get(w, ())) if (w, k) not in have]


def options_section(cells: Sequence[dict[str, Any]], expected: dict[int, set[str]]) -> list[str]:
    """The options of where the mean is tested side by side, and the rule's verdict (none decided: [])."""
    if not any(decided_by(cells, o) for o in MEAN_TESTS):
        return []
    # Every option, so that one decided nowhere holds the rule back instead of dropping out of it.
    options = list(MEAN_TESTS)
    rows, verdict = apply_rule(cells, options, expected)
    judges = ", ".join(sorted({"×".join(map(str, c["correction"]["judge"])) for c in cells
                               if (c.get("correction") or {}).get("judge")})) or "–"
    return [
        "### Where the mean is tested: the options side by side (docs/method.md §8)", "",
        "Every option decides the same proposal with the judge at the test sequences rendered again at "
        f"{judges} (the same poses). Per option: the removal (axis, mean over the test "
        "sequences), the largest change of the rotational segment error / rotational m-ATE against the "
        "prior, and per test sequence what was applied with the p of the mean's test at the judge's size "
        "/ at the network's (– where not tested).", "",
        options_table(cells, options),
        table(["option", "test sequences decided (worlds 0–2)", "worst final change (r or m-ATE)",
               f"safe (≤ +{TOLERANCE_PCT:g} %)", "median removal, ×1, N = 1,000, 64×96",
               f"worst on world {CHECKING_WORLD} (check)"], rows),
        verdict, ""]

