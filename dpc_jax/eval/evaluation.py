"""Evaluate estimated trajectories against ground truth (its report: :mod:`dpc_jax.report.evaluation_report`).

:func:`evaluate` is the one entry point every command that reports metrics uses (``evaluate``,
``train``, ``correct``, ``demo``). It prepares the trajectories as the papers do, then computes every
metric of :mod:`dpc_jax.eval.metrics` in one compiled call per estimate:

* **Re-anchoring** (docs/method.md §7): each estimate is moved rigidly onto the first ground-truth pose,
  ``E_i ← G_0 · inv(E_0) · E_i``.
* **Static frames** (``remove_static=True``, docs/method.md §6): the ss-DPC-Net rule, read on the prior
  (the estimate named ``static_prior``, by default the first one), selects the kept frames; the
  ground truth and every estimate lose the same frames, and each estimate is re-composed from its
  relative poses between consecutive kept frames, starting at the first kept ground-truth pose.

**Pairing by time.** :func:`evaluate` pairs the poses of its arrays by index. Trajectories with
times (TUM files) are paired first by :func:`associate_by_time` (evo's rule, one tolerance and offset
for every estimate), which says which ground-truth and estimate poses to pass and how many matched.

Precision is an argument, not process state: :func:`evaluate` and :func:`segment_summary` compute in
float64 by default (``precision="float32"`` for the faster, coarser figures), in a local
``jax.enable_x64`` scope whatever the process's setting. The result is an :class:`Evaluation`: a
read-only mapping equal to the JSON summary ``{"num_poses": N, "estimates": {label: {metric:
value}}}`` (NaN becomes ``None``), with the prepared trajectories and the per-length and cumulative
curves as attributes.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from dpc_jax.data.poses_io import MAX_TIME_DIFF, associate
from dpc_jax.eval.diagnosis import Diagnosis
from dpc_jax.geometry.poses import (
    compose,
    invert_poses,
    relative_poses,
    remove_static_frames,
    validate_poses,
)

SUMMARY_KEYS: tuple[str, ...] = (
    "m_ate_trans_m",
    "m_ate_rot_deg",
    "seg_trans_pct",
    "seg_rot_deg_per_100m",
    "kitti_trans_pct",
    "kitti_rot_deg_per_100m",
    "ate_m",
    "rpe_trans_m",
    "rpe_rot_deg",
    "loop_closures",
)
_LABEL = re.compile(r"[A-Za-z0-9_.+-]+")
GT_LABEL = "gt"
PRECISIONS = ("float64", "float32")
# One estimate's summary: SUMMARY_KEYS -> value (None for NaN); what a results table reads of an estimate.
Metrics = dict[str, float | int | None]


@dataclass(frozen=True)
class EstimateMetrics:
    """Metrics of one estimate: the summary scalars and the curves behind the plots."""

    summary: Metrics
    seg_lengths_m: np.ndarray  # [L]
    seg_per_length_trans_pct: np.ndarray  # [L], NaN where no segment exists
    seg_per_length_rot_deg_per_100m: np.ndarray  # [L]
    seg_counts: np.ndarray  # [L]
    c_ate_trans_m: np.ndarray  # [N]
    c_ate_rot_deg: np.ndarray  # [N]


@dataclass(frozen=True, eq=False)
class Evaluation(Mapping[str, object]):
    """Result of :func:`evaluate`.

    As a mapping it is the JSON summary (``result["estimates"][label]["seg_trans_pct"]``,
    ``dict(result)``, :meth:`to_json`); the attributes hold what the report plots: the evaluated
    ground truth, the prepared estimates (``trajectories``), the indices of the evaluated frames in
    the input sequence, and each estimate's :class:`EstimateMetrics`.
    """

    gt: np.ndarray  # [N, 4, 4] ground truth of the evaluated frames
    trajectories: dict[str, np.ndarray]  # label -> [N, 4, 4] prepared (re-anchored) estimate
    frames: np.ndarray  # [N] indices of the evaluated frames in the input sequence
    metrics: dict[str, EstimateMetrics]
    align: str = "none"
    rpe_delta: int = 1
    remove_static: bool = False
    # label -> error composition (dpc_jax.eval.diagnosis); empty unless evaluate(diagnose=True)
    diagnoses: dict[str, Diagnosis] = field(default_factory=dict)
    # How the poses were paired by time (Association.to_dict), None when paired by index: set with
    # dataclasses.replace by whoever associated them (the command line does).
    association: dict[str, object] | None = None
    _summary: dict[str, object] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        summary: dict[str, object] = {
            "num_poses": int(self.gt.shape[0]),
            "estimates": {label: dict(m.summary) for label, m in self.metrics.items()},
        }
        if self.association is not None:
            summary["association"] = self.association
        if self.diagnoses:
            summary["diagnosis"] = {label: d.to_dict() for label, d in self.diagnoses.items()}
        object.__setattr__(self, "_summary", summary)

    def __getitem__(self, key: str) -> object:
        return self._summary[key]

    @property
    def estimates(self) -> dict[str, Metrics]:
        """``self["estimates"]`` with its type: label -> the estimate's summary (SUMMARY_KEYS)."""
        # Built in __post_init__ with this type; the mapping's values are typed ``object``.
        return cast(dict[str, Metrics], self._summary["estimates"])

    def __iter__(self) -> Iterator[str]:
        return iter(self._summary)

    def __len__(self) -> int:
        return len(self._summary)

    def to_json(self) -> str:
        """The summary as JSON text (strict: no NaN literals)."""
        return json.dumps(self._summary, indent=2, allow_nan=False) + "\n"

    def __repr__(self) -> str:
        """One line: the poses, the estimates and their main figures (the arrays are in the attributes;
        printed whole they run to tens of kilobytes)."""
        figures = ", ".join(f"{label}: m-ATE {m['m_ate_trans_m']:.4g} m, segments {m['seg_trans_pct']:.4g} %"
                            for label, m in self.estimates.items())
        return f"Evaluation({self.gt.shape[0]} poses, align={self.align!r}; {figures})"


