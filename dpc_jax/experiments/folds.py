"""The runner of the protocol scripts (``experiments/protocols/``): load the config, let the script plan and
prepare its folds, train each fold's network, correct and evaluate its test sequences, write the table.

A script gives :func:`run_protocol` its parser (with :func:`add_protocol_arguments`) and its ``plan``:
from the :class:`Context` (options, training config, protocol), check the inputs, claim the work folder
(:meth:`Context.claim`), prepare the caches and return the :class:`Plan`. Everything lands
under the work folder (``dpc_jax.pipelines.protocol``'s layout) with ``results.md``, ``results.csv`` and
``results.json`` (:class:`dpc_jax.results.fold.FoldResult`); a rerun resumes every training.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dpc_jax._io import atomic_write
from dpc_jax.experiments.detection_answer import TOLERANCE_PCT
from dpc_jax.experiments.records import Records
from dpc_jax.experiments.script import (
    Clock,
    add_no_progress,
    add_results_page,
    claim,
    progress_flag,
    publish,
    refuse,
)
from dpc_jax.pipelines.protocol import (
    SMOKE,
    ExperimentProtocol,
    Fold,
    Named,
    correct_and_evaluate,
    load_protocol,
    parse_overrides,
    path_argument,
    train_fold,
)
from dpc_jax.report.protocol_report import results_csv, results_markdown
from dpc_jax.results.fold import RESULTS, FoldResult, read_fold_results, write_fold_results
from dpc_jax.runtime.progress import Progress

# (markdown, CSV) of the results and the notes above the table.
Tables = Callable[[Sequence[FoldResult], Sequence[str]], tuple[str, str]]


@dataclass(frozen=True)
class Test:
    """A test sequence a fold's network corrects: its cache, its prior's name in the table, and the same
    frames prepared larger where every acceptance test is measured too (None: none)."""

    cache: Path
    prior_label: str
    judge: Path | None = None


@dataclass(frozen=True)
class FoldRun:
    """A fold with its training config and its test sequences."""

    fold: Fold
    config: Any
    tests: tuple[Test, ...]


@dataclass(frozen=True)
class Plan:
    """What a script planned and prepared: the folds, the table's ``title`` and the paragraph above it
    (``notes``: what ran), the adaptation steps (None: the protocol's) and the tables (None:
    ``dpc_jax.report.protocol_report``'s)."""

    runs: Sequence[FoldRun]
    title: str
    notes: str
    adapt_steps: int | None = None
    tables: Tables | None = None


@dataclass(frozen=True)
class Context:
    """What a plan starts from: the parsed options, the training config and protocol of ``--config``, the
    training overrides (``--smoke``, ``--set``), the epoch selection, the progress flag and the script's
    name (which claims the work folder)."""

    args: argparse.Namespace
    base: Any
    protocol: ExperimentProtocol
    overrides: dict[str, Any]
    select: str
    progress: Progress
    script: str

    @property
    def workdir(self) -> Path:
        return Path(self.args.workdir)

    @property
    def cache_root(self) -> Path:
        return self.workdir / "cache"

    def claim(self, inputs: Sequence[Named]) -> None:
        """Claim the work folder and the results page against the inputs (and the config) once they are
        checked, before any work."""
        claim(self.workdir, [*inputs, ("--config", self.args.config)], script=self.script,
              page=self.args.results_page)


def add_protocol_arguments(parser: argparse.ArgumentParser, config: Path) -> None:
    """The options every protocol has: work folder, config (default ``config``), epoch selection, training
    overrides, smoke, progress, results page."""
    from dpc_jax.training.train_config import SELECTIONS

    parser.add_argument("--workdir", required=True, type=path_argument, metavar="DIR",
                        help="everything goes here (made by the script, or one it made before)")
    parser.add_argument("--config", type=path_argument, default=config, metavar="FILE",
                        help="experiment config")
    parser.add_argument("--select", choices=tuple(SELECTIONS),
                        help="epoch selection (default: the protocol's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a TrainConfig field (JSON value), e.g. --set epochs=2")
    parser.add_argument("--smoke", action="store_true",
                        help=f"wiring check: {', '.join(f'{k}={v}' for k, v in SMOKE.items())}")
    add_no_progress(parser)
    add_results_page(parser)


def run_protocol(script: str | Path, parser: argparse.ArgumentParser, plan: Callable[[Context], Plan],
                 argv: Sequence[str] | None = None) -> int:
    """Run a protocol script (module docstring): exit status 0, or 2 with one line for bad input or a
    failed run."""
    args = parser.parse_args(argv)
    name = Path(script).stem
    clock = Clock()
    # Orbax warns once per read-only checkpoint manager when a run is restored for correction.
    logging.getLogger("absl").setLevel(logging.ERROR)
    try:
        base, protocol = load_protocol(args.config)
        claim(None, script=name, page=args.results_page)
        # --smoke's settings, then the --set overrides on top.
        overrides = {**(SMOKE if args.smoke else {}), **parse_overrides(args.set)}
        context = Context(args, base, protocol, overrides, args.select or protocol.select,
                          progress_flag(args.no_progress), name)
        planned = plan(context)
        results = []
        for run in planned.runs:
            run_dir = context.workdir / "runs" / run.fold.name
            train_fold(run.config, run_dir, context.progress)
            for test in run.tests:
                result = correct_and_evaluate(
                    run.fold.name, run_dir, test.cache, context.workdir, protocol, select=context.select,
                    prior_label=test.prior_label, adapt_steps=planned.adapt_steps, judge=test.judge,
                    progress=context.progress)
                results.append(result)
                clock.say(f"{run.fold.name}: {result.sequence} ({test.prior_label} prior): {result.applied}")
    except (OSError, ValueError, KeyError) as error:
        return refuse(name, error)
    smoke = ", ".join(f"{k}={v}" for k, v in SMOKE.items())
    notes = [f"{planned.notes} {clock.minutes:.1f} minutes."
             + (f" SMOKE RUN ({smoke}): the numbers mean nothing." if args.smoke else "")]
    markdown, table = (planned.tables or _tables(planned.title))(results, notes)
    atomic_write(context.workdir / "results.csv", table)
    atomic_write(context.workdir / "results.md", markdown)
    write_fold_results(context.workdir / RESULTS, results)
    publish(markdown, args.results_page, script)
    print(f"results: {context.workdir / 'results.md'}")
    return 0


def _tables(title: str) -> Tables:
    return lambda results, notes: (results_markdown(results, title, notes, tolerance_pct=TOLERANCE_PCT),
                                   results_csv(results))


def finished_protocol(script: str | Path, parser: argparse.ArgumentParser, plan: Callable[[Context], Plan],
                      workdir: Path, argv: Sequence[str], record: dict[str, Any],
                      say: Callable[[str], None]) -> list[FoldResult]:
    """The results of a protocol run into ``workdir`` with the options ``argv``: read when a run with the same
    options and ``record`` (what else it depends on, e.g. the configs it read) finished there, else run
    (:func:`run_protocol`; ``RuntimeError`` when it fails, its error above)."""
    key = {"argv": list(argv), **record}
    records = Records(workdir)
    if records.done("finished_protocol", key) is not None and (workdir / RESULTS).is_file():
        say(f"{workdir}: finished, reused")
    else:
        if run_protocol(script, parser, plan, ["--workdir", str(workdir), *argv]) != 0:
            raise RuntimeError(f"{Path(script).name} --workdir {workdir} {' '.join(argv)} failed")
        records.write("finished_protocol", {"key": key})
    return read_fold_results(workdir / RESULTS)
