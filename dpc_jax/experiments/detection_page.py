"""The detection-limit study's page: one row per cell (:func:`cells_table`), the worlds side by side, the
means the test refused, the answer in words (:func:`markdown`), the long CSV rows (:func:`long_rows`) and
the figure (:func:`figure`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.correction.decision import DEFAULT_MEAN_TEST
from dpc_jax.experiments.detection import FINAL_DECISION
from dpc_jax.experiments.detection_answer import (
    DEFAULT_REMOVAL,
    FOUND,
    TOLERANCE_PCT,
    cell_mean,
    cell_order,
    extrapolate,
    own_world,
    p_text,
    percent,
    smallest_found,
    test_value,
)
from dpc_jax.experiments.detection_rule import OPTION_COLUMNS, options_section
from dpc_jax.report.tables import table

CSV_COLUMNS = ("size", "scale", "pairs", "steps", "world_seed", "sequence", "bias_mrad", "decision",
               "p_whole", "p_mean", "p_remainder", "mean_pairs_needed", "earlier_decision", "prior_axis_mrad",
               "network_axis_mrad", "final_axis_mrad", "earlier_axis_mrad", "prior_r", "network_r", "final_r",
               "earlier_r", "prior_mate_r", "final_mate_r", "earlier_mate_r", "found_axis_network",
               "found_axis_final", "found_axis_earlier", "found_seg_network", "found_seg_final",
               "found_seg_earlier", "final_r_change_pct", "final_mate_r_change_pct", "earlier_r_change_pct",
               "earlier_mate_r_change_pct", "train_s", "epoch", "machine", "commit")


def long_rows(cells: Sequence[dict[str, Any]]) -> list[list[object]]:
    """One row per cell and test sequence: :data:`CSV_COLUMNS`, then :data:`OPTION_COLUMNS`."""
    rows = []
    for c in cells:
        for t in c["tests"]:
            values = {**c, **t, "size": f"{c['size'][0]}x{c['size'][1]}",
                      "world_seed": c.get("world_seed", 0)}
            options = {f"{o}:{k}": v for o, fields in t.get("options", {}).items() for k, v in fields.items()}
            rows.append([values.get(k) for k in CSV_COLUMNS] + [options.get(k) for k in OPTION_COLUMNS])
    return rows


def cells_table(cells: Sequence[dict[str, Any]]) -> str:
    """One row per cell: the removal (network, final, earlier decision), what was applied with each test's
    p, and the final's change of the rotational segment error and m-ATE against the prior."""
    return table(
        ["world", "size", "N pairs", "steps", "bias ×", "removed: network (axis / seg.)",
         "final", "earlier decision", "applied (p whole / mean / remainder)", "final r, m-ATE r vs prior",
         "earlier r, m-ATE r", "train (min)", "machine"],
        ([str(c.get("world_seed", 0)), f"{c['size'][0]}×{c['size'][1]}", str(c["pairs"]),
          f"{c.get('steps', '?')}" + (" (matched)" if c.get("matched") else ""), f"×{c['scale']:g}",
          f"{percent(cell_mean(c, 'found_axis_network'))} / {percent(cell_mean(c, 'found_seg_network'))}",
          f"{percent(cell_mean(c, 'found_axis_final'))} / {percent(cell_mean(c, 'found_seg_final'))}",
          f"{percent(cell_mean(c, 'found_axis_earlier'))} / {percent(cell_mean(c, 'found_seg_earlier'))}",
          "; ".join(f"{t['decision']} ({p_text(t['p_whole'])} / {p_text(t['p_mean'])} / "
                    f"{p_text(t['p_remainder'])})" for t in c["tests"]),
          "; ".join(f"{t['final_r_change_pct']:+.1f}, {t['final_mate_r_change_pct']:+.1f} %"
                    for t in c["tests"]),
          "; ".join(f"{t['earlier_r_change_pct']:+.1f}, {t['earlier_mate_r_change_pct']:+.1f} %"
                    for t in c["tests"]),
          f"{c['train_s'] / 60:.1f}", c["machine"]] for c in sorted(cells, key=cell_order)))


