"""Builders the tests share: tiny KITTI odometry trees (random or rendered with ``dpc_jax.synth``), command
lines run in one fresh interpreter, an analytic stereo scene, tiny prepared caches and training configs,
and a stored training run without training it.

``tests/conftest.py`` sits in this folder and there is no ``tests/__init__.py``, so pytest puts this folder
on ``sys.path`` and a test in any subfolder imports these with ``from support import ...``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    import jax

    from dpc_jax.nn.batch import Batch
    from dpc_jax.nn.outputs import DPCOutputs
    from dpc_jax.training.train_config import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
"""The repository root (the command lines run there)."""

_OLDER_CODE_GENERATOR = "--xla_cpu_use_fusion_emitters=false"
_FAST_CODE_GENERATION = ("--xla_backend_optimization_level=0", _OLDER_CODE_GENERATOR)
_CHOSEN_FLAGS = "DPC_JAX_TEST_XLA_FLAGS"


def _test_xla_flags() -> str:
    """Those of :data:`_FAST_CODE_GENERATION` this XLA knows: it aborts a process on a flag it does not (a
    newer one may drop its older code generator), so one short process tries them first. The answer goes
    into the environment, where the test workers and the processes they start find it."""
    chosen = os.environ.get(_CHOSEN_FLAGS)
    if chosen is None:
        known = [_FAST_CODE_GENERATION[0]]
        for flag in _FAST_CODE_GENERATION[1:]:
            env = {**os.environ, "XLA_FLAGS": " ".join([*known, flag]), "JAX_PLATFORMS": "cpu"}
            probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env,
                                   capture_output=True, check=False)
            known += [flag] if probe.returncode == 0 else []
        chosen = os.environ[_CHOSEN_FLAGS] = " ".join(known)
    return chosen


XLA_TEST_FLAGS = _test_xla_flags()
"""XLA flags of every test process (``tests/conftest.py`` sets them; a test that starts a process with its
own ``XLA_FLAGS`` appends them). The tests' shapes are small, so compiling is most of their time: without
LLVM's optimisation passes, and with XLA's older CPU code generator (an emitter per operation instead of
the MLIR fusion emitters), the same programs compile in about half the time XLA's defaults take. What a
program computes does not depend on them beyond float rounding (the float64 references are met as before;
two programs computing the same float32 value may differ in its last bits, so a test comparing two
programs allows for float32 rounding); users' processes keep XLA's default. A program a test runs many
times at a larger size is slower that way: a test's own ``jax.jit`` of it takes
``compiler_options=OPTIMISED``."""

OPTIMISED: dict[str, Any] = {
    "xla_backend_optimization_level": 2,
    **({"xla_cpu_use_fusion_emitters": True} if _OLDER_CODE_GENERATOR in XLA_TEST_FLAGS.split() else {}),
}
"""``jax.jit``'s ``compiler_options`` that give one program back XLA's default code generation (see
:data:`XLA_TEST_FLAGS`)."""


@contextlib.contextmanager
def optimised_programs() -> Iterator[None]:
    """The library's programs compiled while this holds get XLA's default code generation back (see
    :data:`XLA_TEST_FLAGS`): for a test that runs them many times (a live corrector over hundreds of
    frames), where they run several times faster than they compile slower. A program the process compiled
    before keeps its code; what a program computes does not depend on it beyond float rounding. The programs
    compiled here are forgotten when it ends, so that a later test comparing two programs gets both from one
    code generator."""
    import jax
    import pytest
    from jax._src import compiler  # the options every jit compiles with: no public hook sets them

    test_options = compiler.get_compile_options

    def get_compile_options(*args: Any, **kwargs: Any) -> Any:
        kwargs["env_options_overrides"] = {**(kwargs.get("env_options_overrides") or {}), **OPTIMISED}
        return test_options(*args, **kwargs)

    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.setattr(compiler, "get_compile_options", get_compile_options)
        try:
            yield
        finally:
            jax.clear_caches()


# --------------------------------------------------------------------------- KITTI odometry fixtures

FU, CU, FV, CV = 50.0, 15.5, 48.0, 9.5
"""The intrinsics of :func:`write_odometry`'s default 20×32 images."""
BASELINE_COLOUR = 0.54
BASELINE_GREY = 0.5


