"""Preprocessing cache on the real excerpt (first frames) and on generated odometry fixtures."""

from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from conftest import DATA
from support import write_odometry

from dpc_jax.cli import main
from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.kitti import open_odometry, open_raw
from dpc_jax.data.sequence_cache import (
    CACHE_VERSION,
    MANIFEST,
    CacheError,
    NewerCacheError,
    flow_step,
    load_cache,
    newer_cache_problem,
    read_manifest,
    training_sequences,
)
from dpc_jax.geometry.warp import stereo_warp

RAW = DATA / "kitti-raw"
STEREO_MAT = RAW / "libviso2" / "stereo_2011_09_26_drive_0001.mat"
FRAMES = (3, 12)
SIZE = (240, 376)


@pytest.fixture(scope="module")
def excerpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Frames 3..11 of the real excerpt at 240×376 with forward flow."""
    sequence = open_raw(RAW, "2011_09_26", 1)
    out = tmp_path_factory.mktemp("cache")
    return prepare_sequence(sequence, STEREO_MAT, out, frames=FRAMES, flow=True, progress=False)


def mat(key: str) -> np.ndarray:
    return np.moveaxis(scipy.io.loadmat(str(STEREO_MAT))[key], -1, 0)


def test_excerpt_images_poses_and_intrinsics(excerpt: Path) -> None:
    cache = load_cache(excerpt)
    n = FRAMES[1] - FRAMES[0]
    assert cache.left.shape == cache.right.shape == (n, *SIZE, 3) and cache.left.dtype == np.uint8
    np.testing.assert_array_equal(cache.indices, np.arange(*FRAMES))
    seq = open_raw(RAW, "2011_09_26", 1)
    for k in (0, n - 1):
        for stored, paths in ((cache.left, seq.images.left_paths), (cache.right, seq.images.right_paths)):
            bgr = cv2.imread(str(paths[FRAMES[0] + k]))
            expected = cv2.resize(bgr, SIZE[::-1], interpolation=cv2.INTER_AREA)[..., ::-1]
            np.testing.assert_array_equal(stored[k], expected)
    np.testing.assert_allclose(cache.prior, mat("poses_est")[FRAMES[0]:FRAMES[1]], atol=1e-6)
    np.testing.assert_allclose(cache.gt, mat("poses_gt")[FRAMES[0]:FRAMES[1]], atol=1e-6)
    sx, sy = 376 / 1242, 240 / 375
    # Pixel centres at integers, as cv2.resize: c' = (c + ½) s − ½.
    cu, cv = (609.5593 + 0.5) * sx - 0.5, (172.854 + 0.5) * sy - 0.5
    np.testing.assert_allclose(cache.K, [[721.5377 * sx, 0, cu], [0, 721.5377 * sy, cv], [0, 0, 1]])
    assert cache.baseline == pytest.approx(0.5327, abs=1e-4)
    assert cache.manifest["parameters"]["size"] == list(SIZE)
    assert cache.manifest["flows"] == ["forward"]


def test_flow_is_farneback_of_the_stored_grey_frames(excerpt: Path) -> None:
    cache = load_cache(excerpt)
    assert cache.flows["forward"].shape == (len(cache) - 1, 2, *SIZE, 2)
    k = 4
    grey = lambda img: cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    expected = cv2.calcOpticalFlowFarneback(
        grey(cache.right[k]), grey(cache.right[k + 1]), None, 0.5, 3, 15, 3, 5, 1.2, 0
    )
    # Stored as int16 units of 1/64 px at this size: within half a unit of OpenCV's float flow.
    assert flow_step(SIZE) == 1 / 64
    np.testing.assert_allclose(cache.flows["forward"][k, 1], expected, atol=flow_step(SIZE) / 2 + 1e-6)
    # Driving forward: the image expands away from the focus of expansion, so flow on the
    # left third points left and on the right third points right.
    dx = cache.flows["forward"][k, 0, ..., 0]
    assert np.median(dx[:, :120]) < -0.5 and np.median(dx[:, -120:]) > 0.5


def test_augmentation_flows_pair_the_right_frames(tmp_path: Path) -> None:
    sequence = open_raw(RAW, "2011_09_26", 1)
    path = prepare_sequence(sequence, STEREO_MAT, tmp_path, frames=(0, 5), size=(48, 94),
                            flow_augment=True, progress=False)
    cache = load_cache(path)
    grey = lambda img: cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    farneback = lambda a, b: cv2.calcOpticalFlowFarneback(grey(a), grey(b), None, 0.5, 3, 15, 3, 5, 1.2, 0)
    expected = {"forward": (1, 2), "reverse": (2, 1), "skip": (1, 3), "skip_reverse": (3, 1)}
    for kind, (a, b) in expected.items():
        assert cache.flows[kind].shape[0] == 5 - abs(b - a)
        for camera, frames in enumerate((cache.left, cache.right)):
            stored = cache.flows[kind][1, camera]
            half_unit = flow_step((48, 94)) / 2
            np.testing.assert_allclose(stored, farneback(frames[a], frames[b]), atol=half_unit + 1e-6)


def test_the_cache_holds_the_stereo_sgbm_depth_of_its_stored_pairs(excerpt: Path) -> None:
    """The prepared depth is OpenCV's StereoSGBM disparity on the stored pair (grey), d / (fu·B)."""
    from dpc_jax.data.stereo_depth import MIN_DEPTH, sequence_inverse_depth

    cache = load_cache(excerpt)
    assert cache.manifest["stereo_depth"] and cache.stereo_depth is not None
    inverse, valid = cache.stereo_depth
    assert inverse.shape == valid.shape == (len(cache), 2, *SIZE)
    fu_b = cache.K[0, 0] * cache.baseline
    block = 5
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=16 * int(np.ceil(fu_b / MIN_DEPTH / 16)),
                                 blockSize=block, P1=8 * block * block, P2=32 * block * block,
                                 uniquenessRatio=5, disp12MaxDiff=1, mode=cv2.STEREO_SGBM_MODE_HH)
    grey = lambda img: cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    disparity = sgbm.compute(grey(cache.left[2]), grey(cache.right[2])).astype(np.float32) / 16
    np.testing.assert_array_equal(valid[2, 0], disparity > 0)
    np.testing.assert_allclose(inverse[2, 0], np.where(disparity > 0, disparity / fu_b, 0), rtol=1e-6)
    assert valid[:, 0].mean() > 0.5
    # The same as computing it now from the stored images, frame by frame and camera by camera.
    now = sequence_inverse_depth(np.asarray(cache.left), np.asarray(cache.right), cache.K[0, 0],
                                 cache.baseline, workers=1)
    np.testing.assert_array_equal(inverse, now[0])
    np.testing.assert_array_equal(valid, now[1])


