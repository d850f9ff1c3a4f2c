"""Outputs written all or nothing (:class:`OutputSet`), and the removal of the folders a failed
write created (:func:`new_folders_removed_on_failure`). The rules are summarised in
:mod:`dpc_jax._io`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType

from dpc_jax._io._atomic_write import output_target, stream_write
from dpc_jax._io._temporaries import remove_stale, temp_name

STAGING_PREFIX = ".dpc-jax-staging-"


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
