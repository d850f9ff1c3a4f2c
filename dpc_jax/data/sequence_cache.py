"""The prepared sequence cache's on-disk format and its reader: file names, :class:`SequenceCache`,
:func:`load_cache`.

A cache folder ``OUT/NAME/`` is written by :func:`~dpc_jax.data.cache.prepare_sequence` (its
docstring has the table of the arrays); :func:`load_cache` memory-maps it and checks every file
against ``manifest.json``. This module imports no JAX (nor OpenCV): numpy, json and the trajectory
checks of :mod:`dpc_jax.data.poses_io` only, so the command line checks a cache before it starts JAX.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dpc_jax.data.poses_io import validate_poses
from dpc_jax.data.splits import training_names

MANIFEST = "manifest.json"
FLOW_FILES = {
    "forward": "flow.npy",
    "reverse": "flow_reverse.npy",
    "skip": "flow_skip.npy",
    "skip_reverse": "flow_skip_reverse.npy",
}
# StereoSGBM inverse depth of both cameras and its validity (dpc_jax.data.stereo_depth), when prepared.
STEREO_DEPTH_FILES = ("stereo_inverse_depth.npy", "stereo_valid.npy")
# Pair kind → (frame step, backward): see :mod:`dpc_jax.data.pipeline`.
PAIR_KINDS = {"forward": (1, False), "reverse": (1, True), "skip": (2, False), "skip_reverse": (2, True)}


@dataclass(frozen=True)
class SequenceCache:
    """A prepared sequence, memory-mapped (see :mod:`dpc_jax.data.cache` for the arrays)."""

    path: Path
    name: str
    left: np.ndarray
    right: np.ndarray
    prior: np.ndarray
    gt: np.ndarray | None
    K: np.ndarray
    baseline: float
    indices: np.ndarray
    times: np.ndarray
    flows: dict[str, np.ndarray]
    manifest: dict
    # (inverse depth float32 [N, 2, H, W] 1/m, valid bool [N, 2, H, W]), camera axis (left, right);
    # None in a cache prepared without it.
    stereo_depth: tuple[np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return int(self.left.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.left.shape[1]), int(self.left.shape[2])


class CacheError(ValueError):
    """A cache folder whose files disagree with its manifest (or are unreadable); names the file."""


_MANIFEST_KEYS = {"name": str, "n_frames": int, "image_size": list, "has_gt": bool, "flows": list}


def _read_manifest(path: Path) -> dict:
    try:
        manifest = json.loads(path.read_text())
    except UnicodeDecodeError:
        raise CacheError(f"{path}: not a text file; expected the JSON manifest of the cache") from None
    except json.JSONDecodeError as error:
        raise CacheError(f"{path}: not valid JSON ({error}); prepare the cache again") from None
    if not isinstance(manifest, dict):
        raise CacheError(f"{path}: expected a JSON object, got {type(manifest).__name__}")
    for key, kind in _MANIFEST_KEYS.items():
        if not isinstance(manifest.get(key), kind):
            raise CacheError(
                f"{path}: field {key!r} is missing or not a {kind.__name__}; prepare the cache again"
            )
    size = manifest["image_size"]
    if len(size) != 2 or not all(isinstance(v, int) and v > 0 for v in size) or manifest["n_frames"] < 2:
        raise CacheError(
            f"{path}: expected image_size [H, W] and n_frames >= 2, got {size} and {manifest['n_frames']}"
        )
    unknown = [kind for kind in manifest["flows"] if kind not in FLOW_FILES]
    if unknown:
        raise CacheError(f"{path}: unknown flow kind(s) {unknown}; expected some of {list(FLOW_FILES)}")
    return manifest


def _load_array(
    path: Path, manifest_path: Path, shape: tuple[int, ...], dtype: str, mmap: bool = False
) -> np.ndarray:
    """Load ``path`` and check it against the manifest's ``shape`` and ``dtype``, naming the file."""
    if not path.is_file():
        raise CacheError(f"{path}: missing from the cache (listed in {manifest_path}); prepare it again")
    try:
        array = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError) as error:
        raise CacheError(
            f"{path}: unreadable or truncated .npy file ({error}); prepare the cache again"
        ) from None
    if array.shape != shape or array.dtype != np.dtype(dtype):
        raise CacheError(
            f"{path}: {array.dtype} {array.shape}, but {manifest_path} says {np.dtype(dtype)} {shape}"
        )
    return array


def _check_finite_poses(path: Path, poses: np.ndarray) -> None:
    """Finite, rigid camera-to-world poses (the check of the trajectory readers), naming the file."""
    finite = np.isfinite(poses).all(axis=(1, 2))
    if not finite.all():
        raise CacheError(
            f"{path}: pose {int(np.argmin(finite))} is not finite (NaN or inf); prepare the cache again"
        )
    try:
        validate_poses(poses, source=str(path))
    except ValueError as error:
        raise CacheError(str(error)) from None


