"""Which frame pairs adaptation keeps out for the acceptance test, and which it may fit.

Every ``every``-th consecutive pair ``(k, k+1)``, ``k = every//2, every//2 + every, …``, is kept
out, and with it every sample that reaches frame ``k`` or ``k+1``: the neighbouring pairs share an
image with it and a frame-skip pair ``(k-1, k+1)`` contains its motion, so a network fitted to
them would be judged on what it has seen. :func:`holdout_problem` says when a sequence is too short
for a split, and which split would fit. Pure numpy: the command line checks a split before it
imports JAX.
"""

from __future__ import annotations

import os

import numpy as np

MIN_EVERY = 4  # below it the kept-out pairs' frames leave no consecutive pair to adapt on
# The split when none is asked (``dpc_jax.correction.adapt.AdaptConfig``, ``dpc-jax correct
# --holdout-every``): a fifth of the pairs kept out for the test.
DEFAULT_EVERY = 5


def held_out_pairs(n_pairs: int, every: int) -> np.ndarray:
    """The consecutive pairs ``k < n_pairs`` kept out of adaptation: ``every//2, every//2 + every, …``."""
    return np.arange(every // 2, n_pairs, every, dtype=np.int64)


def touches(first: np.ndarray, last: np.ndarray, held_out: np.ndarray) -> np.ndarray:
    """Whether the sample spanning frames ``first … last`` (``[S]`` each) reaches frame ``k`` or
    ``k+1`` of a held-out pair ``k`` (``held_out [H]``) → bool ``[S]``."""
    k = np.asarray(held_out)[None, :]
    first, last = np.asarray(first)[:, None], np.asarray(last)[:, None]
    return np.any((k <= last) & (k + 1 >= first), axis=1)


def adaptable_pairs(n_pairs: int, every: int) -> np.ndarray:
    """The consecutive pairs ``k`` adaptation may fit: those that touch no kept-out pair's frames."""
    k = np.arange(n_pairs)
    return k[~touches(k, k + 1, held_out_pairs(n_pairs, every))]


def holdout_problem(n_frames: int, every: int, where: str | os.PathLike[str]) -> str | None:
    """Why adaptation cannot keep every ``every``-th pair of the ``n_frames`` frames of ``where`` out
    for its test, or None: the test needs one pair kept out and adaptation one that touches none of
    their frames. The line names the largest ``--holdout-every`` that fits, if any does."""
    n_pairs = n_frames - 1
    held, adaptable = held_out_pairs(n_pairs, every).size, adaptable_pairs(n_pairs, every).size
    if held and adaptable:
        return None
    # From every = 2 * n_pairs on, the first kept-out pair every // 2 is past the last: none fits.
    fits = [k for k in range(MIN_EVERY, 2 * n_pairs + 1)
            if held_out_pairs(n_pairs, k).size and adaptable_pairs(n_pairs, k).size]
    hint = f"; use --holdout-every {max(fits)} or less" if fits else f"; {where} is too short to adapt on"
    return (f"--holdout-every {every}: keeps {held} of the {n_pairs} frame pairs of {where} out of "
            f"adaptation and leaves {adaptable} that touch none of their frames, but its test needs at "
            f"least one kept out and one to adapt on{hint}")
