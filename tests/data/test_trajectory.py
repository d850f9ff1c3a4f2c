"""Trajectory I/O, relative poses, composition and static-frame removal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io
from conftest import DATA
from scipy.spatial.transform import Rotation

from dpc_jax._io import InputWarning
from dpc_jax.data.poses_io import (
    associate,
    detect_format,
    read_kitti_poses,
    read_mat,
    read_trajectory,
    read_tum,
    write_kitti_poses,
    write_tum,
)
from dpc_jax.eval import reference_metrics as ref
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


def _evo_association(stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float, offset_2: float
                     ) -> tuple[list[int], list[int]]:
    """evo's ``sync.associate_trajectories`` (evo.core.sync, as published): each stamp of the shorter
    trajectory with its nearest in the longer (``np.argmin``) where within ``max_diff``; ``offset_2``
    is added to the second trajectory's stamps."""
    second_longer = len(stamps_2) > len(stamps_1)
    short, long = (stamps_1, stamps_2 + offset_2) if second_longer else (stamps_2 + offset_2, stamps_1)
    short_idx, long_idx = [], []
    for i, stamp in enumerate(short):
        diffs = np.abs(long - stamp)
        j = int(np.argmin(diffs))
        if diffs[j] <= max_diff:
            short_idx.append(i)
            long_idx.append(j)
    return (short_idx, long_idx) if second_longer else (long_idx, short_idx)


@pytest.mark.parametrize("case", ["same", "shifted", "other rate", "gaps", "jitter", "sparse estimate"])
def test_associate_pairs_times_as_evo_does(case: str) -> None:
    rng = np.random.default_rng(7)
    reference = np.arange(200) * 0.1 + 1000.0
    times, offset, max_diff = reference.copy(), 0.0, 0.01
    if case == "shifted":
        times, offset = reference + 100.0, -100.0
    elif case == "other rate":
        times = np.arange(300) * 0.0666 + 1000.0
        max_diff = 0.02
    elif case == "gaps":
        times = np.delete(reference, [5, 6, 7, 8, 9, 120])
    elif case == "jitter":
        times = reference + rng.uniform(-0.015, 0.015, reference.size)
    elif case == "sparse estimate":
        times = reference[::3] + 0.004
    ref_idx, idx = associate(reference, times, max_diff, offset)
    expected = _evo_association(reference, times, max_diff, offset)
    # evo may pair two poses with one partner (poses closer than 2 · max_diff); none of these cases does.
    assert len(set(expected[0])) == len(expected[0]) and len(set(expected[1])) == len(expected[1])
    assert ref_idx.tolist() == expected[0] and idx.tolist() == expected[1]
    assert ref_idx.size > 0
    if case == "shifted":  # without the offset nothing is within the tolerance
        assert associate(reference, times, max_diff)[0].size == 0


def test_associate_keeps_one_pair_per_pose() -> None:
    """Where evo pairs two poses of the shorter trajectory with one of the longer, the first pair is kept."""
    reference = np.array([0.0, 1.0, 2.0])
    times = np.array([0.995, 1.004])  # both nearest to 1.0, within 0.01
    assert _evo_association(reference, times, 0.01, 0.0) == ([1, 1], [0, 1])
    ref_idx, idx = associate(reference, times)
    assert ref_idx.tolist() == [1] and idx.tolist() == [0]


def test_mat_without_convention_says_what_it_assumed(tmp_path: Path) -> None:
    poses = random_trajectory(4)
    mat = tmp_path / "noconv.mat"
    scipy.io.savemat(mat, {"poses_gt": np.moveaxis(poses, 0, -1), "poses_est": np.moveaxis(poses, 0, -1)})
    with pytest.warns(InputWarning, match=r"noconv\.mat: no 'convention' key; read as 'Twv' \(camera-to"):
        gt, _ = read_mat(mat)
    np.testing.assert_allclose(gt, poses, atol=1e-12)
    scipy.io.savemat(mat, {"poses_gt": np.moveaxis(poses, 0, -1), "poses_est": np.moveaxis(poses, 0, -1),
                           "convention": "Twv"})
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_trajectory(mat)


def test_writers_refuse_an_empty_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    for write in (write_kitti_poses, write_tum):
        with pytest.raises(ValueError, match=r"^path: expected a path, got an empty one"):
            write("", random_trajectory(3))
    assert list(tmp_path.iterdir()) == []


def test_a_zero_correction_gives_back_a_float32_prior() -> None:
    """libviso2's KITTI 00 as stored (float32-rounded rotations, orthonormal to about 1e-7, not projected
    as the readers would): ξ = 0 gives back every position to float64 rounding. Composing the steps back
    with the rigid inverse of unprojected rotations moved them by 2.8 mm over the 4,541 frames."""
    from dpc_jax.geometry.pose_correction import corrected_trajectory

    stored = np.moveaxis(scipy.io.loadmat(LIBVISO2 / "stereo_00.mat")["poses_est"], -1, 0).astype(np.float64)
    rotations = stored[:, :3, :3]
    assert np.abs(np.einsum("nji,njk->nik", rotations, rotations) - np.eye(3)).max() > 1e-8  # not projected
    corrected = corrected_trajectory(np.zeros((len(stored) - 1, 6)), stored, stored[0])
    assert np.abs(corrected[:, :3, 3] - stored[:, :3, 3]).max() < 1e-9
    assert np.abs(corrected[:, :3, :3] - rotations).max() < 1e-6
