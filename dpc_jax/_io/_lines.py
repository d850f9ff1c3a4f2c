"""Outputs written as they grow, one whole line at a time (the live correction's poses and CSV rows):
:class:`LiveOutputs`, and :func:`whole_lines`, which holds Ctrl-C back while a step's lines are written.

They are written in place, not through a temporary file: a reader follows them as they grow, and after
an error or Ctrl-C they hold the lines written before it, every one whole. The rules are summarised
in :mod:`dpc_jax._io`.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from dpc_jax._io._atomic_write import output_target, standard_fd, write_all
from dpc_jax._io._own_files import record_beside


@contextlib.contextmanager
def whole_lines() -> Iterator[None]:
    """Hold Ctrl-C back while one step's lines are written, then deliver it: every file then ends with
    the same step's line, whole. In the main thread only (Python runs signal handlers there)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda number, frame: pending.append(number))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if pending:
        signal.raise_signal(signal.SIGINT)


class _Line:
    """One output written a line at a time: a regular file (created or truncated, parent folders made)
    or a stream (the process's standard output or error through its descriptor, else opened for
    appending, as ``stream_write`` does), one whole line per ``os.write``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd: int | None = None
        self.own = True

    def open(self) -> None:
        if output_target(self.path)[0] == "stream":
            standard = standard_fd(self.path)
            if standard is not None:
                self.fd, self.own = standard, False
                return
            self.fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_NOCTTY)
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOCTTY, 0o666)

    def write(self, text: str) -> None:
        assert self.fd is not None
        try:
            write_all(self.fd, text.encode("utf-8"))
        except OSError as error:
            raise OSError(error.errno, f"{self.path}: {error.strerror}") from None

    def close(self) -> None:
        if self.fd is not None and self.own:
            os.close(self.fd)
        self.fd = None


class LiveOutputs:
    """The outputs of one run written as it goes: ``lines``, files that get one line per step (a None
    path is not written), and ``table``, a CSV (or None) headed by the ``header`` columns that gets one
    row per step after them. They are opened together with the first step, so that a run that writes
    none (no input, a bad first one, Ctrl-C before it) leaves every file as it was; ``stale``: the
    summaries of an earlier run beside them, removed when they are opened (a run writes its own at the
    end); ``beside``: the files named after an output rather than by the user, recorded as the command's
    own when they are opened (:func:`~dpc_jax._io.record_beside`)."""

    def __init__(self, lines: Sequence[Path | None], table: Path | None, header: Sequence[str], *,
                 stale: Sequence[Path | None] = (), beside: Sequence[Path | None] = ()) -> None:
        self.lines = [None if path is None else _Line(path) for path in lines]
        self.table = None if table is None else _Line(table)
        self.header = ",".join(header) + "\n"
        self.stale = [path for path in stale if path is not None]
        self.beside = [path for path in beside if path is not None]
        self.opened = False

    def __enter__(self) -> LiveOutputs:
        return self

    def _open(self) -> None:
        self.opened = True
        try:
            for path in self.stale:
                if path.is_file():
                    path.unlink()
            for path in self.beside:
                path.parent.mkdir(parents=True, exist_ok=True)
            record_beside(self.beside)
            for line in self._files():
                line.open()
            if self.table is not None:
                self.table.write(self.header)
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for line in self._files():
            line.close()

    def _files(self) -> list[_Line]:
        return [line for line in (*self.lines, self.table) if line is not None]

    def write(self, lines: Sequence[str], row: Callable[[float], str]) -> float:
        """Write one step: its ``lines`` (one per path of ``lines`` given, in their order; those of the
        paths not given are dropped), then its row ``row(written)`` of the table, ``written`` the clock
        (``time.perf_counter``) when the lines were out; returns ``written``."""
        with whole_lines():
            if not self.opened:
                self._open()
            for line, text in zip(self.lines, lines, strict=True):
                if line is not None:
                    line.write(text)
            written = time.perf_counter()
            if self.table is not None:
                self.table.write(row(written))
        return written
