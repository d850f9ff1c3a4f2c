"""``dpc-jax train``: train a DPC network on prepared sequences, resumably."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax.cli._common import Formatter, import_jax, output_problem, restore_problem

if TYPE_CHECKING:
    from dpc_jax.training.config import TrainConfig

HELP = "Train ss-DPC-Net or Stereo DPC on prepared sequences (checkpoints, metrics.csv, TensorBoard)."
# Restart with huge-page malloc (dpc_jax.hugepages): the training step is a fifth faster.
HUGE_PAGES = True

EPILOG = """examples:
  dpc-jax train --config experiments/configs/own_data.py --workdir runs/own_data
  dpc-jax train --config experiments/configs/own_data.py --workdir runs/own_data --resume
experiments/configs/own_data.py is the minimal config for a cache of your own (from `dpc-jax prepare`).
The config file defines CONFIG = TrainConfig(...) or a dict of its fields (see dpc_jax.training.config).
Outputs in WORKDIR: checkpoints/{epochs,best_gradient_loss,best_loop_closures}/EPOCH, checkpoints/config.json,
checkpoints/split.json, metrics.csv, tensorboard/. Several hosts: set distributed=True in the config and
pass --coordinator-address/--num-processes/--process-id on each host (or nothing on clusters JAX detects)."""



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    parser.add_argument(
        "--config",
        required=True,
        type=Path,
        metavar="FILE",
        help="experiments/configs/NAME.py defining CONFIG (or a config.json of a run)",
    )
    parser.add_argument("--workdir", required=True, type=Path, metavar="DIR", help="run folder")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in WORKDIR from its newest epoch (same config required)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--workers", type=int, default=2, metavar="N", help="data-loading threads")
    parser.add_argument("--coordinator-address", metavar="HOST:PORT", help="multi-host: process 0's address")
    parser.add_argument("--num-processes", type=int, help="multi-host: number of processes")
    parser.add_argument("--process-id", type=int, help="multi-host: this process's index")


def run(args: argparse.Namespace) -> int:
    from dpc_jax import config as config_lib
    from dpc_jax.config import ConfigError
    from dpc_jax.training.config import TrainConfig

    problem = output_problem(args.workdir, "--workdir", folder=True)
    if problem is not None:
        print(f"dpc-jax train: error: {problem}", file=sys.stderr)
        return 2
    try:
        config = config_lib.load_file(args.config, TrainConfig)
    except ConfigError as error:
        print(f"dpc-jax train: error: {error}", file=sys.stderr)
        return 2
    problem = _cache_problem(config)
    if problem is not None:
        print(f"dpc-jax train: error: {problem}", file=sys.stderr)
        return 2
    import_jax()
    from dpc_jax.data.sequence_cache import CacheError
    from dpc_jax.training.checkpoints import CheckpointError
    from dpc_jax.training.loop import train
    from dpc_jax.training.steps import NonFiniteLossError

    distributed = {
        "coordinator_address": args.coordinator_address,
        "num_processes": args.num_processes,
        "process_id": args.process_id,
    }
    try:
        summary = train(
            config,
            args.workdir,
            resume=args.resume,
            progress=False if args.no_progress else None,
            distributed=distributed,
            workers=args.workers,
        )
    except (ConfigError, CacheError, FileNotFoundError) as error:
        print(f"dpc-jax train: error: {error}", file=sys.stderr)
        return 2
    except CheckpointError as error:
        problem = restore_problem(error.folder, error.__cause__ or error)
        print(f"dpc-jax train: error: {problem}", file=sys.stderr)
        return 2
    except NonFiniteLossError as error:
        print(f"dpc-jax train: stopped: {error}", file=sys.stderr)
        return 1
    print(json.dumps(summary, indent=2, default=float))
    return 0


def _cache_problem(config: TrainConfig) -> str | None:
    """The first problem of the caches the run reads (its training and validation sequences, chosen as
    :func:`~dpc_jax.training.train_data.open_data` does; a resumed run reads the same), or None. Checked
    without JAX, so a missing or damaged cache costs no JAX start-up."""
    from dpc_jax.data.sequence_cache import load_cache, training_sequences

    try:
        train = training_sequences(
            config.cache_root, config.train_sequences, config.validation_sequences, config.test_sequences
        )
        caches = {name: load_cache(Path(config.cache_root) / name)
                  for name in [*train, *config.validation_sequences]}
    except (OSError, ValueError) as error:
        return str(error)
    if not config.use_flow:
        return None
    # The flows the network reads, as the training loader asks for them: its pair kinds for a
    # training sequence, consecutive pairs for a validation one.
    kinds = ["forward"] + (["skip"] if config.frame_skip else [])
    if config.reverse:
        kinds += ["reverse"] + (["skip_reverse"] if config.frame_skip else [])
    for name, cache in caches.items():
        needed = kinds if name in train else ["forward"]
        missing = [kind for kind in needed if kind not in cache.flows]
        if missing:
            how = "--flow" if missing == ["forward"] else "--flow-augment"
            alternative = "" if how == "--flow" else ", or set frame_skip=False, reverse=False in the config"
            return (f"{cache.path}: no {' or '.join(missing)} flow in the cache, which method "
                    f"{config.method!r} reads (frame_skip={config.frame_skip}, reverse={config.reverse}); "
                    f"prepare it with `dpc-jax prepare ... {how}`{alternative}")
    return None
