"""``dpc-jax train``: train a DPC network on prepared sequences, resumably."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io import foreign_folder_problem, output_problem, overlap_problem
from dpc_jax.cli._common import Formatter, import_jax, path_option, restore_problem
from dpc_jax.runtime.progress import progress_mode

if TYPE_CHECKING:
    from dpc_jax.data.sequence_cache import SequenceCache
    from dpc_jax.training.train_config import TrainConfig

HELP = "Train ss-DPC-Net or Stereo DPC on prepared sequences (checkpoints, metrics.csv, TensorBoard)."
# Restart with huge-page malloc (dpc_jax.runtime.hugepages): the training step is a fifth faster.
HUGE_PAGES = True

EPILOG = """examples:
  dpc-jax train --config experiments/protocols/configs/own_data.py --workdir runs/own_data
  dpc-jax train --config experiments/protocols/configs/own_data.py --workdir runs/own_data --resume
experiments/protocols/configs/own_data.py is the minimal config for a cache of your own (from
`dpc-jax prepare`).
The config file defines CONFIG = TrainConfig(...) or a dict of its fields (see dpc_jax.training.train_config).
Outputs in WORKDIR: checkpoints/{epochs,best_gradient_loss,best_loop_closures,best_delta}/EPOCH
(best_delta: the epoch of most negative validation Δ, once one beats no correction; `correct --select delta`,
its default, reads it), checkpoints/config.json, checkpoints/split.json, metrics.csv, tensorboard/.
Several hosts: set distributed=True in the config and pass --coordinator-address/--num-processes/--process-id
on each host (or nothing on clusters JAX detects); the flags are refused without distributed=True.
While the run trains, .NAME.lock beside WORKDIR holds the process id (of process 0 in a distributed run
given --process-id 0): a second train or --resume of the same run is refused, and a lock left by a killed
run is reported with its process id, to be removed by hand."""



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = Formatter
    parser.add_argument(
        "--config",
        required=True,
        type=path_option,
        metavar="FILE",
        help="experiments/protocols/configs/NAME.py defining CONFIG (or a config.json of a run)",
    )
    parser.add_argument("--workdir", required=True, type=path_option, metavar="DIR", help="run folder")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in WORKDIR from its newest epoch (same config required)",
    )
    parser.add_argument("--verify", action="store_true",
                        help="check every byte of the caches the run reads against the digests of their "
                        "manifests before training (default: their sizes and a sample of their bytes)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--workers", type=int, default=2, metavar="N", help="data-loading threads")
    parser.add_argument("--coordinator-address", metavar="HOST:PORT", help="multi-host: process 0's address")
    parser.add_argument("--num-processes", type=int, help="multi-host: number of processes")
    parser.add_argument("--process-id", type=int, help="multi-host: this process's index")


def _labelled(config: Path, problem: str | None) -> str | None:
    return None if problem is None else f"--config {config}: {problem}"


def run(args: argparse.Namespace) -> int:
    from dpc_jax import config as config_lib
    from dpc_jax.config import ConfigError
    from dpc_jax.training.train_config import TrainConfig

    # The run writes checkpoints, metrics.csv and tensorboard/ into the workdir: it must be new,
    # empty or a training run.
    # Resuming a run from its own config.json (the form --help gives) reads the file the run wrote
    # and does not change it: that input inside the workdir is not an overlap.
    own = args.workdir / "checkpoints" / "config.json"
    resumed_own = (args.resume and own.is_file() and args.config.is_file()
                   and os.path.samefile(args.config, own))
    config_input = [] if resumed_own else [("--config", args.config)]
    problem = (output_problem(args.workdir, "--workdir", folder=True)
               or overlap_problem(config_input, [("--workdir", args.workdir)])
               or foreign_folder_problem(args.workdir, f"--workdir {args.workdir}",
                                         marker="checkpoints/config.json", made_by="a training run"))
    if problem is not None:
        print(f"dpc-jax train: error: {problem}", file=sys.stderr)
        return 2
    try:
        config = config_lib.load_file(args.config, TrainConfig)
    except ConfigError as error:
        print(f"dpc-jax train: error: {error}", file=sys.stderr)
        return 2
    problem = (overlap_problem([("--config's cache_root", config.cache_root or None)],
                               [("--workdir", args.workdir)])
               or _options_problem(args, config) or _labelled(args.config, config.pose_training_problem())
               or _cache_problem(config, args.config, args.verify))
    if problem is not None:
        print(f"dpc-jax train: error: {problem}", file=sys.stderr)
        return 2
    from dpc_jax._io import LockError, output_lock

    # One writer per run, locked before JAX starts. The processes of a distributed run share the
    # workdir: the one that says it is process 0 holds the lock (a cluster JAX detects names none).
    with contextlib.ExitStack() as lock:
        if not config.distributed or args.process_id == 0:
            try:
                lock.enter_context(output_lock(args.workdir, f"--workdir {args.workdir}"))
            except LockError as error:
                print(f"dpc-jax train: error: {error}", file=sys.stderr)
                return 2
        return _train(args, config)


def _train(args: argparse.Namespace, config: TrainConfig) -> int:
    """Train ``config`` into ``--workdir`` once every check has passed; the exit status."""
    from dpc_jax.config import ConfigError

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
            progress=progress_mode(args.no_progress),
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


def _options_problem(args: argparse.Namespace, config: TrainConfig) -> str | None:
    """The first option that cannot take effect or does not fit the workdir, or None (no JAX needed).

    The multi-host flags are refused without ``distributed=True`` rather than switching it on: the
    config is what a resumed run must match, so the run's way of training stays in the config and
    two hosts started with flags but no such config cannot train independently into one workdir.
    """
    from dpc_jax.config import ConfigError
    from dpc_jax.training.workdir import check_workdir

    if args.workers < 0:
        return f"--workers {args.workers}: expected 0 (load in the main thread) or more threads"
    flags = {"--coordinator-address": args.coordinator_address, "--num-processes": args.num_processes,
             "--process-id": args.process_id}
    given = [name for name, value in flags.items() if value is not None]
    if given and not config.distributed:
        return (f"{', '.join(given)}: multi-host flags, but {args.config} does not set distributed=True, so "
                "this process would train alone; set distributed=True in the config, or leave them out")
    address = args.coordinator_address
    if address is not None:
        host, _, port = address.rpartition(":")
        if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            return f"--coordinator-address {address!r}: expected HOST:PORT (such as 10.0.0.1:1234)"
    if args.num_processes is not None and args.num_processes < 1:
        return f"--num-processes {args.num_processes}: expected 1 or more"
    if args.process_id is not None:
        if args.process_id < 0:
            return f"--process-id {args.process_id}: expected 0 or more"
        if args.num_processes is not None and args.process_id >= args.num_processes:
            return (f"--process-id {args.process_id}: expected 0 to {args.num_processes - 1} for "
                    f"--num-processes {args.num_processes}")
    stored = Path(args.workdir) / "checkpoints" / "config.json"
    if args.resume and not stored.is_file():
        return (f"--resume: {args.workdir} holds no training run to continue (no {stored}); "
                "leave out --resume to start one")
    try:
        check_workdir(config, args.workdir, args.resume)
    except ConfigError as error:
        return str(error)
    return None


def _cache_problem(config: TrainConfig, config_name: str | Path, verify: bool = False) -> str | None:
    """The first problem of the caches the run reads (its training and validation sequences, chosen as
    :func:`~dpc_jax.training.train_data.open_data` does; a resumed run reads the same), or None. Checked
    without JAX, so a missing or damaged cache costs no JAX start-up; ``verify``: every byte of their
    files against their digests (:func:`~dpc_jax.data.sequence_cache.load_cache`)."""
    from dpc_jax.data.sequence_cache import load_cache, training_sequences

    try:
        train = training_sequences(
            config.cache_root, config.train_sequences, config.validation_sequences, config.test_sequences
        )
        caches = {name: load_cache(Path(config.cache_root) / name, verify=verify)
                  for name in [*train, *config.validation_sequences]}
    except (OSError, ValueError) as error:
        return str(error)
    h, w = config.resolved_image_size
    for cache in caches.values():
        if cache.image_size != (h, w):
            return (f"{cache.path}: images are {cache.image_size[0]}x{cache.image_size[1]}, but "
                    f"{config_name} asks for image_size {h}x{w}; prepare the cache with --size {h}x{w} or "
                    "set image_size to the cache's")
    kinds = _pair_kinds(config)
    problem = _batch_problem(config, [caches[name] for name in train], kinds, config_name)
    if problem is not None or not config.use_flow:
        return problem
    # The flows the network reads, as the training loader asks for them: its pair kinds for a
    # training sequence, consecutive pairs for a validation one.
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


def _pair_kinds(config: TrainConfig) -> list[str]:
    """The pair kinds the training loader reads (``dpc_jax.data.pipeline.TrainLoader``)."""
    kinds = ["forward"] + (["skip"] if config.frame_skip else [])
    if config.reverse:
        kinds += ["reverse"] + (["skip_reverse"] if config.frame_skip else [])
    return kinds


def _batch_problem(
    config: TrainConfig, train: list[SequenceCache], kinds: list[str], config_name: str | Path
) -> str | None:
    """Why the training caches hold fewer samples than one batch, or None: the loader's samples are
    one per frame pair of each kind it reads."""
    from dpc_jax.data.sequence_cache import PAIR_KINDS

    samples = sum(max(len(cache) - PAIR_KINDS[kind][0], 0) for cache in train for kind in kinds)
    if samples >= config.batch_size:
        return None
    return (f"{config_name}: batch_size {config.batch_size} is more than the {samples} training samples of "
            f"{', '.join(str(cache.path) for cache in train)} (pair kinds {', '.join(kinds)}); lower "
            "batch_size or prepare more frames")
