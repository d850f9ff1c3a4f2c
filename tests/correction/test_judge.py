"""The judge policy (``dpc_jax.correction.judge.judge_policy``): the judge ``correct``, ``vo --correct``
and ``live`` take from the user's options, checked against sizes worked out by hand."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from dpc_jax.correction.judge import Judge, JudgeRequest, judge_policy

RUN = "the run runs/r"


@pytest.mark.parametrize(("run_size", "source", "expected", "words"), [
    # KITTI's 375x1242 images: the papers' 240x376.
    ((64, 96), (375, 1242), (240, 376),
     "measured at 240x376 (the default judge of a stereo run on raw inputs; --no-judge: at the run's 64x96 "
     "only)"),
    # Images smaller than 240x376 in one dimension: as large as they allow, never upsampled.
    ((64, 96), (200, 1242), (200, 376),
     "measured at 200x376 (the default judge of a stereo run on raw inputs, the largest the 200x1242 source "
     "images allow of 240x376"),
    ((32, 48), (48, 72), (48, 72), "measured at 48x72"),
])
def test_a_small_stereo_run_on_raw_images_is_judged_by_default(
    run_size: tuple[int, int], source: tuple[int, int], expected: tuple[int, int], words: str
) -> None:
    judge = judge_policy("stereo_dpc", run_size, source, JudgeRequest(), RUN)
    assert judge.size == expected and judge.problem is None
    assert judge.note is not None and words in judge.note


def test_no_judge_where_none_can_see_more_than_the_network() -> None:
    """Source images no larger than the run's: no judge, and a note that says why; a run at 240x376 or
    larger, and a monocular run, take none and need no note."""
    limited = judge_policy("stereo_dpc", (48, 72), (48, 72), JudgeRequest(), RUN)
    assert limited.size is None and limited.problem is None
    assert limited.note == ("note: the acceptance test was measured at the run's 48x72 only: the source "
                            "images (48x72) are no larger, and a judge is not upsampled")
    assert judge_policy("stereo_dpc", (240, 376), (375, 1242), JudgeRequest(), RUN) == Judge()
    assert judge_policy("stereo_dpc", (256, 512), (375, 1242), JudgeRequest(), RUN) == Judge()
    assert judge_policy("ss_dpc_net", (64, 96), (375, 1242), JudgeRequest(), RUN) == Judge()


def test_off_and_force_turn_the_default_off_but_a_given_size_is_checked_and_kept() -> None:
    for request in (JudgeRequest(off=True), JudgeRequest(force=True)):
        assert judge_policy("stereo_dpc", (64, 96), (375, 1242), request, RUN) == Judge()
    forced = judge_policy("stereo_dpc", (64, 96), (375, 1242), JudgeRequest(size=(120, 188), force=True), RUN)
    assert forced == Judge((120, 188))


@pytest.mark.parametrize(("size", "problem"), [
    ((96, 144), "--judge-size 96x144: larger than the source images (48x72); a judge upsampled from smaller "
                "images sees nothing they do not: give at most 48x72"),
    ((24, 72), "--judge-size 24x72: smaller than the run's images (32x48); a judge measures Δ on more pixels "
               "than the network saw, not fewer"),
    ((48, 64), None),
    ((32, 48), None),  # the run's own size: allowed (the judge's depth is StereoSGBM's, not the network's)
])
def test_a_given_size_lies_between_the_runs_images_and_the_sources(
    size: tuple[int, int], problem: str | None
) -> None:
    judge = judge_policy("stereo_dpc", (32, 48), (48, 72), JudgeRequest(size=size), RUN)
    assert judge.problem == problem and judge.size == size and judge.note is None


def test_a_monocular_run_takes_no_judge() -> None:
    size = judge_policy("ss_dpc_net", (64, 96), (375, 1242), JudgeRequest(size=(240, 376)), RUN)
    assert size.problem == ("--judge-size 240x376: a judge measures Δ with stereo depth (stereo_dpc); the "
                            "run runs/r is ss_dpc_net, which has no stereo pair")
    cache = judge_policy("ss_dpc_net", (64, 96), None, JudgeRequest(cache="cache/05_big"), "--correct runs/r")
    assert cache.problem == ("--judge cache/05_big: a judge measures Δ with stereo depth (stereo_dpc); "
                             "--correct runs/r is ss_dpc_net, which has no stereo pair")


def test_a_cache_is_judged_only_by_a_judge_cache() -> None:
    """A prepared cache has no larger frames: no size to prepare; a small stereo run is told how to get a
    judge, unless one is given or the correction is forced."""
    told = judge_policy("stereo_dpc", (64, 96), None, JudgeRequest(), RUN)
    assert told.size is None and told.problem is None
    assert told.note is not None and told.note.startswith("note: the acceptance test was measured at the "
                                                          "cache's 64x96 only")
    assert "`dpc-jax prepare ... --size 240x376`" in told.note
    assert judge_policy("stereo_dpc", (64, 96), None, JudgeRequest(cache="cache/05_big"), RUN) == Judge()
    assert judge_policy("stereo_dpc", (64, 96), None, JudgeRequest(force=True), RUN) == Judge()
    assert judge_policy("stereo_dpc", (240, 376), None, JudgeRequest(), RUN) == Judge()


def test_a_judge_cache_holds_the_same_frames_at_least_as_large() -> None:
    """``judge_frames_problem`` reads what a cache records: its sequence, its frames, its size."""
    from types import SimpleNamespace

    from dpc_jax.correction.judge import judge_frames_problem

    def cache(sequence: str, indices: list[int], size: tuple[int, int]) -> Any:
        return SimpleNamespace(manifest={"sequence": sequence}, indices=np.asarray(indices), image_size=size)

    network = cache("05", [0, 2, 3], (64, 96))
    assert judge_frames_problem(cache("05", [0, 2, 3], (240, 376)), network, "j", "c") is None
    assert judge_frames_problem(cache("05", [0, 2, 3], (64, 96)), network, "j", "c") is None
    other = ("j: holds frames other than those of c; a judge must be the same frames prepared at another "
             "size")
    assert judge_frames_problem(cache("06", [0, 2, 3], (240, 376)), network, "j", "c") == other
    assert judge_frames_problem(cache("05", [0, 1, 2], (240, 376)), network, "j", "c") == other
    assert judge_frames_problem(cache("05", [0, 2, 3], (240, 90)), network, "j", "c") == (
        "j: images are 240x90, smaller than those of c (64x96); a judge measures Δ on more pixels than the "
        "network saw, not fewer")
