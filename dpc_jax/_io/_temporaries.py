"""Temporary names a process can be identified by, and the removal of those whose process is gone.

Every temporary file or folder that a writer leaves beside its target while it works carries the
writing process's id (:func:`temp_name`); :func:`remove_stale` removes the ones whose process is
gone (``kill -9``, a power cut), never those of a live run.
"""

from __future__ import annotations

import os
import secrets
import shutil
from pathlib import Path

# A process that started this long after a temporary folder was last modified cannot own it; the
# margin covers the one-second resolution of the boot time in /proc/stat.
_START_TIME_MARGIN_S = 2.0


def temp_name(prefix: str) -> str:
    """``PREFIX<pid>-<random>``: a temporary name that :func:`remove_stale` can attribute to its process."""
    return f"{prefix}{os.getpid()}-{secrets.token_hex(4)}"


def _process_start_time(pid: int) -> float | None:
    """Start time of process ``pid`` (seconds since the epoch) from /proc, or None where unknown."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        boot = next(
            float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
            if line.startswith("btime ")
        )
        # Field 22 (starttime, clock ticks after boot); the command name before ')' may hold spaces.
        ticks = int(stat.rsplit(")", 1)[1].split()[19])
    except (OSError, StopIteration, ValueError, IndexError):
        return None
    return boot + ticks / os.sysconf("SC_CLK_TCK")


def _owner_alive(pid: int, modified: float) -> bool:
    """Whether process ``pid`` may still own a temporary entry last modified at ``modified``."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's live process
    started = _process_start_time(pid)
    # A live process that started after the entry was last written is a reused pid, not the owner.
    return started is None or started <= modified + _START_TIME_MARGIN_S


def remove_stale(folder: str | os.PathLike[str], prefix: str) -> list[Path]:
    """Remove the entries ``PREFIX<pid>-...`` of ``folder`` whose process is gone; return them.

    Entries of live processes (this one included) are kept. A missing folder holds nothing.
    """
    folder = Path(folder)
    removed: list[Path] = []
    try:
        entries = list(folder.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return removed
    for entry in entries:
        if not entry.name.startswith(prefix):
            continue
        pid_text = entry.name[len(prefix):].split("-", 1)[0]
        if not pid_text.isdigit():
            continue
        try:
            modified = entry.lstat().st_mtime
        except FileNotFoundError:
            continue
        if _owner_alive(int(pid_text), modified):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed
