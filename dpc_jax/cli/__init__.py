"""The ``dpc-jax`` command line.

Every module in this package except this one is a subcommand. It defines ``HELP`` (one line for
``dpc-jax --help``), ``add_arguments(parser)`` and ``run(args) -> int``. Heavy imports (JAX, the
models) happen inside ``run`` so that ``--help`` and argument errors are instant.

Around every subcommand: Ctrl-C ends it with one line, ``dpc-jax COMMAND: interrupted; nothing
half-written``, and exit status 130 (every writer is atomic or all-or-nothing, so that is true), and
an :class:`~dpc_jax._io.InputWarning` is printed as one ``dpc-jax COMMAND: warning: ...`` line.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import warnings
from collections.abc import Sequence
from typing import Any

import dpc_jax
from dpc_jax._io import InputWarning
from dpc_jax.cli._common import Formatter
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
        command = sub.add_parser(name, help=module.HELP, description=module.HELP, formatter_class=Formatter)
        module.add_arguments(command)
        command.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    show_warning = warnings.showwarning

    def one_line(message: Any, category: type[Warning], *rest: Any, **kw: Any) -> None:
        if issubclass(category, InputWarning):
            print(f"dpc-jax {args.command}: warning: {message}", file=sys.stderr)
        else:
            show_warning(message, category, *rest, **kw)

    with warnings.catch_warnings():
        warnings.showwarning = one_line
        try:
            return int(args._run(args) or 0)
        except KeyboardInterrupt:
            print(f"dpc-jax {args.command}: interrupted; nothing half-written", file=sys.stderr)
            return 130


def console_main() -> None:
    """The ``dpc-jax`` executable: restart with huge-page malloc if useful (see
    ``dpc_jax.hugepages``), then ``main``."""
    reexec_with_huge_pages()
    sys.exit(main())


if __name__ == "__main__":
    console_main()
