"""The detection-limit study (``experiments/studies/detection_limit.py``): its grid and its cells. How small
a rotation bias of libviso2-s's structure self-supervision removes, by bias scale, training pairs, optimizer
steps, input resolution and world.

* :class:`Study`: one profile's grid (``experiments/studies/configs/detection_limit.py``) with its world,
  training and correction; :func:`load_study`.
* :func:`libviso2_reference`: the reference ×1 from libviso2-s's own error.
* :func:`prepare`: the caches of a (size, scale), the priors planted (``dpc_jax.experiments.world``).
* :func:`run_cell`: a cell trained (no ground truth) and measured against the ground truth, with the
  study's decision and the earlier one.

What the cells answer is :mod:`dpc_jax.experiments.detection_answer`; the options of where the mean is
tested and the rule that chooses among them, :mod:`dpc_jax.experiments.detection_rule`; the tables, the
page and the figure, :mod:`dpc_jax.experiments.detection_page`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import runpy
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.correction.decision import MEAN_TESTS
from dpc_jax.experiments.world import World, planted

# The one-sided test's normal quantiles at α = 0.01 and 80 % power, and the Wilcoxon test's asymptotic
# efficiency against the t test (3/π): the pairs a mean test needs, from its differences' mean and spread.
Z_ALPHA, Z_POWER, WILCOXON_EFFICIENCY = 2.326, 0.842, 3.0 / math.pi
# The study's "final" column: the mean tested at the network's size (the decision its earliest cells were
# measured by), whatever the default of ``correct`` is, so that cells measured before and after a change of
# the default agree; the default's figures are its option's, decided with the judge (``decisions``).
FINAL_DECISION = "mean-at-network"


@dataclasses.dataclass(frozen=True)
class Study:
    """One profile's grid with its world and training (see ``configs/detection_limit.py``)."""

    scales: tuple[float, ...]
    pairs: tuple[int, ...]
    sizes: tuple[tuple[int, int], ...]
    render: tuple[int, int]
    world: dict[str, Any]
    training: dict[str, Any]
    correction: dict[str, Any]
    matched: tuple[int, ...] = ()  # the N that also train for as many steps as ``steps_of`` pairs
    steps_of: int = 0
    world_seed: int = 0

    def sequences(self) -> dict[str, tuple[int, int]]:
        """Rendered sequence name → (frames, seed offset), in rendering order."""
        w = self.world
        count = max(1, *(n // (w["train_frames"] - 1) for n in self.pairs))
        names = {f"train{i}": (w["train_frames"], i) for i in range(count)}
        names["val"] = (w["validation_frames"], 100)
        names |= {f"test{i}": (w["test_frames"], 200 + i) for i in range(w["test_sequences"])}
        return names

    def train_names(self, pairs: int) -> tuple[str, ...]:
        """The caches a cell with ``pairs`` training pairs trains on: whole training sequences, or for
        fewer pairs than one holds the first ``pairs + 1`` frames of ``train0`` (:meth:`prefixes`)."""
        per = self.world["train_frames"] - 1
        if 0 < pairs < per:
            return (f"train0_first{pairs}",)
        if pairs <= 0 or pairs % per:
            raise ValueError(f"pairs {pairs} is neither below nor a multiple of a training sequence's "
                             f"{per} pairs")
        return tuple(f"train{i}" for i in range(pairs // per))

    def prefixes(self) -> dict[str, int]:
        """Cache name → frames, for the cells that train on a prefix of ``train0``."""
        per = self.world["train_frames"] - 1
        return {f"train0_first{n}": n + 1 for n in self.pairs if n < per}

    @property
    def tests(self) -> tuple[str, ...]:
        return tuple(f"test{i}" for i in range(self.world["test_sequences"]))

    @property
    def judge(self) -> tuple[int, int] | None:
        """The size the test sequences are rendered and prepared at again to judge the options, or None."""
        size = self.correction.get("judge")
        return None if size is None else (int(size[0]), int(size[1]))

    @property
    def seed(self) -> int:
        """The world's seed: sequence k renders with ``seed + offset``."""
        return int(self.world["seed"]) + 1000 * self.world_seed

    def cells(self) -> list[tuple[tuple[int, int], float, int, bool]]:
        """Every (size, scale, pairs, matched) of the grid: the largest bias first at each size (a run cut
        short keeps the cells most likely to show a removal), a matched cell after its fixed-epoch one."""
        scales = sorted(self.scales, reverse=True)
        return [(size, scale, pairs, matched) for size in self.sizes for scale in scales
                for pairs in self.pairs for matched in (False, True) if not matched or pairs in self.matched]

    def restricted(self, pairs: Sequence[int] | None, sizes: Sequence[tuple[int, int]] | None,
                   scales: Sequence[float] | None) -> Study:
        """The cells of these N, sizes and scales only (None: all); ``ValueError`` naming the option for
        one the grid does not have."""
        study = self
        for option, field, given, text in (("--pairs", "pairs", pairs, str),
                                           ("--sizes", "sizes", sizes, lambda v: f"{v[0]}x{v[1]}"),
                                           ("--scales", "scales", scales, lambda v: f"{v:g}")):
            if not given:
                continue
            grid = getattr(study, field)
            unknown = [v for v in given if v not in grid]
            if unknown:
                listed = ", ".join(map(text, grid))
                raise ValueError(f"{option} {text(unknown[0])}: not in the grid ({listed})")
            kept: dict[str, Any] = {field: tuple(v for v in grid if v in given)}
            study = dataclasses.replace(study, **kept)
        return study

    def training_for(self, pairs: int, matched: bool) -> dict[str, Any]:
        """The cell's training: the config's, or for a matched cell the epochs (with the learning-rate
        halving and the depth-only warm-up at the same fractions) scaled by ``steps_of / pairs``."""
        if not matched:
            return dict(self.training)
        factor = self.steps_of / pairs
        epochs = max(1, round(self.training["epochs"] * factor))
        scaled = {key: max(1, round(self.training.get(key, default) * factor))
                  for key, default in (("lr_halving_epochs", 1), ("pose_warmup_epochs", 1))}
        return {**self.training, "epochs": epochs, **scaled}


def load_study(config_file: Path, profile: str, quick: bool, world_seed: int = 0) -> tuple[Study, int]:
    """The grid of ``profile`` (or the quick one) of the study's ``config_file`` in world ``world_seed``,
    and the papers' pair count."""
    config = runpy.run_path(str(config_file))
    grid = config["QUICK"]["profile"] if quick else config["PROFILES"][profile]
    world = {**config["WORLD"], **(config["QUICK"]["world"] if quick else {})}
    training = {**config["TRAINING"], **(config["QUICK"]["training"] if quick else {})}
    matched = config["QUICK"]["matched"] if quick else config["MATCHED"]
    pairs = tuple(int(n) for n in grid["pairs"])
    correction = {**config["CORRECTION"], "judge": None if grid.get("judge") is None else list(grid["judge"])}
    unknown = [d for d in correction.get("decisions", ()) if d not in MEAN_TESTS]
    if unknown:
        raise ValueError(f"{config_file}: CORRECTION decisions: {unknown[0]!r} is not one of "
                         f"{list(MEAN_TESTS)}")
    study = Study(tuple(float(s) for s in grid["scales"]), pairs, tuple(tuple(s) for s in grid["sizes"]),
                  tuple(grid["render"]), world, training, correction,
                  tuple(n for n in matched["pairs"] if n in pairs and grid.get("matched", True)),
                  int(matched["steps_of"]), world_seed)
    for n in study.pairs:
        study.train_names(n)
    return study, int(config["PAPER_PAIRS"])


# -- libviso2-s's error, the reference "×1" ------------------------------------------------------------

def libviso2_reference(folder: Path) -> dict[str, Any]:
    """``--diagnose`` of every ``stereo_*.mat`` in ``folder``: per sequence the per-step rotation mean and
    spread (mrad, camera axes x, y, z), and their per-axis medians (the reference ×1)."""
    from dpc_jax.data.poses_io import read_trajectory
    from dpc_jax.eval.diagnosis import diagnose

    files = sorted(folder.glob("stereo_*.mat"))
    if not files:
        raise FileNotFoundError(f"{folder}: no stereo_*.mat (libviso2-s with ground truth); "
                                "pass --libviso2 DIR")
    sequences = {}
    for path in files:
        gt = read_trajectory(path, mat_key="poses_gt")
        est = read_trajectory(path, mat_key="poses_est")
        est = gt[0] @ np.linalg.inv(est[0]) @ est  # from the first ground-truth pose, as evaluate does
        d = diagnose(gt, est)
        name = path.stem.removeprefix("stereo_")
        sequences[name] = {"mean": list(d.mean[3:]), "spread": list(d.spread[3:])}
    means = np.array([s["mean"] for s in sequences.values()])
    spreads = np.array([s["spread"] for s in sequences.values()])
    return {"source": str(folder), "sequences": sequences, "mean": list(np.median(means, 0)),
            "spread": list(np.median(spreads, 0))}


# -- data ------------------------------------------------------------------------------------------------

def render(study: Study, data: Path) -> None:
    """Render every sequence of the study into ``data`` (KITTI odometry layout), once."""
    w = study.world
    nuisances = {k: w[k] for k in ("moving_objects", "illumination_drift", "noise")}
    world = World(study.render, study.seed, nuisances)
    world.render(data, study.sequences(), lambda line: print(line, flush=True))
    if study.judge is not None:  # the same sequences (same seeds, same poses) at the judge's size
        tests = {name: v for name, v in study.sequences().items() if name in study.tests}
        World(study.judge, study.seed, nuisances).render(judge_data(data), tests,
                                                         lambda line: print(line, flush=True))


def judge_data(data: Path) -> Path:
    """Where the test sequences are rendered at the judge's size, beside ``data``."""
    return data.with_name(data.name + "_judge")


def judge_root(workdir: Path, study: Study, scale: float) -> Path | None:
    """The root of the judge caches of bias scale ``scale`` (None without a judge): a folder of their own,
    apart from the network's caches even at the network's size (the quick grid's judge)."""
    if study.judge is None:
        return None
    return workdir / "cache" / f"judge_{study.judge[0]}x{study.judge[1]}" / f"s{scale:g}"


def prepare(study: Study, workdir: Path, reference: dict[str, Any], scale: float,
            size: tuple[int, int]) -> Path:
    """The caches the study's cells read at ``size`` with the prior of bias scale ``scale``; their root."""
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry

    root = workdir / "cache" / f"{size[0]}x{size[1]}" / f"s{scale:g}"
    bias = scale * 1e-3 * np.asarray(reference["mean"])
    spread = scale * 1e-3 * np.asarray(reference["spread"])
    read = {n for pairs in study.pairs for n in study.train_names(pairs)} | {"val", *study.tests}
    prefixes = study.prefixes()
    for name, (_, offset) in study.sequences().items():
        sequence = open_odometry(workdir / "data", name)
        # The same noise draw at every scale: cells of one sequence differ only by s.
        prior = planted(workdir / "data", name, bias, spread, seed=offset + 1000 * study.world_seed)
        if name in read:
            prepare_sequence(sequence, prior, root, size=size, progress=False)
        if name == "train0":
            for prefix, frames in prefixes.items():
                prepare_sequence(sequence, prior, root, size=size, frames=(0, frames), name=prefix,
                                 progress=False)
        judged = judge_root(workdir, study, scale)
        if judged is not None and study.judge is not None and name in study.tests:
            # The judge replaces this prior by the network's cache's (the same planted one) when it measures.
            prepare_sequence(open_odometry(judge_data(workdir / "data"), name), prior, judged,
                             size=study.judge, progress=False)
    return root


# -- one cell ----------------------------------------------------------------------------------------------

def cell_key(size: tuple[int, int], scale: float, pairs: int, matched: bool = False) -> str:
    return f"{size[0]}x{size[1]}_s{scale:g}_n{pairs}" + ("_steps" if matched else "")


def rotation_mean_mrad(gt: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """The mean per-step rotation error ``[3]`` (mrad) of ``estimate`` against ``gt``."""
    from dpc_jax.eval.diagnosis import diagnose

    return np.asarray(diagnose(gt, estimate).mean[3:])


def _found(prior: float, after: float) -> float:
    return float("nan") if not (prior > 0 and math.isfinite(after)) else 1.0 - after / prior


def _number(value: float | None) -> float:
    """A metric as a float: NaN where there is none (a sequence shorter than 100 m has no segment
    error), which no change and no removal is computed from."""
    return math.nan if value is None else float(value)


def _change_pct(prior: float, after: float) -> float:
    return 100.0 * (after / prior - 1.0) if prior > 0 else math.nan


def train_cell(study: Study, workdir: Path, cache_root: Path, size: tuple[int, int], pairs: int,
               matched: bool, key: str) -> tuple[float, int]:
    """Train the cell's network in ``WORKDIR/runs/KEY`` (no ground truth; resumed when interrupted);
    the seconds it took and the optimizer steps it made."""
    from dpc_jax import config as config_lib
    from dpc_jax.training.loop import train
    from dpc_jax.training.train_config import TrainConfig

    config = config_lib.from_dict(TrainConfig, {
        **study.training_for(pairs, matched), "image_size": size, "cache_root": str(cache_root),
        "train_sequences": study.train_names(pairs), "validation_sequences": ("val",),
        "test_sequences": study.tests}, where="the study's TRAINING")
    began = time.perf_counter()
    trained = train(config, workdir / "runs" / key, resume=True, progress=False)
    return time.perf_counter() - began, int(trained["step"])


def pairs_needed(test: Any) -> float:
    """The pairs a one-sided mean test of these differences (``PairedTest``) needs at α = 0.01 with 80 %
    power (normal approximation, Wilcoxon efficiency); inf when their mean is not below 0."""
    if not test.mean_delta < 0 or not test.std_delta > 0:
        return math.inf
    ratio = (Z_ALPHA + Z_POWER) * test.std_delta / -test.mean_delta
    return ratio**2 / WILCOXON_EFFICIENCY


def measure_cell(study: Study, run_dir: Path, cache_root: Path,
                 judges: Path | None = None) -> tuple[int, list[dict[str, Any]]]:
    """Correct each test sequence with the run's epoch of most negative validation Δ behind the acceptance
    test (the study's decision at the network's size, the earlier one, and with the judge caches under
    ``judges`` every option of ``decisions``, all from the same proposal) and measure the removal against
    the ground truth (read here only): the epoch and one record per test sequence."""
    from dpc_jax.correction.corrector import correct_sequence, decided_again
    from dpc_jax.correction.inference import load_run
    from dpc_jax.eval.evaluation import evaluate

    run = load_run(run_dir, "delta")
    rotation_only = bool(study.correction["rotation_only"])
    first = "rotation" if rotation_only else "full"
    names = {"whole": first, "mean": f"mean of {first}", "remainder": f"{first} − mean"}
    tests = []
    for name in study.tests:
        # One store of Δ per sequence: each candidate is measured once, whichever decision asks for it.
        common = {"rotation_only": rotation_only, "window": study.correction["mean_window"], "store": {}}
        done = correct_sequence(run, cache_root / name, mean_test=study.correction["mean_test"],
                                mean=MEAN_TESTS[FINAL_DECISION], **common)
        final = done.trained
        earlier = decided_again(run, cache_root / name, done=done, mean_test=False, **common).trained
        decided = {} if judges is None else {
            option: decided_again(run, cache_root / name, done=done, mean=MEAN_TESTS[option],
                                  judge=judges / name, **common).trained
            for option in study.correction.get("decisions", ())}
        gt = np.asarray(final.ground_truth, np.float64)
        estimates = {"prior": final.prior, "network": final.proposed, "final": final.corrected,
                     "earlier": earlier.corrected, **{o: c.corrected for o, c in decided.items()}}
        summary = evaluate(gt, estimates).estimates
        axis = {k: float(np.linalg.norm(rotation_mean_mrad(gt, v))) for k, v in estimates.items()}
        seg = {k: _number(summary[k]["seg_rot_deg_per_100m"]) for k in estimates}
        mate = {k: _number(summary[k]["m_ate_rot_deg"]) for k in estimates}
        acceptance = final.acceptance
        p = {part: acceptance.tests[name].p_value if name in acceptance.tests else None
             for part, name in names.items()}
        mean_test = acceptance.tests.get(f"mean of {first}")
        options = {}
        for option, correction in decided.items():
            made = correction.acceptance.tests
            options[option] = {
                "decision": correction.acceptance.part,
                # p of each part at the network's size and at the judge's (None: not tested there)
                **{f"p_{part}{where}": made[n + suffix].p_value if n + suffix in made else None
                   for part, n in names.items() for where, suffix in (("", ""), ("_judge", " (judge)"))},
                "p": {n: test.p_value for n, test in made.items()},
                "found_axis": _found(axis["prior"], axis[option]),
                "found_seg": _found(seg["prior"], seg[option]),
                "axis_mrad": axis[option], "r": seg[option], "mate_r": mate[option],
                "r_change_pct": _change_pct(seg["prior"], seg[option]),
                "mate_r_change_pct": _change_pct(mate["prior"], mate[option])}
        tests.append({
            "sequence": name, "decision": acceptance.part, "earlier_decision": earlier.acceptance.part,
            "p_whole": p["whole"], "p_mean": p["mean"], "p_remainder": p["remainder"],
            "mean_pairs_needed": None if mean_test is None else pairs_needed(mean_test),
            "mean_test_pairs": None if mean_test is None else mean_test.pairs,
            "scale_applied": acceptance.scale,
            **{f"{k}_axis_mrad": axis[k] for k in ("prior", "network", "final", "earlier")},
            **{f"{k}_r": seg[k] for k in ("prior", "network", "final", "earlier")},
            **{f"{k}_mate_r": mate[k] for k in ("prior", "network", "final", "earlier")},
            **{f"found_axis_{k}": _found(axis["prior"], axis[k]) for k in ("network", "final", "earlier")},
            **{f"found_seg_{k}": _found(seg["prior"], seg[k]) for k in ("network", "final", "earlier")},
            **{f"{k}_r_change_pct": _change_pct(seg["prior"], seg[k]) for k in ("final", "earlier")},
            **{f"{k}_mate_r_change_pct": _change_pct(mate["prior"], mate[k]) for k in ("final", "earlier")},
            "options": options,
        })
    return run.epoch, tests


def run_cell(study: Study, workdir: Path, cache_root: Path, cell: tuple[tuple[int, int], float, int, bool],
             stamp: dict[str, str], done: dict[str, Any] | None) -> dict[str, Any]:
    """The cell's record: trained (unless ``done`` holds its record, whose training is kept) and measured
    with the study's correction."""
    size, scale, pairs, matched = cell
    key = cell_key(size, scale, pairs, matched)
    if done:  # trained: its training is kept
        train_s, steps = done["train_s"], done.get("steps") or _steps_made(workdir / "runs" / key)
    else:
        train_s, steps = train_cell(study, workdir, cache_root, size, pairs, matched, key)
    epoch, tests = measure_cell(study, workdir / "runs" / key, cache_root, judge_root(workdir, study, scale))
    bias = scale * float(np.linalg.norm(study_reference_mean(workdir)))
    trained = {k: done[k] for k in ("machine", "commit", "python")} if done else stamp
    return {"key": key, "size": list(size), "scale": scale, "pairs": pairs, "matched": matched,
            "steps": steps, "world_seed": study.world_seed, "bias_mrad": bias, "train_s": train_s,
            "epoch": epoch, "correction": study.correction, "tests": tests, **trained,
            "measured_commit": stamp["commit"]}


def _steps_made(run_dir: Path) -> int:
    """The optimizer steps a finished run made: its metrics log's last ``step``."""
    import csv

    with (run_dir / "metrics.csv").open(newline="") as log:
        return int(list(csv.DictReader(log))[-1]["step"])


def study_reference_mean(workdir: Path) -> np.ndarray:
    return np.asarray(json.loads((workdir / "reference.json").read_text())["mean"])
