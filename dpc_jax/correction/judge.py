"""The judge's size: where the acceptance test is measured besides the network's own size.

A judge is the same frames prepared at a larger size, with StereoSGBM depth and no network
(``dpc_jax.correction.measure.judge_measurement``); what passes at the network's size must pass there
too. ``dpc-jax correct`` with raw inputs and the live correction take the same default
(:func:`judge_rule`) and check a given size the same way (:func:`judge_size_problem`). Pure Python: the
command line decides it before JAX starts.
"""

from __future__ import annotations

# The size a stereo_dpc run smaller than it is judged at by default (the papers' input size): the
# photometric loss at 64x96 resolves rotations too coarsely to tell a helpful correction from a harmful
# one (docs/method.md §8; experiments/protocols/configs/kitti_raw_excerpt.py).
JUDGE_SIZE = (240, 376)


def judge_rule(method: str, size: tuple[int, int], source: tuple[int, int]) -> tuple[int, int] | None:
    """The default judge of a ``method`` run of image ``size`` on ``source`` images (``correct`` and the
    live correction): :data:`JUDGE_SIZE`, no larger than the source, when that is larger than ``size``
    and the run is ``stereo_dpc``; else None."""
    if method != "stereo_dpc" or not smaller_than_judge(size):
        return None
    judge = (min(JUDGE_SIZE[0], source[0]), min(JUDGE_SIZE[1], source[1]))
    return judge if smaller_than(size, judge) else None


def judge_size_problem(
    judge: tuple[int, int], run_size: tuple[int, int], source: tuple[int, int]
) -> str | None:
    """Why ``--judge-size`` cannot judge a run of ``run_size`` on ``source`` images (``(H, W)`` px), or
    None."""
    (jh, jw), (sh, sw), (rh, rw) = judge, source, run_size
    if jh > sh or jw > sw:
        return (f"--judge-size {jh}x{jw}: larger than the source images ({sh}x{sw}); a judge upsampled from "
                f"smaller images sees nothing they do not: give at most {sh}x{sw}")
    if jh < rh or jw < rw:
        return (f"--judge-size {jh}x{jw}: smaller than the run's images ({rh}x{rw}); a judge measures Δ on "
                "more pixels than the network saw, not fewer")
    return None


def smaller_than(size: tuple[int, int], other: tuple[int, int]) -> bool:
    """Whether ``size`` is smaller than ``other`` (and no larger in either dimension)."""
    return tuple(size) != tuple(other) and size[0] <= other[0] and size[1] <= other[1]


def smaller_than_judge(size: tuple[int, int]) -> bool:
    """Whether an image ``size`` is smaller than :data:`JUDGE_SIZE` (and no larger in either dimension)."""
    return smaller_than(size, JUDGE_SIZE)
