"""The table of ``experiments/studies/supervised_comparison.py``: per test (a demo seed's test sequence, a
real drive) the prior, the supervised linear baselines and two networks (trained with DPC-Net's supervised
loss, and self-supervised), each as trained, adapted and final, and the change against the prior over the
demo seeds."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dpc_jax.experiments.drives import METRICS, TITLES
from dpc_jax.report.tables import EMPTY, change_pct, csv_text, number, table
from dpc_jax.results.demo import DemoSummary
from dpc_jax.results.fold import FoldResult

CHANGED = METRICS[:4]  # the metrics whose change against the prior the summary gives
# Row kinds in table order → their label (supervised rows say so: they read ground truth to train).
KINDS = {
    "prior": "prior (our VO)",
    "linear": "linear baseline, **supervised** (rotation)",
    "constant": "constant bias, **supervised** (rotation)",
    "supervised_trained": "network, **supervised**: trained",
    "supervised_adapted": "network, **supervised**: adapted (self-supervised)",
    "supervised_final": "network, **supervised**: final",
    "self_trained": "network, self-supervised: trained",
    "self_adapted": "network, self-supervised: adapted",
    "self_final": "network, self-supervised: final",
}
Metrics = dict[str, float | None]


@dataclass(frozen=True)
class Row:
    """One row: a test, what its networks trained on, the row kind (:data:`KINDS`), the acceptance decision
    (empty for the prior) and the metrics (None where undefined, e.g. segments of a test under 100 m)."""

    test: str
    trained_on: str
    kind: str
    decision: str
    metrics: Metrics


def metrics_of(summary: Mapping[str, Any]) -> Metrics:
    """The table's metrics of an estimate's summary: NaN and missing as None."""
    return {k: None if summary.get(k) is None or math.isnan(summary[k]) else float(summary[k])
            for k in METRICS}


def rows_of(test: str, trained_on: str, prior: Metrics, baselines: Mapping[str, Metrics],
            networks: Mapping[str, Mapping[str, tuple[str, Metrics]]]) -> list[Row]:
    """A test's rows: the prior, the baselines (``linear``, ``constant``) and each network's (``supervised``,
    ``self``: stage → (decision, metrics)) trained, adapted and final."""
    rows = [Row(test, trained_on, "prior", "", prior)]
    rows += [Row(test, trained_on, kind, "applied (no test)", baselines[kind])
             for kind in ("linear", "constant")]
    for network, stages in networks.items():
        rows += [Row(test, trained_on, f"{network}_{label}", *stages[label])
                 for label in ("trained", "adapted", "final") if label in stages]
    return rows


def demo_stages(summary: DemoSummary) -> dict[str, tuple[str, Metrics]]:
    """A demo's network rows: trained and adapted with their decisions, final with the network it kept."""
    stages: dict[str, tuple[str, Metrics]] = {
        label: (summary.decisions.get(label, ""), metrics_of(summary.test[label]))
        for label in ("trained", "adapted") if label in summary.test}
    final = summary.final
    final = final if final == "prior" else f"{final}: {summary.decisions[final]}"
    return {**stages, "final": (final, metrics_of(summary.test["corrected"]))}


def fold_stages(result: FoldResult) -> dict[str, tuple[str, Metrics]]:
    """A drive's network rows: trained and adapted with their decisions, final with what it applied."""
    stages = {label: (result.decisions[label], metrics_of(m)) for label, m in result.stages.items()}
    return {**stages, "final": (result.applied, metrics_of(result.metrics["corrected"]))}


def change_summary(rows: Sequence[Row]) -> list[str]:
    """Markdown lines: per row kind, the best and worst change against the prior (%) over the demo seeds in
    ``rows``, per metric of :data:`CHANGED` (with the seed), empty where no seed has it."""
    priors = {r.test: r.metrics for r in rows if r.kind == "prior" and r.test.startswith("demo ")}
    if not priors:
        return []
    seeds = ", ".join(t.removeprefix("demo seed ") for t in priors)
    cells_of = []
    for kind, label in KINDS.items():
        own = [r for r in rows if r.kind == kind and r.test in priors]
        if kind == "prior" or not own:
            continue
        cells = []
        for key in CHANGED:
            changes = [(c, r.test.removeprefix("demo seed ")) for r in own
                       if not math.isnan(c := change_pct(priors[r.test][key], r.metrics[key]))]
            if not changes:
                cells.append(EMPTY)
                continue
            (best, at_best), (worst, at_worst) = min(changes), max(changes)
            cells.append(f"{best:+.1f} % ({at_best}) … {worst:+.1f} % ({at_worst})")
        cells_of.append([label, *cells])
    return [f"Change against the prior over the demo seeds ({seeds}): best … worst, with the seed.", "",
            *table(["row", *TITLES[: len(CHANGED)]], cells_of).splitlines()]


def comparison_markdown(rows: Sequence[Row], notes: Sequence[str]) -> str:
    """The table (one line per :class:`Row`), the notes above it, the change summary below it."""
    body = table(["test", "trained on", "row", "decision", *TITLES],
                 ([r.test, r.trained_on, KINDS[r.kind], r.decision, *(number(r.metrics[k]) for k in METRICS)]
                  for r in rows))
    lines = ["# Prior → linear baseline → supervised network → self-supervised network", "", *notes, "",
             *body.splitlines()]
    summary = change_summary(rows)
    if summary:
        lines += ["", *summary]
    return "\n".join(lines) + "\n"


def comparison_csv(rows: Sequence[Row]) -> str:
    """Long form: one line per :class:`Row` (``row`` = its kind), empty cells for undefined metrics."""
    return csv_text(("test", "trained_on", "row", "decision", *METRICS),
                    ([r.test, r.trained_on, r.kind, r.decision, *(r.metrics[k] for k in METRICS)]
                     for r in rows))
