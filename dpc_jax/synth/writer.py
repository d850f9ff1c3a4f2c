"""Write synthetic sequences in the KITTI odometry layout (the shell around :mod:`sequence`).

``OUT/`` receives::

    sequences/XX/image_2/NNNNNN.png    left RGB (PNG, written for cv2's BGR order, so it reads back RGB)
    sequences/XX/image_3/NNNNNN.png    right RGB
    sequences/XX/depth_2/NNNNNN.npy    left z-depth, float32 [H, W], metres, inf where the sky is seen
    sequences/XX/depth_3/NNNNNN.npy    right z-depth
    sequences/XX/moving_2/NNNNNN.png   uint8 mask, 255 where a pixel shows an independently moving car
    sequences/XX/moving_3/NNNNNN.png
    sequences/XX/calib.txt             P0..P3 (3×4, row-major) and Tr, as in KITTI
    sequences/XX/times.txt             one timestamp (s) per frame, 10 Hz
    sequences/XX/synth.json            the generating configuration
    poses/XX.txt                       12 numbers per frame: left-camera-to-world [R|t], first = identity

``calib.txt``: ``P2 = K [I | 0]`` (left colour camera) and ``P3 = K [I | −B e_x]`` (right colour
camera, ``P3[0, 3] = −fu·B``), so that ``baseline = (P2[0, 3] − P3[0, 3]) / fu`` as for KITTI; the
grey pair is written identical (``P0 = P2``, ``P1 = P3``) because the images are the same cameras;
``Tr`` (velodyne → camera in KITTI) is the identity. Sequence ``XX`` (00, 01, ...) is rendered with
seed ``seed + XX``. Every sequence is rendered into a temporary directory beside its final place
(``sequences/.XX.tmp-<pid>-<random>``) and renamed when complete; ``poses/XX.txt`` is written
atomically too. The temporary folders of a killed run are removed by the next run writing into
the same ``OUT`` (those of a run still going are left alone); an interrupted or failed run removes
the folders it made that are still empty.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from dpc_jax._io import atomic_write, install_folder, new_folders_removed_on_failure, remove_stale, temp_name
from dpc_jax.runtime.progress import Progress, progress_bar
from dpc_jax.synth.sequence import SynthConfig, iter_frames, kitti_intrinsics, sequence_poses


def _fmt(values: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(values, np.float64).ravel())


def calib_text(K: np.ndarray, baseline: float) -> str:
    """KITTI ``calib.txt`` contents for a rectified pair (see the module docstring)."""
    p_left = np.concatenate([K, np.zeros((3, 1))], 1)
    p_right = p_left.copy()
    p_right[0, 3] = -K[0, 0] * baseline
    rows = {"P0": p_left, "P1": p_right, "P2": p_left, "P3": p_right, "Tr": np.eye(4)[:3]}
    return "".join(f"{name}: {_fmt(m)}\n" for name, m in rows.items())


def _imwrite(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


def _save(path: Path, array: np.ndarray) -> None:
    """``np.save``, whose error on a full disk ("6144 requested and 3040 written") names no file."""
    try:
        np.save(path, array)
    except OSError as error:
        raise OSError(f"could not write {path} ({error})") from None


def write_sequence(out: Path | str, name: str, config: SynthConfig, overwrite: bool = False,
                   on_frame: Callable[[], None] | None = None) -> Path:
    """Render ``config`` and write it as sequence ``name`` under ``out`` (KITTI layout).

    Returns the sequence directory. Raises ``FileExistsError`` if it exists and not ``overwrite``.
    ``on_frame`` is called after each frame (progress reporting).
    """
    out = Path(out)
    seq_dir = out / "sequences" / name
    if seq_dir.exists() and not overwrite:
        raise FileExistsError(f"{seq_dir} already exists (use overwrite to replace it)")
    made = [folder for folder in (out / "sequences", out / "poses") if not folder.is_dir()]
    (out / "sequences").mkdir(parents=True, exist_ok=True)
    (out / "poses").mkdir(parents=True, exist_ok=True)
    for kind in ("tmp", "old"):
        remove_stale(out / "sequences", f".{name}.{kind}-")
    tmp = out / "sequences" / temp_name(f".{name}.tmp-")
    dirs = {d: tmp / d for d in ("image_2", "image_3", "depth_2", "depth_3", "moving_2", "moving_3")}
    try:
        for d in dirs.values():
            d.mkdir(parents=True)
        for frame in iter_frames(config):
            stem = f"{frame.index:06d}"
            _imwrite(dirs["image_2"] / f"{stem}.png", frame.left[..., ::-1])
            _imwrite(dirs["image_3"] / f"{stem}.png", frame.right[..., ::-1])
            _save(dirs["depth_2"] / f"{stem}.npy", frame.depth_left)
            _save(dirs["depth_3"] / f"{stem}.npy", frame.depth_right)
            _imwrite(dirs["moving_2"] / f"{stem}.png", frame.moving_left.astype(np.uint8) * 255)
            _imwrite(dirs["moving_3"] / f"{stem}.png", frame.moving_right.astype(np.uint8) * 255)
            if on_frame is not None:
                on_frame()
        poses, times, _, _ = sequence_poses(config)
        K = kitti_intrinsics(config.height, config.width)
        (tmp / "calib.txt").write_text(calib_text(K, config.baseline))
        (tmp / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
        meta = {"generator": "dpc_jax.synth", "config": dataclasses.asdict(config),
                "depth": "float32 z-depth in metres, inf = sky", "poses": f"poses/{name}.txt"}
        (tmp / "synth.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        install_folder(tmp, seq_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for folder in made:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only where still empty
        raise
    atomic_write(out / "poses" / f"{name}.txt", "".join(_fmt(p[:3]) + "\n" for p in poses))
    return seq_dir


def is_rendered(out: Path | str, name: str, config: SynthConfig) -> bool:
    """Whether sequence ``name`` under ``out`` is a finished rendering of ``config``: its poses file (written
    last) is there and its ``synth.json`` holds this configuration (a changed world is rendered again)."""
    record = Path(out) / "sequences" / name / "synth.json"
    if not (record.is_file() and (Path(out) / "poses" / f"{name}.txt").is_file()):
        return False
    try:
        stored = json.loads(record.read_text()).get("config")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
        return False
    # Through JSON, as it was stored: tuples become lists.
    return bool(stored == json.loads(json.dumps(dataclasses.asdict(config))))


def _sequence_names(sequences: int) -> list[str]:
    if sequences < 1:
        raise ValueError(f"sequences must be >= 1, got {sequences}")
    return [f"{i:02d}" for i in range(sequences)]


def check_sequences_free(out: Path | str, sequences: int) -> None:
    """Raise ``FileExistsError`` naming those of the sequences ``00, 01, ...`` (``sequences`` of them)
    that already exist under ``out``, as :func:`write_sequences` does without ``overwrite``; the
    command line calls it before it imports JAX."""
    existing = [n for n in _sequence_names(sequences) if (Path(out) / "sequences" / n).exists()]
    if existing:
        raise FileExistsError(f"{Path(out) / 'sequences'} already holds sequence(s) {', '.join(existing)}")


def write_sequences(out: Path | str, config: SynthConfig, sequences: int = 4, overwrite: bool = False,
                    progress: Progress = None) -> list[Path]:
    """Write ``sequences`` sequences ``00, 01, ...`` (seeds ``config.seed + i``) under ``out``.

    ``progress``: a tqdm bar over all frames (default: only when stderr is a terminal), or
    ``"lines"`` for plain progress lines (see :mod:`dpc_jax.runtime.progress`).
    """
    out = Path(out)
    names = _sequence_names(sequences)
    if not overwrite:
        check_sequences_free(out, sequences)
    paths = []
    # Interrupted before a sequence is complete, the run leaves no folder it made behind.
    total = sequences * config.frames
    with new_folders_removed_on_failure(out), progress_bar(total, "synth", progress) as bar:
        for i, name in enumerate(names):
            bar.set_postfix(sequence=name)
            cfg = dataclasses.replace(config, seed=config.seed + i)
            paths.append(write_sequence(out, name, cfg, overwrite=overwrite, on_frame=lambda: bar.update(1)))
    return paths
