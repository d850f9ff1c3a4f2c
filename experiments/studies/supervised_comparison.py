"""The papers' comparison on what we can run: prior → supervised linear baseline → supervised network →
self-supervised network (configs/supervised_comparison.py).

    python experiments/studies/supervised_comparison.py --workdir runs/supervised_comparison
    python experiments/studies/supervised_comparison.py --workdir /tmp/smoke --smoke --seeds 0  # wiring

Test data: the synthetic demo's held-out test sequence per seed (``--seeds``, default 0–4) and the
two real KITTI raw drives, each corrected by networks trained on the other (prior: our VO;
``--skip-drives`` leaves them out). Rows per test: the prior; the linear baseline
(``dpc_jax.eval.linear_baseline``, rotation only, fit by least squares on the training sequences'
ground truth: **supervised**) and its constant term alone (a per-axis bias); Stereo DPC trained with
DPC-Net's supervised loss (**supervised**: its training reads the ground truth) as trained, adapted
to the test sequence (self-supervised) and final; the same network trained self-supervised, as
trained, adapted and final. Each network row carries its ground-truth-free acceptance decision.

The demo runs through ``dpc_jax.pipelines.synthetic_demo`` into ``WORKDIR/seed_K`` (self-supervised; the
layout of ``demo_seeds.py``) and ``WORKDIR/supervised/seed_K``; the drives through
``kitti_raw_drives.py`` (``dpc_jax.pipelines.protocol``) into ``WORKDIR/drives`` and
``WORKDIR/supervised/drives``. A supervised folder links the self-supervised one's data, priors
and caches, so both networks read the same inputs. Re-running reuses what is finished: a demo whose
``summary.json`` has the same config, drives whose recorded arguments and config match, and
within a run every stage its pipeline reuses.

Writes ``WORKDIR/comparison.md`` (the table; per row kind the best and worst change against the
prior over the seeds) and ``WORKDIR/comparison.csv`` (long form: one row per test and row kind),
after every test.
"""

from __future__ import annotations

import argparse
import csv
import functools
import importlib.util
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from dpc_jax.pipelines.protocol import claim_workdir, path_argument
from dpc_jax.report.pages import check_results_page, write_results
from dpc_jax.report.tables import EMPTY, change_pct, csv_text, number, table
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "configs" / "supervised_comparison.py"
PROTOCOLS = HERE.parent / "protocols"

METRICS = ("seg_trans_pct", "seg_rot_deg_per_100m", "m_ate_trans_m", "m_ate_rot_deg", "ate_m",
           "rpe_trans_m", "rpe_rot_deg")
TITLES = ("seg. t (%)", "seg. r (°/100 m)", "m-ATE (m)", "m-ATE (°)", "ATE (m)", "RPE t (m)", "RPE r (°)")
# The metrics whose change against the prior the summary gives.
CHANGED = METRICS[:4]
# Row kinds in table order → their label (supervised rows say so: they read ground truth to train).
KINDS = {
    "prior": "prior (our VO)",
    "linear": "linear baseline, **supervised** (rotation)",
    "constant": "constant bias, **supervised** (rotation)",
    "supervised_trained": "network, **supervised**: trained",
    "supervised_adapted": "network, **supervised**: adapted (self-supervised)",
    "supervised_final": "network, **supervised**: final",
    "self_trained": "network, self-supervised: trained",
    "self_adapted": "network, self-supervised: adapted",
    "self_final": "network, self-supervised: final",
}
CSV_COLUMNS = ("test", "trained_on", "row", "decision", *METRICS)

Metrics = dict[str, float | None]


@dataclass(frozen=True)
class Row:
    """One row of the table: a test sequence, what its networks were trained on, the row kind
    (:data:`KINDS`), the acceptance decision (empty for the prior) and the metrics (:data:`METRICS`,
    None where undefined, e.g. segment errors of a trajectory shorter than 100 m)."""

    test: str
    trained_on: str
    kind: str
    decision: str
    metrics: Metrics


# --------------------------------------------------------------------------- the table (pure)


def _number(value: Any) -> float | None:
    """A metric from a summary (float, None, NaN) or a CSV cell (text, empty) → float or None."""
    if value is None or value == "":
        return None
    number = float(value)
    return None if math.isnan(number) else number


def _metrics(summary: Mapping[str, Any]) -> Metrics:
    return {k: _number(summary.get(k)) for k in METRICS}