def test_stereo_warp_with_block_matching_disparity_reconstructs_left(excerpt: Path) -> None:
    """Acceptance check: images, baseline and K of the cache agree with real stereo geometry."""
    cache = load_cache(excerpt)
    left, right = cache.left[0], cache.right[0]
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=5, P1=200, P2=800,
                                 uniquenessRatio=10, speckleWindowSize=50, speckleRange=2)
    grey = lambda img: cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    disparity = sgbm.compute(grey(left), grey(right)).astype(np.float64) / 16.0
    matched = disparity > 0.5
    assert matched.mean() > 0.5
    source = right.astype(np.float64) / 255
    recon, valid = stereo_warp(source, np.where(matched, disparity, 0.0), "right_to_left")
    use = np.asarray(valid) & matched
    target = left.astype(np.float64) / 255
    warped_error = np.abs(np.asarray(recon) - target)[use].mean()
    unwarped_error = np.abs(source - target)[use].mean()
    assert warped_error < 0.5 * unwarped_error
    # Depth of the road just in front of the car (bottom rows, centre): Z = fu·B/d, a few metres.
    fu_b = cache.K[0, 0] * cache.baseline
    road = disparity[-20:, 150:230]
    depth = fu_b / np.median(road[road > 0.5])
    assert 3.0 < depth < 12.0


