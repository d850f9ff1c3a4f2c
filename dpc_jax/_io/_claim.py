"""Which scripts a folder belongs to: a marker file in it names them, so that a script writes only into a
folder it made (or one made by a script it is documented to share with), never into another's
(:func:`claim_problem`, :func:`claim_folder`). The rules are summarised in :mod:`dpc_jax._io`.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from dpc_jax._io._atomic_write import atomic_write


def claimants(marker: str | os.PathLike[str]) -> list[str]:
    """The scripts a ``marker`` names (its lines after the first, which says what the folder is), in the
    order they claimed the folder; none for a missing marker, or one made before markers named them."""
    try:
        lines = Path(marker).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return []
    return [line.strip() for line in lines[1:] if line.strip()]


def claim_problem(folder: str | os.PathLike[str], label: str, *, marker: str, owner: str,
                  shares: Iterable[str] = ()) -> str | None:
    """Why ``owner`` may not write into ``folder``, or None: its ``marker`` (a name inside it) names other
    scripts, none of them ``owner`` or one of ``shares`` (the scripts ``owner`` is documented to share a
    folder with). A folder without a marker, or whose marker names no script, is free (a folder that
    holds files but no marker is :func:`~dpc_jax._io.foreign_folder_problem`'s). ``label``: the option and
    its value, which the message starts with."""
    owners = claimants(Path(folder) / marker)
    if not owners or owner in owners or set(shares) & set(owners):
        return None
    return (f"{label}: {folder} is the work folder of {', '.join(owners)}, and {owner} would write its "
            f"results over theirs; give {owner} a work folder of its own")


def claim_folder(folder: str | os.PathLike[str], *, marker: str, owner: str | None, about: str) -> None:
    """Make ``folder`` (and its parents) and mark it as ``owner``'s (None: the marker is only made):
    ``marker`` holds ``about`` (one line, what the folder is), then each script that claimed it. A marker
    that already names ``owner`` is left as it is."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / marker
    if path.is_file() and (owner is None or owner in claimants(path)):
        return
    owners = claimants(path) + ([] if owner is None else [owner])
    atomic_write(path, "".join(f"{line}\n" for line in [about, *owners]))