def _network_rows(test: str, trained_on: str, kind: str,
                  stages: Mapping[str, tuple[str, Metrics]]) -> list[Row]:
    """The trained, adapted and final rows of one network (``stages``: label → (decision, metrics))."""
    return [Row(test, trained_on, f"{kind}_{label}", *stages[label])
            for label in ("trained", "adapted", "final") if label in stages]


def _demo_stages(summary: Mapping[str, Any]) -> dict[str, tuple[str, Metrics]]:
    """A demo ``summary.json``'s network rows: trained and adapted with their decisions, final."""
    stages = {label: (summary["decisions"].get(label, ""), _metrics(summary["test"][label]))
              for label in ("trained", "adapted") if label in summary["test"]}
    final = summary["final"]
    decision = final if final == "prior" else f"{final}: {summary['decisions'][final]}"
    stages["final"] = (decision, _metrics(summary["test"]["corrected"]))
    return stages


def _baseline_rows(test: str, trained_on: str, baselines: Mapping[str, Mapping[str, Any]]) -> list[Row]:
    """The supervised baselines' rows (``baselines``: ``linear`` and ``constant`` → metrics)."""
    return [Row(test, trained_on, kind, "applied (no test)", _metrics(baselines[kind]))
            for kind in ("linear", "constant")]


def demo_rows(seed: int, supervised: Mapping[str, Any], self_supervised: Mapping[str, Any],
              baselines: Mapping[str, Mapping[str, Any]], trained_on: str) -> list[Row]:
    """The rows of demo seed ``seed`` from the two demos' summaries (``summary.json``) and the
    baselines' metrics on the same test sequence (:func:`baseline_metrics`)."""
    test = f"demo seed {seed}"
    return [Row(test, trained_on, "prior", "", _metrics(self_supervised["test"]["prior"])),
            *_baseline_rows(test, trained_on, baselines),
            *_network_rows(test, trained_on, "supervised", _demo_stages(supervised)),
            *_network_rows(test, trained_on, "self", _demo_stages(self_supervised))]


def _drive_stages(rows: Sequence[Mapping[str, str]]) -> dict[str, tuple[str, Metrics]]:
    """``kitti_raw_drives.py``'s ``results.csv`` rows of one test drive → estimate → (decision, metrics)."""
    return {r["estimate"]: (r["decision"], _metrics(r)) for r in rows}


def drive_rows(drive: str, trained_on: str, supervised: Sequence[Mapping[str, str]],
               self_supervised: Sequence[Mapping[str, str]],
               baselines: Mapping[str, Mapping[str, Any]]) -> list[Row]:
    """The rows of test drive ``drive`` from the two drive runs' ``results.csv`` rows of that drive
    (estimates prior, trained, adapted, final) and the baselines' metrics (:func:`baseline_metrics`)."""
    test = f"drive {drive}"
    own = _drive_stages(self_supervised)
    prior = own.pop("prior")[1]
    other = _drive_stages(supervised)
    other.pop("prior", None)
    return [Row(test, trained_on, "prior", "", prior),
            *_baseline_rows(test, trained_on, baselines),
            *_network_rows(test, trained_on, "supervised", other),
            *_network_rows(test, trained_on, "self", own)]


def change_summary(rows: Sequence[Row]) -> list[str]:
    """Markdown lines: per row kind, the best and worst change against the prior (%) over the demo
    seeds in ``rows``, per metric of :data:`CHANGED` (with the seed), empty where no seed has it."""
    priors = {r.test: r.metrics for r in rows if r.kind == "prior" and r.test.startswith("demo ")}
    if not priors:
        return []
    seeds = ", ".join(t.removeprefix("demo seed ") for t in priors)
    cells_of = []
    for kind, label in KINDS.items():
        if kind == "prior":
            continue
        own = [r for r in rows if r.kind == kind and r.test in priors]
        if not own:
            continue
        cells = []
        for key in CHANGED:
            changes = [(c, r.test.removeprefix("demo seed ")) for r in own
                       if not math.isnan(c := change_pct(priors[r.test][key], r.metrics[key]))]
            if not changes:
                cells.append(EMPTY)
                continue
            (best, at_best), (worst, at_worst) = min(changes), max(changes)
            cells.append(f"{best:+.1f} % ({at_best}) … {worst:+.1f} % ({at_worst})")
        cells_of.append([label, *cells])
    return [f"Change against the prior over the demo seeds ({seeds}): best … worst, with the seed.", "",
            *table(["row", *TITLES[: len(CHANGED)]], cells_of).splitlines()]


