"""Raw inputs prepared for a correction (``dpc_jax.correction.raw_inputs``): the sequence at the network's
size and the same frames at the judge's, kept or in a temporary folder removed after; the folders a
preparation would replace are checked first. The caches are read back with ``load_cache``."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from dpc_jax.correction.raw_inputs import (
    JUDGE_SUFFIX,
    TEMPORARY_PREFIX,
    cache_folders_problem,
    prepared_inputs,
)
from dpc_jax.data.kitti import open_odometry
from dpc_jax.data.sequence_cache import load_cache


def test_the_sequence_and_its_judge_are_the_same_frames_at_two_sizes(tmp_path: Path) -> None:
    from support import write_fake_odometry

    kitti = write_fake_odometry(tmp_path / "kitti", ["05"], frames=6, prior_dir=tmp_path / "priors")
    sequence, prior = open_odometry(kitti, "05"), tmp_path / "priors" / "stereo_05.mat"
    options = {"frames": (1, 6), "progress": False, "workers": 1}
    with prepared_inputs(sequence, prior, None, size=(16, 24), flow=True, judge_size=(48, 72),
                         **options) as (cache, judge):
        assert judge is not None and judge.name == "05" + JUDGE_SUFFIX and judge.parent == cache.parent
        assert cache.parent.parent == Path(tempfile.gettempdir()) and cache.parent.name.startswith(
            f"{TEMPORARY_PREFIX}{os.getpid()}-")
        small, large = load_cache(cache), load_cache(judge)
        assert (small.image_size, large.image_size) == ((16, 24), (48, 72))
        np.testing.assert_array_equal(small.indices, np.arange(1, 6))
        np.testing.assert_array_equal(large.indices, small.indices)
        assert "forward" in small.flows
    assert not cache.parent.exists()  # the temporary folder is gone with the block
    with prepared_inputs(sequence, prior, tmp_path / "kept", size=(16, 24), flow=False, judge_size=None,
                         **options) as (cache, judge):
        assert judge is None
    assert cache == tmp_path / "kept" / "05" and load_cache(cache).image_size == (16, 24)
    # Prepared there: a later run may replace it, and its judge's folder, which is not a cache, not.
    assert cache_folders_problem(tmp_path / "kept", "05", False, "--cache k") is None
    (tmp_path / "kept" / ("05" + JUDGE_SUFFIX)).mkdir()
    (tmp_path / "kept" / ("05" + JUDGE_SUFFIX) / "notes.txt").write_text("mine\n")
    problem = cache_folders_problem(tmp_path / "kept", "05", True, "--cache k")
    assert problem is not None and problem.startswith("--cache k") and "05_judge" in problem
