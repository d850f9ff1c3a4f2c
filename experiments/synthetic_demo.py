"""The synthetic end-to-end demo (what ``dpc-jax demo`` runs); see configs/synthetic_demo.py.

    python experiments/synthetic_demo.py --out runs/synthetic_demo
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax.hugepages import reexec_with_huge_pages

CONFIG = Path(__file__).resolve().parent / "configs" / "synthetic_demo.py"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", type=Path, default=CONFIG, help="file defining CONFIG (a DemoConfig)")
    parser.add_argument("--out", type=Path, default=Path("runs/synthetic_demo"), help="output folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    from dpc_jax.cli import main as cli_main

    command = ["demo", "--config", str(args.config), "--out", str(args.out)]
    return cli_main(command + (["--no-progress"] if args.no_progress else []))


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(main())
