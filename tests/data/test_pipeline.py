"""Input pipeline: pair sampling, priors of augmented pairs, shuffling, padding, prefetch, splits."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from conftest import DATA
from support import write_odometry

from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.kitti import open_odometry, open_raw
from dpc_jax.data.pipeline import (
    TrainLoader,
    iterate_sequence,
    leave_one_out,
    prefetch,
)
from dpc_jax.data.sequence_cache import load_cache

RAW = DATA / "kitti-raw"
STEREO_MAT = RAW / "libviso2" / "stereo_2011_09_26_drive_0001.mat"
N = 8
SIZE = (30, 47)


@pytest.fixture(scope="module")
def caches(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The excerpt's first 8 frames (with GT, all flows) and a fixture without GT (forward flow)."""
    out = tmp_path_factory.mktemp("caches")
    excerpt = prepare_sequence(
        open_raw(RAW, "2011_09_26", 1), STEREO_MAT, out, frames=(0, N), size=SIZE,
        flow_augment=True, progress=False,
    )
    root = tmp_path_factory.mktemp("kitti")
    written = write_odometry(root, name="04", n=5, size=SIZE)
    (root / "poses" / "04.txt").unlink()
    fixture = prepare_sequence(
        open_odometry(root, "04"), written["poses"], out, flow=True, progress=False, size=SIZE
    )
    return excerpt, fixture


def xi_reference(transform: np.ndarray) -> np.ndarray:
    log = np.real(scipy.linalg.logm(transform))
    return np.array([log[0, 3], log[1, 3], log[2, 3], log[2, 1], log[0, 2], log[1, 0]])


def frame_of(frames: np.ndarray, image: np.ndarray) -> int:
    [match] = [k for k in range(frames.shape[0]) if np.array_equal(frames[k], image)]
    return match


def test_training_batches_match_the_cache(caches: tuple[Path, Path]) -> None:
    excerpt, _ = caches
    cache = load_cache(excerpt)
    loader = TrainLoader([excerpt], batch_size=4, seed=3, reverse=True)
    # forward 7 + skip 6, and as many reversed: 26 samples, 6 full batches, 2 dropped.
    assert loader.num_samples == 26 and len(loader) == 6
    kinds = {1: "forward", 2: "skip", -1: "reverse", -2: "skip_reverse"}
    seen = []
    for batch in loader.epoch(0):
        assert batch.left.shape == batch.right.shape == (4, 2, *SIZE, 3) and batch.left.dtype == np.uint8
        assert batch.flow.shape == (4, 2, *SIZE, 2) and batch.flow.dtype == np.float32
        assert batch.xi_vo.dtype == batch.xi_gt.dtype == batch.intrinsics.dtype == np.float32
        np.testing.assert_array_equal(batch.weight, 1.0)
        for n in range(4):
            i, j = frame_of(cache.left, batch.left[n, 0]), frame_of(cache.left, batch.left[n, 1])
            seen.append((i, j))
            np.testing.assert_array_equal(batch.right[n], cache.right[[i, j]])
            np.testing.assert_array_equal(batch.flow[n], cache.flows[kinds[j - i]][min(i, j)])
            rel_vo = np.linalg.inv(cache.prior[j]) @ cache.prior[i]
            rel_gt = np.linalg.inv(cache.gt[j]) @ cache.gt[i]
            np.testing.assert_allclose(batch.xi_vo[n], xi_reference(rel_vo), atol=2e-6)
            np.testing.assert_allclose(batch.xi_gt[n], xi_reference(rel_gt), atol=2e-6)
            np.testing.assert_allclose(batch.intrinsics[n], cache.K, rtol=1e-6)
            assert batch.baseline[n] == pytest.approx(cache.baseline, rel=1e-6)
    assert len(set(seen)) == 24
    allowed = {(k, k + s) for s in (1, 2) for k in range(N - s)}
    assert set(seen) <= allowed | {(j, i) for i, j in allowed}