def fixture_poses(n: int, seed: int = 0, step: float = 1.0) -> np.ndarray:
    """Camera-to-world poses driving forward (+z) with small random rotations."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(1, n):
        rel = np.eye(4)
        rel[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix()
        rel[:3, 3] = [0.0, 0.0, step]
        poses[k] = poses[k - 1] @ rel
    return poses


def projection_row(fu: float, cu: float, fv: float, cv: float, tx: float) -> str:
    p = np.array([[fu, 0, cu, tx], [0, fv, cv, 0], [0, 0, 1, 0]])
    return " ".join(f"{v:.12e}" for v in p.ravel())


def write_odometry(
    root: Path, name: str = "00", n: int = 6, size: tuple[int, int] = (20, 32), seed: int = 0,
    poses: np.ndarray | None = None,
) -> dict:
    """A tiny KITTI odometry sequence: colour and grey pairs, calib.txt, times.txt, poses/XX.txt.

    Returns what was written (images as RGB uint8, poses, times) for comparisons.
    """
    rng = np.random.default_rng(seed)
    seq = root / "sequences" / name
    images = {}
    for cam in (0, 1, 2, 3):
        folder = seq / f"image_{cam}"
        folder.mkdir(parents=True)
        shape = size if cam < 2 else (*size, 3)
        images[cam] = rng.integers(0, 256, size=(n, *shape), dtype=np.uint8)
        for k in range(n):
            img = images[cam][k] if cam < 2 else cv2.cvtColor(images[cam][k], cv2.COLOR_RGB2BGR)
            assert cv2.imwrite(str(folder / f"{k:06d}.png"), img)
    # FU, CU, FV, CV describe the default 20×32 images; other sizes get them scaled (pixel centres at
    # integers), as a calibration must fit its images (dpc_jax.data.kitti.check_intrinsics).
    sx, sy = size[1] / 32, size[0] / 20
    fu, cu, fv, cv = FU * sx, (CU + 0.5) * sx - 0.5, FV * sy, (CV + 0.5) * sy - 0.5
    calib = [
        f"P0: {projection_row(fu, cu, fv, cv, 0.0)}",
        f"P1: {projection_row(fu, cu, fv, cv, -fu * BASELINE_GREY)}",
        f"P2: {projection_row(fu, cu, fv, cv, fu * 0.06)}",
        f"P3: {projection_row(fu, cu, fv, cv, fu * (0.06 - BASELINE_COLOUR))}",
        "Tr: " + " ".join(["0"] * 12),
    ]
    (seq / "calib.txt").write_text("\n".join(calib) + "\n")
    times = np.arange(n) * 0.1
    (seq / "times.txt").write_text("".join(f"{t:e}\n" for t in times))
    poses = fixture_poses(n, seed) if poses is None else poses
    (root / "poses").mkdir(exist_ok=True)
    np.savetxt(root / "poses" / f"{name}.txt", poses[:, :3, :].reshape(n, 12), fmt="%.12e")
    return {"images": images, "poses": poses, "times": times}


def write_fake_odometry(
    root: Path, names: Sequence[str], *, frames: int = 12, size: tuple[int, int] = (48, 72), seed: int = 0,
    prior_dir: Path | None = None, prior_noise: tuple[float, float] = (0.02, 0.002),
) -> Path:
    """A KITTI odometry tree rendered with ``dpc_jax.synth`` (one world per sequence) → ``root``, so the
    experiment entry points run end to end without KITTI.

    ``dpc_jax.synth.write_sequence`` writes ``sequences/XX/`` (images, ``calib.txt``,
    ``times.txt``) and ``poses/XX.txt``. With ``prior_dir``: priors in the libviso2 release's
    ``.mat`` layout — ``stereo_XX.mat`` (``poses_est`` = ground truth with each step perturbed by
    Gaussian noise of ``prior_noise`` = (m, rad) per axis; ``poses_gt``) and ``mono_XX.mat`` (the
    same steps with their translations scaled by 0.3, an arbitrary monocular scale).
    """
    import scipy.io

    from dpc_jax._io import atomic_write
    from dpc_jax.geometry.lie import se3_exp
    from dpc_jax.geometry.poses import compose, relative_poses
    from dpc_jax.synth import SynthConfig, sequence_poses, write_sequence

    rng = np.random.default_rng(seed)
    for k, name in enumerate(names):
        config = SynthConfig(frames=frames, height=size[0], width=size[1], seed=seed + 101 * k)
        write_sequence(root, name, config, overwrite=True)
        if prior_dir is None:
            continue
        poses = sequence_poses(config)[0]
        prior_dir.mkdir(parents=True, exist_ok=True)
        steps = relative_poses(poses)
        noise = np.concatenate([rng.normal(0, prior_noise[0], (len(steps), 3)),
                                rng.normal(0, prior_noise[1], (len(steps), 3))], axis=1)
        noisy = np.asarray(se3_exp(noise), np.float64) @ steps
        for kind, scale in (("stereo", 1.0), ("mono", 0.3)):
            scaled = noisy.copy()
            scaled[:, :3, 3] *= scale
            estimate = compose(scaled, poses[0])
            buffer = io.BytesIO()
            scipy.io.savemat(buffer, {
                "poses_est": np.moveaxis(estimate, 0, -1), "poses_gt": np.moveaxis(poses, 0, -1),
                "convention": "Twv",
            })
            atomic_write(prior_dir / f"{kind}_{name}.mat", buffer.getvalue())
    return root


# --------------------------------------------------------------------------- command lines

CACHE_SIZE = (10, 16)
"""The size of the tiny caches the command-line tests prepare (:func:`train_config`'s ``image_size``)."""


def dead_pid() -> int:
    """The pid of a process that has exited."""
    process = subprocess.Popen([sys.executable, "-c", ""])
    process.wait()
    return process.pid


def in_one_process(argvs: list[list[object]]) -> tuple[list[int], list[str], subprocess.CompletedProcess]:
    """Run each command line through ``dpc_jax.cli.main`` in one fresh interpreter: the exit
    statuses, which of jax/jaxlib/flax got imported, and the finished process (its stderr)."""
    texts = [[str(a) for a in argv] for argv in argvs]
    code = ("import json, sys; from dpc_jax.cli import main; "
            f"status = [main(argv) for argv in {texts!r}]; "
            "print(json.dumps([status, [m for m in ('jax', 'jaxlib', 'flax') if m in sys.modules]]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    status, imported = json.loads(done.stdout)
    return status, imported, done


def train_config(path: Path, cache_root: Path, **fields: object) -> None:
    """Write a valid training config file (a dict CONFIG) reading the caches under ``cache_root``."""
    config = {"method": "stereo_dpc", "preset": "small", "image_size": CACHE_SIZE, "batch_size": 2,
              "epochs": 1, "pose_warmup_epochs": 0, "cache_root": str(cache_root),
              "validation_sequences": ("05",), **fields}
    path.write_text(f"CONFIG = {config!r}\n")


# --------------------------------------------------------------------------- an analytic stereo scene
# A textured ground plane and a textured wall, seen by a rectified stereo rig, rendered with numpy and
# scipy only (the references of the warps and the losses).

_SCENE_HEIGHT, _SCENE_WIDTH = 48, 64
K_SCENE = np.array([[40.0, 0.0, 31.5], [0.0, 40.0, 23.5], [0.0, 0.0, 1.0]])
SCENE_BASELINE = 0.5
_GROUND_Y = 1.5  # world y points down: the ground lies 1.5 m below the first camera
_WALL_Z = 5.0


def camera_pose(translation: tuple[float, float, float], rotvec: tuple[float, float, float]) -> np.ndarray:
    """Camera-to-world 4×4 pose (float64)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


def _texture(points: np.ndarray) -> np.ndarray:
    """Smooth solid RGB texture in [0.15, 0.85] of world points ``[..., 3]``.

    A function of 3-D position, so it is continuous across the ground–wall crease.
    """
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    # Frequencies low enough (≤ 0.15 rad/pixel, also on the foreshortened ground near the wall)
    # that bilinear interpolation is accurate to ~1e-4.
    channels = [
        0.5 + 0.2 * np.sin(0.8 * x + 0.6 * y + 0.3 * z + phase) + 0.15 * np.cos(0.3 * z - 0.7 * x + 2 * phase)
        for phase in (0.0, 1.0, 2.5)
    ]
    return np.stack(channels, axis=-1)


def render_scene(T_w_c: np.ndarray, K: np.ndarray = K_SCENE) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the ground plane ``y = 1.5`` and the wall ``z = 5`` (a 48×64 image).

    Returns the image ``[H, W, 3]`` and the exact z-depth ``[H, W]`` of the camera, float64.
    """
    u, v = np.meshgrid(np.arange(_SCENE_WIDTH, dtype=np.float64), np.arange(_SCENE_HEIGHT, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z component 1
    directions = rays @ T_w_c[:3, :3].T
    origin = T_w_c[:3, 3]
    with np.errstate(divide="ignore"):
        s_ground = np.where(directions[..., 1] > 0, (_GROUND_Y - origin[1]) / directions[..., 1], np.inf)
        s_wall = np.where(directions[..., 2] > 0, (_WALL_Z - origin[2]) / directions[..., 2], np.inf)
    s = np.minimum(s_ground, s_wall)
    assert np.isfinite(s).all() and (s > 0).all()
    return _texture(origin + s[..., None] * directions), s


def right_of(T_w_left: np.ndarray) -> np.ndarray:
    """Pose of the right camera of the rig (at +B along the left camera's x)."""
    offset = np.eye(4)
    offset[0, 3] = SCENE_BASELINE
    return T_w_left @ offset


# --------------------------------------------------------------------------- tiny training

# The tiny network is the protocols' --smoke one (``dpc_jax.pipelines.protocol.SMOKE["model"]``, two
# blocks: compiles in seconds, enough to exercise every part of the loop), at its image size.
TINY_SIZE = (32, 48)


def make_caches(root: Path, names: list[str], n_frames: int = 12, flow: bool = False) -> Path:
    """Prepared caches of tiny textured sequences moving 1 m/frame forward, with ground truth (and with
    ``flow``, the optical flow ss-DPC-Net reads)."""
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.frames import ImageFiles
    from dpc_jax.data.kitti import StereoSequence

    h, w = TINY_SIZE
    K = np.array([[0.7 * w, 0, w / 2], [0, 0.7 * w, h / 2], [0, 0, 1.0]])
    rng = np.random.default_rng(0)
    for name in names:
        texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 2 * n_frames + 2, 3)), (5, 5), 1.5)
        folder = root / "images" / name
        folder.mkdir(parents=True)
        paths: dict[str, list[Path]] = {"l": [], "r": []}
        for i in range(n_frames):
            for cam, shift in (("l", 0), ("r", 2)):
                path = folder / f"{cam}{i:03d}.png"
                cv2.imwrite(str(path), texture[:, 2 * i + shift:2 * i + shift + w].astype(np.uint8))
                paths[cam].append(path)
        gt = np.tile(np.eye(4), (n_frames, 1, 1))
        gt[:, 2, 3] = np.arange(n_frames)
        prior = gt.copy()
        prior[:, 0, 3] += rng.normal(0, 0.01, n_frames)
        sequence = StereoSequence(name, ImageFiles(tuple(paths["l"]), tuple(paths["r"])), K, 0.5, TINY_SIZE,
                                  np.arange(n_frames) * 0.1, gt)
        prepare_sequence(sequence, prior, root / "cache", size=TINY_SIZE, flow=flow, progress=False,
                         workers=1)
    return root / "cache"


def tiny_config(cache_root: Path, **overrides: object) -> TrainConfig:
    """A training config of the tiny network on :func:`make_caches`' sequences (``02`` validates)."""
    from dpc_jax import config as config_lib
    from dpc_jax.pipelines.protocol import SMOKE
    from dpc_jax.training.train_config import TrainConfig

    fields = dict(method="stereo_dpc", preset="small", model=SMOKE["model"], image_size=TINY_SIZE,
                  batch_size=4, epochs=2, learning_rate=1e-3, steps_per_epoch=3, cache_root=str(cache_root),
                  validation_sequences=("02",), log_every=1)
    fields.update(overrides)
    return config_lib.from_dict(TrainConfig, fields)


@contextlib.contextmanager
def train_loss(function: Callable[..., Any]) -> Iterator[None]:
    """The train step with ``function(outputs, batch, config)`` in place of ``dpc_loss`` while this holds.

    A process keeps its compiled train steps (one per loss config, shared by runs of equal settings:
    ``dpc_jax.training.steps``), so they are dropped on entry, for the step to be traced with
    ``function``, and on exit, for no later run to get a program traced with it."""
    import pytest

    from dpc_jax.training import steps

    steps._compiled_step.cache_clear()
    try:
        with pytest.MonkeyPatch.context() as monkeypatch:
            monkeypatch.setattr(steps, "dpc_loss", function)
            yield
    finally:
        steps._compiled_step.cache_clear()


def cheap_loss(outputs: DPCOutputs, batch: Batch, config: object) -> tuple[jax.Array, dict[str, jax.Array]]:
    """A stand-in for ``dpc_loss`` that compiles fast, with a pose gradient that is not zero at ξ_corr = 0."""
    import jax.numpy as jnp

    pull = jnp.sum((outputs.xi_corr - 0.1) ** 2)
    value = jnp.mean(outputs.left.inv_depth) + jnp.mean(outputs.right.mask) + pull
    return value, {"xi_norm": jnp.sum(outputs.xi_corr**2)}


def se3_logs(poses: np.ndarray, step: int) -> np.ndarray:
    """se(3) logs ``[ρ, φ]`` of ``inv(T_{k+step}) T_k`` by scipy's matrix logarithm (float64)."""
    from scipy.linalg import logm

    out = []
    for a, b in zip(poses[:-step], poses[step:], strict=True):
        m = np.real(logm(np.linalg.inv(b) @ a))
        out.append([m[0, 3], m[1, 3], m[2, 3], m[2, 1], m[0, 2], m[1, 0]])
    return np.asarray(out)


# --------------------------------------------------------------------------- a stored training run


def write_stored_run(
    folder: Path, config: Any, epochs: dict[int, tuple[int, float, int, float]]
) -> dict[int, Any]:
    """A run folder as ``dpc-jax train`` writes it, with each epoch's network initialised from a seed instead
    of trained: ``epochs`` maps epoch → ``(seed, val gradient loss, val loop closures, val Δ)``. Returns the
    models by epoch. Writing the run directly keeps a test free of the training step's compilation."""
    from dpc_jax import config as config_lib
    from dpc_jax.nn.models import create_model
    from dpc_jax.training.checkpoints import Checkpoints
    from dpc_jax.training.optim import create_train_state, make_optimizer

    config_lib.save_json(folder / "checkpoints" / "config.json", config)
    models = {}
    with Checkpoints(folder) as checkpoints:
        best = Checkpoints.best_records(None)
        for epoch, (seed, gradient_loss, loops, delta) in epochs.items():
            models[epoch] = create_model(config.method, config.model_config(), seed)
            _, state = create_train_state(models[epoch], make_optimizer(config, 1))
            metrics = {"val_gradient_loss": gradient_loss, "val_loop_closures": loops, "val_delta": delta}
            best = checkpoints.save(epoch, state, {"step": epoch, "metrics": metrics}, best)
    return models