def test_rerun_with_same_inputs_does_nothing(excerpt: Path) -> None:
    manifest = excerpt / "manifest.json"
    before = (manifest.stat().st_mtime_ns, (excerpt / "left.npy").stat().st_mtime_ns)
    sequence = open_raw(RAW, "2011_09_26", 1)
    again = prepare_sequence(sequence, STEREO_MAT, excerpt.parent, frames=FRAMES, flow=True, progress=False)
    assert again == excerpt
    assert (manifest.stat().st_mtime_ns, (excerpt / "left.npy").stat().st_mtime_ns) == before


def test_changed_parameters_rebuild_in_place(tmp_path: Path) -> None:
    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    prior = seq.poses
    first = prepare_sequence(seq, prior, tmp_path / "out", size=(10, 16), progress=False)
    digest = json.loads((first / "manifest.json").read_text())["input_hash"]
    second = prepare_sequence(seq, prior, tmp_path / "out", size=(12, 16), progress=False)
    assert second == first
    manifest = json.loads((second / "manifest.json").read_text())
    assert manifest["input_hash"] != digest and load_cache(second).left.shape == (5, 12, 16, 3)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["00"]  # no temporary folders left


def test_touched_image_changes_the_input_hash(tmp_path: Path) -> None:
    write_odometry(tmp_path / "kitti", n=4)
    seq = open_odometry(tmp_path / "kitti", "00")
    path = prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False)
    digest = json.loads((path / "manifest.json").read_text())["input_hash"]
    image = seq.images.left_paths[2]
    stat = image.stat()
    os.utime(image, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False)
    assert json.loads((path / "manifest.json").read_text())["input_hash"] != digest


def test_bad_input_writes_no_cache_and_keeps_the_old_one(tmp_path: Path) -> None:
    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="prior array: 4 prior poses for 5 frames"):
        prepare_sequence(seq, seq.poses[:4], out, size=(10, 16), progress=False)
    assert not (out / "00").exists()
    good = prepare_sequence(seq, seq.poses, out, size=(10, 16), progress=False)
    bad_png = seq.images.right_paths[3]
    bad_png.write_bytes(bad_png.read_bytes()[:50])
    with pytest.raises(ValueError, match=r"image_3/000003\.png: cannot decode"):
        prepare_sequence(seq, seq.poses, out, size=(12, 16), progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["00"]
    assert load_cache(good).left.shape == (5, 10, 16, 3)  # the previous cache is intact


def test_image_of_wrong_size_is_named(tmp_path: Path) -> None:
    write_odometry(tmp_path / "kitti", n=4)
    seq = open_odometry(tmp_path / "kitti", "00")
    cv2.imwrite(str(seq.images.left_paths[2]), np.zeros((21, 32, 3), np.uint8))
    with pytest.raises(ValueError, match=r"image_2/000002\.png: image is 21×32, expected 20×32"):
        prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False)
    assert not (tmp_path / "out" / "00").exists()


