"""The synthetic demo's report (``dpc_jax.pipelines.synthetic_demo``): ``OUT/report.md`` with the data
and network overview, each sequence's prior error composition, the test table, the per-length errors, the
training record and the plots, beside the evaluation's CSV and JSON files.

It is built from the demo's summary (:class:`dpc_jax.results.demo.DemoSummary`), the test sequence's
:class:`dpc_jax.eval.evaluation.Evaluation`, the run's ``metrics.csv`` and the overview paragraph the demo
writes of its own settings.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax._io import atomic_write
from dpc_jax.eval.evaluation import Evaluation
from dpc_jax.report.correction_report import applied_words
from dpc_jax.report.evaluation_report import segment_section, write_figures, write_tables
from dpc_jax.report.tables import EMPTY, number, row, rule, table
from dpc_jax.results.acceptance import Acceptance
from dpc_jax.results.correction import AdaptationSummary
from dpc_jax.results.demo import DemoSummary


def _fmt(value: float | None, digits: int = 3) -> str:
    return number(value, f".{digits}f")


def decision_label(acceptance: Acceptance) -> str:
    """What the acceptance test let through, in the words of the test table and the progress lines."""
    if acceptance.forced:
        return "not tested (applied)"
    return "rejected" if acceptance.part == "none" else f"accepted ({applied_words(acceptance)})"


def _epoch_table(metrics_csv: Path, selected: int) -> str:
    """Markdown table of the run's per-epoch validation figures (the selected epoch marked)."""
    with metrics_csv.open(newline="") as f:
        rows = list(csv.DictReader(f))
    header = ["epoch", "train loss", "val gradient loss", "val r_err prior → corrected (°/100 m)",
              "val t_err prior → corrected (%)"]
    return table(header, (
        [f"{int(r['epoch'])}{' (selected)' if int(r['epoch']) == selected else ''}",
         f"{float(r['train_loss']):.4f}", f"{float(r['val_gradient_loss']):.5f}",
         f"{_fmt(float(r['val_prior_r_err']))} → {_fmt(float(r['val_corrected_r_err']))}",
         f"{_fmt(float(r['val_prior_t_err']), 2)} → {_fmt(float(r['val_corrected_t_err']), 2)}"]
        for r in rows
    ))


def _composition_table(records: dict[str, dict[str, Any]]) -> str:
    axes = ("ρx", "ρy", "ρz", "φx", "φy", "φz")
    header = ["sequence", "fallbacks", "offset measured (px)",
              *(f"{a} mean ± std ({'mm' if a[0] == 'ρ' else 'mrad'})" for a in axes),
              "end-point drift the mean explains (position / heading)", "mean rotation per step (px)"]
    lines = [row(header), rule(len(header))]
    for name, r in records.items():
        error = r["error"]
        cells = [f"{m:+.2f} ± {s:.2f}" for m, s in zip(error["mean"], error["std"], strict=True)]
        shares = " / ".join(
            EMPTY if error.get(k) is None else f"{100 * error[k]:.0f} %"
            for k in ("drift_trans_explained", "drift_rot_explained")
        )
        px = EMPTY if error.get("mean_rot_px_norm") is None else f"{error['mean_rot_px_norm']:.3f}"
        lines.append(row([name, f"{r['fallbacks']}/{r['pairs']}", f"{r['offset']:+.3f}", *cells, shares, px]))
    return "\n".join(lines) + "\n"


def _results_table(summary: DemoSummary) -> str:
    columns = (("seg_trans_pct", "seg. t (%)"), ("seg_rot_deg_per_100m", "seg. r (°/100 m)"),
               ("m_ate_trans_m", "m-ATE (m)"), ("m_ate_rot_deg", "m-ATE (°)"), ("ate_m", "ATE (m)"))
    rows = [("prior (our VO)", "prior", "")]
    labels = (("trained", "network as trained"), ("adapted", "network adapted to the test sequence"))
    for key, label in labels:
        if key in summary.test:
            rows.append((f"{label} (epoch {summary.selected_epoch})", key, summary.decisions[key]))
    reason = "" if summary.choice is None else str(summary.choice["reason"])
    rows.append((f"**final: {summary.final}** (corrected.txt)", "corrected", reason))
    return table(["estimate", "acceptance test", *(t for _, t in columns)],
                 ([label, decision, *(_fmt(summary.test[key][k]) for k, _ in columns)]
                  for label, key, decision in rows))


