"""Stereo VO: geometry pieces against closed forms, the whole loop on an exactly rendered scene with
known motion, the constant-velocity fallback, bad input, and (slow) the real KITTI excerpt
against libviso2-s."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import DATA

from dpc_jax.data.frames import ImageFiles
from dpc_jax.data.kitti import StereoSequence, open_raw
from dpc_jax.vo import StereoVO, VOConfig, VOStatus, run_vo, run_vo_frames
from dpc_jax.vo.features import detect_bucketed
from dpc_jax.vo.motion import apply_offset, camera_pixels, estimate_motion, refine_pose
from dpc_jax.vo.odometry import per_frame_table
from dpc_jax.vo.stereo import triangulate

HEIGHT, WIDTH = 256, 832
K = np.array([[480.0, 0.0, 415.5], [0.0, 480.0, 127.5], [0.0, 0.0, 1.0]])
BASELINE = 0.54
CONFIG = VOConfig(bucket_size=(40, 40), per_bucket=4)


def _rot(axis: int, angle: float) -> np.ndarray:
    v = np.zeros(3)
    v[axis] = angle
    return cv2.Rodrigues(v)[0]


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# --- an exactly rendered textured corridor (ground, two walls, an end wall) ---------------------

_PLANES = (  # (axis, value, the two world axes that index the texture, texture offset)
    (1, 1.6, (0, 2), 0.0),
    (0, -5.0, (2, 1), 137.0),
    (0, 5.0, (2, 1), 311.0),
    (2, 70.0, (0, 1), 523.0),
)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.random((512, 512)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return np.ascontiguousarray(tex * 230 + 10, np.float32)


def _render(texture: np.ndarray, T_w_c: np.ndarray, camera_x: float = 0.0) -> np.ndarray:
    """Grey uint8 image of the corridor seen by the camera at ``T_w_c`` shifted by ``camera_x`` m."""
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays = rays_c @ T_w_c[:3, :3].T
    origin = T_w_c[:3, 3] + T_w_c[:3, :3] @ np.array([camera_x, 0.0, 0.0])
    best = np.full(u.shape, np.inf)
    tex_uv = np.zeros((*u.shape, 2), np.float32)
    texels_per_metre = 24.0
    for axis, value, (a, b), shift in _PLANES:
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (value - origin[axis]) / rays[..., axis]
        hit = (s > 0) & (s < best)
        point = origin + s[..., None] * rays
        best = np.where(hit, s, best)
        tex_uv[hit, 0] = point[hit, a] * texels_per_metre + shift
        tex_uv[hit, 1] = point[hit, b] * texels_per_metre + shift
    image = cv2.remap(texture, tex_uv[..., 0], tex_uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    image[~np.isfinite(best)] = 128.0
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def _trajectory(n: int) -> np.ndarray:
    """Camera-to-world poses: forward ~0.8 m per frame with a slow yaw and a little pitch."""
    poses = [np.eye(4)]
    step = _pose(_rot(1, 0.01) @ _rot(0, 0.003), np.array([0.05, 0.01, 0.8]))
    for _ in range(n - 1):
        poses.append(poses[-1] @ step)
    return np.stack(poses)


@pytest.fixture(scope="module")
def scene(texture: np.ndarray) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    poses = _trajectory(6)
    frames = [(_render(texture, T), _render(texture, T, BASELINE)) for T in poses]
    return poses, frames


def _relative_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) of ``inv(estimate) truth`` per pair."""
    error = np.linalg.inv(estimate) @ truth
    angles = np.array([np.degrees(np.linalg.norm(cv2.Rodrigues(e[:3, :3])[0])) for e in error])
    return np.linalg.norm(error[:, :3, 3], axis=1), angles


# --- pieces ------------------------------------------------------------------------------------


def test_triangulate_inverts_projection() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform([-5, -2, 3], [5, 2, 60], size=(50, 3))
    left, _ = camera_pixels(np.eye(4), points, K)
    right, _ = camera_pixels(np.eye(4), points, K, BASELINE)
    np.testing.assert_allclose(left[:, 1], right[:, 1], atol=1e-9)
    np.testing.assert_allclose(triangulate(left, left[:, 0] - right[:, 0], K, BASELINE), points, rtol=1e-9)


