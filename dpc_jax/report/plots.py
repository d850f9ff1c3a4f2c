"""PNG plots of evaluations (matplotlib's Agg canvas, no pyplot state; files written atomically).

* :func:`plot_trajectories` — ground truth and estimates seen from above. KITTI's camera frame
  has y pointing down, so "above" is the x–z plane; trajectories in a z-up frame (the OXTS/IMU
  frame of some releases) would collapse there, so the plane is the one spanned by the two axes
  along which the ground truth extends most, and the axes are labelled accordingly. The subtitle
  says how the estimates were placed (by default: started at the first ground-truth pose, not
  aligned — the trajectories of :func:`dpc_jax.eval.evaluation.evaluate`).
* :func:`plot_segment_errors` — per-length translation (%) and rotation (°/100 m) errors; a
  sequence too short for the shortest length gets a note instead of empty axes.
* :func:`plot_c_ate` — cumulative translation (m) and rotation (°) errors (c-ATE) per frame; the
  subtitle defines "cumulative".
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from dpc_jax._io import atomic_write
from dpc_jax.eval.evaluation import EstimateMetrics

_AXES = "xyz"
_DPI = 120
ANCHORED = "estimates start at the first ground-truth pose; not aligned"


def _save(figure: Figure, path: str | Path) -> Path:
    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=_DPI)
    atomic_write(path, buffer.getvalue())
    return Path(path)


def horizontal_axes(positions: np.ndarray) -> tuple[int, int]:
    """Indices of the two coordinate axes with the largest extent of ``positions`` ``[N, 3]``, in order."""
    extent = np.ptp(positions, axis=0)
    first, second = sorted(np.argsort(extent)[1:])
    return int(first), int(second)


def plot_trajectories(
    path: str | Path, gt: np.ndarray, estimates: Mapping[str, np.ndarray], placement: str = ANCHORED
) -> Path:
    """Top view of the ground truth and every estimate (``[N, 4, 4]`` each), equal axis scales.

    ``placement`` (the subtitle) says how the estimates were placed relative to the ground truth.
    """
    a, b = horizontal_axes(gt[:, :3, 3])
    figure = Figure(figsize=(7.5, 7.0))
    ax = figure.add_subplot()
    ax.plot(gt[:, a, 3], gt[:, b, 3], color="black", linewidth=1.6, label="ground truth")
    for label, est in estimates.items():
        ax.plot(est[:, a, 3], est[:, b, 3], linewidth=1.1, label=label)
    ax.plot(gt[0, a, 3], gt[0, b, 3], "o", color="black", markersize=6, label="start")
    ax.set_xlabel(f"{_AXES[a]} (m)")
    ax.set_ylabel(f"{_AXES[b]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(f"Trajectories (top view)\n{placement}", fontsize=11)
    figure.tight_layout()
    return _save(figure, path)


def plot_segment_errors(path: str | Path, metrics: Mapping[str, EstimateMetrics]) -> Path:
    """Per-length segment errors of every estimate: translation (%) left, rotation (°/100 m) right."""
    figure = Figure(figsize=(11.0, 4.2))
    ax_t, ax_r = figure.subplots(1, 2)
    lengths = next(iter(metrics.values())).seg_lengths_m if metrics else np.zeros(0)
    empty = all(np.isnan(m.seg_per_length_trans_pct).all() for m in metrics.values())
    for label, m in metrics.items():
        ax_t.plot(m.seg_lengths_m, m.seg_per_length_trans_pct, "o-", label=label)
        ax_r.plot(m.seg_lengths_m, m.seg_per_length_rot_deg_per_100m, "o-", label=label)
    for ax, unit in ((ax_t, "translation error (%)"), (ax_r, "rotation error (°/100 m)")):
        ax.set_xlabel("segment length (m)")
        ax.set_ylabel(unit)
        ax.grid(True, alpha=0.3)
        if lengths.size:
            step = float(np.min(np.diff(lengths))) if lengths.size > 1 else 100.0
            ax.set_xlim(lengths[0] - step / 2, lengths[-1] + step / 2)
        if empty:
            ax.set_ylim(0.0, 1.0)
            ax.text(0.5, 0.5, f"the sequence is shorter than {lengths[0]:g} m:\nno segment to evaluate"
                    if lengths.size else "no segment to evaluate",
                    transform=ax.transAxes, ha="center", va="center", fontsize=12, color="0.3")
        else:
            ax.set_ylim(bottom=0.0)
            ax.legend(loc="best")
    figure.suptitle("Segment errors per length")
    figure.tight_layout()
    return _save(figure, path)


def plot_c_ate(path: str | Path, metrics: Mapping[str, EstimateMetrics]) -> Path:
    """Cumulative absolute errors (c-ATE) against the evaluated frame index: translation and rotation."""
    figure = Figure(figsize=(11.0, 4.2))
    ax_t, ax_r = figure.subplots(1, 2)
    for label, m in metrics.items():
        frames = np.arange(m.c_ate_trans_m.shape[0])
        ax_t.plot(frames, m.c_ate_trans_m, label=label)
        ax_r.plot(frames, m.c_ate_rot_deg, label=label)
    for ax, unit in ((ax_t, "cumulative translation error (m)"), (ax_r, "cumulative rotation error (°)")):
        ax.set_xlabel("frame")
        ax.set_ylabel(unit)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
    figure.suptitle(
        "Cumulative absolute trajectory error (c-ATE)\ncumulative: the value at frame k is the sum, over "
        "frames 0…k, of each frame's absolute error (position in m, rotation angle in °)",
        fontsize=11,
    )
    figure.tight_layout()
    return _save(figure, path)