def worlds_table(cells: Sequence[dict[str, Any]]) -> str | None:
    """The removal (axis, the default decision) of each (size, N, steps, scale) measured in more than one
    world: per world, and the mean and spread (min–max) over them; None when no cell is."""
    groups: dict[tuple, dict[int, float]] = {}
    for c in cells:
        key = (tuple(c["size"]), c["pairs"], bool(c.get("matched")), c["scale"])
        groups.setdefault(key, {})[c.get("world_seed", 0)] = cell_mean(c, DEFAULT_REMOVAL)
    shared = {k: v for k, v in groups.items() if len(v) > 1}
    if not shared:
        return None
    worlds = sorted({w for v in shared.values() for w in v})
    return table(
        ["size", "N pairs", "bias ×", *(f"world {w}" for w in worlds), "mean", "spread (min–max)"],
        ([f"{k[0][0]}×{k[0][1]}", f"{k[1]}" + (" (matched steps)" if k[2] else ""), f"×{k[3]:g}",
          *(percent(v[w]) if w in v else "–" for w in worlds), percent(float(np.mean(list(v.values())))),
          f"{percent(min(v.values()))} – {percent(max(v.values()))}"] for k, v in sorted(shared.items())))


def refused_means(cells: Sequence[dict[str, Any]]) -> list[str]:
    """The test sequences where the earlier decision removed at least :data:`FOUND` of the bias and the
    mean test refused the mean: the p it got and the pairs its power would need."""
    lines = []
    for c in sorted(cells, key=cell_order):
        for t in c["tests"]:
            lost = t["found_axis_earlier"] >= FOUND and t["found_axis_final"] < t["found_axis_earlier"] - 0.05
            if lost and t["p_mean"] is not None:
                needed = t["mean_pairs_needed"]
                lines.append(
                    f"- world {c.get('world_seed', 0)}, {c['size'][0]}×{c['size'][1]}, N = {c['pairs']}, "
                    f"×{c['scale']:g}, {t['sequence']}: the earlier decision removed "
                    f"{percent(t['found_axis_earlier'])}, now {percent(t['found_axis_final'])}; the mean's "
                    f"p = {t['p_mean']:.2g} on {t['mean_test_pairs']} pairs, "
                    + ("its differences' mean is not below 0: no number of pairs passes it" if not
                       math.isfinite(needed) else f"about {needed:,.0f} pairs would pass it (80 % power)"))
    return lines


