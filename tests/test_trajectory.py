"""Trajectory I/O, relative poses, composition and static-frame removal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import reference_metrics as ref
import scipy.io
from conftest import DATA
from scipy.spatial.transform import Rotation

from dpc_jax.data.poses_io import (
    detect_format,
    read_kitti_poses,
    read_mat,
    read_trajectory,
    read_tum,
    write_kitti_poses,
    write_tum,
)
from dpc_jax.geometry.poses import compose, invert_poses, relative_poses, remove_static_frames

LIBVISO2 = DATA / "kitti-libviso2"


def random_trajectory(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(scale=10.0, size=(n, 3))
    return poses


def test_kitti_round_trip(tmp_path: Path) -> None:
    poses = random_trajectory(20)
    path = tmp_path / "poses.txt"
    write_kitti_poses(path, poses)
    assert len(path.read_text().splitlines()) == 20
    np.testing.assert_allclose(read_kitti_poses(path), poses, atol=1e-14)
    np.testing.assert_allclose(read_trajectory(path), poses, atol=1e-14)
    assert detect_format(path) == "kitti"
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_kitti_reads_numpy_savetxt(tmp_path: Path) -> None:
    poses = random_trajectory(5, seed=1)
    path = tmp_path / "p.txt"
    np.savetxt(path, poses[:, :3, :].reshape(5, 12), fmt="%.6e")
    np.testing.assert_allclose(read_kitti_poses(path), poses, atol=1e-5)


def test_tum_round_trip_and_quaternion_convention(tmp_path: Path) -> None:
    poses = random_trajectory(30, seed=2)
    stamps = np.linspace(0.0, 2.9, 30)
    path = tmp_path / "traj.tum"
    write_tum(path, poses, stamps)
    rows = np.loadtxt(path)
    # Scalar-last Hamilton quaternion, as scipy's default (and TUM's) convention.
    expected = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    expected *= np.sign(expected[:, 3:4])
    np.testing.assert_allclose(rows[:, 4:], expected, atol=1e-12)
    np.testing.assert_allclose(rows[:, 1:4], poses[:, :3, 3], atol=1e-12)
    times, read = read_tum(path)
    np.testing.assert_allclose(times, stamps, atol=1e-15)
    np.testing.assert_allclose(read, poses, atol=1e-12)
    assert detect_format(path) == "tum"


def test_tum_rotations_near_pi_each_shepperd_branch(tmp_path: Path) -> None:
    angles = [np.pi, np.pi - 1e-9, np.pi / 2, 1e-12]
    axes = np.eye(3)
    rotations = [Rotation.from_rotvec(a * axis) for a in angles for axis in axes]
    poses = np.tile(np.eye(4), (len(rotations), 1, 1))
    poses[:, :3, :3] = np.stack([r.as_matrix() for r in rotations])
    path = tmp_path / "t.txt"
    write_tum(path, poses)
    assert detect_format(path) == "tum"
    np.testing.assert_allclose(read_trajectory(path), poses, atol=1e-12)


def test_mat_conventions(tmp_path: Path) -> None:
    gt, est = random_trajectory(10, 3), random_trajectory(10, 4)
    twv = tmp_path / "twv.mat"
    scipy.io.savemat(twv, {"poses_gt": np.moveaxis(gt, 0, -1), "poses_est": np.moveaxis(est, 0, -1),
                           "convention": "Twv"})
    g, e = read_mat(twv)
    np.testing.assert_allclose(g, gt, atol=1e-14)
    np.testing.assert_allclose(e, est, atol=1e-14)
    np.testing.assert_allclose(read_trajectory(twv), est, atol=1e-14)
    tvw = tmp_path / "tvw.mat"
    scipy.io.savemat(tvw, {"poses_gt": np.moveaxis(np.linalg.inv(gt), 0, -1),
                           "poses_est": np.moveaxis(np.linalg.inv(est), 0, -1), "convention": "Tvw"})
    g, e = read_mat(tvw)
    np.testing.assert_allclose(g, gt, atol=1e-12)
    np.testing.assert_allclose(e, est, atol=1e-12)


def test_real_mat() -> None:
    gt, est = read_mat(LIBVISO2 / "stereo_07.mat")
    raw = scipy.io.loadmat(LIBVISO2 / "stereo_07.mat")
    assert gt.shape == est.shape == (1101, 4, 4)
    np.testing.assert_allclose(gt, np.moveaxis(raw["poses_gt"], -1, 0), atol=1e-6)
    np.testing.assert_allclose(gt[0], est[0], atol=1e-12)
    np.testing.assert_allclose(ref.cumulative_distance(gt), raw["cum_dists"][0], atol=1e-6)


@pytest.mark.parametrize(
    ("line", "needle"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1", "expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 x", "not a number"),
        ("1 0 0 nan 0 1 0 0 0 0 1 0", "non-finite"),
        ("2 0 0 0 0 1 0 0 0 0 1 0", "not rigid"),
    ],
)
def test_kitti_malformed_names_file_and_line(tmp_path: Path, line: str, needle: str) -> None:
    good = "1 0 0 0 0 1 0 0 0 0 1 0"
    path = tmp_path / "bad.txt"
    path.write_text(f"{good}\n{good}\n\n{line}\n{good}\n")
    with pytest.raises(ValueError, match=needle) as info:
        read_kitti_poses(path)
    assert str(path) in str(info.value)
    assert "line 4" in str(info.value)


def test_tum_malformed(tmp_path: Path) -> None:
    path = tmp_path / "bad.tum"
    path.write_text("# header\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 0.5\n")
    with pytest.raises(ValueError, match=r"line 3: quaternion .* norm 0\.5"):
        read_tum(path)
    path.write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="line 2: expected 8 numbers"):
        read_tum(path)


def test_unknown_formats_and_keys(tmp_path: Path) -> None:
    odd = tmp_path / "odd.txt"
    odd.write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"line 1: 3 columns; expected a trajectory of 12 \(KITTI: .*\) or 8 "
                                         r"\(TUM: .*\) numbers per line, or a \.mat file$"):
        read_trajectory(odd)
    with pytest.raises(ValueError, match="unknown trajectory format 'csv'"):
        read_trajectory(odd, format="csv")
    with pytest.raises(FileNotFoundError):
        read_trajectory(tmp_path / "missing.txt")
    empty = tmp_path / "empty.txt"
    empty.write_text("\n")
    with pytest.raises(ValueError, match="empty"):
        read_trajectory(empty)
    mat = tmp_path / "keys.mat"
    scipy.io.savemat(mat, {"poses": np.zeros((4, 4, 3))})
    with pytest.raises(ValueError, match=r"no key 'poses_gt'.*found \['poses'\]"):
        read_mat(mat)
    scipy.io.savemat(mat, {"poses_gt": np.tile(np.eye(4)[..., None], 3),
                           "poses_est": np.tile(np.eye(4)[..., None], 4)})
    with pytest.raises(ValueError, match="'poses_gt' has 3 poses but 'poses_est' has 4"):
        read_mat(mat)
    scipy.io.savemat(mat, {"poses_gt": np.tile(np.eye(4)[..., None], 3),
                           "poses_est": np.tile(np.eye(4)[..., None], 3), "convention": "XYZ"})
    with pytest.raises(ValueError, match="convention"):
        read_mat(mat)
    notmat = tmp_path / "text.mat"
    notmat.write_text("hello")
    with pytest.raises(ValueError, match="not a readable MATLAB"):
        read_mat(notmat)


def test_writers_reject_bad_poses_and_write_nothing(tmp_path: Path) -> None:
    poses = random_trajectory(3)
    poses[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_kitti_poses(tmp_path / "a.txt", poses)
    with pytest.raises(ValueError, match="timestamps"):
        write_tum(tmp_path / "b.txt", random_trajectory(3), np.zeros(2))
    assert list(tmp_path.iterdir()) == []


def test_relative_poses_and_compose() -> None:
    traj = random_trajectory(50, seed=5)
    rel = relative_poses(traj)
    expected = np.stack([np.linalg.inv(traj[t + 1]) @ traj[t] for t in range(49)])
    np.testing.assert_allclose(rel, expected, atol=1e-12)
    np.testing.assert_allclose(compose(rel, traj[0]), traj, atol=1e-10)
    np.testing.assert_allclose(invert_poses(traj), np.linalg.inv(traj), atol=1e-12)
    # T_{t+1,t} maps a point of frame t into frame t+1.
    p_t = np.array([1.0, 2.0, 3.0, 1.0])
    np.testing.assert_allclose(rel[0] @ p_t, np.linalg.inv(traj[1]) @ (traj[0] @ p_t), atol=1e-12)
    assert rel.dtype == np.float64
    assert relative_poses(traj.astype(np.float32)).dtype == np.float32
    assert compose(rel.astype(np.float32), traj[0]).dtype == np.float32


def straight_trajectory(steps: np.ndarray, yaw_rates: np.ndarray) -> np.ndarray:
    """Drive along z with per-frame step lengths (m) and yaw increments (rad)."""
    rel = np.tile(np.eye(4), (len(steps), 1, 1))
    rel[:, :3, :3] = Rotation.from_rotvec(np.outer(yaw_rates, [0.0, 1.0, 0.0])).as_matrix()
    rel[:, 2, 3] = -np.asarray(steps)  # T_{t+1,t}: the point ahead comes closer
    return compose(rel, np.eye(4))


def test_remove_static_frames_matches_the_reference_loop() -> None:
    rng = np.random.default_rng(0)
    steps = rng.choice([0.0, 0.3, 1.0, 2.0], size=120)
    yaws = rng.choice([0.0, 0.001, 0.02], size=120)
    prior = straight_trajectory(steps, yaws)
    gt = random_trajectory(121)
    kept = remove_static_frames(gt, prior)
    np.testing.assert_array_equal(kept, ref.remove_static_frames(prior))
    assert 0 < kept.size < 121
    assert kept[-1] == 120
    np.testing.assert_array_equal(remove_static_frames(prior), kept)


def test_remove_static_frames_fixed_point() -> None:
    # Ten 1 m straight steps: each pass halves the even pairs until steps reach ≥ 1.5 m.
    prior = straight_trajectory(np.ones(10), np.zeros(10))
    kept = remove_static_frames(prior)
    np.testing.assert_array_equal(kept, ref.remove_static_frames(prior))
    assert (np.diff(kept) >= 2).all()
    # A pass over what is kept drops nothing.
    np.testing.assert_array_equal(remove_static_frames(prior[kept]), np.arange(kept.size))
    with pytest.raises(ValueError, match="prior has 11 poses but reference has 5"):
        remove_static_frames(prior[:5], prior)


def test_remove_static_frames_real_sequence() -> None:
    gt, est = read_mat(LIBVISO2 / "stereo_07.mat")
    np.testing.assert_array_equal(remove_static_frames(gt, est), ref.remove_static_frames(est))