def test_static_frames_removed_from_images_prior_and_ground_truth(tmp_path: Path) -> None:
    # Forward positions (m); frames 2, 3, 4 are at one place. By hand (docs/method.md §6): pass 1 reads
    # pairs (0,1) 2 m, (2,3) 0 m → drop 2, (4,5) 2 m; pass 2 on [0,1,3,4,5,6] reads (0,1),
    # (3,4) 0 m → drop 3, (5,6); pass 3 on [0,1,4,5,6] drops nothing.
    z = [0.0, 2.0, 4.0, 4.0, 4.0, 6.0, 8.0]
    poses = np.tile(np.eye(4), (len(z), 1, 1))
    poses[:, 2, 3] = z
    written = write_odometry(tmp_path / "kitti", n=len(z), poses=poses)
    seq = open_odometry(tmp_path / "kitti", "00")
    gt = seq.poses.copy()
    gt[:, 0, 3] = 0.01  # a ground truth that differs from the prior: it loses the same frames
    path = prepare_sequence(
        seq, poses, tmp_path / "out", ground_truth=gt, size=(20, 32), remove_static=True, progress=False
    )
    cache = load_cache(path)
    kept = [0, 1, 4, 5, 6]
    np.testing.assert_array_equal(cache.indices, kept)
    np.testing.assert_allclose(cache.prior, poses[kept])
    np.testing.assert_allclose(cache.gt, gt[kept], atol=1e-10)
    np.testing.assert_array_equal(cache.left, written["images"][2][kept])  # size unchanged: exact
    np.testing.assert_array_equal(cache.right, written["images"][3][kept])


def test_mono_rescale_needs_ground_truth(tmp_path: Path) -> None:
    write_odometry(tmp_path / "kitti", n=4)
    (tmp_path / "kitti" / "poses" / "00.txt").unlink()
    seq = open_odometry(tmp_path / "kitti", "00")
    prior = np.tile(np.eye(4), (4, 1, 1))
    with pytest.raises(ValueError, match="mono_rescale needs ground truth"):
        prepare_sequence(seq, prior, tmp_path / "out", mono_rescale=True, progress=False)


def test_mono_rescale_applies_ground_truth_step_lengths(tmp_path: Path) -> None:
    written = write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    prior = written["poses"].copy()
    prior[:, :3, 3] *= 0.1  # a monocular estimate of a tenth of the true scale
    path = prepare_sequence(seq, prior, tmp_path / "out", mono_rescale=True, size=(10, 16), progress=False)
    stored = load_cache(path).prior
    steps = lambda t: np.linalg.norm(np.diff(t[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps(stored), steps(written["poses"]), rtol=1e-9)


def test_cli_prepares_fixture_and_reports_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    written = write_odometry(tmp_path / "kitti", n=5)
    prior = tmp_path / "prior_00.txt"
    np.savetxt(prior, written["poses"][:, :3, :].reshape(5, 12))
    args = ["prepare", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00",
            "--prior", str(tmp_path / "prior_{seq}.txt"), "--out", str(tmp_path / "out"),
            "--size", "10x16", "--flow", "--no-progress"]
    assert main(args) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "out" / "00")
    assert load_cache(tmp_path / "out" / "00").flows["forward"].shape == (4, 2, 10, 16, 2)

    np.savetxt(prior, written["poses"][:3, :3, :].reshape(3, 12))
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "prior_00.txt: 3 prior poses for 5 frames" in err and "Traceback" not in err


def test_the_cache_reader_imports_neither_jax_nor_opencv() -> None:
    # The command line loads and checks a cache before it starts JAX.
    code = ("import sys, dpc_jax.data.sequence_cache; "
            "print([m for m in ('jax', 'jaxlib', 'flax', 'cv2') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_training_sequences_default_to_every_cached_one_but_validation_and_test(tmp_path: Path) -> None:
    for name in ("00", "02", "05", "07"):
        (tmp_path / name).mkdir()
        (tmp_path / name / MANIFEST).write_text("{}")
    (tmp_path / "08").mkdir()  # no manifest: not a cache (an interrupted prepare)
    assert training_sequences(tmp_path, (), ("05",), ("07",)) == ["00", "02"]
    assert training_sequences(tmp_path, ("02",), ("05",), ()) == ["02"]
    with pytest.raises(ValueError, match=r"train_sequences \['08'\] are not prepared under"):
        training_sequences(tmp_path, ("08",), ("05",), ())
    with pytest.raises(ValueError, match="no training sequence under"):
        training_sequences(tmp_path, (), ("00", "02"), ("05", "07"))
    with pytest.raises(ValueError, match="is not a directory"):
        training_sequences(tmp_path / "missing", (), ("05",), ())


def test_a_cache_of_another_format_version_is_refused_in_one_line(tmp_path: Path) -> None:
    """A version-2 cache (no digests) is refused by the reader, which every command reads caches
    with, naming what rebuilds it; `prepare` with the same options does (the version is part of the
    input hash). A cache of a newer version is refused as such, and `prepare` leaves it alone."""
    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    path = prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False)
    manifest = json.loads((path / MANIFEST).read_text())
    older = {**manifest, "version": 2, "input_hash": "0" * 64}
    del older["arrays"]
    (path / MANIFEST).write_text(json.dumps(older))
    refusal = r"cache format version 2, this dpc_jax reads version 3; run the same `dpc-jax prepare` again"
    with pytest.raises(ValueError, match=refusal):
        load_cache(path)
    prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False)
    assert load_cache(path).manifest["version"] == 3

    (path / MANIFEST).write_text(json.dumps({**manifest, "version": 4}))
    files = {p.name: p.read_bytes() for p in path.iterdir()}
    newer = "this cache was written by a newer dpc_jax (cache format version 4; this one reads version 3"
    with pytest.raises(CacheError, match=re.escape(newer)):
        load_cache(path)
    with pytest.raises(CacheError, match=re.escape(newer)):
        prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False, force=True)
    assert {p.name: p.read_bytes() for p in path.iterdir()} == files


