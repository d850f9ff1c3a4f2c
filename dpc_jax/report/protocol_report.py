"""The results table of an experiment's folds (:class:`dpc_jax.results.fold.FoldResult`): prior against
corrected per test sequence, as the text of ``results.md`` and ``results.csv``."""

from __future__ import annotations

from collections.abc import Sequence

from dpc_jax.report.tables import EMPTY, csv_text, number, row, rule
from dpc_jax.results.fold import FoldResult

COLUMNS = (
    ("seg_trans_pct", "seg. t (%)"), ("seg_rot_deg_per_100m", "seg. r (°/100 m)"),
    ("m_ate_trans_m", "m-ATE (m)"), ("m_ate_rot_deg", "m-ATE (°)"), ("ate_m", "ATE (m)"),
)


def results_markdown(results: Sequence[FoldResult], title: str, notes: Sequence[str] = ()) -> str:
    """The results table: one row per test sequence and prior, prior → corrected for each metric."""
    header = ["fold", "sequence", "prior", "epoch", "applied", "frames", *(t for _, t in COLUMNS)]
    preamble: list[str | None] = [f"# {title}", "", *(f"{n}" for n in notes), "" if notes else None]
    lines = [x for x in preamble if x is not None]
    lines += [row(header), rule(len(header))]
    for r in results:
        cells = [f"{number(r.metrics['prior'][k])} → {number(r.metrics['corrected'][k])}" for k, _ in COLUMNS]
        lines.append(row([r.fold, r.sequence, r.prior_label, f"{r.epoch} ({r.selection})", r.applied,
                          str(r.frames), *cells]))
    lines += ["", "Each cell: prior → corrected. Segment errors are the mean of the per-length means over "
              f"100–800 m ({EMPTY} when the sequence is shorter than 100 m). applied: which network's "
              "correction the final trajectory holds and what its acceptance test let through (full, "
              "rotation), or prior (no test passed); with the test off, what was applied (test off: forced)."]
    staged = [r for r in results if r.stages]
    if staged:
        lines += ["", "Per network (each row: that network's correction applied, whatever its test said; "
                  "final, earlier decision: the same networks decided without the test of the mean):",
                  "", row(["sequence", "prior", "estimate", "acceptance test", *(t for _, t in COLUMNS)]),
                  rule(4 + len(COLUMNS))]
        for r in staged:
            rows = [("prior", "", r.metrics["prior"])]
            rows += [(f"network {label}", r.decisions[label], m) for label, m in r.stages.items()]
            rows.append((f"final ({r.applied})", "", r.metrics["corrected"]))
            if r.earlier is not None:
                rows.append((f"final, earlier decision ({r.earlier.applied})", "", r.earlier.metrics))
            for label, decision, m in rows:
                cells = [number(m[k]) for k, _ in COLUMNS]
                lines.append(row([r.sequence, r.prior_label, label, decision, *cells]))
    return "\n".join(lines) + "\n"


def results_csv(results: Sequence[FoldResult]) -> str:
    """CSV: one row per test sequence, prior and corrected value of every summary metric."""
    keys = list(results[0].metrics["prior"]) if results else []
    return csv_text(
        ["fold", "sequence", "prior", "epoch", "selection", "applied", "frames",
         *(f"{which}_{k}" for which in ("prior", "corrected") for k in keys)],
        ([r.fold, r.sequence, r.prior_label, r.epoch, r.selection, r.applied, r.frames,
          *(r.metrics[which][k] for which in ("prior", "corrected") for k in keys)] for r in results),
    )
