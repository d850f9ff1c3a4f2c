"""Progress reporting for long loops: tqdm bars on a terminal, plain lines in logs.

``progress`` arguments of the data writers take ``True`` (a tqdm bar), ``False`` (nothing),
``None`` (a bar when stderr is a terminal, else nothing) or ``"lines"``: one line on stderr at most
every ``LINE_INTERVAL_S`` seconds and a last one when the loop completes (not when it is
interrupted), which is what a log file or ``nohup`` wants (a tqdm bar there is one ever-growing
line of carriage returns).
"""

from __future__ import annotations

import sys
import time
from typing import Any, Literal

from tqdm.auto import tqdm

Progress = bool | None | Literal["lines"]
LINE_INTERVAL_S = 5.0


class LineProgress:
    """A tqdm-like counter that prints ``DESC: n/total units (rate/s)`` lines to stderr."""

    def __init__(self, total: int, desc: str, unit: str, interval: float = LINE_INTERVAL_S) -> None:
        self.total, self.desc, self.unit, self.interval = total, desc, unit, interval
        self.n = 0
        self.postfix = ""
        self.start = self.last = time.monotonic()

    def _line(self, now: float) -> None:
        rate = self.n / (now - self.start) if now > self.start else 0.0
        extra = f", {self.postfix}" if self.postfix else ""
        print(f"{self.desc}: {self.n}/{self.total} {self.unit}s ({rate:.1f}/s{extra})", file=sys.stderr,
              flush=True)
        self.last = now

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        if now - self.last >= self.interval and self.n < self.total:
            self._line(now)

    def set_postfix(self, **values: Any) -> None:
        self.postfix = ", ".join(f"{k} {v}" for k, v in values.items())

    def close(self) -> None:
        if self.total and self.n >= self.total:
            self._line(time.monotonic())
        self.n = 0

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def progress_mode(no_progress: bool = False) -> Progress:
    """The one progress policy of the command line: nothing with ``--no-progress``, else a bar on a
    terminal and a line every few seconds in a log (stderr redirected to a file or a pipe)."""
    if no_progress:
        return False
    return True if sys.stderr.isatty() else "lines"


def progress_bar(total: int, desc: str, progress: Progress, unit: str = "frame") -> Any:
    """A tqdm bar, a :class:`LineProgress` or a disabled bar, by ``progress`` (module docstring)."""
    if progress == "lines":
        return LineProgress(total, desc, unit)
    show = sys.stderr.isatty() if progress is None else bool(progress)
    return tqdm(total=total, desc=desc, unit=unit, disable=not show)