def test_apply_offset_equals_triangulating_with_the_larger_offset() -> None:
    rng = np.random.default_rng(2)
    left = rng.uniform([0, 0], [WIDTH, HEIGHT], size=(20, 2))
    disparity = rng.uniform(2, 60, size=20)
    right = np.stack([left[:, 0] - disparity, left[:, 1]], 1)
    points, shifted = apply_offset(triangulate(left, disparity + 0.4, K, BASELINE), right, 0.7, K, BASELINE)
    np.testing.assert_allclose(points, triangulate(left, disparity + 1.1, K, BASELINE), rtol=1e-12)
    np.testing.assert_allclose(shifted[:, 0], right[:, 0] - 0.7)


def _correspondences(
    T: np.ndarray, n: int, seed: int, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points triangulated in frame k from disparities measured ``offset`` px too small, and their
    exact left/right pixels in frame k+1 (right ones shifted like every measured right pixel)."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform([-8, -3, 4], [8, 2, 50], size=(n, 3))
    left_k, _ = camera_pixels(np.eye(4), truth, K)
    right_k, _ = camera_pixels(np.eye(4), truth, K, BASELINE)
    points = triangulate(left_k, left_k[:, 0] - right_k[:, 0] - offset, K, BASELINE)
    left, _ = camera_pixels(T, truth, K)
    right, _ = camera_pixels(T, truth, K, BASELINE)
    right[:, 0] += offset
    return points, left, right, np.ones(n, bool)


def test_refine_pose_converges_to_the_true_motion() -> None:
    T_true = _pose(_rot(1, 0.02) @ _rot(2, -0.01), np.array([0.1, -0.02, -1.2]))
    points, left, right, valid = _correspondences(T_true, 80, 3)
    start = _pose(_rot(0, 0.01), np.array([0.0, 0.0, -1.0])) @ T_true
    T, increment, information = refine_pose(start, points, left, right, valid, K, BASELINE, np.ones(80), 20)
    np.testing.assert_allclose(T, T_true, atol=1e-9)
    assert increment == 0.0 and information == 0.0


def test_refine_pose_recovers_a_disparity_offset() -> None:
    T_true = _pose(_rot(1, 0.02), np.array([0.05, 0.0, -1.3]))
    points, left, right, valid = _correspondences(T_true, 120, 4, offset=1.2)
    # Without the offset the translation is biased (far points look farther away) ...
    T_fixed, _, _ = refine_pose(T_true, points, left, right, valid, K, BASELINE, np.ones(120), 20)
    assert abs(np.linalg.norm(T_fixed[:3, 3]) - 1.3) > 0.02
    # ... estimating it jointly (no prior) recovers both exactly.
    T, increment, information = refine_pose(
        T_true, points, left, right, valid, K, BASELINE, np.ones(120), 30, offset_prior=0.0
    )
    assert increment == pytest.approx(1.2, abs=1e-6)
    assert information > 0
    np.testing.assert_allclose(T, T_true, atol=1e-7)


def test_estimate_motion_rejects_outliers() -> None:
    T_true = _pose(_rot(1, -0.015), np.array([-0.05, 0.01, -0.9]))
    points, left, right, valid = _correspondences(T_true, 150, 5)
    rng = np.random.default_rng(6)
    bad = rng.choice(150, 40, replace=False)
    left[bad] += rng.uniform(5, 30, size=(40, 2)) * rng.choice([-1, 1], size=(40, 2))
    motion = estimate_motion(
        points, left, right, valid, K, BASELINE, ransac_iterations=200, ransac_threshold=2.0,
        inlier_threshold=1.0, min_inliers=20, refine_iterations=10, reweight=True,
    )
    assert motion.success
    expected = np.ones(150, bool)
    expected[bad] = False
    np.testing.assert_array_equal(motion.inliers, expected)
    np.testing.assert_allclose(motion.T, T_true, atol=1e-8)


def test_estimate_motion_fails_cleanly_with_too_few_points() -> None:
    points, left, right, valid = _correspondences(np.eye(4), 8, 7)
    motion = estimate_motion(
        points, left, right, valid, K, BASELINE, ransac_iterations=50, ransac_threshold=2.0,
        inlier_threshold=1.0, min_inliers=20, refine_iterations=5, reweight=False,
    )
    assert not motion.success and not motion.inliers.any()
    np.testing.assert_array_equal(motion.T, np.eye(4))


def test_detect_bucketed_respects_quota_and_spacing(texture: np.ndarray) -> None:
    image = _render(texture, np.eye(4))
    existing = np.array([[30.0, 10.0], [31.0, 28.0], [200.0, 100.0]], np.float32)
    new = detect_bucketed(
        image, existing, bucket_size=(52, 32), per_bucket=3, min_distance=8, threshold=8, margin=6
    )
    assert len(new) > 50
    per_row = -(-WIDTH // 52)
    buckets = (new[:, 1] // 32).astype(int) * per_row + (new[:, 0] // 52).astype(int)
    counts = np.bincount(buckets)
    assert counts.max() <= 3 and counts[0] <= 1  # bucket 0 already holds two points
    cells = (new // 8).astype(int)
    assert len(np.unique(cells, axis=0)) == len(new)
    near = np.abs(cells[:, None, :] - (existing // 8).astype(int)[None]).max(-1) <= 1
    assert not near.any()
    assert (new >= 6).all() and (new[:, 0] < WIDTH - 6).all() and (new[:, 1] < HEIGHT - 6).all()


# --- the loop on a rendered sequence -----------------------------------------------------------


def test_vo_recovers_known_motion(scene: tuple[np.ndarray, list]) -> None:
    poses, frames = scene
    result = run_vo_frames(frames, K, BASELINE, CONFIG, first_pose=poses[0])
    truth = np.linalg.inv(poses[1:]) @ poses[:-1]
    trans, rot = _relative_errors(result.relative, truth)
    assert (result.status == VOStatus.OK).all()
    assert (result.inliers >= 50).all()
    assert trans.max() < 0.008  # 1 % of the 0.8 m step
    assert rot.max() < 0.03
    # No disparity offset in an exact rendering: the self-calibration must stay near zero.
    assert np.abs(result.disparity_offset).max() < 0.1
    np.testing.assert_allclose(result.poses[0], poses[0])
    composed = result.poses[:-1] @ np.linalg.inv(result.relative)
    np.testing.assert_allclose(result.poses[1:], composed, atol=1e-12)
    assert result.times.shape == (5,) and (result.times > 0).all()
    table = per_frame_table(result).splitlines()
    assert table[0] == "frame,inliers,status,disparity_offset_px,time_s" and len(table) == 6
    assert table[1].startswith(f"1,{result.inliers[0]},ok,")


def test_constant_velocity_fallback_on_a_black_frame(scene: tuple[np.ndarray, list]) -> None:
    poses, frames = scene
    black = np.zeros((HEIGHT, WIDTH), np.uint8)
    broken = [*frames[:3], (black, black), *frames[4:]]
    result = run_vo_frames(broken, K, BASELINE, CONFIG)
    # Pairs (2,3) and (3,4) touch the black frame; both reuse the motion of pair (1,2).
    expected = [VOStatus.OK, VOStatus.OK, VOStatus.CONSTANT_VELOCITY, VOStatus.CONSTANT_VELOCITY, VOStatus.OK]
    np.testing.assert_array_equal(result.status, expected)
    np.testing.assert_array_equal(result.inliers[2:4], [0, 0])
    np.testing.assert_array_equal(result.relative[2], result.relative[1])
    np.testing.assert_array_equal(result.relative[3], result.relative[1])
    truth = np.linalg.inv(poses[1:]) @ poses[:-1]
    trans, rot = _relative_errors(result.relative, truth)
    # Constant motion in this scene: the fallback is right, and tracking resumes after it.
    assert trans.max() < 0.01 and rot.max() < 0.03


def test_first_pair_failure_falls_back_to_identity(scene: tuple[np.ndarray, list]) -> None:
    _, frames = scene
    black = np.zeros((HEIGHT, WIDTH), np.uint8)
    result = run_vo_frames([(black, black), *frames[:2]], K, BASELINE, CONFIG)
    assert result.status[0] == VOStatus.CONSTANT_VELOCITY
    np.testing.assert_array_equal(result.relative[0], np.eye(4))
    assert result.status[1] == VOStatus.OK


# --- bad input ---------------------------------------------------------------------------------


def test_rejects_bad_images_and_calibration() -> None:
    grey = np.zeros((HEIGHT, WIDTH), np.uint8)
    with pytest.raises(ValueError, match="grey uint8"):
        StereoVO(K, BASELINE).process(np.zeros((HEIGHT, WIDTH, 3), np.uint8), grey)
    with pytest.raises(ValueError, match="differ in size"):
        StereoVO(K, BASELINE).process(grey, np.zeros((HEIGHT, 10), np.uint8))
    with pytest.raises(ValueError, match="baseline"):
        StereoVO(K, -0.5)
    with pytest.raises(ValueError, match="intrinsic"):
        StereoVO(np.eye(2), BASELINE)
    with pytest.raises(ValueError, match="at least two frames"):
        run_vo_frames([(np.zeros((HEIGHT, WIDTH), np.uint8),) * 2], K, BASELINE)


def _sequence(tmp_path: Path, frames: list, n_right: int | None = None) -> StereoSequence:
    left, right = [], []
    for i, (a, b) in enumerate(frames):
        left.append(tmp_path / f"l{i}.png")
        right.append(tmp_path / f"r{i}.png")
        cv2.imwrite(str(left[-1]), a)
        cv2.imwrite(str(right[-1]), b)
    n = len(frames)
    return StereoSequence(
        name="synthetic", images=ImageFiles(tuple(left), tuple(right[:n_right])), K=K,
        baseline=BASELINE, image_size=(HEIGHT, WIDTH), times=np.arange(n, dtype=float),
    )


def test_run_vo_errors_name_the_files(tmp_path: Path, scene: tuple[np.ndarray, list]) -> None:
    _, frames = scene
    with pytest.raises(ValueError, match=r"3 left images .* but 2 right images"):
        _sequence(tmp_path, frames[:3], n_right=2)
    sequence = _sequence(tmp_path, frames[:3])
    sequence.images.right_paths[1].write_bytes(sequence.images.right_paths[1].read_bytes()[:100])
    with pytest.raises(ValueError, match=r"r1\.png"):
        run_vo(sequence)
    (tmp_path / "missing").mkdir()
    sequence = _sequence(tmp_path / "missing", frames[:3])
    sequence.images.left_paths[2].unlink()
    with pytest.raises(FileNotFoundError, match=r"l2\.png"):
        run_vo(sequence)


def test_run_vo_reads_a_sequence(tmp_path: Path, scene: tuple[np.ndarray, list]) -> None:
    poses, frames = scene
    from_files = run_vo(_sequence(tmp_path, frames[:4]), CONFIG, first_pose=poses[0])
    in_memory = run_vo_frames(frames[:4], K, BASELINE, CONFIG, first_pose=poses[0])
    np.testing.assert_array_equal(from_files.poses, in_memory.poses)


# --- the real excerpt --------------------------------------------------------------------------


@pytest.mark.slow
def test_real_excerpt_within_125_percent_of_libviso2() -> None:
    from dpc_jax.data.poses_io import read_mat
    from dpc_jax.eval.metrics import m_ate

    root = DATA / "kitti-raw"
    mat = root / "libviso2" / "stereo_2011_09_26_drive_0001.mat"
    gt, libviso2 = read_mat(mat)
    sequence = open_raw(root, "2011_09_26", "0001", poses=mat)
    result = run_vo(sequence, VOConfig(), first_pose=gt[0])
    assert (result.status == VOStatus.OK).all()

    def errors(est: np.ndarray) -> tuple[float, float]:
        est = gt[0] @ np.linalg.inv(est[0]) @ est
        return float(m_ate(gt, est)[0]), float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))

    ours, theirs = errors(result.poses), errors(libviso2)
    assert ours[0] <= 1.25 * theirs[0], (ours, theirs)
    assert ours[1] <= 1.25 * theirs[1], (ours, theirs)


def _odometry_layout(root: Path, frames: list, poses: np.ndarray) -> None:
    seq = root / "sequences" / "00"
    for cam in ("image_2", "image_3"):
        (seq / cam).mkdir(parents=True)
    for i, (left, right) in enumerate(frames):
        cv2.imwrite(str(seq / "image_2" / f"{i:06d}.png"), left)
        cv2.imwrite(str(seq / "image_3" / f"{i:06d}.png"), right)
    P = np.hstack([K, np.zeros((3, 1))])
    P_right = P.copy()
    P_right[0, 3] = -K[0, 0] * BASELINE
    rows = [P, P, P, P_right]
    calib = "".join(f"P{i}: " + " ".join(map(str, m.ravel())) + "\n" for i, m in enumerate(rows))
    (seq / "calib.txt").write_text(calib)
    (seq / "times.txt").write_text("".join(f"{0.1 * i}\n" for i in range(len(frames))))
    (root / "poses").mkdir()
    (root / "poses" / "00.txt").write_text("".join(" ".join(map(str, T[:3].ravel())) + "\n" for T in poses))


def test_cli_writes_trajectory_and_csv(
    tmp_path: Path, scene: tuple[np.ndarray, list], capsys: pytest.CaptureFixture[str]
) -> None:
    from dpc_jax.cli import main
    from dpc_jax.data.poses_io import read_kitti_poses

    poses, frames = scene
    _odometry_layout(tmp_path / "kitti", frames[:4], poses[:4])
    out = tmp_path / "out" / "00.txt"
    code = main(["vo", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00", "--out", str(out),
                 "--start", "gt", "--no-progress"])
    assert code == 0
    written = read_kitti_poses(out)
    expected = run_vo_frames(frames[:4], K, BASELINE, VOConfig(), first_pose=poses[0]).poses
    np.testing.assert_allclose(written, expected, atol=1e-12)
    lines = out.with_suffix(".csv").read_text().splitlines()
    assert len(lines) == 4 and lines[0].startswith("frame,inliers,status")
    assert "m-ATE" in capsys.readouterr().out
    root = str(tmp_path / "kitti")
    assert main(["vo", "--kitti-odometry", root, "--out", str(out)]) == 2
    assert main(["vo", "--kitti-odometry", root, "--sequence", "07", "--out", str(out)]) == 1
    assert "07" in capsys.readouterr().err


def test_cli_warns_when_the_vo_falls_back_too_often(
    tmp_path: Path, scene: tuple[np.ndarray, list], capsys: pytest.CaptureFixture[str]
) -> None:
    """Two featureless pairs of five: 40 % constant-velocity fallbacks; a warning on stderr and in JSON."""
    import json

    from dpc_jax.cli import main

    poses, frames = scene
    blank = np.full_like(frames[0][0], 128)
    broken = [*frames[:3], (blank, blank), (blank, blank), frames[5]]
    _odometry_layout(tmp_path / "kitti", broken, poses[:6])
    out = tmp_path / "00.txt"
    assert main(["vo", "--kitti-odometry", str(tmp_path / "kitti"), "--sequence", "00", "--out", str(out),
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "warning: 00:" in err and "fell back to constant velocity, more than 5 %" in err
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["pairs"] == 5 and record["fallbacks"] >= 2 and record["fallback_share"] >= 0.4
    assert "extrapolated" in record["warning"]
    statuses = [line.split(",")[2] for line in out.with_suffix(".csv").read_text().splitlines()[1:]]
    assert statuses.count("constant_velocity") == record["fallbacks"]
    # A clean run: no warning.
    _odometry_layout(tmp_path / "clean", frames[:4], poses[:4])
    assert main(["vo", "--kitti-odometry", str(tmp_path / "clean"), "--sequence", "00", "--out",
                 str(tmp_path / "clean.txt"), "--no-progress"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert json.loads((tmp_path / "clean.json").read_text())["warning"] is None


def test_vo_prior_file_is_reused_until_its_inputs_change(
    tmp_path: Path, scene: tuple[np.ndarray, list]
) -> None:
    import json

    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.data.poses_io import read_kitti_poses
    from dpc_jax.vo.prior import write_vo_prior

    poses, frames = scene
    _odometry_layout(tmp_path / "kitti", frames[:4], poses[:4])
    sequence = open_odometry(tmp_path / "kitti", "00")
    out = tmp_path / "priors" / "00.txt"
    first = write_vo_prior(sequence, out, first_pose=poses[0])
    expected = run_vo_frames(frames[:4], K, BASELINE, VOConfig(), first_pose=poses[0])
    np.testing.assert_allclose(read_kitti_poses(out), expected.poses, atol=1e-12)
    assert first["pairs"] == 3 and first["path"] == str(out)
    assert json.loads(out.with_suffix(".json").read_text())["summary"]["fallbacks"] == first["fallbacks"]
    stamp = out.stat().st_mtime_ns
    assert write_vo_prior(sequence, out, first_pose=poses[0]) == first and out.stat().st_mtime_ns == stamp
    # Another VO configuration, or other images, run the VO again.
    write_vo_prior(sequence, out, VOConfig(estimate_offset=False), first_pose=poses[0])
    assert out.stat().st_mtime_ns != stamp
    stamp = out.stat().st_mtime_ns
    image = sequence.images.left_paths[2]
    cv2.imwrite(str(image), cv2.flip(cv2.imread(str(image)), 1))
    write_vo_prior(sequence, out, VOConfig(estimate_offset=False), first_pose=poses[0])
    assert out.stat().st_mtime_ns != stamp
    # The trajectory file edited beside its record: run again, not taken for what the record describes.
    made = out.read_bytes()
    out.write_text(out.read_text().replace("0", "1", 1))
    write_vo_prior(sequence, out, VOConfig(estimate_offset=False), first_pose=poses[0])
    assert out.read_bytes() == made
