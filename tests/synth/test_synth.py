"""Synthetic driving world: exact geometry, KITTI layout, nuisances, determinism.

References are independent of the renderer: the foundation's warps (``dpc_jax.geometry.warp``), float64
numpy geometry of the road layout, the KITTI odometry reader (``dpc_jax.data.kitti``), and the
closed-form illumination and noise models.
"""

from __future__ import annotations

import dataclasses
import filecmp
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from dpc_jax.cli import main
from dpc_jax.data.kitti import load_image, open_odometry
from dpc_jax.geometry.warp import inverse_warp, stereo_warp
from dpc_jax.synth import SynthConfig, render_sequence, sequence_poses, write_sequences
from dpc_jax.synth.render import nearest_hits
from dpc_jax.synth.sequence import _plan, frame_scene, kitti_intrinsics
from dpc_jax.synth.shapes import FACADE, GROUND, FrameScene

H, W = 64, 160
BASE = SynthConfig(frames=3, height=H, width=W, seed=3)


@pytest.fixture(scope="module")
def moving():
    return render_sequence(dataclasses.replace(BASE, moving_objects=4))


@pytest.fixture(scope="module")
def static():
    return render_sequence(BASE)


def _finite(depth: np.ndarray, fill: float) -> np.ndarray:
    return np.where(np.isfinite(depth), depth, fill)


def _temporal(seq, k: int, pose_error: float = 0.0):
    """Rebuild left frame k+1 from frame k with the true depth and pose; also carry the source
    depth and moving mask through the warp to find occlusions and moving points."""
    depth_t = _finite(seq.depth_left[k + 1].astype(np.float64), 1.0)
    T = np.linalg.inv(seq.poses[k]) @ seq.poses[k + 1]
    T[2, 3] += pose_error
    source = np.concatenate([seq.left[k].astype(np.float64), _finite(seq.depth_left[k], 1e4)[..., None],
                             seq.moving_left[k][..., None]], -1)
    rec, valid = inverse_warp(jnp.asarray(source), jnp.asarray(depth_t), jnp.asarray(T), jnp.asarray(seq.K))
    rec, valid = np.asarray(rec), np.asarray(valid)
    v, u = np.mgrid[0:H, 0:W]
    K = seq.K
    points = np.stack([(u - K[0, 2]) / K[0, 0] * depth_t, (v - K[1, 2]) / K[1, 1] * depth_t, depth_t,
                       np.ones_like(depth_t)], -1)
    z_source = (points @ T.T)[..., 2]
    visible = valid & np.isfinite(seq.depth_left[k + 1]) & (np.abs(rec[..., 3] - z_source) < 0.03 * z_source)
    error = np.abs(rec[..., :3] - seq.left[k + 1]).mean(-1)
    return error, visible, rec[..., 4] > 0, valid


def test_temporal_warp_with_true_depth_and_pose_reconstructs_next_frame(moving):
    for k in range(2):
        error, visible, moved_src, _ = _temporal(moving, k)
        static_px = visible & ~moving.moving_left[k + 1] & ~moved_src
        assert static_px.mean() > 0.6
        # Bilinear interpolation of band-limited texture: small typical error, a tail at edges.
        assert np.median(error[static_px]) < 1.5
        assert error[static_px].mean() < 5.0
        wrong, visible_wrong, _, _ = _temporal(moving, k, pose_error=1.0)
        assert np.median(error[static_px]) < 0.5 * np.median(wrong[static_px & visible_wrong])


def test_moving_objects_violate_the_static_warp(moving):
    for k in range(2):
        error, visible, moved_src, valid = _temporal(moving, k)
        mv = valid & moving.moving_left[k + 1]
        assert mv.sum() > 20
        static_px = valid & np.isfinite(moving.depth_left[k + 1]) & ~moving.moving_left[k + 1] & ~moved_src
        # Under the camera motion alone, a moving car's pixels land where the source frame saw
        # something at another depth, and their colours do not match.
        assert (~visible[mv]).mean() > 0.5
        assert (~visible[static_px]).mean() < 0.15
        assert np.median(error[mv]) > 2.0 * np.median(error[static_px & visible])


def test_moving_objects_leave_the_static_world_unchanged(moving, static):
    assert np.array_equal(moving.poses, static.poses)
    for k in range(BASE.frames):
        mask = moving.moving_left[k]
        grown = mask.copy()
        grown[1:] |= mask[:-1]
        grown[:-1] |= mask[1:]
        grown[:, 1:] |= grown[:, :-1]
        grown[:, :-1] |= grown[:, 1:]
        # Moving cars only add occluders: the depth shrinks where they are and nothing else changes
        # (one pixel around them the texture band-limiting sees the new neighbours).
        assert np.all(moving.depth_left[k][mask] < static.depth_left[k][mask])
        assert np.array_equal(moving.depth_left[k][~mask], static.depth_left[k][~mask])
        assert np.array_equal(moving.left[k][~grown], static.left[k][~grown])
    assert not static.moving_left.any()