def _composition_section(summary: DemoSummary) -> list[str]:
    """The report's section on what each sequence's prior error consists of."""
    return [
        "## What the prior's error consists of (ground truth, for this report only)",
        "",
        "Per sequence: constant-velocity fallbacks of the prior's VO, the disparity offset our VO measured, "
        "and the correction each step needs — its mean per frame (systematic: what a correction can learn) "
        "and its spread (random: it averages out over a segment); the share of the end-point drift that the "
        "mean alone produces (the bias-only trajectory's drift projected on the prior's); the mean "
        "rotation's image shift at the principal point at the rendered images' focal length "
        "(`dpc-jax evaluate --diagnose`).",
        "",
        _composition_table(summary.sequences),
    ]


def _adaptation_paragraph(adaptation: AdaptationSummary | None) -> str:
    """What the adaptation to the test sequence did, or that there was none."""
    if not adaptation:
        return "No adaptation (adapt_steps = 0)."
    return (
        f"Adaptation: {adaptation['steps']} steps on the test sequence's own pairs "
        f"({adaptation['seconds']:.0f} s), every {adaptation['holdout_every']}th pair "
        f"({adaptation['held_out']} pairs) kept out for its "
        "acceptance test; the adapted network is in `adapted/`."
    )


def _test_section(evaluation: Evaluation, summary: DemoSummary) -> list[str]:
    """The report's test section: the table, the final trajectory against the prior, the adaptation, the
    per-length errors and the plots."""
    prior, corrected = (summary.test[k] for k in ("prior", "corrected"))
    change = {k: summary.change_pct[k] for k in ("seg_trans_pct", "seg_rot_deg_per_100m")}
    return [
        "## Test sequence",
        "",
        _results_table(summary),
        f"Final trajectory against the prior: translation {_fmt(prior['seg_trans_pct'])} → "
        f"{_fmt(corrected['seg_trans_pct'])} % ({change['seg_trans_pct']:+.1f} %), rotation "
        f"{_fmt(prior['seg_rot_deg_per_100m'])} → {_fmt(corrected['seg_rot_deg_per_100m'])} °/100 m "
        f"({change['seg_rot_deg_per_100m']:+.1f} %). The acceptance test decides without ground truth "
        "(docs/method.md §8); the network rows show each network's proposal whatever its test said.",
        "",
        _adaptation_paragraph(summary.adaptation),
        "",
        *segment_section(evaluation),
        "![trajectories](trajectory.png)",
        "",
        "![segment errors](segment_errors.png)",
        "",
        "![cumulative errors](c_ate.png)",
        "",
    ]


def _training_section(summary: DemoSummary, run_dir: Path) -> list[str]:
    """The report's training section (per-epoch validation figures), the wall time and the list of files."""
    stages = ", ".join(f"{k} {v:.0f} s" for k, v in summary.seconds.items())
    return [
        "## Training (validation sequence; ground-truth errors logged, never used)",
        "",
        _epoch_table(run_dir / "metrics.csv", summary.selected_epoch),
        f"Wall time: {summary.seconds_total:.0f} s ({stages}).",
        "",
        "Files: `corrected.txt` (KITTI poses of the final test trajectory), `metrics.csv`, "
        "`segment_errors.csv`, `metrics.json`, `summary.json`, `run/` (checkpoints, metrics.csv, "
        "TensorBoard), `adapted/` (the adapted network, its log), `vo/` (priors and calibration runs), "
        "`data/` (rendered sequences), `cache/`.",
        "",
    ]


def write_demo_report(out: Path, overview: Sequence[str], evaluation: Evaluation, summary: DemoSummary,
                      run_dir: Path) -> Path:
    """``OUT/report.md`` with the tables, the per-length errors, the records and the plots, and beside it
    the plots and the metric files (``metrics.csv``, ``segment_errors.csv``, ``metrics.json``).
    ``overview``: the report's first lines (title and the paragraph on the data and the network, in the
    demo's words of its own settings)."""
    write_figures(out, evaluation)
    write_tables(out, evaluation)
    atomic_write(out / "metrics.json", evaluation.to_json())
    text = "\n".join([
        *overview,
        *_composition_section(summary),
        *_test_section(evaluation, summary),
        *_training_section(summary, run_dir),
    ])
    atomic_write(out / "report.md", text)
    return out / "report.md"
