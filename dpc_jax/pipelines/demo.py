"""The synthetic end-to-end demo (``dpc-jax demo``): render, VO, train, correct, adapt, report.

:func:`run_demo` chains the library on data it makes itself, so it runs on a fresh machine:

1. **Render** (``dpc_jax.synth``) the training, validation and test sequences in the KITTI odometry
   layout under ``OUT/data`` at 240×376, with the nuisances a real rig has: moving cars, a slow
   illumination drift, image noise and a stereo calibration residual: the right camera's
   principal point 0.8 px off the written calibration (2.6 px at KITTI's 1242 px width, about twice
   the residual of KITTI's colour pair; ``disparity_offset=-0.36`` is KITTI's own level, at which
   the prior's rotation drift, ≈ 0.2 mrad per frame, is as small as the photometric loss's own
   rotation bias at 64×96 and the rotation gains vary in sign from seed to seed — README, "The
   demo"). Every sequence has its own seed (a different town and route).
2. **Prior**: our classical stereo VO (``dpc_jax.vo``) with its online disparity-offset estimate
   *off*, as libviso2, which ignores such a residual: its trajectory then carries a scale error
   and a slow rotation drift, systematic errors that a correction can learn (the report tabulates
   each sequence's prior error: mean per frame against spread). A prior that falls back to
   constant velocity on more than 5 % of the pairs is refused: it would not be VO.
3. **Calibrate and prepare**: the same VO with the estimate *on* measures the residual from the
   images (no ground truth); ``prepare`` rectifies the network's images by it, so the network sees
   a calibrated rig and its stereo depth is metric.
4. **Train** Stereo DPC (``dpc_jax.training.loop``, the improved settings of ``dpc_jax.training.config``) on
   the training sequences; the validation sequence selects the epoch by Δ (the correction's paired
   photometric effect, no ground truth). The test sequence is never read by training.
5. **Correct the test sequence twice**: with the network as trained (acceptance test on all its
   pairs), and after adapting the network to the test sequence's own images for ``adapt_steps``
   steps (``dpc_jax.adapt``; every ``holdout_every``-th pair kept out, the acceptance test on those).
   The final trajectory (``corrected.txt``, ``summary.json``'s ``test.corrected``) is chosen by
   ``dpc_jax.correct.choose``: the adapted correction if its test passes *and* it beats the trained
   one on the kept-out pairs, else the trained one if its test passes, else the prior.
6. **Report** ``OUT/report.md``: the prior's error composition, the test table (prior, trained,
   adapted, final), plots, the training and adaptation records. The ground truth is read only here.

Re-running with the same ``OUT`` reuses what is already there and up to date: rendered sequences
whose ``synth.json`` matches, VO runs whose record matches, caches (by their input hash) and a
finished training run (resumed when interrupted; a run with a different config is refused).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dpc_jax import config as config_lib
from dpc_jax._io import atomic_write
from dpc_jax.data.holdout import MIN_EVERY
from dpc_jax.training.config import SELECTIONS
from dpc_jax.vo.odometry import FALLBACK_WARNING_SHARE

if TYPE_CHECKING:
    from dpc_jax.adapt import Adaptation
    from dpc_jax.correct import Correction
    from dpc_jax.data.kitti import StereoSequence
    from dpc_jax.data.sequence_cache import SequenceCache
    from dpc_jax.eval.evaluation import Evaluation
    from dpc_jax.training.config import TrainConfig

# Training defaults of the demo (``TrainConfig`` fields); ``DemoConfig.training`` overrides them.
TRAINING: dict[str, Any] = {
    "method": "stereo_dpc",
    "preset": "small",
    "image_size": (64, 96),
    "batch_size": 8,
    "epochs": 8,
    "learning_rate": 2e-3,
    "lr_halving_epochs": 2,
    "keep_checkpoints": 1,
}
# The demo sets these itself (paths and split).
_MANAGED = ("cache_root", "train_sequences", "validation_sequences", "test_sequences")
# The run and the caches inside OUT (the report lists them as `run/` and `cache/`).
_RUN_DIR, _CACHE_DIR = "run", "cache"


class DemoError(ValueError):
    """The demo cannot go on (e.g. its VO prior is not VO); the message says why and what to change."""


@dataclass(frozen=True)
class DemoConfig:
    """What the demo renders, how it trains and how it corrects.

    Data
        * ``train_sequences``, ``train_frames``: number and length (frames, 10 Hz) of the training
          sequences; ``validation_frames``, ``test_frames``: the one validation (epoch selection)
          and one test (held out) sequence.
        * ``render_size``: ``(H, W)`` of the rendered images (the VO runs on them; the network
          sees them resized to the training ``image_size``).
        * ``moving_objects``, ``illumination_drift``, ``noise``, ``disparity_offset``: see
          ``dpc_jax.synth.SynthConfig``.
        * ``vo_estimate_offset``: the prior's VO self-calibrates the disparity offset (False: it
          ignores the residual, as libviso2).
        * ``rectify_offset``: measure the residual with our VO's online estimate and rectify the
          network's images by it.
        * ``seed``: training sequence i has seed ``seed + i``, validation ``seed + 100``, test
          ``seed + 200``.
    Training and correction
        * ``training``: ``TrainConfig`` fields overriding :data:`TRAINING` (not the cache root
          or the split, which the demo sets).
        * ``select``: the epoch used for the test: ``delta`` (most negative validation Δ; no ground
          truth), ``gradient``, ``loop`` or ``last``.
        * ``acceptance``: apply a correction only where the acceptance test passes (False: apply
          every correction, as the papers do).
        * ``adapt_steps`` (0: no adaptation), ``holdout_every``: see ``dpc_jax.adapt``.
        * ``max_fallback_share``: the demo refuses a prior whose VO fell back to constant velocity on
          more of the pairs than this (default ``dpc_jax.vo.odometry.FALLBACK_WARNING_SHARE``).
    """

    train_sequences: int = 2
    train_frames: int = 300
    validation_frames: int = 150
    test_frames: int = 300
    render_size: tuple[int, int] = (240, 376)
    moving_objects: int = 6
    illumination_drift: float = 0.3
    noise: float = 1.0
    disparity_offset: float = -0.8
    vo_estimate_offset: bool = False
    rectify_offset: bool = True
    seed: int = 0
    training: dict[str, Any] = field(default_factory=dict)
    select: str = "delta"
    acceptance: bool = True
    adapt_steps: int = 300
    holdout_every: int = 5
    max_fallback_share: float = FALLBACK_WARNING_SHARE

    def __post_init__(self) -> None:
        problems = []
        if self.train_sequences < 1:
            problems.append(f"train_sequences must be >= 1, got {self.train_sequences}")
        for name in ("train_frames", "validation_frames", "test_frames"):
            if getattr(self, name) < 3:
                problems.append(f"{name} must be >= 3, got {getattr(self, name)}")
        if self.select not in SELECTIONS:
            problems.append(f"select must be one of {tuple(SELECTIONS)}, got {self.select!r}")
        if self.adapt_steps < 0 or self.holdout_every < MIN_EVERY:
            problems.append(f"adapt_steps must be >= 0 and holdout_every >= {MIN_EVERY}, got "
                            f"{self.adapt_steps}, {self.holdout_every}")
        managed = sorted(set(self.training) & set(_MANAGED))
        if managed:
            problems.append(f"training sets {managed}, which the demo chooses itself")
        if problems:
            raise config_lib.ConfigError("invalid DemoConfig: " + "; ".join(problems))
        self.synth_config("test")  # SynthConfig's own checks
        self.train_config("cache")  # TrainConfig's own checks

    @property
    def sequences(self) -> dict[str, str]:
        """Sequence name → role (``train``, ``validation``, ``test``), in rendering order."""
        names = {f"train{i}": "train" for i in range(self.train_sequences)}
        return {**names, "val": "validation", "test": "test"}

    def synth_config(self, name: str) -> Any:
        """The ``SynthConfig`` of sequence ``name`` (see :attr:`sequences`)."""
        from dpc_jax.synth import SynthConfig

        if name.startswith("train"):
            frames, seed = self.train_frames, self.seed + int(name[5:])
        elif name == "val":
            frames, seed = self.validation_frames, self.seed + 100
        elif name == "test":
            frames, seed = self.test_frames, self.seed + 200
        else:
            raise KeyError(f"no demo sequence {name!r}; expected one of {list(self.sequences)}")
        return SynthConfig(
            frames=frames, height=self.render_size[0], width=self.render_size[1], seed=seed,
            moving_objects=self.moving_objects, illumination_drift=self.illumination_drift, noise=self.noise,
            disparity_offset=self.disparity_offset,
        )

    def train_config(self, cache_root: str | os.PathLike) -> Any:
        """The ``TrainConfig`` of the demo's run on the caches under ``cache_root``."""
        from dpc_jax.training.config import TrainConfig

        roles = self.sequences
        values = {
            **TRAINING,
            **self.training,
            "cache_root": str(cache_root),
            "train_sequences": tuple(n for n, r in roles.items() if r == "train"),
            "validation_sequences": ("val",),
            "test_sequences": ("test",),
        }
        return config_lib.from_dict(TrainConfig, values, where="DemoConfig.training")