def comparison_markdown(rows: Sequence[Row], notes: Sequence[str]) -> str:
    """The table (one line per :class:`Row`), the notes above it, the change summary below it."""
    body = table(["test", "trained on", "row", "decision", *TITLES],
                 ([r.test, r.trained_on, KINDS[r.kind], r.decision, *(number(r.metrics[k]) for k in METRICS)]
                  for r in rows))
    lines = ["# Prior → linear baseline → supervised network → self-supervised network", "", *notes, "",
             *body.splitlines()]
    summary = change_summary(rows)
    if summary:
        lines += ["", *summary]
    return "\n".join(lines) + "\n"


def comparison_csv(rows: Sequence[Row]) -> str:
    """Long form: one line per :class:`Row` (``row`` = its kind), empty cells for undefined metrics."""
    return csv_text(CSV_COLUMNS, ([r.test, r.trained_on, r.kind, r.decision, *(r.metrics[k] for k in METRICS)]
                                  for r in rows))


# --------------------------------------------------------------------------- running the tests


def baseline_metrics(train_caches: Sequence[Path], test_cache: Path) -> dict[str, Metrics]:
    """The rotation-only linear baseline (``linear``) and its constant-only form (``constant``, a
    per-axis bias), fit on the ground truth and prior of ``train_caches`` and applied to
    ``test_cache``'s prior, evaluated as every correction is (``dpc_jax.eval.evaluate``)."""
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.eval.evaluation import evaluate
    from dpc_jax.eval.linear_baseline import apply_linear_correction, fit_linear_correction

    def pair(path: Path) -> tuple[Any, Any]:
        cache = load_cache(path)
        if cache.gt is None:
            raise ValueError(f"{path}: no ground truth to fit or evaluate the linear baseline")
        return cache.gt, cache.prior

    train = [pair(p) for p in train_caches]
    gt, prior = pair(test_cache)
    estimates = {kind: apply_linear_correction(
        fit_linear_correction(train, rotation_only=True, constant_only=kind == "constant"), prior)
        for kind in ("linear", "constant")}
    evaluation = evaluate(gt, estimates)
    return {kind: _metrics(evaluation.estimates[kind]) for kind in estimates}


def share(source: Path, target: Path, names: Sequence[str]) -> None:
    """Link ``target/NAME`` to ``source/NAME`` for each existing ``source/NAME`` that ``target`` lacks,
    so a second run reads (and reuses) the first one's inputs instead of recomputing them."""
    target.mkdir(parents=True, exist_ok=True)
    for name in names:
        if (source / name).is_dir() and not os.path.lexists(target / name):
            (target / name).symlink_to(os.path.relpath(source / name, target), target_is_directory=True)


def _same_json(a: Any, b: Any) -> bool:
    return bool(json.loads(json.dumps(a)) == json.loads(json.dumps(b)))


def demo_config(path: Path, seed: int, smoke: Mapping[str, Any] | None) -> Any:
    """The ``DemoConfig`` of demo config file ``path`` at ``seed`` (with ``smoke``'s overrides, its
    ``training`` merged into the file's)."""
    from dpc_jax import config as config_lib
    from dpc_jax.pipelines.synthetic_demo import DemoConfig

    values = config_lib.to_dict(config_lib.load_file(path, DemoConfig))
    if smoke:
        values = {**values, **smoke, "training": {**values["training"], **smoke.get("training", {})}}
    return config_lib.from_dict(DemoConfig, {**values, "seed": seed}, where=str(path))


def finished_demo(config: Any, out: Path, say: Callable[[str], None], progress: bool) -> dict[str, Any]:
    """The demo's summary in ``out``: read when a finished one with this config is there, else run."""
    from dpc_jax import config as config_lib
    from dpc_jax.pipelines.synthetic_demo import run_demo

    stored = out / "summary.json"
    if stored.is_file():
        summary: dict[str, Any] = json.loads(stored.read_text())
        if _same_json(summary.get("config"), config_lib.to_dict(config)):
            say(f"{out}: finished, reused")
            return summary
    return run_demo(config, out, progress=progress, log=say)


