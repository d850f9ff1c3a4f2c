"""Synthetic stereo driving sequences: configuration, per-frame scenes, rendering (Python API).

``render_sequence(SynthConfig(...))`` returns a whole :class:`SynthSequence` in memory;
``iter_frames`` yields one :class:`SynthFrame` at a time (what the writer uses, so that long
sequences never sit in memory). Everything is deterministic from ``SynthConfig.seed``: the world,
the trajectories, the illumination drift and the image noise.

Camera model (docs/method.md §1): rectified stereo pair, KITTI colour intrinsics (P2 of the odometry
calibration: fu = fv = 721.5377, cu = 609.5593, cv = 172.854 at 1242×375) scaled to the image
size (row 0 by W/1242, row 1 by H/375), right camera ``baseline`` metres along the left camera's
x axis. Poses are camera-to-world of the left camera, re-anchored so that the first pose is the
identity (as in KITTI's ``poses/XX.txt``). Depth is the z-depth along the optical axis in metres,
``inf`` where a pixel sees the sky (so the disparity ``fu·B/Z`` is 0 there, which is exact).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from dpc_jax.synth.trajectory import _Wave, ego_trajectory, moving_cars
from dpc_jax.synth.world import Layout, make_layout

KITTI_SIZE = (375, 1242)
KITTI_FU, KITTI_CU, KITTI_CV = 721.5377, 609.5593, 172.854

# Fixed table sizes so that one compilation serves every frame and sequence of an image size:
# road pieces near the camera, and the nearest objects inside the view frustum.
_STRAIGHTS, _ARCS = 4, 4
_CYLINDERS, _SPHERES, _PARKED = 20, 12, 16
_PIECES_BEHIND, _PIECES_AHEAD = 30.0, 320.0


@dataclass(frozen=True)
class SynthConfig:
    """What to render. ``noise`` is the standard deviation of Gaussian image noise in [0, 255]
    units; ``illumination_drift`` the amplitude of the slow global gain (``1 ± X``) and gamma
    (``1 ± X/2``) variation; ``moving_objects`` the number of independently moving cars;
    ``disparity_offset`` (px at the rendered size) a stereo calibration residual: the right
    camera's principal point lies that far left of the written calibration's, so every disparity
    measured with ``calib.txt`` is that much larger than ``fu·B/Z`` (KITTI's colour pair needs a
    correction of about +1.2 px at 1242 px width, i.e. a residual of about −1.2 px)."""

    frames: int = 200
    height: int = 240
    width: int = 376
    seed: int = 0
    moving_objects: int = 0
    illumination_drift: float = 0.0
    noise: float = 0.0
    baseline: float = 0.54
    fps: float = 10.0
    disparity_offset: float = 0.0

    def __post_init__(self) -> None:
        if self.frames < 2:
            raise ValueError(f"frames must be at least 2, got {self.frames}")
        if self.seed < 0:  # sequence i is seeded with seed + i, and numpy's seeds are not negative
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.height < 8 or self.width < 8:
            raise ValueError(f"image size must be at least 8×8, got {self.height}×{self.width}")
        if self.moving_objects < 0:
            raise ValueError(f"moving_objects must be >= 0, got {self.moving_objects}")
        if not (0.0 <= self.illumination_drift < 1.0):
            raise ValueError(f"illumination_drift must be in [0, 1), got {self.illumination_drift}")
        if self.noise < 0:
            raise ValueError(f"noise must be >= 0, got {self.noise}")
        if self.baseline <= 0 or self.fps <= 0:
            raise ValueError(f"baseline and fps must be > 0, got {self.baseline} and {self.fps}")
        if not abs(self.disparity_offset) < 0.05 * self.width:
            raise ValueError(f"disparity_offset must be a few pixels at most (less than 5 % of the width, "
                             f"{0.05 * self.width:g} px), got {self.disparity_offset}")


@dataclass(frozen=True)
class SynthFrame:
    """One stereo frame: ``left``/``right`` uint8 ``[H, W, 3]`` RGB, ``depth_left``/``depth_right``
    float32 ``[H, W]`` (m, ``inf`` = sky), ``moving_left``/``moving_right`` bool ``[H, W]``."""

    index: int
    left: np.ndarray
    right: np.ndarray
    depth_left: np.ndarray
    depth_right: np.ndarray
    moving_left: np.ndarray
    moving_right: np.ndarray


@dataclass(frozen=True)
class SynthSequence:
    """A rendered sequence: arrays stacked over frames (``[N, ...]``, see :class:`SynthFrame`),
    ``poses [N, 4, 4]`` float64 camera-to-world of the left camera (first = identity),
    ``K [3, 3]`` float64, ``baseline`` (m), ``times [N]`` (s), ``gain``/``gamma [N]`` (the
    illumination actually applied)."""

    left: np.ndarray
    right: np.ndarray
    depth_left: np.ndarray
    depth_right: np.ndarray
    moving_left: np.ndarray
    moving_right: np.ndarray
    poses: np.ndarray
    K: np.ndarray
    baseline: float
    times: np.ndarray
    gain: np.ndarray
    gamma: np.ndarray


def kitti_intrinsics(height: int, width: int) -> np.ndarray:
    """KITTI colour-camera intrinsics scaled to ``height × width`` (float64 ``[3, 3]``)."""
    sx, sy = width / KITTI_SIZE[1], height / KITTI_SIZE[0]
    return np.array([[KITTI_FU * sx, 0.0, KITTI_CU * sx],
                     [0.0, KITTI_FU * sy, KITTI_CV * sy],
                     [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class _Plan:
    """Everything about a sequence except the pixels (cheap to compute)."""

    layout: Layout
    times: np.ndarray
    world_poses: np.ndarray
    ego_s: np.ndarray
    movers: np.ndarray
    gain: np.ndarray
    gamma: np.ndarray


def _plan(config: SynthConfig) -> _Plan:
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, 0x5EC]))
    times = np.arange(config.frames) / config.fps
    # 15 m/s is the top speed; the road continues well past the last frame so that the far view
    # and oncoming traffic are complete.
    length = 20.0 + 15.0 * times[-1] + _PIECES_AHEAD + 200.0
    layout = make_layout(rng, length)
    poses, ego_s = ego_trajectory(rng, layout.road, times, s_start=20.0)
    movers = moving_cars(rng, layout.road, times, ego_s, config.moving_objects)
    x = config.illumination_drift
    gain = 1.0 + x * _Wave(rng, [0.6, 0.4], (6.0, 25.0))(times)
    gamma = 1.0 + 0.5 * x * _Wave(rng, [0.6, 0.4], (6.0, 25.0))(times)
    return _Plan(layout, times, poses, ego_s, movers, gain, gamma)


def _in_view(centres: np.ndarray, radii: np.ndarray, pose: np.ndarray, K: np.ndarray, size: tuple[int, int],
             baseline: float) -> np.ndarray:
    """Which bounding spheres ``centres [N, 3]``, ``radii [N]`` meet the view of either camera."""
    p = (centres - pose[:3, 3]) @ pose[:3, :3]
    px, py, pz = p[:, 0] - 0.5 * baseline, p[:, 1], p[:, 2]
    r = radii + 0.5 * baseline
    h, w = size
    ok = pz > -r
    for coord, tan in ((px, (w - 1 - K[0, 2]) / K[0, 0]), (-px, K[0, 2] / K[0, 0]),
                       (py, (h - 1 - K[1, 2]) / K[1, 1]), (-py, K[1, 2] / K[1, 1])):
        ok &= coord - tan * pz <= r * np.sqrt(1.0 + tan * tan)
    return ok


def _nearest_visible(table: np.ndarray, centres: np.ndarray, radii: np.ndarray, view: tuple, size: int,
                     pad: np.ndarray) -> np.ndarray:
    """The ``size`` rows of ``table`` nearest to the camera among those in view, padded with ``pad``."""
    pose = view[0]
    visible = np.flatnonzero(_in_view(centres, radii, *view))
    dist = np.linalg.norm(centres[visible] - pose[:3, 3], axis=1)
    rows = table[visible[np.argsort(dist, kind="stable")[:size]]]
    if len(rows) < size:
        rows = np.concatenate([rows, np.tile(pad, (size - len(rows), 1))], 0)
    return rows


_PAD_CYLINDER = np.array([1e9, 1e7, 1e7, 0.0, 0.0, 0.0])
_PAD_SPHERE = np.array([1e9, 1e7, 1e7, 1e7, 0.0, 0.0])
_PAD_CAR = np.array([1e9, 1e7, 1e7, 0.0, 0.0, 0.0, 0.0])


def frame_scene(plan: _Plan, index: int, K: np.ndarray, size: tuple[int, int],
                baseline: float) -> tuple[np.ndarray, ...]:
    """Float32 tables of :class:`render.FrameScene` for frame ``index``."""
    road = plan.layout.road
    lay = plan.layout
    view = (plan.world_poses[index], K, size, baseline)
    s_cam = float(plan.ego_s[index])
    near = (road.s0 + road.length > s_cam - _PIECES_BEHIND) & (road.s0 < s_cam + _PIECES_AHEAD)
    rows = np.stack([road.x0, road.z0, road.psi0, road.s0, road.length, road.kappa], 1)[near]
    straight = rows[rows[:, 5] == 0][:_STRAIGHTS]
    arcs = rows[rows[:, 5] != 0][:_ARCS]
    straight = np.concatenate([straight, np.zeros((_STRAIGHTS - len(straight), 6))], 0)
    arcs = np.concatenate([arcs, np.zeros((_ARCS - len(arcs), 6))], 0)
    cyl = lay.cylinders
    cyl = _nearest_visible(cyl, np.stack([cyl[:, 1], -0.5 * cyl[:, 4], cyl[:, 2]], 1),
                           np.hypot(cyl[:, 3], 0.5 * cyl[:, 4]), view, _CYLINDERS, _PAD_CYLINDER)
    sph = _nearest_visible(lay.spheres, lay.spheres[:, 1:4], lay.spheres[:, 4], view, _SPHERES, _PAD_SPHERE)
    car_radius = np.sqrt(lay.cars[:, 4] ** 2 + lay.cars[:, 5] ** 2 + 0.75**2)
    car_centres = np.stack([lay.cars[:, 1], np.full(len(lay.cars), -0.75), lay.cars[:, 2]], 1)
    cars = _nearest_visible(lay.cars, car_centres, car_radius, view, _PARKED, _PAD_CAR)
    movers = plan.movers[index]
    # Moving-car slots come in fours (at least four) so that most counts share one compilation.
    slots = max(4, -(-len(movers) // 4) * 4)
    movers = np.concatenate([movers, np.tile(_PAD_CAR, (slots - len(movers), 1))], 0)
    cars = np.concatenate([np.concatenate([cars, np.zeros((_PARKED, 1))], 1),
                           np.concatenate([movers, np.ones((slots, 1))], 1)], 0)
    tables = (straight, arcs, lay.layers, cyl, sph, cars, lay.sun)
    return tuple(np.asarray(t, np.float32) for t in tables)


def iter_frames(config: SynthConfig) -> Iterator[SynthFrame]:
    """Render the frames of ``config`` one by one (deterministic)."""
    import jax.numpy as jnp

    from dpc_jax.synth.render import FrameScene, render_stereo

    plan = _plan(config)
    K = kitti_intrinsics(config.height, config.width)
    baseline = jnp.float32(config.baseline)
    size = (config.height, config.width)
    for i in range(config.frames):
        scene = FrameScene(*(jnp.asarray(t) for t in frame_scene(plan, i, K, size, config.baseline)))
        image, depth_map, moving_map = render_stereo(
            scene, jnp.asarray(plan.world_poses[i], jnp.float32), jnp.asarray(K, jnp.float32), baseline,
            float(plan.gain[i]), float(plan.gamma[i]), height=config.height, width=config.width,
            quantise=config.noise == 0, disparity_offset=config.disparity_offset,
        )
        pixels, depth, moving = np.asarray(image), np.asarray(depth_map), np.asarray(moving_map)
        if config.noise > 0:
            rng = np.random.default_rng(np.random.SeedSequence([config.seed, 0x1015E, i]))
            noisy = pixels + rng.standard_normal(pixels.shape, np.float32) * np.float32(config.noise)
            pixels = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
        yield SynthFrame(i, pixels[0], pixels[1], depth[0], depth[1], moving[0], moving[1])


def sequence_poses(config: SynthConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth without rendering: ``poses [N, 4, 4]`` (first = identity), ``times``, and the
    illumination ``gain``, ``gamma`` per frame."""
    plan = _plan(config)
    return _anchor(plan.world_poses), plan.times, plan.gain, plan.gamma


def _anchor(poses: np.ndarray) -> np.ndarray:
    anchored = np.linalg.inv(poses[0]) @ poses
    anchored[0] = np.eye(4)
    return anchored


def render_sequence(config: SynthConfig) -> SynthSequence:
    """Render a whole sequence into memory (for tests and the demo; see :func:`iter_frames`)."""
    frames = list(iter_frames(config))
    poses, times, gain, gamma = sequence_poses(config)

    def stack(name: str) -> np.ndarray:
        return np.stack([getattr(f, name) for f in frames])

    return SynthSequence(
        stack("left"), stack("right"), stack("depth_left"), stack("depth_right"), stack("moving_left"),
        stack("moving_right"), poses, kitti_intrinsics(config.height, config.width), config.baseline,
        times, gain, gamma,
    )
