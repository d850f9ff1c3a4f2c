"""Markdown table rows and CSV text shared by the reports."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Sequence


def row(cells: Iterable[str]) -> str:
    """One Markdown table row: ``| a | b |``."""
    return "| " + " | ".join(cells) + " |"


def rule(columns: int) -> str:
    """The Markdown rule under a header of ``columns`` cells: ``|---|---|``."""
    return "|---" * columns + "|"


def table(header: Sequence[str], rows: Iterable[Iterable[str]]) -> str:
    """A Markdown table (header, rule, rows), ending with a newline."""
    return "\n".join([row(header), rule(len(header)), *(row(cells) for cells in rows)]) + "\n"


def csv_text(header: Sequence[str], rows: Iterable[Iterable[object]]) -> str:
    """CSV text with ``\\n`` line ends; ``None`` becomes an empty cell."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for cells in rows:
        writer.writerow(["" if value is None else value for value in cells])
    return buffer.getvalue()

