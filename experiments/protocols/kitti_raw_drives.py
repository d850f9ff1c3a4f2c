"""Two real KITTI raw drives, cross-drive: train on one, correct the other (configs/kitti_raw_drives.py).

    python experiments/protocols/kitti_raw_drives.py --workdir runs/kitti_raw_drives
    python experiments/protocols/kitti_raw_drives.py --workdir /tmp/drives_smoke --smoke   # wiring, minutes

Writes ``WORKDIR/results.md`` (the table, with what each row was trained on) and ``WORKDIR/results.csv``
(long form: one row per test drive, prior, training prior and estimate ∈ prior, trained, adapted, final;
segment errors empty where the drive is shorter than 100 m; RPE over one frame); the protocol itself is
``dpc_jax.experiments.drives``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax.experiments import drives
from dpc_jax.experiments.folds import run_protocol
from dpc_jax.experiments.script import interruptible
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

CONFIG = Path(__file__).resolve().parent / "configs" / "kitti_raw_drives.py"


def main(argv: Sequence[str] | None = None) -> int:
    return run_protocol(__file__, drives.build_parser(__doc__, CONFIG), drives.plan, argv)


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
