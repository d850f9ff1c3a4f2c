"""The judge's size: where the acceptance test is measured besides the network's own size.

A judge is the same frames prepared at a larger size, with StereoSGBM depth and no network
(``dpc_jax.correction.measure.judge_measurement``); what passes at the network's size must pass there
too. :func:`judge_policy` decides a command's judge from the user's options (``correct``, ``vo
--correct`` and ``live`` alike): the default (:func:`judge_rule`), the check of a given size
(:func:`judge_size_problem`) and the line saying where the test was measured;
:func:`judge_frames_problem` checks a judge given as a cache. Python and numpy: the command line
decides it before JAX starts.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dpc_jax.data.sequence_cache import SequenceCache

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


@dataclass(frozen=True)
class JudgeRequest:
    """What the user asked of the judge: ``size`` (``--judge-size``, ``(H, W)`` px; None: not given),
    ``cache`` (``--judge CACHE``: the same frames already prepared at a larger size; None: not given),
    ``off`` (``--no-judge``) and ``force`` (``--force``: a forced correction is not judged by default)."""

    size: tuple[int, int] | None = None
    cache: str | os.PathLike[str] | None = None
    off: bool = False
    force: bool = False


@dataclass(frozen=True)
class Judge:
    """The judge a command uses (:func:`judge_policy`): ``size``, ``(H, W)`` px the frames are also
    prepared at to measure the acceptance test there (None: none is prepared); ``problem``, the one
    line saying why the request cannot be met (None: it can); ``note``, one line saying where the test
    was measured when that is not the obvious (None: nothing to say)."""

    size: tuple[int, int] | None = None
    problem: str | None = None
    note: str | None = None


def judge_policy(
    method: str, run_size: tuple[int, int], source: tuple[int, int] | None, request: JudgeRequest,
    run_label: str,
) -> Judge:
    """The judge of a ``method`` run of images ``run_size`` on ``source`` images (``(H, W)`` px; None:
    the frames of a prepared cache at the run's size, which holds no larger ones) as ``request`` asks:
    ``correct``, ``vo --correct`` and ``live`` decide it alike. ``run_label`` names the run in a
    problem (e.g. ``the run runs/kitti``).

    A judge measures Δ with stereo depth, so only a ``stereo_dpc`` run takes one. A given size is
    checked (:func:`judge_size_problem`) and used; otherwise ``off`` and ``force`` mean none, and raw
    inputs get :func:`judge_rule`'s default. The note says so when the default judge is used, when the
    source images are too small for one, and when a cache is corrected without ``--judge CACHE``.
    """
    (h, w), full = run_size, f"{JUDGE_SIZE[0]}x{JUDGE_SIZE[1]}"
    given = (f"--judge-size {request.size[0]}x{request.size[1]}" if request.size is not None
             else f"--judge {request.cache}" if request.cache is not None else None)
    stereo = method == "stereo_dpc"
    if given is not None and not stereo:
        return Judge(problem=f"{given}: a judge measures Δ with stereo depth (stereo_dpc); {run_label} is "
                     f"{method}, which has no stereo pair")
    if request.size is not None:
        if source is None:
            raise ValueError("a judge size needs the source images' size")
        return Judge(request.size, judge_size_problem(request.size, run_size, source))
    if request.cache is not None or request.off or request.force or not stereo:
        return Judge()
    if source is None:
        if not smaller_than_judge(run_size):
            return Judge()
        return Judge(note=f"note: the acceptance test was measured at the cache's {h}x{w} only (a cache has "
                     f"no full-size images to judge at); to judge at {full}, prepare the same frames with "
                     f"`dpc-jax prepare ... --size {full}` and pass that cache as --judge CACHE (or correct "
                     "from the raw inputs, judged there by default)")
    size = judge_rule(method, run_size, source)
    if size is not None:
        jh, jw = size
        smaller = ("" if size == JUDGE_SIZE
                   else f", the largest the {source[0]}x{source[1]} source images allow of {full}")
        return Judge(size, note=f"acceptance test: measured at {jh}x{jw} (the default judge of a stereo run "
                     f"on raw inputs{smaller}; --no-judge: at the run's {h}x{w} only)")
    if smaller_than_judge(run_size) and not smaller_than(run_size, source):
        return Judge(note=f"note: the acceptance test was measured at the run's {h}x{w} only: the source "
                     f"images ({source[0]}x{source[1]}) are no larger, and a judge is not upsampled")
    return Judge()


def judge_frames_problem(judge: SequenceCache, cache: SequenceCache, judge_label: str, cache_label: str
                         ) -> str | None:
    """Why the cache ``judge`` cannot judge the corrections of ``cache`` (named ``judge_label`` and
    ``cache_label`` in the line), or None: it must hold the same frames of the same sequence, at least
    as large as ``cache``'s."""
    same = judge.manifest.get("sequence") == cache.manifest.get("sequence")
    if not same or not np.array_equal(np.asarray(judge.indices), np.asarray(cache.indices)):
        return (f"{judge_label}: holds frames other than those of {cache_label}; a judge must be the same "
                "frames prepared at another size")
    (jh, jw), (ch, cw) = judge.image_size, cache.image_size
    if jh < ch or jw < cw:
        return (f"{judge_label}: images are {jh}x{jw}, smaller than those of {cache_label} ({ch}x{cw}); a "
                "judge measures Δ on more pixels than the network saw, not fewer")
    return None


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
