"""The checks of a training workdir before any compute: another run's config (:func:`check_workdir`)
and, on resume, the data the run started with (:func:`check_split`)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from dpc_jax import config as config_lib
from dpc_jax._io import lock_holder
from dpc_jax.config import ConfigError
from dpc_jax.training.train_config import TrainConfig


def check_workdir(config: TrainConfig, workdir: str | os.PathLike, resume: bool) -> bool:
    """Refuse a workdir that holds another run; return whether there is a run to resume.

    A workdir with a stored config needs ``resume=True`` and the same config (the error lists
    the differing keys). ``resume=True`` on a workdir without a run starts a new one.
    """
    stored_path = Path(workdir) / "checkpoints" / "config.json"
    if not stored_path.is_file():
        return False
    stored = config_lib.load_file(stored_path, TrainConfig)
    if not resume:
        # A run being written now: say by whom, not only that the folder holds a run.
        busy = lock_holder(workdir, f"--workdir {workdir}")
        if busy is not None:
            raise ConfigError(busy)
        raise ConfigError(
            f"{workdir} already holds a training run ({stored_path}); pass --resume to continue it "
            "or choose another --workdir"
        )
    differences = config_lib.diff(stored, config)
    if differences:
        raise ConfigError(
            f"{workdir} holds a run with a different config ({stored_path}); cannot resume with: "
            + "; ".join(differences)
        )
    return True


def check_split(workdir: Path, split: dict[str, Any]) -> None:
    """Refuse to resume on data that differ from the run's stored split (re-prepared cache, ...)."""
    path = workdir / "checkpoints" / "split.json"
    if not path.is_file():
        return
    stored = json.loads(path.read_text())
    changes = [f"{k}: {stored.get(k)!r} → {split.get(k)!r}" for k in sorted(set(stored) | set(split))
               if stored.get(k) != split.get(k)]
    if changes:
        message = "; ".join(changes)
        raise ConfigError(f"{path}: the data changed since the run started, cannot resume: {message}")