def test_every_user_of_a_manifest_reads_it_the_same(tmp_path: Path) -> None:
    """The manifest `prepare` writes is what the one reader, the caches' reader and `prepare`'s reuse all
    read; a damaged one is refused by the readers in the same words and rebuilt by `prepare`; a newer one
    is refused by every user in the same words and left alone."""
    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")

    def prepare(**options: bool) -> Path:
        return prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False, **options)

    path = prepare()
    written = json.loads((path / MANIFEST).read_text())
    assert read_manifest(path) == written == load_cache(path).manifest
    assert newer_cache_problem(path) is None
    inode = (path / MANIFEST).stat().st_ino
    assert prepare() == path and (path / MANIFEST).stat().st_ino == inode  # reused, not rebuilt
    for text, said in (("{", "not valid JSON"), ("[]", "expected a JSON object"),
                       (json.dumps({**written, "n_frames": "5"}), "field 'n_frames' is missing or not")):
        (path / MANIFEST).write_text(text)
        with pytest.raises(CacheError, match=said) as read:
            read_manifest(path)
        with pytest.raises(CacheError) as loaded:
            load_cache(path)
        assert str(loaded.value) == str(read.value) and newer_cache_problem(path) is None
        assert prepare() == path and read_manifest(path) == written  # rebuilt as it was
    (path / MANIFEST).write_text(json.dumps({**written, "version": CACHE_VERSION + 1}))
    with pytest.raises(NewerCacheError, match="written by a newer dpc_jax") as read:
        read_manifest(path)
    assert newer_cache_problem(path) == str(read.value)
    for user in (lambda: load_cache(path), lambda: prepare(force=True)):
        with pytest.raises(NewerCacheError) as refused:
            user()
        assert str(refused.value) == str(read.value)
    assert json.loads((path / MANIFEST).read_text())["version"] == CACHE_VERSION + 1
    (path / MANIFEST).unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(f"{path}: not a prepared cache (no {MANIFEST})")):
        read_manifest(path)
    assert newer_cache_problem(path) is None


