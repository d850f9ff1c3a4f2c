"""Markdown tables, CSV text, table cells and the change against the prior, shared by every report
and experiment."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Mapping, Sequence

# The cell of a figure that does not exist (a segment error of a trajectory shorter than 100 m, a
# network that was not run): one word in every table, Markdown and text alike.
EMPTY = "n/a"


def number(value: float | int | None, spec: str = ".4g") -> str:
    """``value`` formatted by ``spec`` (e.g. ``".4g"``, ``"+.1f"``), or :data:`EMPTY` when it is None
    or not finite."""
    if value is None or not math.isfinite(value):
        return EMPTY
    return format(value, spec)


def change_pct(prior: float | None, value: float | None) -> float:
    """Relative change of ``value`` against ``prior`` in % (negative: lower than the prior).

    NaN when either is missing (None or NaN) or the prior is 0: the change is then undefined, NaN
    keeps it a float through sums, comparisons (always false) and JSON, and :func:`number` shows it
    as :data:`EMPTY`."""
    if prior is None or value is None or prior == 0:
        return math.nan
    return 100.0 * (value - prior) / prior


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


def records_csv(records: Sequence[Mapping[str, object]]) -> str:
    """:func:`csv_text` of dicts: the columns are their keys in first-seen order, a key a record
    lacks is an empty cell."""
    columns = list(dict.fromkeys(key for record in records for key in record))
    return csv_text(columns, ([record.get(key) for key in columns] for record in records))
