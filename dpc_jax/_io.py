"""File output shared by every writer and command: one atomic writer, all-or-nothing output sets,
output-path checks, and the removal of temporary folders that killed runs left behind.

* :func:`atomic_write`: the bytes go to a hidden temporary file beside the target, which then
  replaces it, so a reader never sees half a file. The file is created with mode ``0666`` minus
  the process umask (``0644`` with the usual umask), like any file a program opens for writing.
* :class:`OutputSet`: outputs that belong together (a trajectory and its CSV, a corrected
  trajectory and its report) are written into hidden staging folders inside their destination
  folders, then moved into place together; if a move fails (or Ctrl-C arrives) the moves already
  made are undone and the files they replaced are put back.
* :func:`output_target`: where an output path leads. A regular file, or a new one, is written
  atomically as above; a symbolic link to one is followed and its target replaced the same way (the
  link stays). A character device (``/dev/null``), a FIFO (``>(gzip > x)``) or a link into
  ``/proc`` (``/dev/stdout``, ``/dev/fd/N``) cannot be replaced: the bytes are streamed into it,
  once complete (:func:`stream_write`). Anything else (a block device, a socket) is refused.
* :func:`output_problem`: what is wrong with an output path, checked before any work starts.
  The rule for folders, the same for every command: missing parent folders are created when the
  outputs are written (never when the run fails before), and the nearest existing one must be a
  writable folder.
* Temporary names carry the writing process's id (:func:`temp_name`); :func:`remove_stale` removes
  the ones whose process is gone (``kill -9``, a power cut), never those of a live run.

This module holds :class:`InputWarning` and the output checks (:func:`writable`,
:func:`output_problem`); the writers live in :mod:`dpc_jax._atomic_write` (output targets, the
atomic writer, streams, :func:`install_folder`), :mod:`dpc_jax._output_set` (output sets) and
:mod:`dpc_jax._temporaries` (temporary names, stale removal), and are imported from here.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from dpc_jax._atomic_write import OutputKind, atomic_write, install_folder, output_target, stream_write
from dpc_jax._output_set import STAGING_PREFIX, OutputSet, new_folders_removed_on_failure
from dpc_jax._temporaries import remove_stale, temp_name

__all__ = [
    "STAGING_PREFIX",
    "InputWarning",
    "OutputKind",
    "OutputSet",
    "atomic_write",
    "install_folder",
    "new_folders_removed_on_failure",
    "output_problem",
    "output_target",
    "remove_stale",
    "stream_write",
    "temp_name",
    "writable",
]


class InputWarning(UserWarning):
    """Input that is accepted but probably not what the user meant (the command line prints it as
    one ``warning:`` line)."""


# ----------------------------------------------------------------------------- output checks


def writable(folder: Path) -> bool:
    """Whether this process may create entries in ``folder``.

    Tried for real (a temporary file, removed at once): ``os.access`` says yes to root in a
    read-only mount or ``/proc``, where the write would fail after the work is done."""
    if not os.access(folder, os.W_OK | os.X_OK):
        return False
    try:
        with tempfile.TemporaryFile(dir=folder):
            return True
    except OSError:
        return False


def _nearest_existing(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def output_problem(path: str | os.PathLike[str], option: str, *, folder: bool = False) -> str | None:
    """What keeps ``path`` from receiving an output (a file, or a folder when ``folder``), or None.

    The message starts with ``option`` and the path. Missing parent folders are fine (they are
    created when the output is written); the nearest existing one must be a writable folder.
    """
    path = Path(path)
    label = f"{option} {path}"
    if folder:
        if path.exists() and not path.is_dir():
            return f"{label}: exists and is not a folder"
        destination = path
    else:
        try:
            kind, target = output_target(path)
        except OSError as error:
            return f"{label}: {error.strerror}"
        if kind == "stream":
            return None if os.access(target, os.W_OK) else f"{label}: not writable"
        if kind == "folder":
            return f"{label}: is a folder; expected a file name"
        if kind != "file":
            return f"{label}: is a {kind}; expected a regular file, a character device or a FIFO"
        destination = target.parent
    existing = _nearest_existing(destination)
    if not existing.is_dir():
        return f"{label}: {existing} is a file, not a folder"
    if not writable(existing):
        return f"{label}: folder {existing} is not writable"
    return None
