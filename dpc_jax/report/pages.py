"""A generated block in a hand-written page: the text between ``<!-- NAME:begin -->`` and
``<!-- NAME:end -->``, replaced by the script that measures it and nothing else of the page.

Each page of ``docs/results/`` holds its experiment's table in a ``results`` block, which the
experiment's script rewrites when given ``--results-page`` (:func:`write_results`);
``docs/performance.md`` holds the ``performance`` and ``scale`` blocks of
``benchmarks/performance_table.py`` and ``experiments/studies/paper_scale.py``.
"""

from __future__ import annotations

import datetime
import subprocess
from pathlib import Path

from dpc_jax._io import atomic_write
from dpc_jax.runtime.versions import versions_line

RESULTS = "results"


def markers(name: str) -> tuple[str, str]:
    """The begin and end markers of block ``name``."""
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def _split(text: str, name: str, path: Path) -> tuple[str, str, str]:
    """``text`` as (everything up to the begin marker, included; the block; the end marker onwards)."""
    begin, end = markers(name)
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        raise ValueError(f"{path}: no {begin} … {end} block")
    head = start + len(begin)
    return text[:head], text[head:stop], text[stop:]


def read_block(path: Path, name: str) -> str:
    """The text of block ``name`` in ``path`` (ValueError without its markers)."""
    return _split(path.read_text(encoding="utf-8"), name, path)[1]


def replace_block(path: Path, name: str, block: str) -> None:
    """Replace block ``name`` of ``path`` by ``block`` (one line break either side), atomically."""
    before, _, after = _split(path.read_text(encoding="utf-8"), name, path)
    atomic_write(path, before + "\n" + block.strip("\n") + "\n" + after)


def commit(directory: Path) -> str:
    """The commit checked out in ``directory`` (``git describe --always --dirty``: ``-dirty`` when
    tracked files differ from it), or ``unknown`` outside a git checkout."""
    found = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=directory, capture_output=True,
                           text=True)
    return found.stdout.strip() or "unknown"


def check_results_page(page: Path | None) -> None:
    """Raise (OSError, ValueError) unless ``page`` is None or a page with a ``results`` block: checked
    before an experiment runs, not after."""
    if page is not None:
        read_block(page, RESULTS)


def write_results(page: Path, markdown: str, script: Path) -> None:
    """Put an experiment's Markdown into the ``results`` block of ``page``, under a line naming the
    script, the commit, the date and the library versions (``dpc_jax.runtime.versions``); its ``# title``
    line is dropped (the page has its own)."""
    text = markdown.strip("\n")
    if text.startswith("# "):
        text = text.partition("\n")[2].strip("\n")
    stamp = (f"Written by `{script.name}` at commit {commit(script.parent)}, "
             f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d}, with {versions_line()}.")
    replace_block(page, RESULTS, f"{stamp}\n\n{text}")