def markdown(cells: Sequence[dict[str, Any]], reference: dict[str, Any], paper_pairs: int, minutes: float,
             quick: bool, expected: dict[int, set[str]] | None = None) -> str:
    per_machine: dict[str, float] = {}
    for c in cells:
        per_machine[c["machine"]] = per_machine.get(c["machine"], 0.0) + c["train_s"] / 60
    trained = "; ".join(f"{m:.0f} min on {name}" for name, m in per_machine.items()) or "none"
    values = {field: [test_value(t, field) for c in cells for t in c["tests"]]
              for field in ("r_change_pct_default", "mate_r_change_pct_default", "earlier_r_change_pct",
                            "earlier_mate_r_change_pct")}
    worst = {field: max((v for v in vs if v is not None and math.isfinite(v)), default=math.nan)
             for field, vs in values.items()}
    base = own_world(cells)
    fixed = [c for c in base if not c.get("matched")]
    smallest = smallest_found(fixed)
    lines = [f"- {s[0]}×{s[1]}, N = {n}: " + ("none of the grid's biases" if v is None else f"×{v:g}")
             for (s, n), v in sorted(smallest.items())]
    answer = [f"- {s[0]}×{s[1]}: " + _extrapolation_text(extrapolate(fixed, s), paper_pairs)
              for s in sorted({tuple(c["size"]) for c in fixed})]
    at_x1 = [c for c in base if c["scale"] <= 1.0 and cell_mean(c, DEFAULT_REMOVAL) >= FOUND]
    goal = [f"- {s[0]}×{s[1]}: " + _goal_text([c for c in at_x1 if tuple(c["size"]) == s])
            for s in sorted({tuple(c["size"]) for c in base})]
    ref = reference
    worlds = worlds_table(cells)
    refused = refused_means(cells)

    def verdict(value: float) -> str:
        return "holds" if not value > TOLERANCE_PCT else "**violated**"

    return "\n".join([
        "# How small an error self-supervision can find" + (" (QUICK RUN: wiring only)" if quick else ""), "",
        f"Reference ×1 (libviso2-s, median over {', '.join(ref['sequences'])} of `evaluate --diagnose`): "
        f"rotation bias per step {_vec(ref['mean'])} mrad (‖·‖ {np.linalg.norm(ref['mean']):.3f}), spread "
        f"{_vec(ref['spread'])} mrad (camera x, y, z: pitch, yaw, roll). A cell's prior carries s times "
        f"both. Removed: 1 − after / prior of the mean per-axis rotation error per step (axis) and of the "
        f"rotational segment error (seg.), mean over the {len(cells[0]['tests']) if cells else 0} held-out "
        f"test sequences; network = the proposal applied whatever its tests said; final = behind the "
        f"acceptance tests at the network's size (no judge), the correction's mean tested on its own there "
        f"({FINAL_DECISION}); earlier decision = the same proposal "
        f"behind the earlier tests (the mean not tested apart). Applied: what the tests let through "
        f"(`− mean`: without its mean), with the p of the whole rotation, of its mean and of its remainder "
        f"(– where not tested). Steps: the optimizer steps the network trained for (matched: a small N "
        f"trained as long as N = 1,000). This invocation ran {minutes:.0f} min (cells it found done are not "
        f"counted); training summed over the cells: {trained}.", "",
        cells_table(cells),
        "![Removal against N and against the bias](detection_limit.png)", "",
        *(["Removal (axis, the default decision) in the worlds measured:", "", worlds] if worlds else []),
        f"Never worse: the worst change of the default decision ({DEFAULT_MEAN_TEST}) against the prior over "
        f"every cell and test sequence is {worst['r_change_pct_default']:+.2f} % in the rotational segment "
        f"error ({verdict(worst['r_change_pct_default'])}) and {worst['mate_r_change_pct_default']:+.2f} % "
        f"in the rotational m-ATE ({verdict(worst['mate_r_change_pct_default'])}), the bar being "
        f"{TOLERANCE_PCT:g} %; "
        f"with the earlier decision {worst['earlier_r_change_pct']:+.2f} % and "
        f"{worst['earlier_mate_r_change_pct']:+.2f} %.", "",
        "Where the earlier decision removed half the bias or more and the final's mean test (at the "
        "network's size) refused the mean:",
        *(refused or ["- nowhere."]), "",
        f"The default decision ({DEFAULT_MEAN_TEST}; with the judge where the option decided the cell): "
        f"libviso2-s's bias (×1) removed by ≥ {100 * FOUND:.0f} % (axis) at the smallest N of pairs:",
        *goal, "",
        f"Smallest bias removed by ≥ {100 * FOUND:.0f} % (axis, the default decision; fixed epochs) at each "
        "(N, resolution):", *lines, "",
        "The N at which libviso2-s's bias (×1) is removed by half (the default decision, fixed epochs; else "
        "a fit of log s50 against log N over the grid's N, s50 interpolated in log s):", *answer, "",
        *options_section(cells, expected or {})])


def _goal_text(found: Sequence[dict[str, Any]]) -> str:
    """The smallest N of pairs among ``found`` (cells at ×1 removed by half), and whether only a cell
    trained with a larger N's steps reached it there."""
    if not found:
        return "not reached at any N of the grid"
    smallest = min(c["pairs"] for c in found)
    matched_only = all(c.get("matched") for c in found if c["pairs"] == smallest)
    return f"N = {smallest:,} pairs" + (" (with the steps of N = 1,000)" if matched_only else "")


def _vec(values: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:+.3f}" for v in values) + ")"


