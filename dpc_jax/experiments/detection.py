"""The detection-limit study (``experiments/studies/detection_limit.py``): how small a rotation bias of
libviso2-s's structure self-supervision removes, by bias scale, training pairs, optimizer steps,
input resolution and world.

* :class:`Study`: one profile's grid (``experiments/studies/configs/detection_limit.py``) with its world,
  training and correction; :func:`load_study`.
* :func:`libviso2_reference`: the reference ×1 from libviso2-s's own error.
* :func:`prepare`: the caches of a (size, scale), the priors planted (``dpc_jax.experiments.world``).
* :func:`run_cell`: a cell trained (no ground truth) and measured against the ground truth, with the
  study's decision and the earlier one.
* The answer: :func:`smallest_found`, :func:`half_scale`, :func:`extrapolate`; the tables
  (:func:`markdown`, :func:`long_rows`) and the :func:`figure`.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import runpy
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.correction.decision import DEFAULT_MEAN_TEST, MEAN_TESTS
from dpc_jax.experiments.world import World, planted
from dpc_jax.report.tables import table

# A removal this large counts as found (the bar).
FOUND = 0.5
# Deliver 3: a final trajectory may not raise the rotational segment error by more than this.
TOLERANCE_PCT = 2.0
# The one-sided test's normal quantiles at α = 0.01 and 80 % power, and the Wilcoxon test's asymptotic
# efficiency against the t test (3/π): the pairs a mean test needs, from its differences' mean and spread.
Z_ALPHA, Z_POWER, WILCOXON_EFFICIENCY = 2.326, 0.842, 3.0 / math.pi
CSV_COLUMNS = ("size", "scale", "pairs", "steps", "world_seed", "sequence", "bias_mrad", "decision",
               "p_whole", "p_mean", "p_remainder", "mean_pairs_needed", "earlier_decision", "prior_axis_mrad",
               "network_axis_mrad", "final_axis_mrad", "earlier_axis_mrad", "prior_r", "network_r", "final_r",
               "earlier_r", "prior_mate_r", "final_mate_r", "earlier_mate_r", "found_axis_network",
               "found_axis_final", "found_axis_earlier", "found_seg_network", "found_seg_final",
               "found_seg_earlier", "final_r_change_pct", "final_mate_r_change_pct", "earlier_r_change_pct",
               "earlier_mate_r_change_pct", "train_s", "epoch", "machine", "commit")
# Per option of where the mean is tested (``options`` of a test's record), ``OPTION:FIELD`` columns.
OPTION_FIELDS = ("decision", "p_whole", "p_mean", "p_remainder", "p_whole_judge", "p_mean_judge",
                 "p_remainder_judge", "found_axis", "found_seg", "r_change_pct", "mate_r_change_pct")
OPTION_COLUMNS = tuple(f"{option}:{field}" for option in MEAN_TESTS for field in OPTION_FIELDS)
# The rule of docs/method.md §8 (stated before the options' results): the worlds it chooses on, the one
# that checks the choice, the cells whose median removal it compares, and a tie.
CHOOSING_WORLDS, CHECKING_WORLD = (0, 1, 2), 3
RULE_CELLS = {"size": (64, 96), "scale": 1.0, "pairs": 1000}
TIE_POINTS = 1.0


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
        done = correct_sequence(run, cache_root / name, mean_test=study.correction["mean_test"], **common)
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


# -- the answer ------------------------------------------------------------------------------------------

def cell_mean(cell: dict[str, Any], field: str) -> float:
    values = [t[field] for t in cell["tests"] if t[field] is not None and math.isfinite(t[field])]
    return float(np.mean(values)) if values else math.nan


def own_world(cells: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The cells of the first world among ``cells`` (the tabulating work folder's, whose cells come
    first): the answer and the figure are one world's; the others enter the worlds' spread table."""
    seed = cells[0].get("world_seed", 0) if cells else 0
    return [c for c in cells if c.get("world_seed", 0) == seed]