@pytest.mark.parametrize("damage", ["truncate", "nan_prior"])
def test_prepare_rebuilds_a_damaged_cache_instead_of_reusing_it(tmp_path: Path, damage: str) -> None:
    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    path = prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False)
    good = np.asarray(load_cache(path).left).copy()
    if damage == "truncate":
        left = path / "left.npy"
        left.write_bytes(left.read_bytes()[:-100])
    else:
        prior = np.load(path / "prior.npy")
        prior[2, 0, 3] = np.nan
        np.save(path / "prior.npy", prior)
    with pytest.raises(ValueError):
        load_cache(path)
    assert prepare_sequence(seq, seq.poses, tmp_path / "out", size=(10, 16), progress=False) == path
    cache = load_cache(path)
    np.testing.assert_array_equal(cache.left, good)
    np.testing.assert_allclose(cache.prior, seq.poses)


def test_a_prior_of_the_frame_range_alone_is_that_range(tmp_path: Path) -> None:
    """`vo --frames 1:4` writes the range's 3 poses: `prepare --frames 1:4` takes them as the range's
    prior, as it takes the same frames cut from a prior of the whole sequence."""
    written = write_odometry(tmp_path / "kitti", n=6)
    seq = open_odometry(tmp_path / "kitti", "00")
    whole = written["poses"]
    from_whole = prepare_sequence(seq, whole, tmp_path / "a", frames=(1, 4), size=(10, 16), progress=False)
    from_range = prepare_sequence(seq, whole[1:4], tmp_path / "b", frames=(1, 4), size=(10, 16),
                                  progress=False)
    np.testing.assert_array_equal(load_cache(from_range).prior, load_cache(from_whole).prior)
    with pytest.raises(ValueError, match=r"2 prior poses for 6 frames; .* or one per frame of the range 1:4"):
        prepare_sequence(seq, whole[1:3], tmp_path / "c", frames=(1, 4), size=(10, 16), progress=False)


def test_array_digest_of_a_file_written_in_pieces_is_that_of_its_bytes() -> None:
    """The digests a writer records while it streams a file are hashlib's of the whole file and of its
    sample, however the bytes arrive; the sample is 64 blocks of 4 KiB from the first byte to the last."""
    import hashlib

    from dpc_jax.data.sequence_cache import SAMPLE_BLOCK, ArrayDigest, sample_ranges

    data = np.random.default_rng(0).integers(0, 256, 3_000_017, dtype=np.uint8).tobytes()
    ranges = sample_ranges(len(data))
    assert len(ranges) == 64 and ranges[0][0] == 0 and ranges[-1][1] == len(data)
    assert all(b - a == SAMPLE_BLOCK for a, b in ranges)
    assert all(b1 <= a2 for (_, b1), (a2, _) in itertools.pairwise(ranges))
    digest = ArrayDigest(len(data))
    cuts = [0, 1, 4095, 4097, 100_000, 1_500_000, 2_999_999, len(data)]
    for a, b in itertools.pairwise(cuts):
        digest.update(data[a:b])
    record = digest.record()
    assert record["bytes"] == len(data) and record["sha256"] == hashlib.sha256(data).hexdigest()
    assert record["sample_sha256"] == hashlib.sha256(b"".join(data[a:b] for a, b in ranges)).hexdigest()
    assert sample_ranges(1000) == [(0, 1000)]  # a small file is its own sample


def test_the_manifest_records_the_digest_of_every_array_it_lists(tmp_path: Path) -> None:
    import hashlib

    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    path = prepare_sequence(seq, seq.poses, tmp_path / "out", size=(20, 32), flow=True, progress=False)
    arrays = json.loads((path / MANIFEST).read_text())["arrays"]
    assert set(arrays) == {p.name for p in path.iterdir() if p.suffix == ".npy"}
    for file, record in arrays.items():
        content = (path / file).read_bytes()
        assert record["bytes"] == len(content) and record["sha256"] == hashlib.sha256(content).hexdigest()


def _changed(path: Path, file: str, change: str) -> None:
    """Change one bit, pixel or value of ``file`` in place, keeping its shape, dtype and validity."""
    array = np.load(path / file, mmap_mode="r+")
    if change == "bit":  # the sign bit of frame 3's z: a rigid pose still, 8 m → −8 m
        array[3, 2, 3:4].view(np.uint64)[...] ^= np.uint64(1 << 63)
    elif change == "pixel":
        array[2, 5, 7, 1] ^= 1
    else:
        array[1, 0, 3] += 0.25
    array.flush()