@dataclass(frozen=True)
class Association:
    """The poses of a ground truth and its estimates that :func:`associate_by_time` paired.

    ``gt_indices`` ``[M]``: the ground-truth poses every estimate has a partner for, increasing;
    ``indices``: label → ``[M]`` the partner of each in that estimate; ``matched``: label → the pairs
    that estimate alone has; ``possible``: label → the most it could have (the shorter trajectory's
    length); ``max_diff``, ``offset`` in seconds.
    """

    gt_indices: np.ndarray
    indices: dict[str, np.ndarray]
    matched: dict[str, int]
    possible: dict[str, int]
    max_diff: float
    offset: float

    def to_dict(self) -> dict[str, object]:
        """The summary's ``"association"``: tolerance, offset, the evaluated and each estimate's count."""
        return {"max_diff_s": self.max_diff, "offset_s": self.offset, "evaluated": int(self.gt_indices.size),
                "matched": dict(self.matched), "possible": dict(self.possible)}


def associate_by_time(
    gt_times: np.ndarray, estimate_times: Mapping[str, np.ndarray], *, max_diff: float = MAX_TIME_DIFF,
    offset: float = 0.0, sources: Mapping[str, str] | None = None,
) -> Association:
    """Pair each estimate's poses with the ground truth's by time (:func:`dpc_jax.data.poses_io.associate`,
    evo's rule: nearest times within ``max_diff`` s, ``offset`` s added to every estimate's times) and
    keep the ground-truth poses every estimate has a partner for.

    ``gt_times`` ``[N]`` and ``estimate_times`` label → ``[K]`` in seconds, increasing. Evaluate
    ``gt[a.gt_indices]`` against ``{label: est[a.indices[label]]}``. Raises ``ValueError`` naming the
    estimate (``sources[label]``, default ``estimate 'label'``) when fewer than half of the poses it
    could pair match (times on another clock, or at another rate than the tolerance allows), and when
    fewer than 2 ground-truth poses are common to every estimate.
    """
    gt_times = np.asarray(gt_times, np.float64)
    names = {label: (sources or {}).get(label, f"estimate {label!r}") for label in estimate_times}
    pairs: dict[str, dict[int, int]] = {}
    matched: dict[str, int] = {}
    possible: dict[str, int] = {}
    for label, times in estimate_times.items():
        gt_idx, est_idx = associate(gt_times, times, max_diff, offset)
        possible[label] = int(min(gt_times.size, np.size(times)))
        matched[label] = int(gt_idx.size)
        if 2 * matched[label] < possible[label]:
            raise ValueError(
                f"{names[label]}: {matched[label]} of its {possible[label]} poses have a ground-truth time "
                f"within {max_diff:g} s (time offset {offset:g} s); fewer than half match: the times are on "
                "another clock or further apart than the tolerance")
        pairs[label] = dict(zip(gt_idx.tolist(), est_idx.tolist(), strict=True))
    common = sorted(set.intersection(*(set(p) for p in pairs.values()))) if pairs else []
    if len(common) < 2:
        raise ValueError(f"{len(common)} ground-truth pose(s) have a partner in every estimate "
                         f"({', '.join(names.values())}); a trajectory to evaluate needs at least 2")
    gt_indices = np.asarray(common, np.int64)
    indices = {label: np.asarray([p[i] for i in common], np.int64) for label, p in pairs.items()}
    return Association(gt_indices, indices, matched, possible, float(max_diff), float(offset))