def smallest_found(cells: Sequence[dict[str, Any]],
                   field: str = "found_axis_final") -> dict[tuple, float | None]:
    """Per (size, pairs): the smallest bias scale removed by at least :data:`FOUND` (None: none)."""
    out: dict[tuple, float | None] = {}
    for cell in cells:
        key = (tuple(cell["size"]), cell["pairs"])
        out.setdefault(key, None)
        if cell_mean(cell, field) >= FOUND:
            found = out[key]
            out[key] = cell["scale"] if found is None else min(found, cell["scale"])
    return out


def half_scale(cells: Sequence[dict[str, Any]], size: tuple[int, int], pairs: int,
               field: str = "found_axis_final") -> tuple[float, str] | None:
    """The bias scale s50 at which the removal crosses :data:`FOUND`, interpolated in log s between the
    grid's scales, as ``(s50, "=")``; ``(smallest scale, "≤")`` when the smallest scale is already
    removed by that much; None when no scale of the grid is."""
    points = sorted((c["scale"], cell_mean(c, field)) for c in cells
                    if tuple(c["size"]) == size and c["pairs"] == pairs)
    if points and math.isfinite(points[0][1]) and points[0][1] >= FOUND:
        return points[0][0], "≤"
    for (s0, f0), (s1, f1) in itertools.pairwise(points):
        if math.isfinite(f0) and math.isfinite(f1) and f0 < FOUND <= f1:
            t = (FOUND - f0) / (f1 - f0)
            return float(math.exp(math.log(s0) + t * (math.log(s1) - math.log(s0)))), "="
    return None


def extrapolate(cells: Sequence[dict[str, Any]], size: tuple[int, int]) -> dict[str, Any]:
    """At ``size``: the smallest N of the grid whose cell at ×1 is removed by :data:`FOUND` or more
    (``found_at``), else the fit ``log s50 = a + b · log N`` over the N with an interpolated crossing and
    the N where it reaches s50 = 1 (``pairs_at_x1``; ``inf`` when s50 does not fall with N)."""
    pairs = sorted({c["pairs"] for c in cells if tuple(c["size"]) == size})
    found = [n for n in pairs for c in cells
             if tuple(c["size"]) == size and c["pairs"] == n and c["scale"] <= 1.0
             and cell_mean(c, "found_axis_final") >= FOUND]
    crossings = {n: half_scale(cells, size, n) for n in pairs}
    points = [(n, h[0]) for n, h in crossings.items() if h is not None and h[1] == "="]
    fit: dict[str, Any] = {"found_at": min(found) if found else None, "points": points, "slope": None,
                           "pairs_at_x1": None}
    if fit["found_at"] is None and len(points) >= 2:
        slope, intercept = np.polyfit(np.log([n for n, _ in points]), np.log([s for _, s in points]), 1)
        fit["slope"] = float(slope)
        fit["pairs_at_x1"] = float(math.exp(-intercept / slope)) if slope < 0 else math.inf
    return fit


def long_rows(cells: Sequence[dict[str, Any]]) -> list[list[object]]:
    """One row per cell and test sequence: :data:`CSV_COLUMNS`, then :data:`OPTION_COLUMNS`."""
    rows = []
    for c in cells:
        for t in c["tests"]:
            values = {**c, **t, "size": f"{c['size'][0]}x{c['size'][1]}",
                      "world_seed": c.get("world_seed", 0)}
            options = {f"{o}:{k}": v for o, fields in t.get("options", {}).items() for k, v in fields.items()}
            rows.append([values.get(k) for k in CSV_COLUMNS] + [options.get(k) for k in OPTION_COLUMNS])
    return rows


def _worst(records: Sequence[dict[str, Any]], field: str) -> float:
    """The largest finite ``field`` of ``records`` (−inf when none has one: a sequence shorter than 100 m
    has no segment error, and raises nothing)."""
    return max((r[field] for r in records if r[field] is not None and math.isfinite(r[field])),
               default=-math.inf)


