"""The prepared sequence cache's on-disk format and its reader: file names, :class:`SequenceCache`,
:func:`load_cache`.

A cache folder ``OUT/NAME/`` is written by :func:`~dpc_jax.data.cache.prepare_sequence` (its
docstring has the table of the arrays); :func:`load_cache` memory-maps it and checks every file
against ``manifest.json``. This module imports no JAX (nor OpenCV): numpy, json and the trajectory
checks of :mod:`dpc_jax.data.poses_io` only, so the command line checks a cache before it starts JAX.

The manifest records each array file's size and two SHA-256 digests, computed by the writer from
the bytes it writes (:class:`ArrayDigest`): of the whole file, and of its sample
(:func:`sample_ranges`: the whole file up to :data:`FULL_CHECK_BYTES`, which holds every pose,
time and intrinsics array of a sequence of up to 8,000 frames; else :data:`SAMPLE_BLOCKS` blocks of
:data:`SAMPLE_BLOCK` bytes spread evenly from the first to the last byte). Opening a cache checks
every file's size and sample digest (a few hundred KiB read per file, whatever its size); with
``verify`` it checks the whole file's digest, which reads every byte.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.data.poses_io import validate_poses
from dpc_jax.data.splits import training_names

MANIFEST = "manifest.json"
# The format written by dpc_jax.data.cache.prepare_sequence; a cache of another version is refused.
# Version 2 stores SGBM's fixed-point disparity and fixed-point flow as int16 (version 1: float32);
# version 3 adds the size and digests of every array file (manifest["arrays"]).
CACHE_VERSION = 3
# Files up to this size are checked whole on every open; larger ones by a sample (module docstring).
FULL_CHECK_BYTES = 1 << 20
SAMPLE_BLOCK = 4096
SAMPLE_BLOCKS = 64
FLOW_FILES = {
    "forward": "flow.npy",
    "reverse": "flow_reverse.npy",
    "skip": "flow_skip.npy",
    "skip_reverse": "flow_skip_reverse.npy",
}
# StereoSGBM disparity of both cameras (dpc_jax.data.stereo_depth), when prepared.
DISPARITY_FILE = "stereo_disparity.npy"
# StereoSGBM's fixed point: disparities are integers in 1/16 px, and ≤ 0 where no match was found.
DISPARITY_UNITS = 16
# Pair kind → (frame step, backward): see :mod:`dpc_jax.data.pipeline`.
PAIR_KINDS = {"forward": (1, False), "reverse": (1, True), "skip": (2, False), "skip_reverse": (2, True)}


class Decoded:
    """A read-only array stored in a compact form and decoded where it is indexed.

    ``decoded[index]`` reads ``stored[index]`` (from a memory map: only the indexed frames) and
    returns ``decode`` of it, so an epoch never holds more than its batches in decoded form.
    ``shape`` is the stored shape (the decoders keep it); ``np.asarray`` decodes everything.
    """

    def __init__(self, stored: np.ndarray, decode: Callable[[np.ndarray], np.ndarray]) -> None:
        self.stored = stored
        self._decode = decode

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.stored.shape)

    def __len__(self) -> int:
        return int(self.stored.shape[0])

    def __getitem__(self, index: Any) -> np.ndarray:
        return self._decode(np.asarray(self.stored[index]))

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        decoded = self._decode(np.asarray(self.stored))
        return decoded if dtype is None else decoded.astype(dtype)


# What the readers index: a numpy array (or memory map), or a compact one decoded on indexing.
Frames = np.ndarray | Decoded
# (inverse depth float32 [N, camera, H, W] 1/m, valid bool [N, camera, H, W]) of every frame.
StereoDepth = tuple[Frames, Frames]


def flow_step(size: tuple[int, int]) -> float:
    """Pixels per unit of the stored int16 flow of images of ``size = (H, W)``: a power of two such
    that ±32767 units cover ±(the next power of two ≥ max(H, W)) px, i.e. any flow that stays in
    the image; 1/64 px at 240×376, a rounding error of at most 1/128 px."""
    return 2.0 ** math.ceil(math.log2(max(size))) / 32768.0


def encode_flow(flow: np.ndarray, step: float) -> np.ndarray:
    """float flow (px) → int16 units of ``step`` px (:func:`flow_step`), rounded to nearest; flow
    beyond the range (it points out of the image) is clipped."""
    return np.clip(np.rint(flow / step), -32767, 32767).astype(np.int16)


def decode_flow(units: np.ndarray, step: float) -> np.ndarray:
    """int16 flow units → float32 px (the inverse of :func:`encode_flow` up to its rounding)."""
    return units.astype(np.float32) * np.float32(step)


def inverse_depth_from_disparity(fixed: np.ndarray, focal_baseline: float) -> np.ndarray:
    """SGBM's fixed-point disparity (int16, 1/16 px) → float32 inverse depth ``d / (fu·B)`` (1/m),
    0 where there is no match (``d ≤ 0``); same shape. ``focal_baseline``: fu (px) times B (m)."""
    disparity = fixed.astype(np.float32) / np.float32(DISPARITY_UNITS)
    return np.where(disparity > 0.0, disparity / focal_baseline, 0.0).astype(np.float32)


def disparity_valid(fixed: np.ndarray) -> np.ndarray:
    """Where SGBM's fixed-point disparity holds a match (bool, same shape)."""
    return fixed > 0


