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
* :func:`overlap_problem`, :func:`foreign_folder_problem`, :func:`nonempty_path`: the rule that keeps
  an output from destroying an input, the same for every command and checked before any work: no
  output path may be, contain or lie inside an input or another output of the command (by resolved
  path and by inode); a folder a command would replace must be one it made; an empty path is
  refused. Outputs named after another (a ``.csv`` beside a trajectory) are not made beside a
  stream (:func:`is_stream`). A command whose standard output is a file it reads is refused
  (:func:`stdout_problem`); a command with an output on standard output prints its own lines to
  standard error (:func:`report_stream`).
* :func:`foreign_files_problem`, :func:`record_own_files`: files written into a folder that may hold
  other files (a report, an export) replace only the files a command recorded there as its own, and a
  report folder holds one command's results. :func:`beside_problem`, :func:`record_beside`: the same for
  the files a command names after an output (``OUT.csv``, ``OUT.json``, ``OUT.prior.txt``): the user
  named ``OUT``, not them, so an existing one is replaced only where a command recorded it.
* Temporary names carry the writing process's id (:func:`temp_name`); :func:`remove_stale` removes
  the ones whose process is gone (``kill -9``, a power cut), never those of a live run.
* :func:`claim_problem`, :func:`claim_folder`: a work folder belongs to the scripts its marker names;
  another script writes into it only where it is documented to share it with one of them.
* :func:`output_lock`: one writer per output; a lock file beside a cache being built, a training
  run or a work folder holds the writer's process id, and a stale one is reported, never taken.
