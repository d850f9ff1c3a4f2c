"""The ``dpc-jax`` command line.

Every module in this package except those starting with ``_`` is a subcommand. It defines ``HELP``
(one line for ``dpc-jax --help``), ``HUGE_PAGES`` (below), ``add_arguments(parser)`` and
``run(args) -> int``. ``run`` first checks its options, inputs and outputs with the
standard library and numpy only, and only then calls :func:`~dpc_jax.cli._common.import_jax` and
imports what uses JAX: a command that fails on its inputs fails in a fraction of a second, before
JAX is imported, with one line on stderr (exit status 2, or 1 where the input's content is at fault).

The executable (``console_main``) turns on JAX's persistent compilation cache
(:mod:`dpc_jax.runtime.compilation_cache`), so a repeated command compiles nothing, and restarts itself with
huge-page malloc (:mod:`dpc_jax.runtime.hugepages`) for the commands whose ``HUGE_PAGES`` says it pays.
``main`` alone, as the tests call it in-process, does neither.

Around every subcommand: Ctrl-C ends it with one line, ``dpc-jax COMMAND: interrupted; nothing
half-written``, and exit status 130 (every writer is atomic or all-or-nothing, so that is true), and
an :class:`~dpc_jax._io.InputWarning` is printed as one ``dpc-jax COMMAND: warning: ...`` line.
Two places where Python cannot deliver Ctrl-C are covered: JAX is imported (``import_jax``) with the
interrupt held back until the import is complete, because a KeyboardInterrupt inside jaxlib's
initialisation crashes the interpreter (SIGSEGV or SIGABRT); and an interrupt that lands in a
garbage-collection callback, where Python would print "Exception ignored" and drop it, is raised
again in the main thread (``console_main``).
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import logging
import os
import pkgutil
import signal
import sys
import threading
import warnings
from collections.abc import Sequence
from typing import Any

import dpc_jax
from dpc_jax._io import InputWarning
from dpc_jax.cli._common import Formatter
from dpc_jax.runtime.compilation_cache import use_compilation_cache
from dpc_jax.runtime.hugepages import reexec_with_huge_pages
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.runtime.versions import versions_line


def _subcommands() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dpc-jax",
        description="Self-supervised deep pose correction of stereo visual odometry.",
        formatter_class=Formatter,
    )
    # What a user who reports a figure ran: the libraries that move figures and the CPU's vector unit.
    parser.add_argument("--version", action="version",
                        version=f"dpc-jax {dpc_jax.__version__}\n{versions_line()}\n{this_cpu()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _subcommands():
        module = importlib.import_module(f"{__name__}.{name}")
        command = sub.add_parser(name, help=module.HELP, description=module.HELP, formatter_class=Formatter)
        module.add_arguments(command)
        if not any("--no-progress" in action.option_strings for action in command._actions):
            # One option set for scripts that run every command alike: where nothing shows progress
            # (evaluate, live), --no-progress is accepted and changes nothing.
            command.add_argument("--no-progress", action="store_true",
                                 help="accepted for scripts that pass it to every command; this one shows "
                                      "no progress")
        command.set_defaults(_run=module.run, _huge_pages=module.HUGE_PAGES)
    return parser


def main(argv: Sequence[str] | None = None, *, entry_point: bool = False) -> int:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); the exit status.

    ``entry_point``: this is the ``dpc-jax`` process itself, which may be restarted with huge-page
    malloc for the command (``console_main``); never in-process.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if entry_point and args._huge_pages:
        reexec_with_huge_pages()
    show_warning = warnings.showwarning

    def one_line(message: Any, category: type[Warning], *rest: Any, **kw: Any) -> None:
        if issubclass(category, InputWarning):
            print(f"dpc-jax {args.command}: warning: {message}", file=sys.stderr)
        else:
            show_warning(message, category, *rest, **kw)

    with warnings.catch_warnings():
        warnings.showwarning = one_line
        # Orbax reports a damaged checkpoint through absl's log before raising; the command's own
        # one-line error says it better.
        logging.getLogger("absl").addFilter(lambda record: record.levelno >= logging.CRITICAL)
        try:
            return int(args._run(args) or 0)
        except KeyboardInterrupt:
            print(f"dpc-jax {args.command}: interrupted; nothing half-written", file=sys.stderr)
            return 130
        except OSError as error:
            # Outputs are checked before the work starts; this is the disk failing afterwards
            # (full, removed, remounted). Output sets have rolled back, so nothing is half-written.
            print(f"dpc-jax {args.command}: error: {error}; nothing half-written", file=sys.stderr)
            return 1


def console_main() -> None:
    """The ``dpc-jax`` executable: ``main`` with the compilation cache on, restarted with huge-page
    malloc where that pays (see the module docstring)."""
    use_compilation_cache()
    ignored = sys.unraisablehook

    def redeliver_interrupt(unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            # Raised from here it would be dropped again; a moment later the main thread is back in
            # ordinary code, where the signal becomes a KeyboardInterrupt that main() reports.
            threading.Timer(0.05, signal.raise_signal, (signal.SIGINT,)).start()
        else:
            ignored(unraisable)

    sys.unraisablehook = redeliver_interrupt
    try:
        status = main(entry_point=True)
    except KeyboardInterrupt:  # before a subcommand was chosen (while the parser is built)
        print("dpc-jax: interrupted; nothing half-written", file=sys.stderr)
        status = 130
    if status == 130:
        _exit_interrupted()
    sys.exit(status)


def _exit_interrupted() -> None:
    """End an interrupted process without freeing XLA's client under a compilation still running.

    jaxlib compiles on its own thread pool while the main thread waits, and the wait gives way to
    Ctrl-C: the KeyboardInterrupt unwinds the command (outputs rolled back, temporaries removed)
    while the compilation goes on. An ordinary exit then frees the PjRt client, first in JAX's
    ``atexit`` handler, otherwise in the interpreter's final garbage collection, and the client's
    destructor frees the devices before it joins the thread pool whose compilation still uses
    them: a segmentation fault. So, once JAX is loaded, the other exit handlers run (logging,
    multiprocessing's), the standard streams are flushed, and the process ends with ``os._exit``,
    which skips JAX's handler and the interpreter's teardown; the kernel stops the threads.
    """
    if "jaxlib" not in sys.modules:
        return
    api = sys.modules.get("jax._src.api")
    if api is not None and hasattr(api, "clean_up"):
        atexit.unregister(api.clean_up)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(130)


if __name__ == "__main__":
    console_main()