def stereo_depth_views(fixed: np.ndarray, focal_baseline: float) -> tuple[Decoded, Decoded]:
    """``(inverse depth, valid)`` views of stored fixed-point disparity ``[N, camera, H, W]``, each
    decoded where indexed (float32 1/m and bool; :func:`inverse_depth_from_disparity`)."""
    return (Decoded(fixed, lambda d: inverse_depth_from_disparity(d, focal_baseline)),
            Decoded(fixed, disparity_valid))


def sample_ranges(size: int) -> list[tuple[int, int]]:
    """The byte ranges ``[start, stop)`` of a file of ``size`` bytes whose digest an open checks:
    the whole file up to :data:`FULL_CHECK_BYTES`, else :data:`SAMPLE_BLOCKS` blocks of
    :data:`SAMPLE_BLOCK` bytes, the first at byte 0 (the ``.npy`` header), the last ending at the end."""
    if size <= FULL_CHECK_BYTES:
        return [(0, size)]
    last = size - SAMPLE_BLOCK
    starts = [round(i * last / (SAMPLE_BLOCKS - 1)) for i in range(SAMPLE_BLOCKS)]
    return [(start, start + SAMPLE_BLOCK) for start in starts]


class ArrayDigest:
    """The size and digests a manifest records of one file of ``size`` bytes, computed from its bytes
    as they are written (:meth:`update`, in order), so the writer reads nothing back."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.offset = 0
        self._whole = hashlib.sha256()
        self._sample = hashlib.sha256()
        self._ranges = sample_ranges(size)

    def update(self, data: bytes | memoryview) -> None:
        """The next ``len(data)`` bytes of the file."""
        end = self.offset + len(data)
        self._whole.update(data)
        for start, stop in self._ranges:
            if start < end and stop > self.offset:
                self._sample.update(data[max(start, self.offset) - self.offset:min(stop, end) - self.offset])
        self.offset = end

    def record(self) -> dict[str, int | str]:
        """``{"bytes", "sha256", "sample_sha256"}`` of the file, once all its bytes were given."""
        if self.offset != self.size:
            raise RuntimeError(f"{self.offset} bytes digested of a file of {self.size}")
        return {"bytes": self.size, "sha256": self._whole.hexdigest(),
                "sample_sha256": self._sample.hexdigest()}


def file_record(path: str | os.PathLike[str]) -> dict[str, int | str]:
    """The manifest's record (:class:`ArrayDigest`) of the file at ``path``, read whole: for a file
    written by other means than the cache writers (a benchmark's random cache)."""
    digest = ArrayDigest(os.path.getsize(path))
    with open(path, "rb") as file:
        for chunk in iter(lambda: file.read(1 << 20), b""):
            digest.update(chunk)
    return digest.record()


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
    flows: dict[str, Frames]  # float32 px where indexed (stored as int16, :func:`decode_flow`)
    manifest: dict
    # (inverse depth float32 [N, 2, H, W] 1/m, valid bool [N, 2, H, W]) where indexed, camera axis
    # (left, right), decoded from the stored disparity; None in a cache prepared without it.
    stereo_depth: StereoDepth | None = None

    def __len__(self) -> int:
        return int(self.left.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.left.shape[1]), int(self.left.shape[2])


class CacheError(ValueError):
    """A cache folder whose files disagree with its manifest (or are unreadable); names the file."""


_MANIFEST_KEYS = {"name": str, "n_frames": int, "image_size": list, "has_gt": bool, "flows": list,
                  "arrays": dict}


class NewerCacheError(CacheError):
    """A cache written by a newer dpc_jax: neither read nor rebuilt over (the dpc_jax that wrote it reads
    it)."""


def read_manifest(folder: str | os.PathLike[str]) -> dict:
    """The manifest of the cache ``folder``, checked: the one reader of ``manifest.json``, for the caches'
    reader (:func:`load_cache`), their writer (which reuses a cache of the same input hash and never
    replaces a newer one) and the command line (:func:`newer_cache_problem`).

    Valid JSON, an object, of this format version, with the fields every reader needs. Raises
    ``FileNotFoundError`` when ``folder`` has no manifest (not a cache, or an interrupted prepare),
    :class:`NewerCacheError` for a cache of a newer format and :class:`CacheError` otherwise, naming
    the file."""
    path = Path(folder) / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"{folder}: not a prepared cache (no {MANIFEST}); run `dpc-jax prepare`")
    try:
        manifest = json.loads(path.read_text())
    except UnicodeDecodeError:
        raise CacheError(f"{path}: not a text file; expected the JSON manifest of the cache") from None
    except json.JSONDecodeError as error:
        raise CacheError(f"{path}: not valid JSON ({error}); prepare the cache again") from None
    if not isinstance(manifest, dict):
        raise CacheError(f"{path}: expected a JSON object, got {type(manifest).__name__}")
    version = manifest.get("version")
    if isinstance(version, int) and not isinstance(version, bool) and version > CACHE_VERSION:
        raise NewerCacheError(
            f"{path}: this cache was written by a newer dpc_jax (cache format version {version}; this one "
            f"reads version {CACHE_VERSION} and does not replace it); use that dpc_jax, or prepare into "
            "another folder")
    if version != CACHE_VERSION:
        raise CacheError(
            f"{path}: cache format version {version}, this dpc_jax reads version "
            f"{CACHE_VERSION}; run the same `dpc-jax prepare` again to rebuild it"
        )
    if manifest.get("flows") and not (isinstance(manifest.get("flow_step"), float)
                                      and manifest["flow_step"] > 0):
        raise CacheError(f"{path}: field 'flow_step' is missing or not a positive number; "
                         "prepare the cache again")
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