def _extrapolation_text(fit: dict[str, Any], paper_pairs: int) -> str:
    points = ", ".join(f"N {n}: ×{s:.2g}" for n, s in fit["points"]) or "none inside the grid"
    if fit["found_at"] is not None:
        return (f"already removed by ≥ {100 * FOUND:.0f} % at ×1 with N = {fit['found_at']:,} (the grid's "
                f"smallest such N; within the papers' {paper_pairs:,} pairs)")
    if fit["slope"] is None:
        return f"too few N with a 50 % crossing inside the grid to fit a trend (crossings: {points})"
    n1 = fit["pairs_at_x1"]
    if not math.isfinite(n1):
        return (f"s50 does not fall with N ({points}; slope {fit['slope']:+.2f}): more pairs alone do not "
                "reach ×1")
    verdict = "within" if n1 <= paper_pairs else "beyond"
    return (f"s50 ∝ N^{fit['slope']:+.2f} ({points}); ×1 at N ≈ {n1:,.0f}, {verdict} the papers' "
            f"{paper_pairs:,} pairs")


def figure(cells: Sequence[dict[str, Any]], reference: dict[str, Any], path: Path) -> None:
    """Left: removal (axis, final) against N, one curve per resolution and scale. Right: removal against
    the bias (mrad/step), one curve per resolution and N, with libviso2-s's per-sequence biases marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    matched = [c for c in own_world(cells) if c.get("matched")]
    cells = [c for c in own_world(cells) if not c.get("matched")]
    sizes = sorted({tuple(c["size"]) for c in cells})
    styles = dict(zip(sizes, ("o-", "s--", "^:"), strict=False))
    for size in sizes:
        for scale in sorted({c["scale"] for c in cells}):
            pts = sorted((c["pairs"], cell_mean(c, "found_axis_network"), cell_mean(c, DEFAULT_REMOVAL))
                         for c in cells if tuple(c["size"]) == size and c["scale"] == scale)
            if pts:
                line, = left.plot([p[0] for p in pts], [p[2] for p in pts], styles[size],
                                  label=f"{size[0]}×{size[1]}, ×{scale:g}")
                left.plot([p[0] for p in pts], [p[1] for p in pts], "x", color=line.get_color())
                steps = sorted((c["pairs"], cell_mean(c, DEFAULT_REMOVAL)) for c in matched
                               if tuple(c["size"]) == size and c["scale"] == scale)
                left.plot([p[0] for p in steps], [p[1] for p in steps], "*", color=line.get_color(), ms=9)
        for pairs in sorted({c["pairs"] for c in cells}):
            by_bias = sorted((c["bias_mrad"], cell_mean(c, DEFAULT_REMOVAL)) for c in cells
                             if tuple(c["size"]) == size and c["pairs"] == pairs)
            if not by_bias:
                continue
            right.plot([p[0] for p in by_bias], [p[1] for p in by_bias], styles[size],
                       label=f"{size[0]}×{size[1]}, N {pairs}")
    for name, seq in reference["sequences"].items():
        bias = float(np.linalg.norm(seq["mean"]))
        right.axvline(bias, color="grey", lw=0.6, alpha=0.6)
        right.text(bias, 1.02, name, fontsize=6, rotation=90, va="bottom", ha="center",
                   transform=right.get_xaxis_transform())
    for ax in (left, right):
        ax.axhline(FOUND, color="k", lw=0.6, ls="--")
        ax.set_ylabel("bias removed (1 − ‖mean after‖ / ‖mean prior‖)")
        ax.set_xscale("log")
        if ax.get_legend_handles_labels()[0]:  # a grid with one N draws no curve on the right
            ax.legend(fontsize=7)
    # Two lines: on one the label runs under the right panel's.
    left.set_xlabel(f"training pairs N\nline: the default decision, {DEFAULT_MEAN_TEST}; x: the network's "
                    "proposal; *: the default with N = 1,000's steps", fontsize=8)
    right.set_xlabel("planted bias (mrad per step); grey: libviso2-s on KITTI 00–10")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
