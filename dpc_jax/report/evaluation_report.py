"""The report of an evaluation against ground truth (:class:`dpc_jax.eval.evaluation.Evaluation`).

Markdown tables of the summary and of the per-length segment errors, their CSV files, the figures
of :mod:`dpc_jax.report.plots`, ``report.md`` with all of them, and evo-readable exports of the
evaluated trajectories.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import cast

import numpy as np

from dpc_jax._io import atomic_write
from dpc_jax.data.poses_io import write_kitti_poses, write_tum
from dpc_jax.eval.diagnosis import AXES, Diagnosis
from dpc_jax.eval.evaluation import GT_LABEL, SUMMARY_KEYS, Evaluation
from dpc_jax.report.tables import EMPTY, csv_text, table

# Column titles of the Markdown table, in the order of SUMMARY_KEYS.
_TITLES = (
    "m-ATE (m)", "m-ATE (°)", "seg. t (%)", "seg. r (°/100 m)", "KITTI t (%)", "KITTI r (°/100 m)",
    "ATE (m)", "RPE t (m)", "RPE r (°)", "loops",
)
# The figures of write_figures, by file name.
TRAJECTORY_PNG, SEGMENT_ERRORS_PNG, C_ATE_PNG = "trajectory.png", "segment_errors.png", "c_ate.png"
# Every file write_report writes, so that a command can check before any work that none of them would
# replace a file it did not make.
REPORT_FILES = ("report.md", "metrics.csv", "segment_errors.csv", TRAJECTORY_PNG, SEGMENT_ERRORS_PNG,
                C_ATE_PNG)


def export_files(labels: list[str]) -> list[str]:
    """The names :func:`export_trajectories` writes for the estimates ``labels`` (and the ground truth)."""
    return [f"{name}{ext}" for name in (GT_LABEL, *labels) for ext in (".kitti.txt", ".tum.txt")]


def association_line(result: Evaluation) -> str | None:
    """One sentence on how the poses were paired by time (None when they were paired by index)."""
    a = result.association
    if a is None:
        return None
    matched, possible = cast(dict[str, int], a["matched"]), cast(dict[str, int], a["possible"])
    counts = ", ".join(f"{label} {matched[label]} of {possible[label]}" for label in matched)
    return (f"Poses paired by time (nearest within {a['max_diff_s']:g} s, estimate times shifted by "
            f"{a['offset_s']:+g} s), matched: {counts}; evaluated: the {a['evaluated']} ground-truth poses "
            "with a partner in every estimate.")


def _fmt(value: float | int | None) -> str:
    if value is None:
        return EMPTY
    if isinstance(value, int):
        return str(value)
    return f"{value:.4g}" if abs(value) < 1e4 else f"{value:.0f}"


def _share(value: float) -> str:
    return EMPTY if math.isnan(value) else f"{100.0 * value:.0f} %"


def format_diagnosis(diagnoses: dict[str, Diagnosis]) -> str:
    """Markdown of :func:`dpc_jax.eval.diagnosis.diagnose`: per estimate, mean ± spread per axis, then
    the drift shares and the pixel shift."""
    units = ("mm", "mm", "mm", "mrad", "mrad", "mrad")
    steps = table(
        ["estimate", "steps", *(f"{a} ({u})" for a, u in zip(AXES, units, strict=True))],
        ([label, str(d.steps), *(f"{m:+.3f} ± {s:.3f} ({e:.3f})"
                                 for m, s, e in zip(d.mean, d.spread, d.standard_error, strict=True))]
         for label, d in diagnoses.items()),
    )
    drift = []
    for label, d in diagnoses.items():
        if d.mean_rot_px is None or d.mean_rot_px_norm is None:
            px = f"{EMPTY} (give --focal)"
        else:
            px = (f"{d.mean_rot_px_norm:.3f} at the centre (φx {d.mean_rot_px[0]:+.3f}, φy "
                  f"{d.mean_rot_px[1]:+.3f}); φz {d.mean_rot_px[2]:+.3f} at f from it (f = {d.focal_px:g})")
        drift.append([label, f"{d.drift_trans_m:.3g}", f"{d.bias_drift_trans_m:.3g}",
                      _share(d.drift_trans_explained), f"{d.drift_rot_deg:.3g}",
                      f"{d.bias_drift_rot_deg:.3g}", _share(d.drift_rot_explained), px])
    return "\n".join([
        "Per-step error (mean ± spread; ± standard error of the mean in brackets):", "", steps.rstrip("\n"),
        "", "End-point drift of the estimate, of the bias-only trajectory (every ground-truth step with the "
        "mean error), and the share of the drift along the bias's own:", "",
        table(["estimate", "position (m)", "bias only (m)", "share explained", "heading (°)", "bias only (°)",
               "share explained", "mean rotation per step (px)"], drift),
    ])


def format_table(result: Evaluation) -> str:
    """Markdown table of the summary, one row per estimate."""
    rows = ([label, *(_fmt(m.summary[k]) for k in SUMMARY_KEYS)] for label, m in result.metrics.items())
    return table(["estimate", *_TITLES], rows)


def format_segment_table(result: Evaluation) -> str:
    """Markdown table of the per-length segment errors (translation % / rotation °/100 m)."""
    lengths = next(iter(result.metrics.values())).seg_lengths_m
    rows = (
        [label, *(EMPTY if np.isnan(t) else f"{t:.3g} / {r:.3g}"
                  for t, r in zip(m.seg_per_length_trans_pct, m.seg_per_length_rot_deg_per_100m,
                                  strict=True))]
        for label, m in result.metrics.items()
    )
    return table(["estimate", *(f"{length:g} m" for length in lengths)], rows)


def segment_section(result: Evaluation) -> list[str]:
    """Report lines: a caption, then :func:`format_segment_table`."""
    return ["Segment errors per length (translation % / rotation °/100 m):", "", format_segment_table(result)]


def metrics_csv(result: Evaluation) -> str:
    """CSV text: header ``label,<SUMMARY_KEYS>``, one row per estimate (empty cell for NaN)."""
    return csv_text(["label", *SUMMARY_KEYS],
                    ([label, *(m.summary[k] for k in SUMMARY_KEYS)] for label, m in result.metrics.items()))


def segment_csv(result: Evaluation) -> str:
    """CSV text: ``label,length_m,count,trans_pct,rot_deg_per_100m``, one row per estimate and length."""
    rows = (
        [label, f"{length:g}", int(count), None if np.isnan(t) else t, None if np.isnan(r) else r]
        for label, m in result.metrics.items()
        for length, count, t, r in zip(
            m.seg_lengths_m, m.seg_counts, m.seg_per_length_trans_pct, m.seg_per_length_rot_deg_per_100m,
            strict=True,
        )
    )
    return csv_text(["label", "length_m", "count", "trans_pct", "rot_deg_per_100m"], rows)


def write_tables(directory: Path, result: Evaluation) -> list[Path]:
    """``metrics.csv`` (:func:`metrics_csv`) and ``segment_errors.csv`` (:func:`segment_csv`) in
    ``directory``."""
    written = []
    for name, text in (("metrics.csv", metrics_csv(result)), ("segment_errors.csv", segment_csv(result))):
        atomic_write(directory / name, text)
        written.append(directory / name)
    return written


def write_figures(directory: Path, result: Evaluation) -> list[Path]:
    """The PNG figures in ``directory``: the trajectories seen from above, the segment errors per
    length (translation and rotation) and the cumulative errors (c-ATE)."""
    # matplotlib is imported only when a report draws: the text outputs do not need it.
    from dpc_jax.report import plots

    return [
        plots.plot_trajectories(directory / TRAJECTORY_PNG, result.gt, result.trajectories),
        plots.plot_segment_errors(directory / SEGMENT_ERRORS_PNG, result.metrics),
        plots.plot_c_ate(directory / C_ATE_PNG, result.metrics),
    ]


def write_report(
    directory: str | Path, result: Evaluation, title: str = "Trajectory evaluation"
) -> list[Path]:
    """Write ``report.md``, ``metrics.csv``, ``segment_errors.csv`` and the PNG plots into ``directory``.

    Plots: ``trajectory.png`` (horizontal plane), ``segment_errors.png`` (per length, translation
    and rotation), ``c_ate.png`` (cumulative errors). Every file is written atomically; the
    directory is created if needed. Returns the written paths.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    settings = [
        f"{result['num_poses']} poses evaluated",
        "static frames removed (ss-DPC-Net rule)" if result.remove_static else "all frames",
        f"ATE alignment: {result.align}",
        f"RPE Δ = {result.rpe_delta} frame(s)",
    ]
    paired = association_line(result)
    report = "\n".join([
        f"# {title}", "", "; ".join(settings) + ".", "", *([paired, ""] if paired else []),
        format_table(result), *segment_section(result),
        *(["## What the error is made of", "", format_diagnosis(result.diagnoses)]
          if result.diagnoses else []),
        f"![trajectories]({TRAJECTORY_PNG})", "", f"![segment errors]({SEGMENT_ERRORS_PNG})", "",
        f"![cumulative error]({C_ATE_PNG})", "",
    ])
    atomic_write(directory / "report.md", report)
    return [directory / "report.md", *write_tables(directory, result), *write_figures(directory, result)]


def export_trajectories(directory: str | Path, result: Evaluation) -> list[Path]:
    """Write the evaluated ground truth and estimates as ``NAME.kitti.txt`` and ``NAME.tum.txt`` (evo).

    ``NAME`` is ``gt`` or the estimate's label (:func:`export_files`). The TUM timestamps are the
    indices of the evaluated frames in the input ground truth, so GT and estimates associate one to one
    in evo.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stamps = result.frames.astype(np.float64)
    written = []
    for name, traj in ((GT_LABEL, result.gt), *result.trajectories.items()):
        write_kitti_poses(directory / f"{name}.kitti.txt", traj)
        write_tum(directory / f"{name}.tum.txt", traj, stamps)
        written += [directory / f"{name}.kitti.txt", directory / f"{name}.tum.txt"]
    return written