def check_label(label: str) -> str:
    """Labels name files and table rows: letters, digits and ``_ . + -``, and not ``gt``."""
    if not isinstance(label, str) or not _LABEL.fullmatch(label) or label == GT_LABEL:
        raise ValueError(
            f"invalid estimate label {label!r}: use letters, digits and _ . + - (and not {GT_LABEL!r})"
        )
    return label


def _scalar(value: np.ndarray, integer: bool = False) -> float | int | None:
    if integer:
        return int(value)
    number = float(value)
    return None if math.isnan(number) else number


def evaluate(
    gt: np.ndarray,
    estimates: Mapping[str, np.ndarray] | np.ndarray,
    remove_static: bool = False,
    align: str = "none",
    rpe_delta: int = 1,
    static_prior: str | None = None,
    diagnose: bool = False,
    focal_px: float | None = None,
    precision: str = "float64",
) -> Evaluation:
    """Evaluate estimates ``{label: [N, 4, 4]}`` (or one array, labelled ``est``) against ``gt``
    (poses ``[N, 4, 4]``, or ``[N, 3, 4]`` KITTI rows, on either side).

    ``align`` (``none | se3 | sim3``) applies to ATE only; ``rpe_delta`` is the RPE frame offset;
    ``remove_static`` and ``static_prior`` are described in the module docstring. ``diagnose`` adds
    each estimate's error composition (:func:`dpc_jax.eval.diagnosis.diagnose`, on the evaluated
    frames; ``focal_px`` for the pixel shift) as ``result.diagnoses`` and the summary's
    ``"diagnosis"``. ``precision``: ``float64`` or ``float32`` (module docstring). Raises
    ``ValueError`` (one line naming the argument) for mismatched lengths (both counts named), bad labels
    or shapes, poses that the trajectory readers would refuse (:func:`~dpc_jax.geometry.poses.validate_poses`:
    non-finite, not rigid, a bottom row other than ``[0, 0, 0, 1]``, as transposed matrices have), a
    ``rpe_delta`` that is not a whole number of frames, and ``focal_px`` without ``diagnose``.
    """
    x64 = _x64(precision)
    gt, estimates = _checked_arguments(gt, estimates, rpe_delta, diagnose, focal_px)
    import jax

    with jax.enable_x64(x64):
        return _evaluate(gt, estimates, remove_static, align, rpe_delta, static_prior, diagnose, focal_px)


