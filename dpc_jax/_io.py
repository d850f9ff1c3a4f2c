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
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Literal

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


# ----------------------------------------------------------------------------- output targets

OutputKind = Literal["file", "stream", "folder", "block device", "socket", "special file"]
_MAX_LINKS = 40  # as the kernel's ELOOP limit


def _follow(path: str | os.PathLike[str]) -> tuple[Path, bool]:
    """``path`` with its symbolic links followed, and whether they led into ``/proc``.

    The links are followed one by one rather than with ``realpath``: ``/dev/stdout`` leads to
    ``/proc/self/fd/1``, whose link text names whatever file descriptor 1 is open on (``pipe:[N]``,
    or a regular file that a shell redirection opened); that is to be written through the
    descriptor's link, never replaced.
    """
    current = os.path.join(os.getcwd(), os.fspath(path))
    for _ in range(_MAX_LINKS):
        # The folders on the way resolved, so that /dev/fd/1 is seen as /proc/<pid>/fd/1.
        current = os.path.join(os.path.realpath(os.path.dirname(current)), os.path.basename(current))
        if current.startswith("/proc/"):
            return Path(current), True
        if not os.path.islink(current):
            return Path(current), False
        current = os.path.join(os.path.dirname(current), os.readlink(current))
    raise OSError(errno.ELOOP, "too many levels of symbolic links", os.fspath(path))


def output_target(path: str | os.PathLike[str]) -> tuple[OutputKind, Path]:
    """What an output written to ``path`` is written into, and where: ``(kind, target)``.

    ``"file"``: a regular file or a new one at ``target`` (``path`` with its symbolic links
    followed), replaced atomically. ``"stream"``: a character device, a FIFO or a link into
    ``/proc`` such as ``/dev/stdout``, written directly (:func:`stream_write`). ``"folder"``, a
    block device, a socket or another special file cannot receive a file output.
    """
    target, through_proc = _follow(path)
    try:
        mode = os.stat(target).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return "file", target
    if stat.S_ISDIR(mode):
        return "folder", target
    if through_proc or stat.S_ISCHR(mode) or stat.S_ISFIFO(mode):
        return "stream", target
    if stat.S_ISREG(mode):
        return "file", target
    if stat.S_ISBLK(mode):
        return "block device", target
    return ("socket" if stat.S_ISSOCK(mode) else "special file"), target


def stream_write(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` into the stream ``path`` (a character device, a FIFO, ``/dev/stdout``).

    The process's own standard output or error (``/dev/stdout``, or any path to the same file) is
    written through its file descriptor, after what the process printed there, so that both keep
    their order in a file the shell redirected them to (a second descriptor would write from the
    file's start, over them). Anything else is opened without creating or truncating it, in append
    mode; a FIFO blocks until a reader opens it, as for any writer.
    """
    payload = data.encode("utf-8") if isinstance(data, str) else data
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError, AttributeError):
            stream.flush()
    status = os.stat(path)
    for fd in (1, 2):
        try:
            same = os.path.samestat(status, os.fstat(fd))
        except OSError:
            continue
        if same:
            with _naming(path):
                _write_all(fd, payload)
            return
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_NOCTTY)
    try:
        with _naming(path):
            _write_all(fd, payload)
    finally:
        os.close(fd)


def _write_all(fd: int, payload: bytes) -> None:
    view = memoryview(payload)
    while view:
        view = view[os.write(fd, view):]


def atomic_write(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then ``os.replace``).

    The parent folder must exist. Text is written as UTF-8. The file gets mode ``0666 & ~umask``.
    A symbolic link is followed (its target is replaced); a stream (:func:`output_target`) is
    written directly; any other non-regular file raises OSError.
    """
    kind, target = output_target(path)
    if kind == "stream":
        stream_write(path, data)
        return
    if kind == "folder":
        raise IsADirectoryError(errno.EISDIR, "is a folder; expected a file", os.fspath(path))
    if kind != "file":
        raise OSError(errno.EINVAL, f"is a {kind}; expected a regular file, a character device or a FIFO",
                      os.fspath(path))
    path = target
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
        with _naming(path), os.fdopen(fd, "wb") as handle:
            handle.write(payload)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def _naming(path: str | os.PathLike[str]) -> Iterator[None]:
    """Give an OSError raised without a file name (a full disk fails the write, which names none)
    the output's ``path``, so the command's one line says which file could not be written."""
    try:
        yield
    except OSError as error:
        if error.filename is not None or error.errno is None:
            raise
        raise type(error)(error.errno, error.strerror, os.fspath(path)) from error


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


@contextlib.contextmanager
def new_folders_removed_on_failure(folder: str | os.PathLike[str]) -> Iterator[Callable[[], None]]:
    """Around the writing of outputs under ``folder``: if the block fails (or Ctrl-C arrives), the
    folders on the way to ``folder`` that did not exist before it are removed again where empty, so
    that folders are made only when an output is written. The block gets the function that does
    this, for a failure it reports without raising."""
    missing = []
    current = Path(os.path.abspath(folder))
    while not current.exists() and current != current.parent:
        missing.append(current)
        current = current.parent

    def remove() -> None:
        _remove_empty(missing[::-1])

    try:
        yield remove
    except BaseException:
        remove()
        raise


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
    for). A file whose path is a symbolic link is staged beside the link's target, which it
    replaces; one whose path is a stream (:func:`output_target`: a character device, a FIFO,
    ``/dev/stdout``) is staged in a private temporary folder and streamed into place last, once
    every other file has been moved (a stream cannot be taken back). :meth:`commit` moves every
    staged file into place, replacing existing files; if a move or a stream
    fails, the moves made so far are undone, the replaced files restored, and the error re-raised.
    Leaving the ``with`` block removes the staging folders, and without a commit also the
    destination folders this set created. Staging folders of killed runs are removed when a later
    set stages into the same folder.
    """

    def __init__(self) -> None:
        self._staging: dict[Path, Path] = {}  # destination folder -> its staging folder
        self._streams: list[tuple[Path, Path]] = []  # (staged file, the stream it goes to)
        self._private: Path | None = None  # the staging folder of streams
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
        kind, target = output_target(path)
        if kind == "stream":
            if self._private is None:
                self._private = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX))
            staged = self._private / f"{len(self._streams)}-{target.name}"
            self._streams.append((staged, Path(path)))
            return staged
        return self._stage(target.parent) / target.name

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
            for staged, stream in self._streams:
                stream_write(stream, staged.read_bytes())
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
        return [final for _, final in moves] + [stream for _, stream in self._streams]

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        for staging in [*self._staging.values(), *filter(None, [self._private])]:
            shutil.rmtree(staging, ignore_errors=True)
        if not self._committed:
            _remove_empty(self._created)
