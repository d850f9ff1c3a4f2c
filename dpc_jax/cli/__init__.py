"""The ``dpc-jax`` command line.

Every module in this package except this one is a subcommand. It defines ``HELP`` (one line for
``dpc-jax --help``), ``add_arguments(parser)`` and ``run(args) -> int``. Heavy imports (JAX, the
models) happen inside ``run`` so that ``--help`` and argument errors are instant.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

import dpc_jax
from dpc_jax.hugepages import reexec_with_huge_pages


def _subcommands() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dpc-jax",
        description="Self-supervised deep pose correction of stereo visual odometry.",
    )
    parser.add_argument("--version", action="version", version=f"dpc-jax {dpc_jax.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _subcommands():
        module = importlib.import_module(f"{__name__}.{name}")
        command = sub.add_parser(
            name, help=module.HELP, description=module.HELP,
            formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        )
        module.add_arguments(command)
        command.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    return int(args._run(args) or 0)


def console_main() -> None:
    """The ``dpc-jax`` executable: restart with huge-page malloc if useful (see
    ``dpc_jax.hugepages``), then ``main``."""
    reexec_with_huge_pages()
    sys.exit(main())


if __name__ == "__main__":
    console_main()