ProgressFn = Callable[[str], None]


def _render(config: DemoConfig, data_root: Path, name: str, progress: bool) -> bool:
    """Render sequence ``name`` unless an identical one is there; whether it rendered."""
    from tqdm.auto import tqdm

    from dpc_jax.synth import write_sequence

    synth = config.synth_config(name)
    record = data_root / "sequences" / name / "synth.json"
    if record.is_file() and (data_root / "poses" / f"{name}.txt").is_file():
        stored = json.loads(record.read_text()).get("config")
        if stored == config_lib.to_dict(synth):
            return False
    with tqdm(total=synth.frames, unit="frame", desc=f"render {name}", disable=not progress,
              leave=False) as bar:
        write_sequence(data_root, name, synth, overwrite=True, on_frame=lambda: bar.update(1))
    return True


def _fmt(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _epoch_table(metrics_csv: Path, selected: int) -> str:
    """Markdown table of the run's per-epoch validation figures (the selected epoch marked)."""
    import csv

    with metrics_csv.open(newline="") as f:
        rows = list(csv.DictReader(f))
    lines = [
        "| epoch | train loss | val gradient loss | val r_err prior → corrected (°/100 m) | "
        "val t_err prior → corrected (%) |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        epoch = int(row["epoch"])
        mark = " (selected)" if epoch == selected else ""
        lines.append(
            f"| {epoch}{mark} | {float(row['train_loss']):.4f} | {float(row['val_gradient_loss']):.5f} | "
            f"{_fmt(float(row['val_prior_r_err']))} → {_fmt(float(row['val_corrected_r_err']))} | "
            f"{_fmt(float(row['val_prior_t_err']), 2)} → {_fmt(float(row['val_corrected_t_err']), 2)} |"
        )
    return "\n".join(lines) + "\n"


def prior_error(gt: np.ndarray, prior: np.ndarray, focal_px: float | None = None) -> dict[str, Any]:
    """What a prior's error consists of (:func:`dpc_jax.eval.diagnosis.diagnose`, the same as
    ``dpc-jax evaluate --diagnose``): the mean per frame (systematic) and the standard deviation
    (``std``, random) of the correction each step needs, per axis, translation in mm and rotation in
    mrad; the share of the end-point drift the mean explains; the mean rotation's image shift."""
    from dpc_jax.eval.diagnosis import diagnose

    record = diagnose(gt, prior, focal_px).to_dict()
    record["std"] = record.pop("spread")
    return record


def _composition_table(records: dict[str, dict[str, Any]]) -> str:
    axes = ("ρx", "ρy", "ρz", "φx", "φy", "φz")
    lines = [
        "| sequence | fallbacks | offset measured (px) | "
        + " | ".join(f"{a} mean ± std ({'mm' if a[0] == 'ρ' else 'mrad'})" for a in axes) + " |",
        "|---" * (3 + len(axes)) + "|",
    ]
    lines[0] += " end-point drift the mean explains (position / heading) | mean rotation per step (px) |"
    lines[1] += "---|---|"
    for name, r in records.items():
        error = r["error"]
        cells = [f"{m:+.2f} ± {s:.2f}" for m, s in zip(error["mean"], error["std"], strict=True)]
        shares = " / ".join(
            "n/a" if error.get(k) is None else f"{100 * error[k]:.0f} %"
            for k in ("drift_trans_explained", "drift_rot_explained")
        )
        px = "n/a" if error.get("mean_rot_px_norm") is None else f"{error['mean_rot_px_norm']:.3f}"
        head = f"| {name} | {r['fallbacks']}/{r['pairs']} | {r['offset']:+.3f} | "
        lines.append(head + " | ".join(cells) + f" | {shares} | {px} |")
    return "\n".join(lines) + "\n"


def _decision(correction: Any) -> str:
    if correction.acceptance.forced:
        return "not tested (applied)"
    names = {"full": "accepted (full 6-DoF)", "rotation": "accepted (rotation only)", "none": "rejected"}
    return names[correction.applied]


def _results_table(summary: dict[str, Any]) -> str:
    columns = (("seg_trans_pct", "seg. t (%)"), ("seg_rot_deg_per_100m", "seg. r (°/100 m)"),
               ("m_ate_trans_m", "m-ATE (m)"), ("m_ate_rot_deg", "m-ATE (°)"), ("ate_m", "ATE (m)"))
    rows = [("prior (our VO)", "prior", "")]
    labels = (("trained", "network as trained"), ("adapted", "network adapted to the test sequence"))
    for key, label in labels:
        if key in summary["test"]:
            rows.append((f"{label} (epoch {summary['selected_epoch']})", key, summary["decisions"][key]))
    rows.append((f"**final: {summary['final']}** (corrected.txt)", "corrected", summary["choice"]["reason"]))
    lines = ["| estimate | acceptance test | " + " | ".join(t for _, t in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    for label, key, decision in rows:
        values = summary["test"][key]
        lines.append(f"| {label} | {decision} | " + " | ".join(_fmt(values[k]) for k, _ in columns) + " |")
    return "\n".join(lines) + "\n"


def _write_evaluation_files(out: Path, evaluation: Evaluation) -> None:
    """The plots and the metric files (``metrics.csv``, ``segment_errors.csv``, ``metrics.json``)."""
    from dpc_jax.eval import plots
    from dpc_jax.eval.evaluation import metrics_csv, segment_csv

    plots.plot_trajectories(out / "trajectory.png", evaluation.gt, evaluation.trajectories)
    plots.plot_segment_errors(out / "segment_errors.png", evaluation.metrics)
    plots.plot_c_ate(out / "c_ate.png", evaluation.metrics)
    atomic_write(out / "metrics.csv", metrics_csv(evaluation))
    atomic_write(out / "segment_errors.csv", segment_csv(evaluation))
    atomic_write(out / "metrics.json", evaluation.to_json())


def _overview(config: DemoConfig, train_config: TrainConfig, summary: dict[str, Any]) -> list[str]:
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
    from dpc_jax.eval.evaluation import format_segment_table

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
        "Segment errors per length (translation % / rotation °/100 m):",
        "",
        format_segment_table(evaluation),
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


def _write_report(out: Path, config: DemoConfig, train_config: TrainConfig, evaluation: Evaluation,
                  summary: dict[str, Any], run_dir: Path) -> Path:
    """``OUT/report.md`` with the tables, the per-length errors, the records and the plots."""
    _write_evaluation_files(out, evaluation)
    text = "\n".join([
        *_overview(config, train_config, summary),
        *_composition_section(summary),
        *_test_section(evaluation, summary),
        *_training_section(summary, run_dir),
    ])
    atomic_write(out / "report.md", text)
    return out / "report.md"


def _change(prior: float | None, corrected: float | None) -> float:
    """Relative change in % (negative: lower than the prior); NaN without a value."""
    if prior is None or corrected is None or prior == 0:
        return math.nan
    return 100.0 * (corrected - prior) / prior


def _vo_prior(config: DemoConfig, name: str, sequence: StereoSequence, first_pose: np.ndarray, vo_dir: Path,
              progress: bool) -> tuple[dict[str, Any], float]:
    """Sequence ``name``'s VO prior (refused if it is not VO) and the disparity offset our VO measures."""
    from dpc_jax.vo import VOConfig
    from dpc_jax.vo.prior import vo_prior

    libviso2_like = VOConfig(estimate_offset=config.vo_estimate_offset)
    prior = vo_prior(sequence, vo_dir / f"{name}.txt", libviso2_like, first_pose=first_pose,
                     progress=progress)
    if prior["fallbacks"] > config.max_fallback_share * prior["pairs"]:
        raise DemoError(
            f"{name}: our VO fell back to constant velocity on {prior['fallbacks']} of {prior['pairs']} "
            f"pairs (more than {config.max_fallback_share:.0%}); a correction trained on such a prior "
            "shows nothing. Render larger images (render_size) or with less noise"
        )
    calibration = vo_prior(sequence, vo_dir / f"{name}.calibration.txt", VOConfig(estimate_offset=True),
                           first_pose=first_pose, progress=progress)
    return prior, calibration["disparity_offset_median_px"]


def _prepare_sequences(config: DemoConfig, out: Path, size: tuple[int, int], seconds: dict[str, float],
                       progress: bool, say: ProgressFn) -> tuple[dict[str, dict[str, Any]], dict[str, float]]:
    """Render every sequence, run its VO prior and calibration, and prepare its cache, one sequence at a
    time; return each sequence's prior record (fallbacks, pairs, offset, error) and its length (m)."""
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.data.poses_io import read_kitti_poses

    data_root, vo_dir, cache_root = out / "data", out / "vo", out / _CACHE_DIR
    records: dict[str, dict[str, Any]] = {}
    lengths = {}
    for name in config.sequences:
        t = time.perf_counter()
        rendered = _render(config, data_root, name, progress)
        seconds["render"] += time.perf_counter() - t
        sequence = open_odometry(data_root, name)
        if sequence.poses is None:  # every rendered sequence has its poses; a reused folder might not
            raise DemoError(f"{name}: no ground-truth poses in {data_root}")
        t = time.perf_counter()
        prior, offset = _vo_prior(config, name, sequence, sequence.poses[0], vo_dir, progress)
        seconds["vo"] += time.perf_counter() - t
        t = time.perf_counter()
        prepare_sequence(sequence, prior["path"], cache_root, size=size,
                         disparity_offset=offset if config.rectify_offset else 0.0, progress=progress)
        seconds["prepare"] += time.perf_counter() - t
        records[name] = {"fallbacks": prior["fallbacks"], "pairs": prior["pairs"], "offset": offset,
                         "error": prior_error(sequence.poses, read_kitti_poses(prior["path"]),
                                              focal_px=float(sequence.K[0, 0]))}
        lengths[name] = float(np.linalg.norm(np.diff(sequence.poses[:, :3, 3], axis=0), axis=1).sum())
        say(f"{name}: {len(sequence)} frames, {lengths[name]:.0f} m"
            + (" (rendered)" if rendered else " (reused)")
            + f"; prior: {prior['fallbacks']} fallbacks, measured disparity offset {offset:+.3f} px")
    return records, lengths


def _train(train_config: TrainConfig, run_dir: Path, seconds: dict[str, float], progress: bool,
           say: ProgressFn) -> dict[str, Any]:
    """Train the network in ``run_dir`` (resuming an interrupted run, restoring a finished one)."""
    from dpc_jax.training.loop import train

    t = time.perf_counter()
    trained = train(train_config, run_dir, resume=True, progress=progress)
    seconds["train"] = time.perf_counter() - t
    say(f"trained: {trained['epochs']} epochs, {trained['step']} steps")
    return trained


@dataclass(frozen=True)
class _TestCorrections:
    """The test sequence's corrections (``trained``, ``adapted`` if adapted), the adaptation, and the
    final one (``result``, chosen as ``final``) with the epoch the network was restored at."""

    epoch: int
    cache: SequenceCache
    corrections: dict[str, Correction]
    adaptation: Adaptation | None
    final: str
    result: Correction


def _correct_test(config: DemoConfig, out: Path, seconds: dict[str, float], progress: bool,
                  say: ProgressFn) -> _TestCorrections:
    """Correct the test sequence with the network as trained and, unless ``adapt_steps`` is 0, adapted to
    it; choose the final correction and write it to ``corrected.txt``."""
    from dpc_jax.adapt import AdaptConfig, adapt_and_correct, save_adapted
    from dpc_jax.correct import choose, correct_cache, write_trajectory
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.inference import load_run

    t = time.perf_counter()
    run = load_run(out / _RUN_DIR, config.select)
    test_cache = load_cache(out / _CACHE_DIR / "test")
    corrections = {"trained": correct_cache(run, test_cache, force=not config.acceptance, progress=progress)}
    seconds["correct"] = time.perf_counter() - t
    say(f"network as trained (epoch {run.epoch}): {_decision(corrections['trained'])} on the test sequence")
    adaptation: Adaptation | None = None
    if config.adapt_steps:
        t = time.perf_counter()
        how = AdaptConfig(config.adapt_steps, holdout_every=config.holdout_every)
        adaptation, corrections["adapted"] = adapt_and_correct(
            run, test_cache, how, force=not config.acceptance, progress=progress)
        save_adapted(out / "adapted", adaptation, {"delta": corrections["adapted"].acceptance.mean_delta})
        seconds["adapt"] = time.perf_counter() - t
        say(f"adapted ({config.adapt_steps} steps): {_decision(corrections['adapted'])} on held-out pairs")
    final, result = choose(corrections["trained"], corrections.get("adapted"))
    write_trajectory(out / "corrected.txt", result)
    return _TestCorrections(run.epoch, test_cache, corrections, adaptation, final, result)


def _evaluate_test(config: DemoConfig, tested: _TestCorrections,
                   trained: dict[str, Any]) -> tuple[Evaluation, dict[str, Any]]:
    """Evaluate the test trajectories against the ground truth (read here only); return the evaluation and
    the summary's entries on the test sequence and the network."""
    import jax

    from dpc_jax.eval.evaluation import evaluate

    gt = np.asarray(tested.cache.gt, np.float64)
    proposals = {k: c.proposed for k, c in tested.corrections.items()}
    estimates = {"prior": tested.result.prior, **proposals, "corrected": tested.result.corrected}
    with jax.enable_x64(True):
        evaluation = evaluate(gt, estimates)
    test_metrics = {label: dict(evaluation.estimates[label]) for label in estimates}
    change = {k: _change(test_metrics["prior"][k], test_metrics["corrected"][k])
              for k in ("seg_trans_pct", "seg_rot_deg_per_100m")}
    return evaluation, {
        "test": test_metrics,
        "decisions": {k: _decision(c) for k, c in tested.corrections.items()},
        "acceptance": {k: c.acceptance.to_dict() for k, c in tested.corrections.items()},
        "final": tested.final,
        "choice": tested.result.choice,
        "change_pct": change,
        "corrected_better": all(v < 0 for v in change.values()),
        "selected_epoch": tested.epoch,
        "select": config.select,
        "steps_per_epoch": trained["step"] // max(1, trained["epochs"]),
    }


def _write_results(out: Path, config: DemoConfig, train_config: TrainConfig, evaluation: Evaluation,
                   summary: dict[str, Any], began: float) -> None:
    """Write ``report.md`` (with its plots and metric files), then ``summary.json``."""
    t = time.perf_counter()
    # The report states the wall time up to itself; summary.json then gets the total with the report's time.
    summary["seconds_total"] = time.perf_counter() - began
    report = _write_report(out, config, train_config, evaluation, summary, out / _RUN_DIR)
    summary["seconds"]["report"] = time.perf_counter() - t
    summary["seconds_total"] = time.perf_counter() - began
    summary["report"] = str(report)
    config_lib.save_json(out / "summary.json", summary)


def run_demo(config: DemoConfig, out: str | os.PathLike, progress: bool = False,
             log: ProgressFn | None = None) -> dict[str, Any]:
    """Run the demo into ``out`` (see the module docstring); return its summary.

    ``progress``: bars for every stage; ``log``: called with one line per finished stage (e.g.
    ``print``). The summary (also ``OUT/summary.json``) holds per sequence the prior's error
    composition; for the test sequence the metrics of ``prior``, ``trained``, ``adapted`` and the
    final ``corrected`` trajectory, the acceptance ``decisions``, ``final`` (which one is in
    ``corrected.txt``) and ``change_pct`` (final against prior, %); the selected epoch, the
    seconds per stage and ``report``. Raises :class:`DemoError` for a VO prior that is not VO.
    """
    import jax

    say = log or (lambda line: None)
    out = Path(out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    train_config = config.train_config(out / _CACHE_DIR)
    size = train_config.resolved_image_size
    seconds = dict.fromkeys(("render", "vo", "prepare"), 0.0)
    began = time.perf_counter()

    records, lengths = _prepare_sequences(config, out, size, seconds, progress, say)
    trained = _train(train_config, out / _RUN_DIR, seconds, progress, say)
    tested = _correct_test(config, out, seconds, progress, say)
    evaluation, summary = _evaluate_test(config, tested, trained)
    summary.update({
        "sequences": records,
        "lengths_m": lengths,
        "seconds": seconds,  # the same dict: the report stage adds its time after the report is written
        "devices": [str(d) for d in jax.devices()],
        "config": config_lib.to_dict(config),
    })
    if tested.adaptation is not None:
        summary["adaptation"] = tested.adaptation.summary()
    _write_results(out, config, train_config, evaluation, summary, began)
    return summary
