"""Writing one output: where its path leads (:func:`output_target`), the atomic replacement of a
file (:func:`atomic_write`) or of a folder (:func:`install_folder`), and the streaming into a
character device, a FIFO or ``/dev/stdout`` that cannot be replaced (:func:`stream_write`).
The rules are summarised in :mod:`dpc_jax._io`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import stat
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

from dpc_jax._io._temporaries import temp_name

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
    standard = standard_fd(path)
    if standard is not None:
        with _naming(path):
            write_all(standard, payload)
        return
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_NOCTTY)
    try:
        with _naming(path):
            write_all(fd, payload)
    finally:
        os.close(fd)


def standard_fd(path: str | os.PathLike[str]) -> int | None:
    """The descriptor (1 or 2) of this process's standard output or error when the stream ``path`` is
    the same file, else None; both are flushed first, so that what the process printed there stays
    before what is written through the descriptor."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError, AttributeError):
            stream.flush()
    status = os.stat(path)
    for fd in (1, 2):
        with contextlib.suppress(OSError):
            if os.path.samestat(status, os.fstat(fd)):
                return fd
    return None


def write_all(fd: int, payload: bytes) -> None:
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
