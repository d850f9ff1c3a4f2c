"""The results table of an experiment's folds (:class:`dpc_jax.results.fold.FoldResult`): prior against
corrected per test sequence, as the text of ``results.md`` and ``results.csv``."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from dpc_jax.report.tables import EMPTY, change_pct, csv_text, number, row, rule, table
from dpc_jax.results.fold import FoldResult

COLUMNS = (
    ("seg_trans_pct", "seg. t (%)"), ("seg_rot_deg_per_100m", "seg. r (°/100 m)"),
    ("m_ate_trans_m", "m-ATE (m)"), ("m_ate_rot_deg", "m-ATE (°)"), ("ate_m", "ATE (m)"),
)


# The figures of a final trajectory decided by several decisions (``FoldResult.decided``), and those of them
# the rule of docs/method.md §8 checks (its final at most the tolerance above the prior's).
DECIDED_COLUMNS = COLUMNS[:4]
RULE_METRICS = ("seg_rot_deg_per_100m", "m_ate_rot_deg")


def results_markdown(results: Sequence[FoldResult], title: str, notes: Sequence[str] = (), *,
                     tolerance_pct: float) -> str:
    """The results table: one row per test sequence and prior, prior → corrected for each metric; then,
    for results with stages, a row per network; then, for results decided by several decisions, their
    finals (:func:`decisions_markdown` with ``tolerance_pct``)."""
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
        lines += ["", "Per network (each row: that network's correction applied, whatever its test said):",
                  "", row(["sequence", "prior", "estimate", "acceptance test", *(t for _, t in COLUMNS)]),
                  rule(4 + len(COLUMNS))]
        for r in staged:
            rows = [("prior", "", r.metrics["prior"])]
            rows += [(f"network {label}", r.decisions[label], m) for label, m in r.stages.items()]
            rows.append((f"final ({r.applied})", "", r.metrics["corrected"]))
            for label, decision, m in rows:
                cells = [number(m[k]) for k, _ in COLUMNS]
                lines.append(row([r.sequence, r.prior_label, label, decision, *cells]))
    if any(r.decided for r in results):
        names = ["sequence", "prior"], lambda r: [r.sequence, r.prior_label]
        lines += ["", decisions_markdown(results, *names, tolerance_pct).rstrip("\n")]
    return "\n".join(lines) + "\n"


def _change(result: FoldResult, decision: str, key: str) -> float:
    """The change (%) of figure ``key`` of the final decided by ``decision`` against the prior's."""
    return change_pct(result.metrics["prior"][key], result.decided[decision].metrics[key])


def decisions_markdown(results: Sequence[FoldResult], header: Sequence[str],
                       names: Callable[[FoldResult], Sequence[str]], tolerance_pct: float) -> str:
    """The finals of the same networks decided by each decision (``FoldResult.decided``): per test sequence
    (its ``header`` cells given by ``names``) the prior's figures and each decision's final, what it
    applied and its change against the prior (%; none where either lacks the figure), and the figures more
    than ``tolerance_pct`` above the prior's; then per decision whether the rule of docs/method.md §8
    holds (:data:`RULE_METRICS` at most ``tolerance_pct`` above the prior's on every test sequence), with
    the worst change of those figures and of the others."""
    titles = dict(COLUMNS)
    decided = [r for r in results if r.decided]
    rows = []
    for r in decided:
        prior = r.metrics["prior"]
        rows.append([*names(r), "prior", "", *(number(prior[k]) for k, _ in DECIDED_COLUMNS), ""])
        for decision, final in r.decided.items():
            changes = {k: _change(r, decision, k) for k, _ in DECIDED_COLUMNS}
            above = ", ".join(f"{titles[k]} {v:+.1f} %" for k, v in changes.items() if v > tolerance_pct)
            rows.append([*names(r), decision, final.applied,
                         *(number(final.metrics[k]) + (f" ({v:+.1f} %)" if math.isfinite(v) else "")
                           for k, v in changes.items()),
                         above or "none"])
    bar = f"+{tolerance_pct:g} %"
    lines = [f"Every test sequence decided by each decision from the same networks: per final, the figure "
             f"(its change against the prior's); above {bar}: the figures more than {bar} above the prior's.",
             "", table([*header, "decision", "applied", *(t for _, t in DECIDED_COLUMNS), f"above {bar}"],
                       rows),
             f"The rule's check (docs/method.md §8): every final's rotational segment error and rotational "
             f"m-ATE at most {bar} above the prior's, per decision:", ""]

    def worst(decision: str, keys: Sequence[str]) -> str:
        changes = [(_change(r, decision, k), f"{' / '.join(names(r))}, {titles[k]}")
                   for r in decided if decision in r.decided for k in keys]
        value, where = max(((v, w) for v, w in changes if math.isfinite(v)), default=(math.nan, EMPTY))
        return f"{number(value, '+.1f')} % ({where})"

    others = [k for k, _ in DECIDED_COLUMNS if k not in RULE_METRICS]
    for decision in dict.fromkeys(d for r in decided for d in r.decided):
        holds = all(not _change(r, decision, k) > tolerance_pct
                    for r in decided if decision in r.decided for k in RULE_METRICS)
        lines.append(f"* {decision}: {'holds' if holds else 'fails'}; worst rotation change "
                     f"{worst(decision, RULE_METRICS)}, worst translation change {worst(decision, others)}.")
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
