"""Raw inputs prepared for a correction: a sequence cached at the network's image size and, with a
judge, the same frames at the judge's size.

``dpc-jax correct`` corrects a KITTI sequence or a recording by preparing it first
(``dpc_jax.data.cache.prepare_sequence``) into a folder it keeps (``--cache``) or a temporary one
(:func:`prepared_inputs`); the judge's cache is the sequence's name with :data:`JUDGE_SUFFIX`.
:func:`cache_folders_problem` says, before any work, why those folders cannot be (re)written. No
JAX.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dpc_jax._io import foreign_folder_problem, remove_stale

if TYPE_CHECKING:
    import numpy as np

    from dpc_jax.data.kitti import StereoSequence

# The judge's cache beside the sequence's: CACHE/NAME and CACHE/NAME_judge.
JUDGE_SUFFIX = "_judge"
# The temporary folder of a correction without a kept cache; the pid in its name lets a later run
# remove the folder of a killed one (dpc_jax._io.remove_stale).
TEMPORARY_PREFIX = "dpc-correct-"


def cache_names(name: str, judged: bool) -> list[str]:
    """The cache folders preparing the sequence ``name`` makes: its own, and its judge's if
    ``judged``."""
    return [name] + ([name + JUDGE_SUFFIX] if judged else [])


def cache_folders_problem(root: Path, name: str, judged: bool, label: str) -> str | None:
    """Why a folder that preparing the sequence ``name`` into ``root`` (named ``label`` in the line)
    would replace is not a cache of ``dpc-jax prepare`` (:func:`cache_names`), or None."""
    from dpc_jax.data.sequence_cache import MANIFEST

    for folder in cache_names(name, judged):
        problem = foreign_folder_problem(root / folder, label, marker=MANIFEST,
                                         made_by="a cache of `dpc-jax prepare`")
        if problem is not None:
            return problem
    return None


@contextlib.contextmanager
def prepared_inputs(
    sequence: StereoSequence, prior: str | Path | np.ndarray, root: Path | None, *,
    size: tuple[int, int], flow: bool, judge_size: tuple[int, int] | None, **options: Any,
) -> Iterator[tuple[Path, Path | None]]:
    """Prepare ``sequence`` with ``prior`` at the network's ``size`` (``flow``: with the forward flow
    the network reads) and, with ``judge_size``, also there as its judge; into ``root``, kept, or
    (None) a temporary folder removed when the block ends. Yields the two caches' folders (the judge's
    None without ``judge_size``). ``options``: those of ``dpc_jax.data.cache.prepare_sequence``
    (``frames``, ``remove_static``, ``ground_truth``, ...)."""
    from dpc_jax.data.cache import prepare_sequence

    with contextlib.ExitStack() as stack:
        if root is None:
            remove_stale(tempfile.gettempdir(), TEMPORARY_PREFIX)
            root = Path(stack.enter_context(
                tempfile.TemporaryDirectory(prefix=f"{TEMPORARY_PREFIX}{os.getpid()}-")))
        cache = prepare_sequence(sequence, prior, root, size=size, flow=flow, **options)
        judge = None
        if judge_size is not None:
            judge = prepare_sequence(sequence, prior, root, size=judge_size,
                                     name=sequence.name + JUDGE_SUFFIX, **options)
        yield cache, judge