def _experiment(name: str) -> ModuleType:
    """The protocol ``experiments/protocols/NAME.py`` as a module (its functions, not a copy of them)."""
    spec = importlib.util.spec_from_file_location(f"experiment_{name}", PROTOCOLS / f"{name}.py")
    if spec is None or spec.loader is None:
        raise OSError(f"cannot load {PROTOCOLS / name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def finished_drives(workdir: Path, argv: list[str], record: Mapping[str, Any], say: Callable[[str], None],
                    no_progress: bool) -> list[dict[str, str]]:
    """``kitti_raw_drives.py``'s ``results.csv`` rows for ``argv`` (its arguments after ``--workdir``):
    read when that run finished with the same arguments and config (``record``), else run."""
    stamp, results = workdir / "comparison_run.json", workdir / "results.csv"
    wanted = {"argv": argv, **record}
    if stamp.is_file() and results.is_file() and _same_json(json.loads(stamp.read_text()), wanted):
        say(f"{workdir}: finished, reused")
    else:
        from dpc_jax._io import atomic_write

        quiet = ["--no-progress"] if no_progress else []
        code = _experiment("kitti_raw_drives").main(["--workdir", str(workdir), *argv, *quiet])
        if code != 0:
            raise RuntimeError(f"kitti_raw_drives.py --workdir {workdir} {' '.join(argv)}: "
                               f"exit status {code}")
        atomic_write(stamp, json.dumps(wanted, indent=2) + "\n")
    with results.open(newline="") as f:
        return list(csv.DictReader(f))


def run_drives(args: argparse.Namespace, namespace: Mapping[str, Any],
               say: Callable[[str], None]) -> list[Row]:
    """Both drives, self-supervised and supervised networks, and the linear baseline: their rows."""
    from dpc_jax import config as config_lib
    from dpc_jax.pipelines import protocol as P

    base, protocol = P.load_protocol(args.config)
    record = {"config": config_lib.to_dict(base), "protocol": config_lib.to_dict(protocol)}
    common = ["--config", str(args.config), "--kitti-raw", str(args.kitti_raw)]
    common += ["--smoke"] * args.smoke
    supervised = [f"--set={key}={json.dumps(value)}" for key, value in namespace["SUPERVISED"].items()]
    own_dir, other_dir = args.workdir / "drives", args.workdir / "supervised" / "drives"
    say("drives, self-supervised networks")
    own = finished_drives(own_dir, common, record, say, args.no_progress)
    share(own_dir, other_dir, ("priors", "cache"))
    say("drives, supervised networks")
    other = finished_drives(other_dir, common + supervised, record, say, args.no_progress)
    drives = protocol.drives
    rows = []
    for test in drives:
        train = next(d for d in drives if d != test)
        first, end = drives[train].train_frames
        baselines = baseline_metrics([own_dir / "cache" / f"{train}_vo_train"],
                                     own_dir / "cache" / f"{test}_vo")

        def of(results: list[dict[str, str]], test: str = test) -> list[dict[str, str]]:
            return [r for r in results if r["drive"] == test and r["prior"] == "vo"]

        rows += drive_rows(test, f"drive {train}, frames {first}–{end - 1}", of(other), of(own), baselines)
    return rows