def test_stereo_warp_with_rendered_disparity_reconstructs_left(static):
    fu = static.K[0, 0]
    for k in range(BASE.frames):
        disparity = fu * static.baseline / static.depth_left[k]  # 0 where the depth is inf (sky)
        source = np.concatenate([static.right[k].astype(np.float64),
                                 _finite(static.depth_right[k], 1e4)[..., None]], -1)
        rec, valid = stereo_warp(jnp.asarray(source), jnp.asarray(disparity), "right_to_left")
        rec, valid = np.asarray(rec), np.asarray(valid)
        depth_l = _finite(static.depth_left[k], 1e4)
        ok = valid & (np.abs(rec[..., 3] - depth_l) < 0.03 * depth_l)
        assert ok.mean() > 0.75
        error = np.abs(rec[..., :3] - static.left[k]).mean(-1)
        assert np.median(error[ok]) < 1.0
        assert error[ok].mean() < 3.0
        shifted, _ = stereo_warp(jnp.asarray(source[..., :3]), jnp.asarray(disparity + 2.0), "right_to_left")
        assert np.abs(np.asarray(shifted) - static.left[k]).mean(-1)[ok].mean() > 2 * error[ok].mean()


def test_disparity_offset_shifts_the_right_image_by_that_many_pixels(static):
    """A calibration residual of δ px: the left view is rebuilt from the right one at fu·B/Z + δ."""
    offset = 1.5
    shifted = render_sequence(dataclasses.replace(BASE, disparity_offset=offset))
    np.testing.assert_array_equal(shifted.left, static.left)
    fu = static.K[0, 0]
    for k in range(BASE.frames):
        disparity = np.nan_to_num(fu * static.baseline / static.depth_left[k])
        errors = []
        for d in (disparity, disparity + offset):
            rec, valid = stereo_warp(jnp.asarray(shifted.right[k].astype(np.float64)), jnp.asarray(d),
                                     "right_to_left")
            valid = np.asarray(valid) & np.isfinite(static.depth_left[k])
            errors.append(np.abs(np.asarray(rec) - static.left[k]).mean(-1)[valid].mean())
        assert errors[1] < 0.5 * errors[0]


def test_prepare_removes_a_disparity_offset(tmp_path: Path, static):
    """``prepare_sequence(disparity_offset=o)`` resamples the right images at u + o: with o = −δ the
    residual δ of the rendering is gone, the right images match a perfectly calibrated rig's."""
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.sequence_cache import load_cache

    offset = 1.0
    write_sequences(tmp_path / "kitti", dataclasses.replace(BASE, disparity_offset=offset), 1)
    sequence = open_odometry(tmp_path / "kitti", "00")
    inner = np.s_[:, :, 4:-4]  # away from the replicated border column
    errors = []
    for correction in (0.0, -offset):
        path = prepare_sequence(sequence, static.poses, tmp_path / f"cache{correction}", size=(H, W),
                                disparity_offset=correction, progress=False, workers=1)
        cache = load_cache(path)
        np.testing.assert_array_equal(cache.left, static.left)
        errors.append(np.abs(cache.right.astype(float) - static.right)[inner].mean())
    assert errors[1] < 0.3 * errors[0]
    # The sequence written is a rendering of its config, not of another; a missing poses file (written
    # last) is an unfinished one.
    from dpc_jax.synth import is_rendered

    rendered = dataclasses.replace(BASE, disparity_offset=offset)
    assert is_rendered(tmp_path / "kitti", "00", rendered)
    assert not is_rendered(tmp_path / "kitti", "00", BASE)
    assert not is_rendered(tmp_path / "kitti", "01", rendered)
    (tmp_path / "kitti" / "poses" / "00.txt").unlink()
    assert not is_rendered(tmp_path / "kitti", "00", rendered)


def test_depth_is_exact_on_ground_and_facades():
    """Back-project rendered depth in float64 and check the points lie on the analytic surfaces."""
    plan = _plan(BASE)
    K = kitti_intrinsics(H, W)
    tables = frame_scene(plan, 1, K, (H, W), BASE.baseline)
    pose = plan.world_poses[1]
    hits = nearest_hits(FrameScene(*(jnp.asarray(t) for t in tables)), jnp.asarray(pose, jnp.float32),
                        jnp.asarray(K, jnp.float32), jnp.float32(BASE.baseline), jnp.float32(0.0),
                        height=H, width=W)
    kind, depth = np.asarray(hits.kind[0]), np.asarray(hits.depth[0]).astype(np.float64)
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    depth = np.where(np.isfinite(depth), depth, 0.0)
    world = rays * depth[..., None] @ pose[:3, :3].T + pose[:3, 3]
    ground = kind == GROUND
    assert ground.mean() > 0.2
    np.testing.assert_allclose(world[ground][:, 1], 0.0, atol=2e-3)
    facade = kind == FACADE
    assert facade.mean() > 0.1
    # Distance of facade points to the road centreline (float64, densely sampled) is a row's offset.
    road = plan.layout.road
    cx, cz, _, _ = road.frame(np.arange(0.0, road.total_length, 0.01))
    lateral, _ = cKDTree(np.stack([cx, cz], 1)).query(world[facade][:, [0, 2]])
    offsets = np.abs(plan.layout.layers[:, 0])
    assert np.min(np.abs(lateral[:, None] - offsets[None]), 1).max() < 5e-3