def load_cache(path: str | os.PathLike[str]) -> SequenceCache:
    """Memory-map the cache folder ``path`` written by :func:`~dpc_jax.data.cache.prepare_sequence`.

    Everything is checked against ``manifest.json`` before it is used: the manifest itself (valid
    JSON with the expected fields), the shape and dtype of every array (a truncated ``.npy`` does
    not load), finite and rigid prior and ground-truth poses, finite intrinsics, baseline and
    times. Raises ``FileNotFoundError`` when the folder has no manifest (not a cache, or an
    interrupted prepare) and :class:`CacheError` (a ``ValueError``) naming the file otherwise.
    """
    path = Path(path)
    manifest_path = path / MANIFEST
    if not manifest_path.is_file():
        raise FileNotFoundError(f"{path}: not a prepared cache (no {MANIFEST}); run `dpc-jax prepare`")
    manifest = _read_manifest(manifest_path)
    n = manifest["n_frames"]
    h, w = manifest["image_size"]

    def array(file: str, shape: tuple[int, ...], dtype: str, mmap: bool = False) -> np.ndarray:
        return _load_array(path / file, manifest_path, shape, dtype, mmap)

    left = array("left.npy", (n, h, w, 3), "uint8", mmap=True)
    right = array("right.npy", (n, h, w, 3), "uint8", mmap=True)
    flows = {
        kind: array(FLOW_FILES[kind], (n - PAIR_KINDS[kind][0], 2, h, w, 2), "float32", mmap=True)
        for kind in manifest["flows"]
    }
    stereo_depth = None
    if manifest.get("stereo_depth"):
        inverse, valid = (array(f, (n, 2, h, w), dtype, mmap=True)
                          for f, dtype in zip(STEREO_DEPTH_FILES, ("float32", "bool"), strict=True))
        stereo_depth = (inverse, valid)
    prior = array("prior.npy", (n, 4, 4), "float64")
    _check_finite_poses(path / "prior.npy", prior)
    gt = None
    if manifest["has_gt"]:
        gt = array("gt.npy", (n, 4, 4), "float64")
        _check_finite_poses(path / "gt.npy", gt)
    K = array("K.npy", (3, 3), "float64")
    baseline = array("baseline.npy", (), "float64")
    times = array("times.npy", (n,), "float64")
    indices = array("indices.npy", (n,), "int64")
    for file, values in (("K.npy", K), ("baseline.npy", baseline), ("times.npy", times)):
        if not np.isfinite(values).all():
            raise CacheError(
                f"{path / file}: holds a value that is not finite (NaN or inf); prepare the cache again"
            )
    return SequenceCache(
        path=path,
        name=manifest["name"],
        left=left,
        right=right,
        prior=prior,
        gt=gt,
        K=K,
        baseline=float(baseline),
        indices=indices,
        times=times,
        flows=flows,
        manifest=manifest,
        stereo_depth=stereo_depth,
    )


def cached_sequences(cache_root: str | os.PathLike[str]) -> list[str]:
    """Names of the prepared sequences (folders with a manifest) under ``cache_root``, sorted.

    Raises ``ValueError`` when ``cache_root`` is not a directory.
    """
    root = Path(cache_root)
    if not root.is_dir():
        raise ValueError(
            f"cache_root {str(root)!r} is not a directory; prepare the data with `dpc-jax prepare`"
        )
    return sorted(d.name for d in root.iterdir() if (d / MANIFEST).is_file())


def training_sequences(
    cache_root: str | os.PathLike[str], train: Sequence[str], validation: Sequence[str], test: Sequence[str]
) -> list[str]:
    """The training sequences under ``cache_root``: ``train``, or when it is empty every cached
    sequence except the ``validation`` and ``test`` ones (the rule of ``TrainConfig.train_sequences``).

    Training reads these and the ``validation`` sequences (the ``test`` ones never). Raises
    ``ValueError`` for a named sequence that is not cached and for an empty training set; the
    caches themselves are not read (:func:`load_cache` checks them).
    """
    available = cached_sequences(cache_root)
    for role, names in (("train", train), ("validation", validation), ("test", test)):
        missing = [s for s in names if s not in available]
        if missing:
            raise ValueError(
                f"{role}_sequences {missing} are not prepared under {cache_root} (found {available})"
            )
    chosen = list(training_names(available, (*validation, *test), list(train) or None))
    if not chosen:
        raise ValueError(f"no training sequence under {cache_root} besides the validation and test ones")
    return chosen
