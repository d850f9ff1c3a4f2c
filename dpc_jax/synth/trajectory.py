"""Car-like motion along the road: the ego camera and independently moving cars (numpy).

The ego car drives in the right lane (``l ≈ +1.75 m``) with a smooth speed profile in
[5, 15] m/s, a slight lateral weave, and a body that pitches with longitudinal acceleration
(squat/dive) and rolls outward in curves with the centripetal acceleration, plus small
suspension oscillations. Poses are camera-to-world (world frame of :mod:`world`, y down), for the
left camera, KITTI axes (x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np

from dpc_jax.synth.world import LANE_OFFSET, Road

CAMERA_HEIGHT = 1.65
"""Height (m) of the left camera above the ground, as on the KITTI car."""


def rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``R = R_y(yaw) R_x(pitch) R_z(roll)`` in the y-down frame, ``[..., 3, 3]``.

    ``yaw`` turns +z towards +x (heading), positive ``pitch`` lifts the nose, ``roll`` is about
    the forward axis.
    """
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    o, i = np.zeros_like(cy), np.ones_like(cy)
    ry = np.stack([np.stack([cy, o, sy], -1), np.stack([o, i, o], -1), np.stack([-sy, o, cy], -1)], -2)
    rx = np.stack([np.stack([i, o, o], -1), np.stack([o, cp, -sp], -1), np.stack([o, sp, cp], -1)], -2)
    rz = np.stack([np.stack([cr, -sr, o], -1), np.stack([sr, cr, o], -1), np.stack([o, o, i], -1)], -2)
    return ry @ rx @ rz


class _Wave:
    """Sum of sinusoids with random periods and phases; value, derivative and integral in closed form."""

    def __init__(self, rng: np.random.Generator, amplitudes: list[float], periods: tuple[float, float]):
        self.a = np.asarray(amplitudes, np.float64)
        self.w = 2 * np.pi / rng.uniform(*periods, size=len(amplitudes))
        self.phi = rng.uniform(0, 2 * np.pi, size=len(amplitudes))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return np.sum(self.a * np.sin(np.multiply.outer(t, self.w) + self.phi), -1)

    def derivative(self, t: np.ndarray) -> np.ndarray:
        return np.sum(self.a * self.w * np.cos(np.multiply.outer(t, self.w) + self.phi), -1)

    def integral(self, t: np.ndarray) -> np.ndarray:
        """∫₀ᵗ."""
        ang = np.multiply.outer(t, self.w) + self.phi
        return np.sum(self.a / self.w * (np.cos(self.phi) - np.cos(ang)), -1)


def ego_speed_profile(rng: np.random.Generator) -> tuple[float, _Wave]:
    """Mean speed and a zero-mean variation that keeps the speed inside [5.5, 14.5] m/s."""
    mean = rng.uniform(8.0, 12.0)
    room = min(mean - 5.5, 14.5 - mean)
    split = rng.uniform(0.3, 0.7)
    return mean, _Wave(rng, [room * split, room * (1 - split)], (8.0, 30.0))


def ego_trajectory(rng: np.random.Generator, road: Road, times: np.ndarray,
                   s_start: float) -> tuple[np.ndarray, np.ndarray]:
    """Left-camera poses ``[N, 4, 4]`` (camera-to-world) and arc lengths ``s [N]`` at ``times``."""
    mean, wave = ego_speed_profile(rng)
    s = s_start + mean * times + wave.integral(times)
    v = mean + wave(times)
    accel = wave.derivative(times)
    weave = _Wave(rng, [0.12, 0.06], (4.0, 12.0))
    lateral = LANE_OFFSET + weave(times)
    x, z, psi, kappa = road.frame(s)
    yaw = psi + np.arctan2(weave.derivative(times), v)
    right = np.stack([np.cos(psi), -np.sin(psi)], -1)
    bounce = _Wave(rng, [0.015, 0.008], (0.6, 2.0))
    pitch_osc = _Wave(rng, [0.004, 0.003], (0.8, 3.0))
    roll_osc = _Wave(rng, [0.004, 0.003], (0.8, 3.0))
    # Squat/dive ≈ 0.3°/(m/s²); outward body roll ≈ 0.5°/(m/s²) of centripetal acceleration.
    pitch = np.deg2rad(0.3) * accel + pitch_osc(times)
    roll = -np.deg2rad(0.5) * v * v * kappa + roll_osc(times)
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    poses[:, :3, :3] = rotation(yaw, pitch, roll)
    poses[:, 0, 3] = x + lateral * right[:, 0]
    poses[:, 1, 3] = -(CAMERA_HEIGHT + bounce(times))
    poses[:, 2, 3] = z + lateral * right[:, 1]
    return poses, s


def moving_cars(rng: np.random.Generator, road: Road, times: np.ndarray, ego_s: np.ndarray,
                count: int) -> np.ndarray:
    """``count`` independently moving cars, ``[N, count, 7]`` rows ``s, x, z, heading, half length,
    half width, seed`` (the layout's car format).

    Even-numbered cars are oncoming traffic in the left lane (6–14 m/s, entering the view at
    different times); odd-numbered ones drive ahead in the ego lane at a gap that varies between
    about 10 and 45 m, so they move relative to the static scene yet stay in view.
    """
    n_frames = len(times)
    out = np.zeros((n_frames, count, 7))
    span = ego_s[-1] - ego_s[0]
    for j in range(count):
        half_len = rng.uniform(1.9, 2.4)
        half_width = rng.uniform(0.85, 0.95)
        seed = rng.integers(0, 1 << 20)
        if j % 2 == 0:
            speed = rng.uniform(6.0, 14.0)
            meet = rng.uniform(0.15, 0.95)
            # Place the car so that it passes the ego car at fraction ``meet`` of the sequence.
            t_meet = times[0] + meet * (times[-1] - times[0])
            s_meet = np.interp(t_meet, times, ego_s) if span > 0 else ego_s[0]
            s = s_meet - speed * (times - t_meet)
            lateral, flip = -LANE_OFFSET, np.pi
        else:
            gap = 14.0 + 14.0 * (j // 2) + _Wave(rng, [rng.uniform(3.0, 8.0)], (6.0, 20.0))(times)
            s = ego_s + gap + 4.0
            lateral, flip = LANE_OFFSET, 0.0
        x, z, psi = road.point(s, np.full_like(s, lateral))
        out[:, j] = np.stack([s, x, z, psi + flip, np.full_like(s, half_len), np.full_like(s, half_width),
                              np.full_like(s, seed)], -1)
    return out
