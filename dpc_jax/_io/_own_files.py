"""The files a command wrote into a folder that may hold other files (a report, an export): a record in
the folder names them, so that a later run may replace them and no file a user put there
(:func:`foreign_files_problem`, :func:`record_own_files`). The rules are summarised in
:mod:`dpc_jax._io`.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from dpc_jax._io._atomic_write import atomic_write

# The record: one file name a line, sorted. Hidden, like the staging folders beside it.
OWN_FILES = ".dpc-jax-files"


def own_files(folder: str | os.PathLike[str]) -> frozenset[str]:
    """The names of the files a command recorded as its own in ``folder`` (none without a record)."""
    try:
        text = (Path(folder) / OWN_FILES).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return frozenset()
    return frozenset(line for line in text.splitlines() if line)


def foreign_files_problem(folder: str | os.PathLike[str], names: Iterable[str], label: str) -> str | None:
    """Why writing the files ``names`` into ``folder`` would replace a file no command made, or None.

    A file of one of the names that exists there must be listed in the folder's record
    (:func:`record_own_files`); the folder's other files are left alone, so a report may go into a
    folder that holds other things. ``label``: the option and its value, which the message starts with.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return None
    recorded = own_files(folder)
    for name in names:
        path = folder / name
        if (path.exists() or path.is_symlink()) and name not in recorded:
            return (f"{label}: {path} exists and was not written by dpc-jax (it is not listed in "
                    f"{folder / OWN_FILES}), and this command would replace it; move it away or choose "
                    "another folder")
    return None


def record_own_files(staged: str | os.PathLike[str], folder: str | os.PathLike[str],
                     names: Iterable[str]) -> None:
    """Write the record of ``folder``'s own files, with ``names`` added, into ``staged``: the folder
    where its files are staged (:meth:`~dpc_jax._io.OutputSet.folder`), so that the record lands with
    them, all or nothing."""
    listed = sorted(own_files(folder) | {Path(name).name for name in names})
    atomic_write(Path(staged) / OWN_FILES, "".join(f"{name}\n" for name in listed))