def _checked_arguments(
    gt: np.ndarray, estimates: Mapping[str, np.ndarray] | np.ndarray, rpe_delta: int, diagnose: bool,
    focal_px: float | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The checks of :func:`evaluate` that need no JAX; returns the poses float64, as given (checked,
    not projected, so that the metrics of exact trajectories stay exact)."""
    if isinstance(rpe_delta, bool) or not isinstance(rpe_delta, (int, np.integer)):
        raise ValueError(f"rpe_delta must be a whole number of frames, got {rpe_delta!r}")
    if focal_px is not None and not diagnose:
        raise ValueError(f"focal_px={focal_px!r} is used only with diagnose=True (the pixel shift of the "
                         "error composition); pass diagnose=True or leave focal_px out")
    if not isinstance(estimates, Mapping):
        estimates = {"est": estimates}
    # The rule of every pose argument (validate_poses): [N, 4, 4], or [N, 3, 4] KITTI rows, made
    # homogeneous here, so that both sides are [N, 4, 4].
    named = {"gt": gt, **{f"estimates[{label!r}]": est for label, est in estimates.items()}}
    arrays = {}
    for name, poses in named.items():
        if isinstance(poses, (str, os.PathLike)):
            raise ValueError(f"{name}: the path {os.fspath(poses)!r}; expected an array of poses [N, 4, 4] "
                             "or [N, 3, 4] (read a file with dpc_jax.data.poses_io.read_trajectory)")
        try:
            array = np.asarray(poses, np.float64)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{name}: not an array of numbers ({error}); expected poses [N, 4, 4] or "
                             "[N, 3, 4]") from None
        validate_poses(array, name)
        if array.shape[1:] == (3, 4):
            array = np.concatenate([array, np.broadcast_to([[[0.0, 0.0, 0.0, 1.0]]], (len(array), 1, 4))], 1)
        arrays[name] = array
    return arrays.pop("gt"), {label: arrays[f"estimates[{label!r}]"] for label in estimates}


def segment_summary(gt: np.ndarray, est: np.ndarray, precision: str = "float64") -> tuple[float, float]:
    """Mean segment errors of ``est`` against ``gt`` (both ``[N, 4, 4]``) → ``(t_err %, r_err °/100 m)``
    over the lengths the trajectory covers (NaN if none), without :func:`evaluate`'s other metrics."""
    import jax

    from dpc_jax.eval.metrics import segment_errors

    with jax.enable_x64(_x64(precision)):
        result = segment_errors(np.asarray(gt, np.float64), np.asarray(est, np.float64))
        return float(result.trans_pct), float(result.rot_deg_per_100m)


def _x64(precision: str) -> bool:
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    return precision == "float64"


def _evaluate(
    gt: np.ndarray,
    estimates: Mapping[str, np.ndarray] | np.ndarray,
    remove_static: bool,
    align: str,
    rpe_delta: int,
    static_prior: str | None,
    diagnose: bool,
    focal_px: float | None,
) -> Evaluation:
    import jax

    from dpc_jax.eval.metrics import ALIGNMENTS, trajectory_metrics

    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {', '.join(ALIGNMENTS)}, got {align!r}")
    gt = np.asarray(gt, dtype=np.float64)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or gt.shape[0] < 2:
        raise ValueError(f"ground truth must have shape [N, 4, 4] with N ≥ 2, got {gt.shape}")
    if not isinstance(estimates, Mapping):
        estimates = {"est": estimates}
    if not estimates:
        raise ValueError("no estimate to evaluate")
    prepared: dict[str, np.ndarray] = {}
    for label, est in estimates.items():
        est = np.asarray(est, dtype=np.float64)
        if est.shape != gt.shape:
            raise ValueError(
                f"estimate {check_label(label)!r} has {est.shape[0] if est.ndim == 3 else est.shape} poses "
                f"but the ground truth has {gt.shape[0]}; they must cover the same frames"
            )
        prepared[check_label(label)] = est
    if static_prior is not None and static_prior not in prepared:
        raise ValueError(f"static_prior {static_prior!r} is not one of the estimates {list(prepared)}")

    if remove_static:
        prior = prepared[static_prior if static_prior is not None else next(iter(prepared))]
        frames = remove_static_frames(gt, prior)
        gt = gt[frames]
        prepared = {k: compose(relative_poses(v[frames]), gt[0]) for k, v in prepared.items()}
    else:
        frames = np.arange(gt.shape[0])
        prepared = {k: gt[0] @ invert_poses(v[0]) @ v for k, v in prepared.items()}
    if remove_static and gt.shape[0] < 2:
        raise ValueError(f"removing static frames left {gt.shape[0]} pose(s); a trajectory to evaluate "
                         "needs at least 2 (the estimate barely moves; evaluate without removing them)")
    if not 1 <= rpe_delta < gt.shape[0]:
        raise ValueError(
            f"rpe_delta must be in [1, {gt.shape[0] - 1}] for {gt.shape[0]} poses, got {rpe_delta}"
        )

    results = {}
    for label, est in prepared.items():
        out = jax.device_get(trajectory_metrics(gt, est, align=align, rpe_delta=rpe_delta))
        results[label] = EstimateMetrics(
            summary={key: _scalar(out[key], integer=key == "loop_closures") for key in SUMMARY_KEYS},
            seg_lengths_m=np.asarray(out["seg_lengths_m"], np.float64),
            seg_per_length_trans_pct=np.asarray(out["seg_per_length_trans_pct"], np.float64),
            seg_per_length_rot_deg_per_100m=np.asarray(out["seg_per_length_rot_deg_per_100m"], np.float64),
            seg_counts=np.asarray(out["seg_counts"], np.int64),
            c_ate_trans_m=np.asarray(out["c_ate_trans_m"], np.float64),
            c_ate_rot_deg=np.asarray(out["c_ate_rot_deg"], np.float64),
        )
    diagnoses: dict[str, Diagnosis] = {}
    if diagnose:
        from dpc_jax.eval.diagnosis import diagnose as diagnose_estimate

        diagnoses = {label: diagnose_estimate(gt, est, focal_px) for label, est in prepared.items()}
    return Evaluation(
        gt=gt, trajectories=prepared, frames=frames, metrics=results, align=align, rpe_delta=rpe_delta,
        remove_static=remove_static, diagnoses=diagnoses,
    )