* :class:`LiveOutputs`, :func:`whole_lines`: outputs written in place as they grow (the live
  correction's poses and rows), one whole line per write with Ctrl-C held back until a step's lines are
  all out, so that an interrupted command leaves whole lines; opened with the first line, so that a run
  that writes none leaves every file as it was.

This module holds :class:`InputWarning` and the output checks (:func:`writable`,
:func:`output_problem`, the overlap rule); the writers live in :mod:`dpc_jax._io._atomic_write` (output
targets, the atomic writer, streams, :func:`install_folder`), :mod:`dpc_jax._io._output_set` (output
sets), :mod:`dpc_jax._io._temporaries` (temporary names, stale removal), :mod:`dpc_jax._io._lock`
(output locks) and :mod:`dpc_jax._io._lines` (outputs written as they grow), and are imported from here.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import IO

from dpc_jax._io._atomic_write import OutputKind, atomic_write, install_folder, output_target, stream_write
from dpc_jax._io._claim import claim_folder, claim_problem
from dpc_jax._io._lines import LiveOutputs, whole_lines
from dpc_jax._io._lock import LockError, lock_holder, lock_path, output_lock
from dpc_jax._io._output_set import STAGING_PREFIX, OutputSet, new_folders_removed_on_failure
from dpc_jax._io._own_files import (
    OWN_FILES,
    Named,
    beside_problem,
    foreign_files_problem,
    record_beside,
    record_own_files,
)
from dpc_jax._io._temporaries import remove_stale, temp_name

__all__ = [
    "EMPTY_PATH",
    "OWN_FILES",
    "STAGING_PREFIX",
    "InputWarning",
    "LiveOutputs",
    "LockError",
    "Named",
    "OutputKind",
    "OutputSet",
    "atomic_write",
    "beside_problem",
    "claim_folder",
    "claim_problem",
    "foreign_files_problem",
    "foreign_folder_problem",
    "install_folder",
    "is_stdout",
    "is_stream",
    "lock_holder",
    "lock_path",
    "new_folders_removed_on_failure",
    "nonempty_path",
    "output_lock",
    "output_problem",
    "output_target",
    "overlap_problem",
    "record_beside",
    "record_own_files",
    "remove_stale",
    "report_stream",
    "stdout_problem",
    "stream_write",
    "temp_name",
    "whole_lines",
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


def output_problem(path: str | os.PathLike[str] | None, option: str, *, folder: bool = False) -> str | None:
    """What keeps ``path`` from receiving an output (a file, or a folder when ``folder``), or None
    (also for ``path`` None: an option not given).

    The message starts with ``option`` and the path. Missing parent folders are fine (they are
    created when the output is written); the nearest existing one must be a writable folder.
    """
    if path is None:
        return None
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


# ----------------------------------------------------------------------------- the overlap rule

EMPTY_PATH = "expected a path, got an empty one (which would mean the current folder)"


def nonempty_path(text: str) -> str:
    """``text``, a path option's value, unless it is empty: ``Path("")`` is the current folder, so an
    unset shell variable would otherwise write into (or replace) whatever folder the user is in.
    Raises ValueError (:data:`EMPTY_PATH`)."""
    if not text:
        raise ValueError(EMPTY_PATH)
    return text


# One place on the way to a path: the resolved folder or file, with its (st_dev, st_ino) where it
# exists. The path compares links and "./", ".." spellings; the inode, hard links and bind mounts.
_Place = tuple[str, tuple[int, int] | None]


def _places(path: str | os.PathLike[str]) -> list[_Place]:
    """``path`` resolved, then each folder above it, with their inodes: where the path is, outermost last."""
    resolved = Path(os.path.realpath(path))
    places: list[_Place] = []
    for place in (resolved, *resolved.parents):
        try:
            status = os.stat(place)
        except OSError:
            places.append((str(place), None))
        else:
            places.append((str(place), (status.st_dev, status.st_ino)))
    return places


def _same(a: _Place, b: _Place) -> bool:
    return a[0] == b[0] or (a[1] is not None and a[1] == b[1])


def _relation(output: list[_Place], other: list[_Place]) -> str | None:
    """How the output's path stands to another path: ``"is"``, ``"lies inside"``, ``"contains"`` or None."""
    if _same(output[0], other[0]):
        return "is"
    if any(_same(place, other[0]) for place in output[1:]):
        return "lies inside"
    if any(_same(place, output[0]) for place in other[1:]):
        return "contains"
    return None


def is_stream(path: str | os.PathLike[str]) -> bool:
    """Whether an output written to ``path`` is streamed (:func:`output_target`): no file is made
    there, so nothing may be made beside it either (a ``.csv`` beside ``/dev/stdout``)."""
    try:
        return output_target(path)[0] == "stream"
    except OSError:
        return False


def is_stdout(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` streams into this process's standard output (``/dev/stdout``, ``/dev/fd/1``,
    the terminal or pipe it is on), where what the command prints would follow the output."""
    if not is_stream(path):
        return False
    try:
        return os.path.samestat(os.stat(path), os.fstat(1))
    except OSError:
        return False


def report_stream(*paths: str | os.PathLike[str] | None) -> IO[str] | None:
    """Where a command's own lines go: standard error when one of its outputs ``paths`` (None: not
    written) is standard output (:func:`is_stdout`), so that what reads it gets the output alone; else
    standard output (None: ``print``'s default)."""
    return sys.stderr if any(is_stdout(path) for path in paths if path is not None) else None


def overlap_problem(inputs: list[Named], outputs: list[Named]) -> str | None:
    """Why an output would overwrite an input or another output of the same command, or None.

    The rule of every command: no output path may be, contain or lie inside an input or another
    output, compared by resolved path (symbolic links, ``./`` and ``..`` spellings) and by inode
    (hard links, bind mounts). A stream output (``/dev/null``, ``/dev/stdout``, a FIFO) replaces
    nothing and is not compared. ``inputs`` and ``outputs`` are ``(option, path)`` pairs, the option
    as the message names it; a None path was not given.
    """
    given_inputs = [(option, path, _places(path)) for option, path in inputs if path is not None]
    given_outputs = [(option, path, _places(path)) for option, path in outputs
                     if path is not None and not is_stream(path)]
    for index, (option, path, places) in enumerate(given_outputs):
        for other_option, other_path, other_places in given_inputs:
            relation = _relation(places, other_places)
            if relation is not None:
                return (f"{option} {path}: {relation} the input {other_option} {other_path}; an output "
                        "must not be, contain or lie inside an input")
        for other_option, other_path, other_places in given_outputs[:index]:
            relation = _relation(places, other_places)
            if relation is not None:
                return (f"{option} {path}: {relation} the output {other_option} {other_path}; give each "
                        "output a path of its own")
    return None


def stdout_problem(inputs: list[Named]) -> str | None:
    """Why this process's standard output may not be written: it is one of the ``inputs`` (a shell
    redirection such as ``>> est.txt`` onto a file the command reads, which what it prints would then
    follow), or None. Compared by inode, like :func:`overlap_problem`."""
    try:
        out = os.fstat(1)
    except OSError:
        return None
    for option, path in inputs:
        if path is None:
            continue
        try:
            same = os.path.samestat(os.stat(path), out)
        except OSError:
            continue
        if same:
            return (f"standard output is the input {option} {path} (redirected there with > or >>); what "
                    "the command prints would be written into it: redirect it elsewhere")
    return None


def foreign_folder_problem(
    folder: str | os.PathLike[str], label: str, *, marker: str, made_by: str
) -> str | None:
    """Why the command may not replace (or write over) ``folder``, or None.

    A folder a command replaces must be one it made, recognised by its ``marker`` (a path inside
    it: a cache's ``manifest.json``, a run's ``checkpoints/config.json``, a rendered sequence's
    ``synth.json``); a missing or empty folder is free. ``label``: the option and its value, which
    the message starts with; ``made_by``: what such a folder is, for the message.
    """
    folder = Path(folder)
    if not folder.exists() and not folder.is_symlink():
        return None
    if not folder.is_dir():
        return f"{label}: {folder} exists and is not a folder, so it cannot be replaced by {made_by}"
    if (folder / marker).is_file() or not any(folder.iterdir()):
        return None
    return (f"{label}: {folder} holds files but is not {made_by} (no {marker}), and this command would "
            "write over it; move it away or choose another path")
