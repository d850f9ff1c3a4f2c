"""Which frame pairs adaptation keeps out for the acceptance test, and which it may fit.

Every ``every``-th consecutive pair ``(k, k+1)``, ``k = every//2, every//2 + every, …``, is kept
out, and with it every sample that reaches frame ``k`` or ``k+1``: the neighbouring pairs share an
image with it and a frame-skip pair ``(k-1, k+1)`` contains its motion, so a network fitted to
them would be judged on what it has seen. Pure numpy: the command line checks a split before it
imports JAX.
"""

from __future__ import annotations

import numpy as np

MIN_EVERY = 4  # below it the kept-out pairs' frames leave no consecutive pair to adapt on


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
