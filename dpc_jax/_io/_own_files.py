"""The files a command wrote into a folder that may hold other files (a report, an export, the folder of
an ``--out`` with the files named after it): a record in the folder names them, so that a later run may
replace them and no file a user put there (:func:`foreign_files_problem`, :func:`record_own_files`,
:func:`beside_problem`, :func:`record_beside`). The rules are summarised in :mod:`dpc_jax._io`.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from dpc_jax._io._atomic_write import atomic_write

if TYPE_CHECKING:
    from dpc_jax._io._output_set import OutputSet

# The record: one file a line, sorted: its name, then (after a tab) the writer whose results it is (for a
# report or an export folder, ``evaluate --report``; nothing for a file named after an output). Hidden,
# like the staging folders beside it.
OWN_FILES = ".dpc-jax-files"


def _records(folder: str | os.PathLike[str]) -> dict[str, str]:
    """The files a command recorded as its own in ``folder``: name → writer ("" where none is recorded)."""
    try:
        text = (Path(folder) / OWN_FILES).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return {}
    records = {}
    for line in text.splitlines():
        name, _, writer = line.partition("\t")
        if name:
            records[name] = writer
    return records


def own_files(folder: str | os.PathLike[str]) -> frozenset[str]:
    """The names of the files a command recorded as its own in ``folder`` (none without a record)."""
    return frozenset(_records(folder))


def foreign_files_problem(folder: str | os.PathLike[str], names: Iterable[str], label: str, *,
                          writer: str | None = None, remedy: str = "choose another folder") -> str | None:
    """Why writing the files ``names`` into ``folder`` would replace a file no command made, or mix two
    commands' results, or None.

    A file of one of the names that exists there must be listed in the folder's record
    (:func:`record_own_files`); the folder's other files are left alone, so a report may go into a
    folder that holds other things. With ``writer`` (the results the files are: ``evaluate --report``),
    a folder holding files recorded as another writer's results is refused too: one report folder, one
    command's report, never a mixture of two. ``label``: the option and its value, which the message
    starts with; ``remedy``: what to do instead, which it ends with.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return None
    records = _records(folder)
    for name in names:
        path = folder / name
        if (path.exists() or path.is_symlink()) and name not in records:
            return (f"{label}: {path} exists and was not written by dpc-jax (it is not listed in "
                    f"{folder / OWN_FILES}), and this command would replace it; move it away or {remedy}")
    if writer is not None:
        others = sorted((other, name) for name, other in records.items()
                        if other and other != writer and (folder / name).exists())
        if others:
            other = others[0][0]
            shown = ", ".join(name for who, name in others if who == other)
            return (f"{label}: {folder} holds the results of `dpc-jax {other}` ({shown}), which this "
                    f"command's `{writer}` would mix with its own; {remedy}")
    return None


def record_own_files(staged: str | os.PathLike[str], folder: str | os.PathLike[str],
                     names: Iterable[str], *, writer: str = "") -> None:
    """Write the record of ``folder``'s own files, with ``names`` added (as ``writer``'s results, see
    :func:`foreign_files_problem`), into ``staged``: the folder where its files are staged
    (:meth:`~dpc_jax._io.OutputSet.folder`; ``folder`` itself for files written in place), so that the
    record lands with them, all or nothing."""
    records = _records(folder)
    records.update({Path(name).name: writer for name in names})
    atomic_write(Path(staged) / OWN_FILES,
                 "".join(f"{name}\t{who}\n" if who else f"{name}\n" for name, who in sorted(records.items())))


Named = tuple[str, str | os.PathLike[str] | None]  # (option, path); a None path was not given


def beside_problem(files: Iterable[Named]) -> str | None:
    """Why a file a command names after an output (``OUT.csv``, ``OUT.json``, ``OUT.prior.txt``: a file the
    user did not name) would replace a file no command made, or None: such a file may exist only where a
    command recorded it as its own (:func:`record_beside`). ``files``: ``(label, path)``, the label as the
    message starts (``--out o/a.txt (its .json summary)``); a None path is not written."""
    for label, path in files:
        if path is None:
            continue
        path = Path(path)
        problem = foreign_files_problem(path.parent, [path.name], label,
                                        remedy="give the output another name")
        if problem is not None:
            return problem
    return None


def record_beside(paths: Iterable[str | os.PathLike[str] | None], outputs: OutputSet | None = None) -> None:
    """Record the files named after an output (:func:`beside_problem`) as the command's own in their
    folders' records: staged with ``outputs`` (they land together), else written now into the folders,
    which must exist (for outputs written in place, before they are created)."""
    by_folder: dict[Path, list[str]] = defaultdict(list)
    for path in paths:
        if path is not None:
            by_folder[Path(os.path.abspath(path)).parent].append(Path(path).name)
    for folder, names in by_folder.items():
        record_own_files(folder if outputs is None else outputs.folder(folder), folder, names)