def test_illumination_drift_follows_gain_and_gamma(static):
    drift = render_sequence(dataclasses.replace(BASE, illumination_drift=0.4))
    _, _, gain, gamma = sequence_poses(dataclasses.replace(BASE, illumination_drift=0.4))
    assert np.ptp(gain) > 0 and np.ptp(gamma) > 0
    for k in range(BASE.frames):
        clean = static.left[k].astype(np.float64) / 255
        expected = 255 * np.clip(gain[k] * clean ** gamma[k], 0, 1)
        # Both images are quantised from the same float image: within one grey level plus rounding.
        assert np.abs(drift.left[k] - expected).max() <= 1.6
    assert np.abs(drift.left.astype(np.float64).mean((1, 2, 3)) - static.left.mean((1, 2, 3))).max() > 3.0
    long_gain = sequence_poses(dataclasses.replace(BASE, frames=300, illumination_drift=0.4))[2]
    assert long_gain.max() - long_gain.min() > 0.3


def test_noise_is_gaussian_with_the_requested_sigma(static):
    noisy = render_sequence(dataclasses.replace(BASE, noise=4.0))
    diff = noisy.left.astype(np.float64) - static.left
    inner = (static.left > 20) & (static.left < 235)
    assert abs(diff[inner].std() - 4.0) < 0.3
    assert abs(diff[inner].mean()) < 0.2
    assert np.array_equal(noisy.depth_left, static.depth_left)


def test_trajectory_is_car_like():
    poses, times, _, _ = sequence_poses(SynthConfig(frames=600, seed=5))
    assert np.allclose(poses[0], np.eye(4))
    assert np.allclose(np.diff(times), 0.1)
    rel = np.linalg.inv(poses[:-1]) @ poses[1:]
    speed = np.linalg.norm(rel[:, :3, 3], axis=1) / 0.1
    assert speed.min() > 5.0 and speed.max() < 15.0
    # Mostly forward motion along the camera's z axis, little sideways or vertical motion.
    assert np.all(rel[:, 2, 3] > 0.95 * np.linalg.norm(rel[:, :3, 3], axis=1))
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    heading = np.degrees(np.arctan2(R[:, 0, 2], R[:, 2, 2]))
    pitch = np.degrees(np.arcsin(-R[:, 1, 2]))
    assert np.ptp(heading) > 20.0  # the road curves
    assert np.abs(pitch).max() < 3.0
    world_height = -_plan(SynthConfig(frames=600, seed=5)).world_poses[:, 1, 3]
    assert np.abs(world_height - 1.65).max() < 0.05  # flat road: only the suspension moves the camera


def test_written_sequences_read_back_through_the_kitti_reader(tmp_path: Path, static):
    config = dataclasses.replace(BASE, frames=2)
    paths = write_sequences(tmp_path, config, sequences=2, progress=False)
    assert [p.name for p in paths] == ["00", "01"]
    seq = open_odometry(tmp_path, "00")
    assert len(seq) == 2 and seq.image_size == (H, W)
    np.testing.assert_allclose(seq.K, kitti_intrinsics(H, W), rtol=1e-12)
    assert seq.baseline == pytest.approx(0.54, rel=1e-12)
    np.testing.assert_allclose(seq.times, [0.0, 0.1])
    np.testing.assert_allclose(seq.poses, static.poses[:2], atol=1e-11)
    assert np.array_equal(load_image(seq.images.left_paths[1]), static.left[1])
    assert np.array_equal(load_image(seq.images.right_paths[0]), static.right[0])
    depth = np.load(tmp_path / "sequences" / "00" / "depth_3" / "000001.npy")
    assert depth.dtype == np.float32 and np.array_equal(depth, static.depth_right[1], equal_nan=True)
    other = open_odometry(tmp_path, "01")
    assert not np.allclose(other.poses[1], seq.poses[1])
    assert not list((tmp_path / "sequences").glob(".*"))  # no temporary directories left behind


def test_same_command_gives_identical_files(tmp_path: Path, capsys):
    args = ["synth", "--sequences", "1", "--frames", "2", "--size", f"{H}x{W}", "--seed", "7",
            "--moving-objects", "2", "--noise", "2", "--illumination-drift", "0.2", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert len(files) == 16
    _, mismatch, errors = filecmp.cmpfiles(tmp_path / "a", tmp_path / "b", [str(f) for f in files],
                                           shallow=False)
    assert not mismatch and not errors
    # Existing output is refused with a message, not a traceback.
    assert main([*args, "--out", str(tmp_path / "a")]) == 2
    assert "already holds" in capsys.readouterr().err


def test_bad_configuration_is_rejected():
    with pytest.raises(ValueError, match="frames"):
        SynthConfig(frames=1)
    with pytest.raises(ValueError, match="illumination_drift"):
        SynthConfig(illumination_drift=1.5)
    with pytest.raises(SystemExit):
        main(["synth", "--out", "x", "--size", "64by160"])
