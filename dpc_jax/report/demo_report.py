"""The synthetic demo's report (``dpc_jax.pipelines.synthetic_demo``): ``OUT/report.md`` with the data
and network overview, each sequence's prior error composition, the test table, the per-length errors, the
training record and the plots, beside the evaluation's CSV and JSON files.

It is built from the demo's summary (``summary.json``: see ``dpc_jax.pipelines.synthetic_demo.run_demo``), the
test sequence's :class:`dpc_jax.eval.evaluation.Evaluation` and the run's ``metrics.csv``; the demo's
and the training's settings are read through :class:`DemoSettings` and :class:`TrainingSettings`.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Protocol

from dpc_jax._io import atomic_write
from dpc_jax.eval.evaluation import Evaluation
from dpc_jax.report.correction_report import AcceptanceResult, applied_words
from dpc_jax.report.evaluation_report import segment_section, write_figures, write_tables
from dpc_jax.report.tables import EMPTY, number, row, rule, table


class DemoSettings(Protocol):
    """What the report reads of a ``dpc_jax.pipelines.synthetic_demo.DemoConfig``."""

    @property
    def render_size(self) -> tuple[int, int]: ...

    @property
    def moving_objects(self) -> int: ...

    @property
    def illumination_drift(self) -> float: ...

    @property
    def noise(self) -> float: ...

    @property
    def disparity_offset(self) -> float: ...

    @property
    def train_sequences(self) -> int: ...

    @property
    def vo_estimate_offset(self) -> bool: ...

    @property
    def rectify_offset(self) -> bool: ...

    @property
    def select(self) -> str: ...

    @property
    def sequences(self) -> dict[str, str]: ...


class TrainingSettings(Protocol):
    """What the report reads of the demo run's ``dpc_jax.training.train_config.TrainConfig``."""

    @property
    def preset(self) -> str: ...

    @property
    def epochs(self) -> int: ...

    @property
    def batch_size(self) -> int: ...

    @property
    def supervision(self) -> str: ...

    @property
    def resolved_image_size(self) -> tuple[int, int]: ...


def _fmt(value: float | None, digits: int = 3) -> str:
    return number(value, f".{digits}f")


def decision_label(acceptance: AcceptanceResult) -> str:
    """What the acceptance test let through, in the words of the test table and the progress lines."""
    if acceptance.forced:
        return "not tested (applied)"
    return "rejected" if acceptance.decision == "none" else f"accepted ({applied_words(acceptance)})"


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


def _results_table(summary: dict[str, Any]) -> str:
    columns = (("seg_trans_pct", "seg. t (%)"), ("seg_rot_deg_per_100m", "seg. r (°/100 m)"),
               ("m_ate_trans_m", "m-ATE (m)"), ("m_ate_rot_deg", "m-ATE (°)"), ("ate_m", "ATE (m)"))
    rows = [("prior (our VO)", "prior", "")]
    labels = (("trained", "network as trained"), ("adapted", "network adapted to the test sequence"))
    for key, label in labels:
        if key in summary["test"]:
            rows.append((f"{label} (epoch {summary['selected_epoch']})", key, summary["decisions"][key]))
    rows.append((f"**final: {summary['final']}** (corrected.txt)", "corrected", summary["choice"]["reason"]))
    return table(["estimate", "acceptance test", *(t for _, t in columns)],
                 ([label, decision, *(_fmt(summary["test"][key][k]) for k, _ in columns)]
                  for label, key, decision in rows))


