"""File output shared by every writer and command: one atomic writer, all-or-nothing output sets,
output-path checks, and the removal of temporary folders that killed runs left behind.

* :func:`atomic_write`: the bytes go to a hidden temporary file beside the target, which then
  replaces it, so a reader never sees half a file. The file is created with mode ``0666`` minus
  the process umask (``0644`` with the usual umask), like any file a program opens for writing.
* :class:`OutputSet`: outputs that belong together (a trajectory and its CSV, a corrected
  trajectory and its report) are written into hidden staging folders inside their destination
  folders, then moved into place together; if a move fails (or Ctrl-C arrives) the moves already
  made are undone and the files they replaced are put back.
* :func:`output_problem`: what is wrong with an output path, checked before any work starts.
  The rule for folders, the same for every command: missing parent folders are created when the
  outputs are written (never when the run fails before), and the nearest existing one must be a
  writable folder.
* Temporary names carry the writing process's id (:func:`temp_name`); :func:`remove_stale` removes
  the ones whose process is gone (``kill -9``, a power cut), never those of a live run.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
import tempfile
from pathlib import Path
from types import TracebackType

STAGING_PREFIX = ".dpc-jax-staging-"
# A process that started this long after a temporary folder was last modified cannot own it; the
# margin covers the one-second resolution of the boot time in /proc/stat.
_START_TIME_MARGIN_S = 2.0


class InputWarning(UserWarning):
    """Input that is accepted but probably not what the user meant (the command line prints it as
    one ``warning:`` line)."""


def temp_name(prefix: str) -> str:
    """``PREFIX<pid>-<random>``: a temporary name that :func:`remove_stale` can attribute to its process."""
    return f"{prefix}{os.getpid()}-{secrets.token_hex(4)}"


def atomic_write(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then ``os.replace``).

    The parent folder must exist. Text is written as UTF-8. The file gets mode ``0666 & ~umask``.
    """
    path = Path(path)
    payload = data.encode("utf-8") if isinstance(data, str) else data
    while True:
        tmp = path.parent / f"{temp_name(f'.{path.name}.')}.tmp"
        try:
            # O_EXCL: never reuse a name; 0o666: the kernel applies the umask, as for open(..., "w").
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(payload)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# ----------------------------------------------------------------------------- stale temporaries


def install_folder(tmp: str | os.PathLike[str], target: str | os.PathLike[str]) -> None:
    """Move the finished folder ``tmp`` to ``target`` (same file system), replacing an older one there.

    The older folder is first renamed aside to ``.NAME.old-<pid>-<random>`` beside ``target``, so
    ``target`` is missing only between two renames; a crash leaves it under a name
    :func:`remove_stale` attributes to this process.
    """
    tmp, target = Path(tmp), Path(target)
    if target.exists():
        old = target.parent / temp_name(f".{target.name}.old-")
        old.mkdir()
        os.replace(target, old / target.name)
        os.replace(tmp, target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, target)


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
    if path.exists():
        if folder and not path.is_dir():
            return f"{label}: exists and is not a folder"
        if not folder and path.is_dir():
            return f"{label}: is a folder; expected a file name"
    destination = path if folder else path.parent
    existing = _nearest_existing(destination)
    if not existing.is_dir():
        return f"{label}: {existing} is a file, not a folder"
    if not writable(existing):
        return f"{label}: folder {existing} is not writable"
    return None


def _make_folders(folder: Path) -> list[Path]:
    """``mkdir -p folder``; return the folders it created, outermost first."""
    missing = []
    current = Path(os.path.abspath(folder))
    while not current.exists():
        missing.append(current)
        current = current.parent
    created = []
    for path in reversed(missing):
        try:
            path.mkdir()
        except FileExistsError:
            continue
        created.append(path)
    return created


def _remove_empty(folders: list[Path]) -> None:
    for path in reversed(folders):
        with contextlib.suppress(OSError):
            path.rmdir()


class OutputSet:
    """Outputs that belong together, written all or nothing.

    Usage::

        with OutputSet() as outputs:
            write_kitti_poses(outputs.file(out), poses)
            write_report(outputs.folder(report), result)
            outputs.commit()

    :meth:`file` and :meth:`folder` create the destination folder (and its missing parents) and
    return where to write instead: inside a hidden staging folder in the destination, so every
    final move is a rename within one file system. Anything written into a staging folder lands
    at the same relative place in its destination (a writer may add files beside the one asked
    for). :meth:`commit` moves every staged file into place, replacing existing files; if a move
    fails, the moves made so far are undone, the replaced files restored, and the error re-raised.
    Leaving the ``with`` block removes the staging folders, and without a commit also the
    destination folders this set created. Staging folders of killed runs are removed when a later
    set stages into the same folder.
    """

    def __init__(self) -> None:
        self._staging: dict[Path, Path] = {}  # destination folder -> its staging folder
        self._created: list[Path] = []
        self._committed = False

    def _stage(self, destination: Path) -> Path:
        destination = Path(os.path.abspath(destination))
        if destination not in self._staging:
            self._created += _make_folders(destination)
            remove_stale(destination, STAGING_PREFIX)
            staging = destination / temp_name(STAGING_PREFIX)
            staging.mkdir()
            self._staging[destination] = staging
        return self._staging[destination]

    def file(self, path: str | os.PathLike[str]) -> Path:
        """Where to write the file that is to end up at ``path``."""
        path = Path(path)
        return self._stage(path.parent) / path.name

    def folder(self, path: str | os.PathLike[str]) -> Path:
        """A folder whose contents are to end up in the folder ``path``."""
        return self._stage(Path(path))

    def commit(self) -> list[Path]:
        """Move every staged file into place, all or none; return the final paths."""
        moves = [
            (staged, destination / staged.relative_to(staging))
            for destination, staging in self._staging.items()
            for staged in sorted(staging.rglob("*"))
            if not staged.is_dir()
        ]
        done: list[tuple[Path, Path | None, list[Path]]] = []
        try:
            for index, (staged, final) in enumerate(moves):
                created = _make_folders(final.parent)
                backup = None
                if final.is_dir() and not final.is_symlink():
                    raise IsADirectoryError(errno.EISDIR, "is a folder; expected a file", str(final))
                if final.exists() or final.is_symlink():
                    backup = staged.parent / f"{staged.name}.replaced-{index}"
                    os.replace(final, backup)
                done.append((final, backup, created))
                os.replace(staged, final)
        except BaseException:
            for final, backup, created in reversed(done):
                with contextlib.suppress(OSError):
                    if backup is not None:
                        os.replace(backup, final)
                    else:
                        final.unlink(missing_ok=True)
                _remove_empty(created)
            raise
        self._committed = True
        return [final for _, final in moves]

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        for staging in self._staging.values():
            shutil.rmtree(staging, ignore_errors=True)
        if not self._committed:
            _remove_empty(self._created)