def _finite_mean(values: Sequence[float]) -> float:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _decided(cells: Sequence[dict[str, Any]], option: str) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(cell, the option's record of one test sequence) for every test sequence ``option`` decided."""
    return [(c, t["options"][option]) for c in cells for t in c["tests"] if option in t.get("options", {})]


def _applied_mean_p(decided: dict[str, Any], suffix: str) -> str:
    """The p of the mean's test of the applied component (the whole rotation's when nothing is applied)
    at one size (``suffix``: " (judge)" or ""), – where it was not tested there."""
    component = decided["decision"].split(" ")[0]
    name = "mean of " + ("rotation" if component == "none" else component) + suffix
    return _p(decided["p"].get(name))


def options_table(cells: Sequence[dict[str, Any]], options: Sequence[str]) -> str:
    """One row per cell decided by the options: per option the removal (axis, mean over the test
    sequences), the largest change of the rotational segment error and m-ATE against the prior, and per
    test sequence what was applied with the p of the mean at the judge's size (and at the network's)."""
    def entry(c: dict[str, Any], option: str) -> str:
        decided = [t["options"][option] for t in c["tests"] if option in t.get("options", {})]
        if not decided:
            return "–"
        axis = _finite_mean([d["found_axis"] for d in decided])
        worst = _worst(decided, "r_change_pct"), _worst(decided, "mate_r_change_pct")
        parts = "; ".join(f"{d['decision']} (mean p {_applied_mean_p(d, ' (judge)')} / "
                          f"{_applied_mean_p(d, '')})" for d in decided)
        return f"{_pct(axis)}, worst {worst[0]:+.1f} / {worst[1]:+.1f} %: {parts}"

    rows = [c for c in sorted(cells, key=_order) if any(t.get("options") for t in c["tests"])]
    return table(["world", "size", "N pairs", "steps", "bias ×", *options],
                 ([str(c.get("world_seed", 0)), f"{c['size'][0]}×{c['size'][1]}", str(c["pairs"]),
                   f"{c.get('steps', '?')}" + (" (matched)" if c.get("matched") else ""), f"×{c['scale']:g}",
                   *(entry(c, o) for o in options)] for c in rows))


def apply_rule(cells: Sequence[dict[str, Any]], options: Sequence[str],
         expected: dict[int, set[str]]) -> tuple[list[list[str]], str]:
    """The rule of ``docs/method.md`` §8 on ``cells``: per option its worst final change (rotational
    segment error, rotational m-ATE) over the choosing worlds, whether that is within
    :data:`TOLERANCE_PCT`, the median removal of its :data:`RULE_CELLS`, the worst change on the checking
    world; and the verdict: the chosen option, or why none is chosen yet (``expected``: per world the keys
    of its grid's cells, every one of which the choosing worlds need decided by every option)."""
    choosing = [c for c in cells if c.get("world_seed", 0) in CHOOSING_WORLDS]
    checking = [c for c in cells if c.get("world_seed", 0) == CHECKING_WORLD]
    rows, measured = [], {}
    for option in options:
        decided = _decided(choosing, option)
        records = [d for _, d in decided]
        worst = max(_worst(records, "r_change_pct"), _worst(records, "mate_r_change_pct"))
        removal = [d["found_axis"] for c, d in decided
                   if tuple(c["size"]) == RULE_CELLS["size"] and c["scale"] == RULE_CELLS["scale"]
                   and c["pairs"] == RULE_CELLS["pairs"] and not c.get("matched")]
        median = float(np.median(removal)) if removal else math.nan
        checked = [d for _, d in _decided(checking, option)]
        check = max(_worst(checked, "r_change_pct"), _worst(checked, "mate_r_change_pct"))
        measured[option] = (worst, median)
        rows.append([option, str(len(decided)), _change(worst), "yes" if worst <= TOLERANCE_PCT else "no",
                     f"{_pct(median)} (of {len(removal)})", _change(check)])
    have = {(c.get("world_seed", 0), c["key"]) for c in choosing
            if all(o in t.get("options", {}) for t in c["tests"] for o in options)}
    missing = [(w, k) for w in CHOOSING_WORLDS for k in sorted(expected.get(w, ())) if (w, k) not in have]
    if missing:
        total = sum(len(expected.get(w, ())) for w in CHOOSING_WORLDS)
        return rows, (f"The rule is not applied: {total - len(missing)} of the {total} cells of worlds "
                      f"{', '.join(map(str, CHOOSING_WORLDS))} are decided by every option (missing: "
                      + ", ".join(f"world {w} {k}" for w, k in missing[:8])
                      + (", …" if len(missing) > 8 else "") + "); the default stays "
                      f"{DEFAULT_MEAN_TEST}.")
    safe = {o: v for o, v in measured.items() if v[0] <= TOLERANCE_PCT and math.isfinite(v[1])}
    if not safe:
        return rows, f"No option is safe on worlds 0–2; the default stays {DEFAULT_MEAN_TEST}."
    best = max(v[1] for v in safe.values())
    tied = [o for o, v in safe.items() if 100 * (best - v[1]) <= TIE_POINTS]
    chosen = min(tied, key=lambda o: safe[o][0])
    if DEFAULT_MEAN_TEST in safe and 100 * (safe[chosen][1] - safe[DEFAULT_MEAN_TEST][1]) <= TIE_POINTS:
        chosen = DEFAULT_MEAN_TEST
    return rows, (f"Chosen by the rule on worlds 0–2: {chosen} (median removal {_pct(safe[chosen][1])}); "
                  f"its check on world {CHECKING_WORLD} is in the table above.")


def _pct(value: float) -> str:
    return "n/a" if not math.isfinite(value) else f"{100 * value:.0f} %"


def _p(value: float | None) -> str:
    return "–" if value is None else f"{value:.2g}"


def _order(c: dict[str, Any]) -> tuple:
    return (c.get("world_seed", 0), c["size"], c["pairs"], c.get("matched", False), c["scale"])


def cells_table(cells: Sequence[dict[str, Any]]) -> str:
    """One row per cell: the removal (network, final, earlier decision), what was applied with each test's
    p, and the final's change of the rotational segment error and m-ATE against the prior."""
    return table(
        ["world", "size", "N pairs", "steps", "bias ×", "removed: network (axis / seg.)",
         "final", "earlier decision", "applied (p whole / mean / remainder)", "final r, m-ATE r vs prior",
         "earlier r, m-ATE r", "train (min)", "machine"],
        ([str(c.get("world_seed", 0)), f"{c['size'][0]}×{c['size'][1]}", str(c["pairs"]),
          f"{c.get('steps', '?')}" + (" (matched)" if c.get("matched") else ""), f"×{c['scale']:g}",
          f"{_pct(cell_mean(c, 'found_axis_network'))} / {_pct(cell_mean(c, 'found_seg_network'))}",
          f"{_pct(cell_mean(c, 'found_axis_final'))} / {_pct(cell_mean(c, 'found_seg_final'))}",
          f"{_pct(cell_mean(c, 'found_axis_earlier'))} / {_pct(cell_mean(c, 'found_seg_earlier'))}",
          "; ".join(f"{t['decision']} ({_p(t['p_whole'])} / {_p(t['p_mean'])} / {_p(t['p_remainder'])})"
                    for t in c["tests"]),
          "; ".join(f"{t['final_r_change_pct']:+.1f}, {t['final_mate_r_change_pct']:+.1f} %"
                    for t in c["tests"]),
          "; ".join(f"{t['earlier_r_change_pct']:+.1f}, {t['earlier_mate_r_change_pct']:+.1f} %"
                    for t in c["tests"]),
          f"{c['train_s'] / 60:.1f}", c["machine"]] for c in sorted(cells, key=_order)))


def worlds_table(cells: Sequence[dict[str, Any]]) -> str | None:
    """The removal (axis, final) of each (size, N, steps, scale) measured in more than one world: per world,
    and the mean and spread (min–max) over them; None when no cell is."""
    groups: dict[tuple, dict[int, float]] = {}
    for c in cells:
        key = (tuple(c["size"]), c["pairs"], bool(c.get("matched")), c["scale"])
        groups.setdefault(key, {})[c.get("world_seed", 0)] = cell_mean(c, "found_axis_final")
    shared = {k: v for k, v in groups.items() if len(v) > 1}
    if not shared:
        return None
    worlds = sorted({w for v in shared.values() for w in v})
    return table(
        ["size", "N pairs", "bias ×", *(f"world {w}" for w in worlds), "mean", "spread (min–max)"],
        ([f"{k[0][0]}×{k[0][1]}", f"{k[1]}" + (" (matched steps)" if k[2] else ""), f"×{k[3]:g}",
          *(_pct(v[w]) if w in v else "–" for w in worlds), _pct(float(np.mean(list(v.values())))),
          f"{_pct(min(v.values()))} – {_pct(max(v.values()))}"] for k, v in sorted(shared.items())))


def refused_means(cells: Sequence[dict[str, Any]]) -> list[str]:
    """The test sequences where the earlier decision removed at least :data:`FOUND` of the bias and the
    mean test refused the mean: the p it got and the pairs its power would need."""
    lines = []
    for c in sorted(cells, key=_order):
        for t in c["tests"]:
            lost = t["found_axis_earlier"] >= FOUND and t["found_axis_final"] < t["found_axis_earlier"] - 0.05
            if lost and t["p_mean"] is not None:
                needed = t["mean_pairs_needed"]
                lines.append(
                    f"- world {c.get('world_seed', 0)}, {c['size'][0]}×{c['size'][1]}, N = {c['pairs']}, "
                    f"×{c['scale']:g}, {t['sequence']}: the earlier decision removed "
                    f"{_pct(t['found_axis_earlier'])}, now {_pct(t['found_axis_final'])}; the mean's p = "
                    f"{t['p_mean']:.2g} on {t['mean_test_pairs']} pairs, "
                    + ("its differences' mean is not below 0: no number of pairs passes it" if not
                       math.isfinite(needed) else f"about {needed:,.0f} pairs would pass it (80 % power)"))
    return lines


def markdown(cells: Sequence[dict[str, Any]], reference: dict[str, Any], paper_pairs: int, minutes: float,
             quick: bool, expected: dict[int, set[str]] | None = None) -> str:
    per_machine: dict[str, float] = {}
    for c in cells:
        per_machine[c["machine"]] = per_machine.get(c["machine"], 0.0) + c["train_s"] / 60
    trained = "; ".join(f"{m:.0f} min on {name}" for name, m in per_machine.items()) or "none"
    worst = {field: max((t[field] for c in cells for t in c["tests"] if math.isfinite(t[field])),
                        default=math.nan)
             for field in ("final_r_change_pct", "final_mate_r_change_pct", "earlier_r_change_pct",
                           "earlier_mate_r_change_pct")}
    base = own_world(cells)
    fixed = [c for c in base if not c.get("matched")]
    smallest = smallest_found(fixed)
    lines = [f"- {s[0]}×{s[1]}, N = {n}: " + ("none of the grid's biases" if v is None else f"×{v:g}")
             for (s, n), v in sorted(smallest.items())]
    answer = [f"- {s[0]}×{s[1]}: " + _extrapolation_text(extrapolate(fixed, s), paper_pairs)
              for s in sorted({tuple(c["size"]) for c in fixed})]
    at_x1 = [c for c in base if c["scale"] <= 1.0 and cell_mean(c, "found_axis_final") >= FOUND]
    goal = [f"- {s[0]}×{s[1]}: " + _goal_text([c for c in at_x1 if tuple(c["size"]) == s])
            for s in sorted({tuple(c["size"]) for c in base})]
    ref = reference
    worlds = worlds_table(cells)
    refused = refused_means(cells)

    def verdict(value: float) -> str:
        return "holds" if not value > TOLERANCE_PCT else "**violated**"

    return "\n".join([
        "# How small an error self-supervision can find" + (" (QUICK RUN: wiring only)" if quick else ""), "",
        f"Reference ×1 (libviso2-s, median over {', '.join(ref['sequences'])} of `evaluate --diagnose`): "
        f"rotation bias per step {_vec(ref['mean'])} mrad (‖·‖ {np.linalg.norm(ref['mean']):.3f}), spread "
        f"{_vec(ref['spread'])} mrad (camera x, y, z: pitch, yaw, roll). A cell's prior carries s times "
        f"both. Removed: 1 − after / prior of the mean per-axis rotation error per step (axis) and of the "
        f"rotational segment error (seg.), mean over the {len(cells[0]['tests']) if cells else 0} held-out "
        f"test sequences; network = the proposal applied whatever its tests said; final = behind the "
        f"acceptance tests, the correction's mean tested on its own; earlier decision = the same proposal "
        f"behind the earlier tests (the mean not tested apart). Applied: what the tests let through "
        f"(`− mean`: without its mean), with the p of the whole rotation, of its mean and of its remainder "
        f"(– where not tested). Steps: the optimizer steps the network trained for (matched: a small N "
        f"trained as long as N = 1,000). This invocation ran {minutes:.0f} min (cells it found done are not "
        f"counted); training summed over the cells: {trained}.", "",
        cells_table(cells),
        "![Removal against N and against the bias](detection_limit.png)", "",
        *(["Removal (axis, final) in the worlds measured:", "", worlds] if worlds else []),
        f"Never worse: the worst final change against the prior over every cell and test sequence is "
        f"{worst['final_r_change_pct']:+.2f} % in the rotational segment error "
        f"({verdict(worst['final_r_change_pct'])}) and {worst['final_mate_r_change_pct']:+.2f} % in the "
        f"rotational m-ATE ({verdict(worst['final_mate_r_change_pct'])}), the bar being {TOLERANCE_PCT:g} %; "
        f"with the earlier decision {worst['earlier_r_change_pct']:+.2f} % and "
        f"{worst['earlier_mate_r_change_pct']:+.2f} %.", "",
        "Where the earlier decision removed half the bias or more and the mean test refused the mean:",
        *(refused or ["- nowhere."]), "",
        f"libviso2-s's bias (×1) removed by ≥ {100 * FOUND:.0f} % (axis, final) at the smallest N of pairs:",
        *goal, "",
        f"Smallest bias removed by ≥ {100 * FOUND:.0f} % (axis, final; fixed epochs) at each (N, "
        "resolution):", *lines, "",
        "The N at which libviso2-s's bias (×1) is removed by half (final, fixed epochs; else a fit of log "
        "s50 against log N over the grid's N, s50 interpolated in log s):", *answer, "",
        *_options_section(cells, expected or {})])


def _change(value: float) -> str:
    return f"{value:+.2f} %" if math.isfinite(value) else "–"


def _options_section(cells: Sequence[dict[str, Any]], expected: dict[int, set[str]]) -> list[str]:
    """The options of where the mean is tested side by side, and the rule's verdict (none decided: [])."""
    options = [o for o in MEAN_TESTS if _decided(cells, o)]
    if not options:
        return []
    rows, verdict = apply_rule(cells, options, expected)
    judges = ", ".join(sorted({"×".join(map(str, c["correction"]["judge"])) for c in cells
                               if (c.get("correction") or {}).get("judge")})) or "–"
    return [
        "### Where the mean is tested: the options side by side (docs/method.md §8)", "",
        "Every option decides the same proposal with the judge at the test sequences rendered again at "
        f"{judges} (the same poses). Per option: the removal (axis, mean over the test "
        "sequences), the largest change of the rotational segment error / rotational m-ATE against the "
        "prior, and per test sequence what was applied with the p of the mean's test at the judge's size "
        "/ at the network's (– where not tested).", "",
        options_table(cells, options),
        table(["option", "test sequences decided (worlds 0–2)", "worst final change (r or m-ATE)",
               f"safe (≤ +{TOLERANCE_PCT:g} %)", "median removal, ×1, N = 1,000, 64×96",
               f"worst on world {CHECKING_WORLD} (check)"], rows),
        verdict, ""]


def _goal_text(found: Sequence[dict[str, Any]]) -> str:
    """The smallest N of pairs among ``found`` (cells at ×1 removed by half), and whether only a cell
    trained with a larger N's steps reached it there."""
    if not found:
        return "not reached at any N of the grid"
    smallest = min(c["pairs"] for c in found)
    matched_only = all(c.get("matched") for c in found if c["pairs"] == smallest)
    return f"N = {smallest:,} pairs" + (" (with the steps of N = 1,000)" if matched_only else "")


def _vec(values: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:+.3f}" for v in values) + ")"


def _extrapolation_text(fit: dict[str, Any], paper_pairs: int) -> str:
    points = ", ".join(f"N {n}: ×{s:.2g}" for n, s in fit["points"]) or "none inside the grid"
    if fit["found_at"] is not None:
        return (f"already removed by ≥ {100 * FOUND:.0f} % at ×1 with N = {fit['found_at']:,} (the grid's "
                f"smallest such N; within the papers' {paper_pairs:,} pairs)")
    if fit["slope"] is None:
        return f"too few N with a 50 % crossing inside the grid to fit a trend (crossings: {points})"
    n1 = fit["pairs_at_x1"]
    if not math.isfinite(n1):
        return (f"s50 does not fall with N ({points}; slope {fit['slope']:+.2f}): more pairs alone do not "
                "reach ×1")
    verdict = "within" if n1 <= paper_pairs else "beyond"
    return (f"s50 ∝ N^{fit['slope']:+.2f} ({points}); ×1 at N ≈ {n1:,.0f}, {verdict} the papers' "
            f"{paper_pairs:,} pairs")


def figure(cells: Sequence[dict[str, Any]], reference: dict[str, Any], path: Path) -> None:
    """Left: removal (axis, final) against N, one curve per resolution and scale. Right: removal against
    the bias (mrad/step), one curve per resolution and N, with libviso2-s's per-sequence biases marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    matched = [c for c in own_world(cells) if c.get("matched")]
    cells = [c for c in own_world(cells) if not c.get("matched")]
    sizes = sorted({tuple(c["size"]) for c in cells})
    styles = dict(zip(sizes, ("o-", "s--", "^:"), strict=False))
    for size in sizes:
        for scale in sorted({c["scale"] for c in cells}):
            pts = sorted((c["pairs"], cell_mean(c, "found_axis_network"), cell_mean(c, "found_axis_final"))
                         for c in cells if tuple(c["size"]) == size and c["scale"] == scale)
            if pts:
                line, = left.plot([p[0] for p in pts], [p[2] for p in pts], styles[size],
                                  label=f"{size[0]}×{size[1]}, ×{scale:g}")
                left.plot([p[0] for p in pts], [p[1] for p in pts], "x", color=line.get_color())
                steps = sorted((c["pairs"], cell_mean(c, "found_axis_final")) for c in matched
                               if tuple(c["size"]) == size and c["scale"] == scale)
                left.plot([p[0] for p in steps], [p[1] for p in steps], "*", color=line.get_color(), ms=9)
        for pairs in sorted({c["pairs"] for c in cells}):
            by_bias = sorted((c["bias_mrad"], cell_mean(c, "found_axis_final")) for c in cells
                             if tuple(c["size"]) == size and c["pairs"] == pairs)
            if not by_bias:
                continue
            right.plot([p[0] for p in by_bias], [p[1] for p in by_bias], styles[size],
                       label=f"{size[0]}×{size[1]}, N {pairs}")
    for name, seq in reference["sequences"].items():
        bias = float(np.linalg.norm(seq["mean"]))
        right.axvline(bias, color="grey", lw=0.6, alpha=0.6)
        right.text(bias, 1.02, name, fontsize=6, rotation=90, va="bottom", ha="center",
                   transform=right.get_xaxis_transform())
    for ax in (left, right):
        ax.axhline(FOUND, color="k", lw=0.6, ls="--")
        ax.set_ylabel("bias removed (1 − ‖mean after‖ / ‖mean prior‖)")
        ax.set_xscale("log")
        if ax.get_legend_handles_labels()[0]:  # a grid with one N draws no curve on the right
            ax.legend(fontsize=7)
    left.set_xlabel("training pairs N (line: final, behind the tests; x: the network's proposal; *: final "
                    "with N = 1,000's steps)")
    right.set_xlabel("planted bias (mrad per step); grey: libviso2-s on KITTI 00–10")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