def run_seed(seed: int, args: argparse.Namespace, namespace: Mapping[str, Any], progress: bool,
             say: Callable[[str], None]) -> list[Row]:
    """Demo seed ``seed``, self-supervised and supervised networks, and the linear baseline: its rows."""
    smoke = namespace["SMOKE_DEMO"] if args.smoke else None
    own_dir, other_dir = args.workdir / f"seed_{seed}", args.workdir / "supervised" / f"seed_{seed}"
    configs = {kind: demo_config(Path(path), seed, smoke) for kind, path in namespace["DEMO"].items()}
    own = finished_demo(configs["self"], own_dir, say, progress)
    share(own_dir, other_dir, ("data", "vo", "cache"))
    other = finished_demo(configs["supervised"], other_dir, say, progress)
    train = [name for name, role in configs["self"].sequences.items() if role == "train"]
    baselines = baseline_metrics([own_dir / "cache" / n for n in train], own_dir / "cache" / "test")
    return demo_rows(seed, other, own, baselines, ", ".join(train))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", required=True, type=path_argument, metavar="DIR",
                        help="everything goes here")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], metavar="K",
                        help="demo seeds (default: %(default)s)")
    parser.add_argument("--skip-drives", action="store_true", help="the demo seeds only")
    parser.add_argument("--config", type=path_argument, default=CONFIG, metavar="FILE",
                        help="comparison config")
    parser.add_argument("--kitti-raw", type=path_argument, metavar="ROOT",
                        help="raw root holding DATE/ and libviso2/ (default: kitti_raw_drives.py's)")
    parser.add_argument("--smoke", action="store_true", help="wiring check: tiny demo (the config's "
                        "SMOKE_DEMO) and kitti_raw_drives.py --smoke")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--results-page", type=path_argument, metavar="FILE",
                        help="also write the table into the results block of FILE (a docs/results/ page)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    import runpy

    from dpc_jax._io import atomic_write

    args = build_parser().parse_args(argv)
    try:
        check_results_page(args.results_page)
    except (OSError, ValueError) as error:
        print(f"supervised_comparison: error: {error}", file=sys.stderr)
        return 2
    try:
        namespace = runpy.run_path(str(args.config))
    except Exception as error:  # the config file's own code failed
        print(f"supervised_comparison: error: {args.config}: {type(error).__name__}: {error}",
              file=sys.stderr)
        return 2
    if args.kitti_raw is None:
        args.kitti_raw = _experiment("kitti_raw_drives").DEFAULT_ROOT
    if not args.skip_drives and not (args.kitti_raw / "libviso2").is_dir():
        print(f"supervised_comparison: error: --kitti-raw {args.kitti_raw}: no libviso2/ folder (or give "
              "--skip-drives)", file=sys.stderr)
        return 2
    try:
        claim_workdir(args.workdir, [("--config", args.config),
                                     ("--kitti-raw", None if args.skip_drives else args.kitti_raw)],
                      files=[("--results-page", args.results_page)])
    except (OSError, ValueError) as error:
        print(f"supervised_comparison: error: {error}", file=sys.stderr)
        return 2
    logging.getLogger("absl").setLevel(logging.ERROR)
    progress = not args.no_progress and sys.stderr.isatty()
    began = time.perf_counter()

    def say(line: str) -> None:
        print(f"[{(time.perf_counter() - began) / 60:.1f} min] {line}", flush=True)

    notes = [
        "Rows: the prior; the linear baseline (a correction linear in the prior's step, rotation only, "
        "fit by least squares on the training sequences' ground truth: **supervised**) and its constant "
        "term alone (the mean correction per step: a bias, which does not depend on the speed); Stereo DPC "
        "trained with DPC-Net's loss on the training sequences' ground truth (**supervised**) and the same "
        "network trained self-supervised, each as trained, adapted to the test sequence's images "
        "(self-supervised, no ground truth) and final (what the acceptance tests and the choice keep). "
        "Decision: the network's ground-truth-free acceptance test (demo: `dpc-jax demo`'s words; drives: "
        "the axes applied, `kitti_raw_drives.py`'s). Demo: the held-out test sequence, trained on the "
        "training sequences named. Drives: real KITTI raw, prior our VO, trained on the other drive's "
        "frames named, rotation only applied; segment errors "
        f"{EMPTY} where the test is shorter than 100 m; RPE over one frame."
    ]
    if args.smoke:
        notes.append("SMOKE RUN (tiny demo, one epoch of two steps, two adaptation steps): the numbers mean "
                     "nothing.")
    rows: list[Row] = []
    try:
        tests: list[tuple[str, Callable[[], list[Row]]]] = [
            (f"demo seed {seed}", functools.partial(run_seed, seed, args, namespace, progress, say))
            for seed in args.seeds]
        if not args.skip_drives:
            tests.append(("drives", functools.partial(run_drives, args, namespace, say)))
        for name, run in tests:
            say(f"{name}: start")
            rows += run()
            atomic_write(args.workdir / "comparison.csv", comparison_csv(rows))
            atomic_write(args.workdir / "comparison.md", comparison_markdown(
                rows, [*notes, f"{(time.perf_counter() - began) / 60:.1f} minutes."]))
            say(f"{name}: done; {args.workdir / 'comparison.md'}")
    except (OSError, ValueError, KeyError, RuntimeError) as error:
        print(f"supervised_comparison: error: {error}", file=sys.stderr)
        return 1
    text = (args.workdir / "comparison.md").read_text()
    print(text, end="")
    if args.results_page is not None:
        write_results(args.results_page, text, Path(__file__))
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(main())