def test_augmented_priors_compose_and_invert(caches: tuple[Path, Path]) -> None:
    excerpt, _ = caches
    cache = load_cache(excerpt)
    loader = TrainLoader([excerpt], batch_size=1, reverse=True, shuffle=False, workers=0)
    by_pair = {}
    for batch in loader.epoch(0):
        pair = (frame_of(cache.left, batch.left[0, 0]), frame_of(cache.left, batch.left[0, 1]))
        by_pair[pair] = batch.xi_vo[0].astype(np.float64)
    step = lambda k: np.linalg.inv(cache.prior[k + 1]) @ cache.prior[k]
    for k in range(N - 2):
        # The frame-skip prior is the composition of the two prior steps.
        np.testing.assert_allclose(by_pair[(k, k + 2)], xi_reference(step(k + 1) @ step(k)), atol=2e-6)
        # Reversed pairs carry the inverted prior: Log(T⁻¹) = −Log(T).
        np.testing.assert_allclose(by_pair[(k + 1, k)], -by_pair[(k, k + 1)], atol=1e-6)
        np.testing.assert_allclose(by_pair[(k + 2, k)], -by_pair[(k, k + 2)], atol=1e-6)


def test_held_out_pairs_are_kept_out_with_every_sample_touching_them(caches: tuple[Path, Path]) -> None:
    excerpt, _ = caches
    cache = load_cache(excerpt)
    held = np.array([2])
    loader = TrainLoader([excerpt], batch_size=1, reverse=True, shuffle=False, held_out=[held], workers=0)
    seen = {(frame_of(cache.left, b.left[0, 0]), frame_of(cache.left, b.left[0, 1])) for b in loader.epoch(0)}
    # Frames 2 and 3 belong to the held-out pair; a sample spanning frames i..j reaches them when
    # either lies in [i, j] (the frame-skip pair (1, 3) contains the motion 2 → 3).
    unseen = {2, 3}
    candidates = [(k, k + 1) for k in range(N - 1)] + [(k, k + 2) for k in range(N - 2)]
    kept = {(i, j) for i, j in candidates if not unseen & set(range(i, j + 1))}
    assert kept == {(0, 1), (4, 5), (5, 6), (6, 7), (4, 6), (5, 7)}
    assert seen == kept | {(j, i) for i, j in kept}
    assert loader.num_samples == 2 * len(kept)


def test_shuffling_is_deterministic_per_seed_and_epoch(caches: tuple[Path, Path]) -> None:
    excerpt, fixture = caches
    loader = TrainLoader([excerpt, fixture], batch_size=3, seed=7, workers=2)
    again = TrainLoader([excerpt, fixture], batch_size=3, seed=7, workers=0, flow=False)
    first = [b.xi_vo for b in loader.epoch(0)]
    np.testing.assert_array_equal(first, [b.xi_vo for b in again.epoch(0)])
    assert not np.array_equal(first, [b.xi_vo for b in loader.epoch(1)])
    other_seed = TrainLoader([excerpt, fixture], batch_size=3, seed=8, flow=False)
    assert not np.array_equal(first, [b.xi_vo for b in other_seed.epoch(0)])
    # 13 + 7 samples; the fixture has no ground truth, so no batch carries xi_gt, and no skip
    # flow, so no batch carries flow.
    assert loader.num_samples == 20 and len(loader) == 6
    assert all(b.xi_gt is None and b.flow is None for b in loader.epoch(0))


def test_missing_augmentation_flow_is_an_error(caches: tuple[Path, Path]) -> None:
    _, fixture = caches
    with pytest.raises(ValueError, match="no skip flow in the cache"):
        TrainLoader([fixture], batch_size=2, flow=True)
    assert next(iter(TrainLoader([fixture], batch_size=2, frame_skip=False).epoch(0))).flow is not None
    assert next(iter(TrainLoader([fixture], batch_size=2, flow=False).epoch(0))).flow is None