def newer_cache_problem(folder: str | os.PathLike[str]) -> str | None:
    """Why a writer must not replace the cache ``folder``, written by a newer dpc_jax
    (:class:`NewerCacheError`), or None: also when it holds no manifest, or one this dpc_jax cannot read
    (such a folder is rebuilt)."""
    try:
        read_manifest(folder)
    except NewerCacheError as error:
        return str(error)
    except (OSError, CacheError):
        return None
    return None


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


def _check_bytes(path: Path, manifest_path: Path, record: Any, verify: bool) -> None:
    """Check the file at ``path`` against its ``record`` in the manifest (:class:`ArrayDigest`): its
    size, and the digest of its sample, or with ``verify`` of all its bytes; names the file."""
    if not (isinstance(record, dict) and isinstance(record.get("bytes"), int)
            and all(isinstance(record.get(key), str) for key in ("sha256", "sample_sha256"))):
        raise CacheError(f"{manifest_path}: field 'arrays' holds no size and digests of {path.name}; "
                         "prepare the cache again")
    size = path.stat().st_size
    if size != record["bytes"]:
        raise CacheError(f"{path}: {size} bytes, but {manifest_path} says {record['bytes']}; the file was "
                         "changed or damaged since it was prepared: prepare the cache again")
    digest = hashlib.sha256()
    with path.open("rb") as file:
        if verify:
            for chunk in iter(lambda: file.read(1 << 20), b""):
                digest.update(chunk)
        else:
            for start, stop in sample_ranges(size):
                file.seek(start)
                digest.update(file.read(stop - start))
    if digest.hexdigest() != record["sha256" if verify else "sample_sha256"]:
        what = "its bytes differ" if verify or size <= FULL_CHECK_BYTES else "a sample of its bytes differs"
        raise CacheError(f"{path}: {what} from those `dpc-jax prepare` wrote (SHA-256 in {manifest_path}); "
                         "the file was changed or damaged since: prepare the cache again")


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


def load_cache(path: str | os.PathLike[str], *, verify: bool = False) -> SequenceCache:
    """Memory-map the cache folder ``path`` written by :func:`~dpc_jax.data.cache.prepare_sequence`.

    Everything is checked against ``manifest.json`` before it is used: the manifest itself
    (:func:`read_manifest`), the shape and dtype of every array (a
    truncated ``.npy`` does not load), finite and rigid prior and ground-truth poses, finite
    intrinsics, baseline and times, and then every file's bytes: its size and the digest of its
    sample, or with ``verify`` of every byte (module docstring). Raises ``FileNotFoundError`` when
    the folder has no manifest (not a cache, or an interrupted prepare) and :class:`CacheError` (a
    ``ValueError``) naming the file otherwise.
    """
    path = Path(path)
    manifest_path = path / MANIFEST
    manifest = read_manifest(path)
    n = manifest["n_frames"]
    h, w = manifest["image_size"]

    loaded: list[str] = []

    def array(file: str, shape: tuple[int, ...], dtype: str, mmap: bool = False) -> np.ndarray:
        loaded.append(file)
        return _load_array(path / file, manifest_path, shape, dtype, mmap)

    left = array("left.npy", (n, h, w, 3), "uint8", mmap=True)
    right = array("right.npy", (n, h, w, 3), "uint8", mmap=True)
    step = float(manifest.get("flow_step", 1.0))
    flows: dict[str, Frames] = {
        kind: Decoded(array(FLOW_FILES[kind], (n - PAIR_KINDS[kind][0], 2, h, w, 2), "int16", mmap=True),
                      functools.partial(decode_flow, step=step))
        for kind in manifest["flows"]
    }
    disparity = None
    if manifest.get("stereo_depth"):
        disparity = array(DISPARITY_FILE, (n, 2, h, w), "int16", mmap=True)
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
    # Last: what the checks above name more precisely (a truncated file, a NaN pose) is said so.
    for file in loaded:
        _check_bytes(path / file, manifest_path, manifest["arrays"].get(file), verify)
    stereo_depth = None
    if disparity is not None:
        # The product prepare matched with (dpc_jax.data.cache_products), from the same stored values.
        stereo_depth = stereo_depth_views(disparity, float(K[0, 0]) * float(baseline))
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
