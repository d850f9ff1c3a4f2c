"""The synthetic demo (``dpc_jax.pipelines.synthetic_demo``) as the studies run it: at another seed or with
other settings, reused when finished, and beside another demo that reads the same inputs."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dpc_jax import config as config_lib
from dpc_jax.experiments.records import as_json
from dpc_jax.pipelines.demo_config import DemoConfig
from dpc_jax.pipelines.protocol import claim_workdir
from dpc_jax.results.demo import SUMMARY, DemoSummary
from dpc_jax.runtime.progress import Progress


def demo_config(path: Path, seed: int, overrides: Mapping[str, Any] | None = None) -> DemoConfig:
    """The ``DemoConfig`` of config file ``path`` with ``overrides`` (DemoConfig fields; their ``training``
    merged into the file's) at ``seed``; a ``ConfigError`` (a ``ValueError``) names what is wrong."""
    values = config_lib.to_dict(config_lib.load_file(path, DemoConfig))
    changes = dict(overrides or {})
    training = {**values["training"], **changes.pop("training", {})}
    return config_lib.from_dict(DemoConfig, {**values, **changes, "training": training, "seed": seed},
                                where=str(path))


def finished_demo(config: DemoConfig, out: Path, say: Callable[[str], None],
                  progress: Progress) -> DemoSummary:
    """The demo's summary in ``out``: read when a finished demo of this config is there, else the demo is
    run (reusing what it finds of its stages)."""
    from dpc_jax.pipelines.synthetic_demo import run_demo

    if (out / SUMMARY).is_file():
        summary = DemoSummary.read(out)
        if summary.config == as_json(config_lib.to_dict(config)):
            say(f"{out}: finished, reused")
            return summary
    return run_demo(config, out, progress=progress, log=say)


def share(source: Path, target: Path, names: Sequence[str]) -> None:
    """Link ``target/NAME`` to ``source/NAME`` for each folder ``source/NAME`` that ``target`` lacks, so a
    second run reads (and reuses) the first one's inputs instead of making them again. ``target`` is
    claimed first (``dpc_jax.pipelines.protocol.claim_workdir``): the run that writes into it then finds
    a work folder an experiment script made, not a folder of someone's files."""
    claim_workdir(target)
    for name in names:
        if (source / name).is_dir() and not os.path.lexists(target / name):
            (target / name).symlink_to(os.path.relpath(source / name, target), target_is_directory=True)
