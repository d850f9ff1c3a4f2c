"""``dpc-jax demo``: the synthetic end-to-end demo (render, VO, prepare, train, correct, report)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from dpc_jax._io import foreign_folder_problem, output_problem, overlap_problem
from dpc_jax.cli._common import (
    Formatter,
    import_jax,
    input_problem,
    path_option,
    restore_problem,
)
from dpc_jax.report.tables import EMPTY
from dpc_jax.runtime.progress import progress_mode

HELP = "Synthetic end-to-end demo: train Stereo DPC on rendered sequences, correct our VO, write a report."
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): the demo's time goes to training.
HUGE_PAGES = True

EPILOG = """examples:
  dpc-jax demo --out demo
  dpc-jax demo --out demo_hard --config my_demo.py     # CONFIG = DemoConfig(...) or a dict of its fields
Writes OUT/report.md (the prior's error, the test table: prior, network as trained, network adapted to the
test sequence, final; trajectory, segment-error and c-ATE plots), OUT/corrected.txt and OUT/summary.json, and
keeps the data, priors, caches, the training run and the adapted network under OUT; re-running reuses what is
up to date."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    parser.add_argument("--out", type=path_option, default=Path("dpc_demo"),
                        metavar="DIR",
                        help="output folder (data, priors, caches, run, report.md); re-running reuses it")
    parser.add_argument("--config", type=path_option, metavar="FILE",
                        help="a Python file defining CONFIG = DemoConfig(...) or a dict of its fields "
                        "(default: the built-in demo, experiments/studies/configs/synthetic_demo.py)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _replaced_problem(out: Path, names: list[str]) -> str | None:
    """Why a folder the demo would replace under ``out`` is not one it made, or None: a rendered
    sequence (``data/sequences/NAME``, with ``synth.json``), a cache (``cache/NAME``, with
    ``manifest.json``) or the training run (``run``); the layout of
    :mod:`dpc_jax.pipelines.synthetic_demo`."""
    from dpc_jax.data.sequence_cache import MANIFEST

    label = f"--out {out}"
    folders = [(out / "data" / "sequences" / name, "synth.json", "a sequence `dpc-jax synth` rendered")
               for name in names]
    folders += [(out / "cache" / name, MANIFEST, "a cache of `dpc-jax prepare`") for name in names]
    folders.append((out / "run", "checkpoints/config.json", "a training run"))
    for folder, marker, made_by in folders:
        problem = foreign_folder_problem(folder, label, marker=marker, made_by=made_by)
        if problem is not None:
            return problem
    return None


def run(args: argparse.Namespace) -> int:
    problem = (output_problem(args.out, "--out", folder=True) or input_problem(args.config, "--config")
               or overlap_problem([("--config", args.config)], [("--out", args.out)]))
    if problem is not None:
        print(f"dpc-jax demo: error: {problem}", file=sys.stderr)
        return 2
    # The config is checked before JAX is imported: a bad one fails at once.
    from dpc_jax.config import ConfigError, load_file
    from dpc_jax.pipelines.synthetic_demo import DemoConfig

    try:
        config = load_file(args.config, DemoConfig) if args.config is not None else DemoConfig()
    except ConfigError as error:
        print(f"dpc-jax demo: error: {error}", file=sys.stderr)
        return 2
    problem = _replaced_problem(args.out, list(config.sequences))
    if problem is not None:
        print(f"dpc-jax demo: error: {problem}", file=sys.stderr)
        return 2
    import_jax()
    from dpc_jax.pipelines.synthetic_demo import DemoError, run_demo
    from dpc_jax.training.checkpoints import CheckpointError

    progress = progress_mode(args.no_progress)
    # orbax logs a warning for every read-only checkpoint directory it opens when restoring the run.
    logging.getLogger("absl").setLevel(logging.ERROR)
    try:
        summary = run_demo(config, args.out, progress=progress, log=lambda line: print(line, flush=True))
    except (ConfigError, DemoError, FileExistsError) as error:
        print(f"dpc-jax demo: error: {error}", file=sys.stderr)
        return 2
    except CheckpointError as error:
        problem = restore_problem(error.folder, error.__cause__ or error)
        print(f"dpc-jax demo: error: {problem}", file=sys.stderr)
        return 2

    def errors(label: str) -> str:
        values = summary.test[label]
        t, r = (values[k] for k in ("seg_trans_pct", "seg_rot_deg_per_100m"))
        return f"{EMPTY} (shorter than 100 m)" if t is None or r is None else f"{t:.3f} % / {r:.3f} °/100 m"

    rows = ", ".join(f"{label} {errors(label)}" for label in summary.test if label != "corrected")
    print(f"test sequence segment errors: {rows}; final ({summary.final}) {errors('corrected')}; "
          f"{summary.seconds_total / 60:.1f} min")
    print(f"report: {summary.report}")
    return 0