def _overview(config: DemoSettings, train_config: TrainingSettings, summary: dict[str, Any]) -> list[str]:
    """The report's title and its paragraph on the data, the prior and the network."""
    lengths = ", ".join(f"{n}: {summary['lengths_m'][n]:.0f} m" for n in config.sequences)
    size = train_config.resolved_image_size
    return [
        "# dpc_jax synthetic demo: Stereo DPC corrects a classical stereo VO",
        "",
        f"Synthetic stereo sequences ({config.render_size[0]}×{config.render_size[1]}, 10 Hz) with moving "
        f"cars ({config.moving_objects}), an illumination drift (±{config.illumination_drift:g}), image "
        f"noise (σ = {config.noise:g}) and a stereo calibration residual of {config.disparity_offset:+g} px: "
        f"{config.train_sequences} for training, one for validation (epoch selection), one held-out test "
        f"sequence ({lengths}). Prior: our classical stereo VO with its online disparity-offset estimate "
        f"{'on' if config.vo_estimate_offset else 'off (as libviso2)'}. "
        + ("The network's images are rectified by the residual our VO measures with the estimate on. "
           if config.rectify_offset else "")
        + f"Network: Stereo DPC, `{train_config.preset}` preset, {size[0]}×{size[1]} input, "
        f"{train_config.epochs} epoch(s) of {summary['steps_per_epoch']} steps (batch "
        f"{train_config.batch_size}); epoch {summary['selected_epoch']} selected by `{config.select}`."
        + (" **Trained with DPC-Net's supervised loss: the training steps read the training sequences' "
           "ground truth** (`supervision: supervised`); validation, the acceptance test and the "
           "adaptation do not." if train_config.supervision == "supervised" else ""),
        "",
    ]


def _composition_section(summary: dict[str, Any]) -> list[str]:
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
        _composition_table(summary["sequences"]),
    ]


def _adaptation_paragraph(adaptation: dict[str, Any] | None) -> str:
    """What the adaptation to the test sequence did, or that there was none."""
    if not adaptation:
        return "No adaptation (adapt_steps = 0)."
    return (
        f"Adaptation: {adaptation['steps']} steps on the test sequence's own pairs "
        f"({adaptation['seconds']:.0f} s), every {adaptation['holdout_every']}th pair "
        f"({adaptation['held_out']} pairs) kept out for its "
        "acceptance test; the adapted network is in `adapted/`."
    )


def _test_section(evaluation: Evaluation, summary: dict[str, Any]) -> list[str]:
    """The report's test section: the table, the final trajectory against the prior, the adaptation, the
    per-length errors and the plots."""
    prior, corrected = (summary["test"][k] for k in ("prior", "corrected"))
    change = {k: summary["change_pct"][k] for k in ("seg_trans_pct", "seg_rot_deg_per_100m")}
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
        _adaptation_paragraph(summary.get("adaptation")),
        "",
        *segment_section(evaluation),
        "![trajectories](trajectory.png)",
        "",
        "![segment errors](segment_errors.png)",
        "",
        "![cumulative errors](c_ate.png)",
        "",
    ]


def _training_section(summary: dict[str, Any], run_dir: Path) -> list[str]:
    """The report's training section (per-epoch validation figures), the wall time and the list of files."""
    stages = ", ".join(f"{k} {v:.0f} s" for k, v in summary["seconds"].items())
    return [
        "## Training (validation sequence; ground-truth errors logged, never used)",
        "",
        _epoch_table(run_dir / "metrics.csv", summary["selected_epoch"]),
        f"Wall time: {summary['seconds_total']:.0f} s ({stages}).",
        "",
        "Files: `corrected.txt` (KITTI poses of the final test trajectory), `metrics.csv`, "
        "`segment_errors.csv`, `metrics.json`, `summary.json`, `run/` (checkpoints, metrics.csv, "
        "TensorBoard), `adapted/` (the adapted network, its log), `vo/` (priors and calibration runs), "
        "`data/` (rendered sequences), `cache/`.",
        "",
    ]


def write_demo_report(out: Path, config: DemoSettings, train_config: TrainingSettings, evaluation: Evaluation,
                      summary: dict[str, Any], run_dir: Path) -> Path:
    """``OUT/report.md`` with the tables, the per-length errors, the records and the plots, and beside it
    the plots and the metric files (``metrics.csv``, ``segment_errors.csv``, ``metrics.json``)."""
    write_figures(out, evaluation)
    write_tables(out, evaluation)
    atomic_write(out / "metrics.json", evaluation.to_json())
    text = "\n".join([
        *_overview(config, train_config, summary),
        *_composition_section(summary),
        *_test_section(evaluation, summary),
        *_training_section(summary, run_dir),
    ])
    atomic_write(out / "report.md", text)
    return out / "report.md"