def test_evaluation_iterates_in_order_and_pads_with_weight_zero(caches: tuple[Path, Path]) -> None:
    excerpt, _ = caches
    cache = load_cache(excerpt)
    batches = list(iterate_sequence(excerpt, batch_size=3))
    assert len(batches) == 3  # 7 pairs
    weights = np.concatenate([b.weight for b in batches])
    np.testing.assert_array_equal(weights, [1, 1, 1, 1, 1, 1, 1, 0, 0])
    sources = [frame_of(cache.left, b.left[n, 0]) for b in batches for n in range(3)]
    assert sources == [0, 1, 2, 3, 4, 5, 6, 6, 6]
    np.testing.assert_array_equal(batches[0].flow[1], cache.flows["forward"][1])
    assert all(b.left.shape == (3, 2, *SIZE, 3) for b in batches)
    # Ground truth as a TrainLoader's: carried when the sequence has it, never with ground_truth=False
    # (what predictions take: one batch structure, so one compiled program, with or without it).
    rel_gt = np.linalg.inv(cache.gt[1]) @ cache.gt[0]
    np.testing.assert_allclose(batches[0].xi_gt[0], xi_reference(rel_gt), atol=2e-6)
    assert all(b.xi_gt is None for b in iterate_sequence(excerpt, batch_size=3, ground_truth=False))


def test_evaluation_batches_carry_the_stereo_depth_of_both_frames(caches: tuple[Path, Path]) -> None:
    excerpt, _ = caches
    cache = load_cache(excerpt)
    rng = np.random.default_rng(0)
    inverse = rng.uniform(0.01, 1.0, (N, 2, *SIZE)).astype(np.float32)  # [frame, camera, H, W]
    valid = rng.uniform(size=inverse.shape) > 0.3
    batches = list(iterate_sequence(cache, batch_size=3, stereo_depth=(inverse, valid)))
    for index, batch in enumerate(batches):
        assert batch.stereo_depth is not None
        got_inverse, got_valid = batch.stereo_depth
        assert got_inverse.shape == got_valid.shape == (3, 2, 2, *SIZE)  # [B, camera, frame, H, W]
        for n in range(3):
            k = min(3 * index + n, N - 2)  # the padding repeats the last pair
            for camera in range(2):
                for frame in range(2):
                    np.testing.assert_array_equal(got_inverse[n, camera, frame], inverse[k + frame, camera])
                    np.testing.assert_array_equal(got_valid[n, camera, frame], valid[k + frame, camera])
    assert next(iter(iterate_sequence(cache, batch_size=3))).stereo_depth is None
    with pytest.raises(ValueError, match="stereo depth must hold its 8 frames"):
        next(iter(iterate_sequence(cache, batch_size=3, stereo_depth=(inverse[:-1], valid[:-1]))))


def test_load_cache_rejects_incomplete_folder(tmp_path: Path) -> None:
    (tmp_path / ".04.tmp-x").mkdir()
    np.save(tmp_path / ".04.tmp-x" / "left.npy", np.zeros((2, 4, 4, 3), np.uint8))
    with pytest.raises(FileNotFoundError, match="not a prepared cache"):
        load_cache(tmp_path / ".04.tmp-x")


def test_prefetch_keeps_order_and_propagates_errors() -> None:
    rng = np.random.default_rng(0)
    delays = rng.uniform(0, 0.01, size=20)

    def tasks():
        for k, d in enumerate(delays):
            yield lambda k=k, d=d: (time.sleep(d), k)[1]

    assert list(prefetch(tasks(), depth=5, workers=3)) == list(range(20))

    def failing():
        yield lambda: 1
        yield lambda: 1 / 0
        yield lambda: 3

    out = []
    with pytest.raises(ZeroDivisionError):
        for value in prefetch(failing(), depth=3, workers=2):
            out.append(value)
    assert out == [1]


def test_prefetch_stops_its_threads_when_the_consumer_stops() -> None:
    started = []

    def tasks():
        for k in range(1000):
            yield lambda k=k: (started.append(k), time.sleep(0.001))[0]

    stream = prefetch(tasks(), depth=4, workers=2)
    next(stream)
    stream.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("dpc-data")]
    assert len(started) < 10


def test_leave_one_out_split() -> None:
    names = ["00", "02", "05", "06", "07"]
    split = leave_one_out(names, test="05", validation="07")
    assert split.train == ("00", "02", "06") and split.validation == "07" and split.test == "05"
    assert leave_one_out(names, test="00").train == ("02", "05", "06", "07")
    with pytest.raises(ValueError, match="'07' is the validation sequence and cannot also be in training"):
        leave_one_out(names, test="05", validation="07", train=["00", "07"])
    with pytest.raises(ValueError, match="both the validation and the test"):
        leave_one_out(names, test="05", validation="05")
    with pytest.raises(ValueError, match="'11' is not one of"):
        leave_one_out(names, test="11")
