"""One writer per output: a lock file beside what a command writes, holding the writer's process id.

``with output_lock(path, label):`` holds the lock of ``path`` (a cache folder being built, a
training run, a work folder, or a file) for the block. The lock is the file ``.NAME.lock`` in the
folder that holds ``path`` (after links: two spellings of one place share one lock), beside rather
than inside, so that it survives the block replacing ``path`` (a cache is built elsewhere and
renamed into place) and never makes a folder look non-empty. It is created whole or not at all (a
hard link of a finished temporary file, where the file system has hard links), so a second writer
either gets it or reads who holds it, and is removed when the block ends. A process may hold a lock
it already holds (the command line locks a cache before JAX starts, the library again while
building it); only the outermost hold removes it.

A lock that cannot be taken raises :class:`LockError`, one line that names the lock file and its
holder's process id: a live holder (wait, or write elsewhere) or a stale lock, whose process is
gone (``kill -9``, a power cut). A stale lock is never taken over silently: the user removes it
once they know no other writer is at work (its process may run on another host sharing the folder).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
from collections.abc import Iterator
from pathlib import Path

from dpc_jax._io._temporaries import _owner_alive, remove_stale, temp_name


class LockError(OSError):
    """The lock of an output is held by another process, or left by one that is gone (one line)."""


def lock_path(path: str | os.PathLike[str]) -> Path:
    """The lock file of ``path``: ``.NAME.lock`` beside it, after resolving links and ``..``."""
    resolved = Path(os.path.realpath(path))
    return resolved.parent / f".{resolved.name}.lock"


def _holder(lock: Path) -> dict | None:
    """The record in ``lock`` (``pid``, ``host``, ``command``), None when it is gone; ``{}`` when it
    holds no such record (not written by this module)."""
    try:
        record = json.loads(lock.read_text())
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return record if isinstance(record, dict) and isinstance(record.get("pid"), int) else {}


def _refusal(lock: Path, holder: dict, path: Path, label: str) -> str:
    """The one line that says who holds ``lock`` and what to do."""
    if not holder:
        return (f"{label}: {path} is locked by {lock}, which names no process; remove it if no other "
                "process writes there")
    pid, host = holder["pid"], holder.get("host")
    command = f" ({holder['command']})" if isinstance(holder.get("command"), str) else ""
    if host != socket.gethostname():
        return (f"{label}: {path} is being written by process {pid} on host {host}{command} (lock {lock}); "
                "wait for it to finish, or remove the lock if that process is gone")
    try:
        modified = lock.stat().st_mtime
    except FileNotFoundError:
        modified = 0.0
    if _owner_alive(pid, modified):
        return (f"{label}: {path} is being written by process {pid}{command} (lock {lock}); wait for it "
                "to finish, or write to another path")
    return (f"{label}: {path} is locked by process {pid}, which is no longer running{command}; the lock "
            f"{lock} was left by a run that was killed: remove it if no other process writes there")


def lock_holder(path: str | os.PathLike[str], label: str) -> str | None:
    """The one line :func:`output_lock` would refuse ``path`` with when its lock is held now (by a live
    process, or left by one that is gone), else None: for checks that run before the lock is taken."""
    lock = lock_path(path)
    holder = _holder(lock)
    return None if holder is None else _refusal(lock, holder, Path(path), label)


@contextlib.contextmanager
def output_lock(path: str | os.PathLike[str], label: str) -> Iterator[Path]:
    """Hold the lock of ``path`` for the block (see the module docstring); yields the lock file.

    The folder that holds ``path`` is created if missing. ``label``: the option and its value (or
    what the path is), which a refusal starts with. Raises :class:`LockError` when another process
    holds the lock or a stale one is in the way.
    """
    path = Path(path)
    lock = lock_path(path)
    mine = {"pid": os.getpid(), "host": socket.gethostname()}
    command = " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])[:200]
    staged = lock.parent / temp_name(f"{lock.name}.tmp-")
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        # The temporary files of writers killed between writing and linking them.
        remove_stale(lock.parent, f"{lock.name}.tmp-")
        staged.write_text(json.dumps({**mine, "command": command}) + "\n")
        outermost = _take(staged, lock, mine, path, label)
    except LockError:
        raise
    except OSError as error:
        raise LockError(f"{label}: cannot write the lock {lock} of {path} ({error.strerror or error}); "
                        "its folder must be writable") from None
    finally:
        staged.unlink(missing_ok=True)
    try:
        yield lock
    finally:
        if outermost and {key: (_holder(lock) or {}).get(key) for key in mine} == mine:
            lock.unlink(missing_ok=True)


def _take(staged: Path, lock: Path, mine: dict, path: Path, label: str) -> bool:
    """Link ``staged`` (the record ``mine`` and the command) as ``lock``; return True when taken,
    False when this process holds it already. Raises :class:`LockError` when another does."""
    # A link fails if the lock exists: of two writers exactly one gets it. A holder that removes its
    # lock between a failed link and the read leaves the place free: try again.
    for _ in range(3):
        try:
            _create(staged, lock)
        except FileExistsError:
            holder = _holder(lock)
            if holder is None:
                continue
            if {key: holder.get(key) for key in mine} == mine:
                return False
            raise LockError(_refusal(lock, holder, path, label)) from None
        return True
    raise LockError(f"{label}: {path}: its lock {lock} keeps changing hands; try again")


def _create(staged: Path, lock: Path) -> None:
    """Create ``lock`` holding the bytes of ``staged``, or raise ``FileExistsError``: a hard link, so the
    lock appears whole; where the file system has none, an exclusive create and a write, which a
    reader can find empty for an instant (it then names no process)."""
    try:
        os.link(staged, lock)
        return
    except FileExistsError:
        raise
    except OSError:
        pass  # no hard links here (some network and FUSE file systems)
    descriptor = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    with os.fdopen(descriptor, "wb") as file:
        file.write(staged.read_bytes())