@pytest.mark.parametrize(("file", "change"),
                         [("prior.npy", "bit"), ("right.npy", "pixel"), ("gt.npy", "value")])
def test_a_cache_whose_bytes_changed_is_refused_and_rebuilt(tmp_path: Path, file: str, change: str) -> None:
    """One bit of the prior, one pixel, one ground-truth value: the readers refuse the cache naming the
    file, and `prepare` with unchanged inputs rebuilds it (a new manifest) with the bytes it had."""
    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    path = prepare_sequence(seq, seq.poses, tmp_path / "out", size=(20, 32), progress=False)
    original = (path / file).read_bytes()
    _changed(path, file, change)
    assert (path / file).read_bytes() != original
    with pytest.raises(CacheError, match=re.escape(f"{path / file}: its bytes differ from those")):
        load_cache(path)
    manifest = (path / MANIFEST).stat().st_ino
    assert prepare_sequence(seq, seq.poses, tmp_path / "out", size=(20, 32), progress=False) == path
    assert (path / MANIFEST).stat().st_ino != manifest and (path / file).read_bytes() == original


def test_opening_samples_large_files_and_verify_reads_every_byte(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Above the whole-file size an open checks 64 blocks; a byte between them is found by --verify
    (`load_cache(verify=True)`, `prepare_sequence(verify=True)`) only. The sizes are scaled down so
    that the fixture's 20×32 images are "large"."""
    import dpc_jax.data.sequence_cache as sequence_cache

    monkeypatch.setattr(sequence_cache, "FULL_CHECK_BYTES", 4096)
    monkeypatch.setattr(sequence_cache, "SAMPLE_BLOCK", 16)
    write_odometry(tmp_path / "kitti", n=5)
    seq = open_odometry(tmp_path / "kitti", "00")
    path = prepare_sequence(seq, seq.poses, tmp_path / "out", size=(20, 32), progress=False)
    size = (path / "left.npy").stat().st_size
    ranges = sequence_cache.sample_ranges(size)
    outside = next(k for k in range(128, size) if not any(a <= k < b for a, b in ranges))  # past the header
    inside = ranges[40][0] + 3
    for offset, found_on_open in ((outside, False), (inside, True)):
        raw = bytearray((path / "left.npy").read_bytes())
        raw[offset] ^= 0x10
        (path / "left.npy").write_bytes(raw)
        if found_on_open:
            with pytest.raises(CacheError, match="a sample of its bytes differs"):
                load_cache(path)
        else:
            load_cache(path)
            assert prepare_sequence(seq, seq.poses, tmp_path / "out", size=(20, 32), progress=False) == path
            assert (path / "left.npy").read_bytes() == bytes(raw)  # reused, as it was
        with pytest.raises(CacheError, match=re.escape(f"{path / 'left.npy'}: its bytes differ")):
            load_cache(path, verify=True)
        prepare_sequence(seq, seq.poses, tmp_path / "out", size=(20, 32), progress=False, verify=True)
        load_cache(path, verify=True)


def test_a_cache_is_never_upsampled(tmp_path: Path) -> None:
    write_odometry(tmp_path / "kitti", n=4)
    seq = open_odometry(tmp_path / "kitti", "00")
    for size in ((40, 32), (20, 33)):
        with pytest.raises(ValueError, match=rf"size {size[0]}x{size[1]} is larger than the source images "
                                             r"\(20x32\); a cache is never upsampled"):
            prepare_sequence(seq, seq.poses, tmp_path / "out", size=size, progress=False)
    assert not (tmp_path / "out" / "00").exists()
    assert load_cache(prepare_sequence(seq, seq.poses, tmp_path / "out", size=(20, 32),
                                       progress=False)).image_size == (20, 32)
