"""What the detection-limit study's cells answer (``dpc_jax.experiments.detection`` makes the cells): the
removal of a cell, the smallest bias removed (:func:`smallest_found`), the scale removed by half
(:func:`half_scale`) and its trend in the training pairs (:func:`extrapolate`); and how the study's pages
write its numbers."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from dpc_jax.correction.decision import DEFAULT_MEAN_TEST

# A removal this large counts as found (the bar).
FOUND = 0.5
# Deliver 3: a final trajectory may not raise the rotational segment error by more than this.
TOLERANCE_PCT = 2.0
# The default decision's figures (``DEFAULT_MEAN_TEST``, with the judge, where the option decided the test
# sequence; a test sequence decided before the options existed has only the study's final), by the name
# a page reads them by: the option's field, the final's.
DEFAULT_REMOVAL = "found_axis_default"
DEFAULT_FIELDS = {DEFAULT_REMOVAL: ("found_axis", "found_axis_final"),
                  "r_change_pct_default": ("r_change_pct", "final_r_change_pct"),
                  "mate_r_change_pct_default": ("mate_r_change_pct", "final_mate_r_change_pct")}


def test_value(test: dict[str, Any], field: str) -> float | None:
    """A test sequence's ``field``, or the default decision's figure named in :data:`DEFAULT_FIELDS`."""
    if field in DEFAULT_FIELDS:
        option, final = DEFAULT_FIELDS[field]
        default = test.get("options", {}).get(DEFAULT_MEAN_TEST)
        return test[final] if default is None else default[option]
    return test[field]


def cell_mean(cell: dict[str, Any], field: str) -> float:
    """The mean of a test record's ``field`` over the cell's test sequences (NaN: none finite);
    :data:`DEFAULT_REMOVAL` reads the default decision's removal."""
    values = [v for v in (test_value(t, field) for t in cell["tests"]) if v is not None and math.isfinite(v)]
    return float(np.mean(values)) if values else math.nan


def own_world(cells: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The cells of the first world among ``cells`` (the tabulating work folder's, whose cells come
    first): the answer and the figure are one world's; the others enter the worlds' spread table."""
    seed = cells[0].get("world_seed", 0) if cells else 0
    return [c for c in cells if c.get("world_seed", 0) == seed]


def smallest_found(cells: Sequence[dict[str, Any]],
                   field: str = DEFAULT_REMOVAL) -> dict[tuple, float | None]:
    """Per (size, pairs): the smallest bias scale removed by at least :data:`FOUND` (None: none)."""
    out: dict[tuple, float | None] = {}
    for cell in cells:
        key = (tuple(cell["size"]), cell["pairs"])
        out.setdefault(key, None)
        if cell_mean(cell, field) >= FOUND:
            found = out[key]
            out[key] = cell["scale"] if found is None else min(found, cell["scale"])
    return out


def half_scale(cells: Sequence[dict[str, Any]], size: tuple[int, int], pairs: int,
               field: str = DEFAULT_REMOVAL) -> tuple[float, str] | None:
    """The bias scale s50 at which the removal crosses :data:`FOUND`, interpolated in log s between the
    grid's scales, as ``(s50, "=")``; ``(smallest scale, "≤")`` when the smallest scale is already
    removed by that much; None when no scale of the grid is."""
    points = sorted((c["scale"], cell_mean(c, field)) for c in cells
                    if tuple(c["size"]) == size and c["pairs"] == pairs)
    if points and math.isfinite(points[0][1]) and points[0][1] >= FOUND:
        return points[0][0], "≤"
    for (s0, f0), (s1, f1) in itertools.pairwise(points):
        if math.isfinite(f0) and math.isfinite(f1) and f0 < FOUND <= f1:
            t = (FOUND - f0) / (f1 - f0)
            return float(math.exp(math.log(s0) + t * (math.log(s1) - math.log(s0)))), "="
    return None


def extrapolate(cells: Sequence[dict[str, Any]], size: tuple[int, int]) -> dict[str, Any]:
    """At ``size``: the smallest N of the grid whose cell at ×1 is removed by :data:`FOUND` or more
    (``found_at``), else the fit ``log s50 = a + b · log N`` over the N with an interpolated crossing and
    the N where it reaches s50 = 1 (``pairs_at_x1``; ``inf`` when s50 does not fall with N)."""
    pairs = sorted({c["pairs"] for c in cells if tuple(c["size"]) == size})
    found = [n for n in pairs for c in cells
             if tuple(c["size"]) == size and c["pairs"] == n and c["scale"] <= 1.0
             and cell_mean(c, DEFAULT_REMOVAL) >= FOUND]
    crossings = {n: half_scale(cells, size, n) for n in pairs}
    points = [(n, h[0]) for n, h in crossings.items() if h is not None and h[1] == "="]
    fit: dict[str, Any] = {"found_at": min(found) if found else None, "points": points, "slope": None,
                           "pairs_at_x1": None}
    if fit["found_at"] is None and len(points) >= 2:
        slope, intercept = np.polyfit(np.log([n for n, _ in points]), np.log([s for _, s in points]), 1)
        fit["slope"] = float(slope)
        fit["pairs_at_x1"] = float(math.exp(-intercept / slope)) if slope < 0 else math.inf
    return fit


def cell_order(c: dict[str, Any]) -> tuple:
    """The order of the tables' rows: by world, size, pairs, matched steps and scale."""
    return (c.get("world_seed", 0), c["size"], c["pairs"], c.get("matched", False), c["scale"])


def percent(value: float) -> str:
    """A removal (a fraction) as a whole percentage, n/a where there is none."""
    # round() gives an int, which has no negative zero: a removal that rounds to zero from below is 0 %.
    return "n/a" if not math.isfinite(value) else f"{round(100 * value)} %"


def p_text(value: float | None) -> str:
    """A test's p to two digits, – where it was not tested."""
    return "–" if value is None else f"{value:.2g}"


def change_text(value: float) -> str:
    """A change against the prior (%), signed, – where there is none."""
    return f"{value:+.2f} %" if math.isfinite(value) else "–"

