"""Preprocessing cache: decoded, resized stereo frames, flow and poses as memory-mappable arrays.

``prepare_sequence`` turns a :class:`~dpc_jax.data.kitti.StereoSequence` and its VO prior into a
folder ``OUT/NAME/`` that the input pipeline memory-maps, so an epoch never decodes a PNG (the file
names and the reader, :func:`~dpc_jax.data.sequence_cache.load_cache`, are in
:mod:`dpc_jax.data.sequence_cache`):

====================  ===================  ==================================================
file                  array                meaning
====================  ===================  ==================================================
``left.npy``          uint8 [N, H, W, 3]   left RGB frames, resized with ``cv2.INTER_AREA``
``right.npy``         uint8 [N, H, W, 3]   right RGB frames
``prior.npy``         float64 [N, 4, 4]    VO prior, camera-to-world (rescaled if asked)
``gt.npy``            float64 [N, 4, 4]    ground truth (only when known)
``K.npy``             float64 [3, 3]       intrinsics of the resized images
``baseline.npy``      float64 []           stereo baseline (m)
``indices.npy``       int64 [N]            frame numbers in the source sequence (kept frames)
``times.npy``         float64 [N]          frame times (s)
``flow.npy``          int16 [N-1,2,H,W,2]  Farnebäck flow k → k+1, left (0) and right (1)
``flow_reverse.npy``  int16 [N-1,2,H,W,2]  flow k+1 → k (stored at index k)
``flow_skip.npy``     int16 [N-2,2,H,W,2]  flow k → k+2
``flow_skip_reverse.npy`` int16 [N-2,2,H,W,2]  flow k+2 → k (stored at index k)
``stereo_disparity.npy`` int16 [N,2,H,W]   StereoSGBM disparity, 1/16 px, left (0), right (1)
``manifest.json``     —                    sources, parameters, input hash, array shapes,
                                           each array file's size and SHA-256 digests
====================  ===================  ==================================================

Flow is stored in units of ``manifest["flow_step"]`` px (``dpc_jax.data.sequence_cache.flow_step``:
1/64 px at 240×376, so the rounding stays below 1/128 px) and
the disparity as the integers StereoSGBM computes (1/16 px, ≤ 0 where it found no match), so the
inverse depth ``d / (fu·B)`` that the readers decode is bit for bit what the matcher gives; both
take half the bytes of float32. The reader (:func:`~dpc_jax.data.sequence_cache.load_cache`)
decodes them where they are indexed and refuses a cache of another format version
(``manifest["version"]``) with the one line that says to prepare it again.

The stereo depth (``dpc_jax.data.stereo_depth``, on the stored pair) is what the acceptance test
measures a correction with by default; it is computed once here rather than by every run that
judges, adapts or validates on the sequence. The three augmentation flows exist only with
``flow_augment`` (needed when training with flow and frame-skip or reversed pairs). Flow channels
are ``[Δx column, Δy row]`` in pixels of the resized images, computed on their grey versions with
the Farnebäck parameters of docs/method.md §6.

Identity of the inputs (``manifest["input_hash"]``): SHA-256 over the cache format version, the
parameters, the calibration/time/pose/prior files by *content* (small), in-memory prior or
ground-truth arrays by content, and the images by what ``StereoFrames.identity`` gives: image files by
*path, size and modification time* — hashing gigabytes of PNGs on every run would cost more than the
check saves; a replaced image changes its mtime — and a recording by its files' path, size and
modification time with the topics and frames read. Re-running with the same hash finds the complete
cache and reuses it when
every file still reads as its manifest says (as ``load_cache`` checks it: shapes, poses, and each
file's size and the digest of its sample, or with ``verify`` of all its bytes), else rebuilds it.
The digests are computed from the bytes as they are written
(:class:`~dpc_jax.data.sequence_cache.ArrayDigest`), so recording them costs no extra pass. A cache of
a newer format version is refused, never rebuilt over. Images are never upsampled: a ``size`` larger
than the source images in either dimension is refused.

One writer per cache: the build holds the lock ``OUT/.NAME.lock`` (:func:`dpc_jax._io.output_lock`),
so two prepares of one cache cannot both write it; a second one is refused with the first's pid.

Atomicity: everything is written into a hidden temporary folder beside the target
(``.NAME.tmp-<pid>-<random>``), the manifest last, and the folder is renamed into place; a failure
removes the temporary folder, so an interrupted or failed prepare never leaves a folder that
:func:`~dpc_jax.data.sequence_cache.load_cache` accepts (it requires ``manifest.json``). The temporary
folders of a killed prepare (``kill -9``) are removed by the next prepare into the same root; those
of a prepare still running are left alone (see :func:`dpc_jax._io.remove_stale`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dpc_jax._io import atomic_write, install_folder, output_lock, remove_stale, temp_name
from dpc_jax.data.cache_products import FARNEBACK, ordered_map, save_array, write_frame_products
from dpc_jax.data.frames import StereoFrame
from dpc_jax.data.kitti import StereoSequence, read_ground_truth
from dpc_jax.data.poses_io import validate_poses
from dpc_jax.data.preparation import prepared_pair, resized_intrinsics
from dpc_jax.data.priors import load_prior, rescale_monocular
from dpc_jax.data.sequence_cache import (
    CACHE_VERSION,
    DISPARITY_FILE,
    FLOW_FILES,
    MANIFEST,
    CacheError,
    NewerCacheError,
    flow_step,
    load_cache,
    read_manifest,
)
from dpc_jax.data.stereo_depth import sgbm_fits
from dpc_jax.geometry.poses import remove_static_frames
from dpc_jax.runtime.progress import Progress

log = logging.getLogger(__name__)

DEFAULT_SIZE = (240, 376)


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def input_hash(
    sequence: StereoSequence,
    prior_source: str | Path | np.ndarray,
    parameters: dict,
    extra_arrays: Iterable[np.ndarray] = (),
) -> str:
    """SHA-256 identifying a cache's inputs (see the module docstring for what is hashed)."""
    h = hashlib.sha256()
    h.update(json.dumps({"version": CACHE_VERSION, "parameters": parameters}, sort_keys=True).encode())
    for path in sequence.sources:
        h.update(f"{Path(path).resolve()}:{_file_digest(Path(path))}".encode())
    if isinstance(prior_source, np.ndarray):
        h.update(np.ascontiguousarray(prior_source, dtype=np.float64).tobytes())
    else:
        h.update(f"{Path(prior_source).resolve()}:{_file_digest(Path(prior_source))}".encode())
    for array in extra_arrays:
        h.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    for text in sequence.images.identity():
        h.update(text.encode())
    return h.hexdigest()


def prepare_sequence(
    sequence: StereoSequence,
    prior: str | Path | np.ndarray,
    out_dir: str | Path,
    *,
    size: tuple[int, int] = DEFAULT_SIZE,
    remove_static: bool = False,
    flow: bool = False,
    flow_augment: bool = False,
    mono_rescale: bool = False,
    frames: tuple[int, int] | None = None,
    prior_format: str | None = None,
    ground_truth: str | Path | np.ndarray | None = None,
    name: str | None = None,
    disparity_offset: float = 0.0,
    half_pixel_intrinsics: bool = True,
    force: bool = False,
    verify: bool = False,
    progress: Progress = None,
    workers: int | None = None,
) -> Path:
    """Build (or find up to date) the cache ``out_dir/name`` of one sequence; return its path.

    * ``prior``: VO estimate of every frame of ``sequence`` (array or file, see
      :func:`~dpc_jax.data.priors.load_prior`; ``prior_format`` overrides the extension).
    * ``ground_truth``: replaces ``sequence.poses`` (array or pose file; ``.mat`` → ``poses_gt``).
      When the sequence has none and the prior is a ``.mat`` file, its ``poses_gt`` is used.
    * ``frames``: ``(start, stop)`` keeps only those source frames (before anything else).
    * ``size``: ``(H, W)`` of the stored images (INTER_AREA), K scaled accordingly
      (``dpc_jax.geometry.camera.scale_intrinsics``; ``half_pixel_intrinsics=False``: the reference code's
      rule, which leaves the principal point off by up to half a pixel).
    * ``mono_rescale``: rescale each prior step to the ground-truth step length (monocular VO);
      needs ground truth.
    * ``remove_static``: drop static frames by the ss-DPC-Net rule (docs/method.md §6) read on the
      *prior*, which exists at test time too (after ``mono_rescale`` when both are asked, so
      the 1.5 m threshold sees metric steps); the ground truth loses the same frames.
    * ``flow``: Farnebäck flow per consecutive kept pair; ``flow_augment`` adds the flows of the
      reversed and frame-skip pairs (implies ``flow``).
    * ``disparity_offset``: px at the source resolution, the rig's disparity calibration residual
      in the VO's convention (``d_true = d_measured + offset``, e.g. ``dpc-jax vo``'s online
      estimate): the right images are resampled at ``u + offset`` before resizing, so the stored
      pairs are rectified with the residual removed and their disparity is ``fu·B/Z``.
    * ``name``: folder name, default ``sequence.name``; ``force`` rebuilds even when up to date;
      ``verify`` reuses a cache only when every byte of every file matches its digest (default:
      its sizes and sampled digests, as every reader checks).
    * ``progress``: tqdm bars (default: when stderr is a terminal), or ``"lines"`` for plain
      progress lines (see :mod:`dpc_jax.runtime.progress`); ``workers``: decoding and flow threads
      (default: CPU count).

    Bad input (unreadable or differently sized images, prior or ground truth of the wrong length
    or not rigid, a prior recorded for other frames, a ``size`` larger than the images) raises
    ``ValueError``/``FileNotFoundError`` naming the file and frame, and no cache is written; a cache
    of a newer format at ``out_dir/name`` raises :class:`~dpc_jax.data.sequence_cache.CacheError`,
    and a cache being built by another process :class:`dpc_jax._io.LockError` (an ``OSError``).
    """
    out_dir = Path(out_dir)
    name = name or sequence.name
    workers = workers or os.cpu_count() or 1
    flow = flow or flow_augment
    size = (int(size[0]), int(size[1]))
    if size[0] < 8 or size[1] < 8:
        raise ValueError(f"image size {size} too small; expected (H, W) of at least 8×8")

    inputs = _load_inputs(sequence, prior, prior_format, ground_truth, frames, mono_rescale)
    source = inputs.sequence.image_size
    if size[0] > source[0] or size[1] > source[1]:
        raise ValueError(
            f"{sequence.name}: size {size[0]}x{size[1]} is larger than the source images "
            f"({source[0]}x{source[1]}); a cache is never upsampled: give at most {source[0]}x{source[1]}"
        )
    parameters = {
        "size": list(size), "remove_static": remove_static, "flow": flow, "flow_augment": flow_augment,
        "mono_rescale": mono_rescale, "frames": [inputs.start, inputs.stop], "prior_format": prior_format,
        "farneback": FARNEBACK if flow else None, "interpolation": "INTER_AREA",
        "disparity_offset": float(disparity_offset),
        "half_pixel_intrinsics": bool(half_pixel_intrinsics), "stereo_depth": "sgbm",
    }
    extra = [inputs.gt_source] if isinstance(inputs.gt_source, np.ndarray) else []
    digest = input_hash(inputs.sequence, prior, parameters, extra)
    target = out_dir / name
    with output_lock(target, name):
        try:
            existing = read_manifest(target)
        except NewerCacheError:
            raise
        except (FileNotFoundError, CacheError):  # none there, or one this dpc_jax does not read: built
            existing = None
        if not force and existing is not None and existing.get("input_hash") == digest:
            # Same inputs; reused only if every file still reads as the manifest says (what train and
            # correct check), else rebuilt: a truncated or edited file is not "up to date".
            try:
                load_cache(target, verify=verify)
            except (CacheError, FileNotFoundError) as error:
                log.warning("%s: rebuilding a damaged cache (%s)", target, error)
            else:
                log.info("%s: up to date (input hash %s)", target, digest[:12])
                return target
        _build(inputs, prior, target, digest, parameters, size=size, remove_static=remove_static,
               flow=flow, flow_augment=flow_augment, disparity_offset=disparity_offset,
               half_pixel_intrinsics=half_pixel_intrinsics, workers=workers, progress=progress)
    return target


def _build(
    inputs: _Inputs, prior: str | Path | np.ndarray, target: Path, digest: str, parameters: dict, *,
    size: tuple[int, int], remove_static: bool, flow: bool, flow_augment: bool, disparity_offset: float,
    half_pixel_intrinsics: bool, workers: int, progress: Progress,
) -> None:
    """Build the cache ``target`` (``OUT/NAME``) of ``inputs`` in a temporary folder beside it, then
    install it (module docstring); the arguments are :func:`prepare_sequence`'s."""
    name = target.name
    kept = _kept_frames(inputs, remove_static)
    K = resized_intrinsics(inputs.sequence.K, inputs.sequence.image_size, size, half_pixel_intrinsics)
    tmp = _new_temp_folder(target.parent, name)
    try:
        kinds = tuple(FLOW_FILES) if flow_augment else ("forward",) if flow else ()
        records = _write_arrays(
            tmp, inputs.sequence, kept, size, K, disparity_offset=disparity_offset, flow_kinds=kinds,
            label=name, workers=workers, progress=progress,
        )
        records |= _write_poses_and_calibration(tmp, inputs, kept, K)
        manifest = _manifest(tmp, name, inputs, prior, digest, parameters, kept, size, K, records)
        atomic_write(tmp / MANIFEST, json.dumps(manifest, indent=2))
        install_folder(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@dataclasses.dataclass(frozen=True)
class _Inputs:
    """The selected frames of a sequence with their poses, as :func:`_load_inputs` returns them."""

    sequence: StereoSequence  # frames [start, stop); sources include the ground-truth file if any
    prior_poses: np.ndarray  # float64 [N, 4, 4] camera-to-world, rescaled when mono_rescale
    gt: np.ndarray | None  # float64 [N, 4, 4], None when unknown
    gt_source: str | Path | np.ndarray | None  # None: the sequence's own poses (or none)
    start: int
    stop: int


def _load_inputs(
    sequence: StereoSequence,
    prior: str | Path | np.ndarray,
    prior_format: str | None,
    ground_truth: str | Path | np.ndarray | None,
    frames: tuple[int, int] | None,
    mono_rescale: bool,
) -> _Inputs:
    """Prior and ground truth of the frames ``[start, stop)``, the prior rescaled with ``mono_rescale``.

    Both are loaded and checked for every source frame before the cut, so a file of the wrong
    length is reported as such rather than silently sliced.
    """
    n_all = len(sequence)
    gt_source = ground_truth
    # ss-DPC-Net .mat priors carry the ground truth too (poses_gt); use it when nothing else has one.
    if gt_source is None and sequence.poses is None and not isinstance(prior, np.ndarray):
        if (prior_format or Path(prior).suffix.lstrip(".").lower()) == "mat":
            gt_source = prior
    gt_all = sequence.poses
    if gt_source is not None:
        gt_all = _load_ground_truth(gt_source, n_all)
    start, stop = frames if frames is not None else (0, n_all)
    prior_all = load_prior(prior, n_all, prior_format, frames=(start, stop))
    sequence = sequence.select(start, stop)
    # The whole sequence's prior, or that of the range alone (load_prior accepts both).
    prior_poses = prior_all[start:stop] if prior_all.shape[0] == n_all else prior_all
    gt = None if gt_all is None else gt_all[start:stop]
    if mono_rescale:
        if gt is None:
            raise ValueError(f"{sequence.name}: mono_rescale needs ground truth, and none was given")
        prior_poses = rescale_monocular(prior_poses, gt)
    # A ground-truth file is an input like the calibration: hashed by content and listed in the manifest.
    if gt_source is not None and not isinstance(gt_source, np.ndarray):
        sequence = dataclasses.replace(sequence, sources=(*sequence.sources, Path(gt_source)))
    return _Inputs(sequence, prior_poses, gt, gt_source, start, stop)


def _kept_frames(inputs: _Inputs, remove_static: bool) -> np.ndarray:
    """Indices into the selected frames that the cache stores, int64 ``[N]`` (at least 2)."""
    kept = np.arange(len(inputs.sequence))
    if remove_static:
        kept = np.asarray(remove_static_frames(inputs.prior_poses), dtype=np.int64)
        if kept.size < 2:
            raise ValueError(
                f"{inputs.sequence.name}: static-frame removal left {kept.size} frame(s); need 2"
            )
    return kept


def _new_temp_folder(out_dir: Path, name: str) -> Path:
    """A new empty hidden folder in ``out_dir`` to build the cache ``name`` in (module docstring)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    # Leftovers of killed prepares into this root would otherwise pile up; running ones are spared.
    for kind in ("tmp", "old"):
        remove_stale(out_dir, f".{name}.{kind}-")
    tmp = out_dir / temp_name(f".{name}.tmp-")
    tmp.mkdir()
    return tmp


def _write_arrays(
    tmp: Path,
    sequence: StereoSequence,
    kept: np.ndarray,
    size: tuple[int, int],
    K: np.ndarray,
    *,
    disparity_offset: float,
    flow_kinds: tuple[str, ...],
    label: str,
    workers: int,
    progress: Progress,
) -> dict[str, dict[str, int | str]]:
    """Write the images (uint8 ``[N, H, W, 3]``, ``size = (H, W)``) of the ``kept`` frames into
    ``tmp`` with their StereoSGBM disparity (when the images are wide enough for it) and the flows
    of ``flow_kinds``, in one pass (:func:`~dpc_jax.data.cache_products.write_frame_products`);
    return each file's record for the manifest.

    Each frame is decoded, resized and matched on one of ``workers`` threads; ``disparity_offset``
    (px at the source resolution) shifts the right images before resizing.
    """
    fu, baseline = float(K[0, 0]), float(sequence.baseline)
    depth = sgbm_fits(size[1], fu, baseline)
    if not depth:
        log.info("%s: images %d px wide are too narrow for StereoSGBM; no stereo depth stored",
                 label, size[1])

    def frame(read: StereoFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        # The one preparation of a frame, the live corrector's too.
        return prepared_pair(*read.decode(), size, K, baseline, disparity_offset, match=depth)

    # The frames are read in order (a recording front to back) and decoded on the workers.
    frames = sequence.images.stream(sequence.image_size, kept.tolist())
    return write_frame_products(
        tmp, ordered_map(frame, frames, workers), kept.size, size, depth=depth,
        flow_kinds=flow_kinds, flow_step=flow_step(size), label=label, workers=workers, progress=progress,
    )


def _write_poses_and_calibration(
    tmp: Path, inputs: _Inputs, kept: np.ndarray, K: np.ndarray
) -> dict[str, dict[str, int | str]]:
    """Write the ``kept`` frames' poses, source frame numbers and times, and K and baseline, into
    ``tmp``; return each file's record for the manifest."""
    arrays = {"prior.npy": inputs.prior_poses[kept], "K.npy": K,
              "baseline.npy": np.float64(inputs.sequence.baseline), "indices.npy": kept + inputs.start,
              "times.npy": inputs.sequence.times[kept]}
    if inputs.gt is not None:
        arrays["gt.npy"] = inputs.gt[kept]
    return {file: save_array(tmp / file, np.asarray(array)) for file, array in arrays.items()}


def _manifest(
    tmp: Path,
    name: str,
    inputs: _Inputs,
    prior: str | Path | np.ndarray,
    digest: str,
    parameters: dict,
    kept: np.ndarray,
    size: tuple[int, int],
    K: np.ndarray,
    records: dict[str, dict[str, int | str]],
) -> dict:
    """The manifest of the cache being built in ``tmp``; its ``flows`` are the flow files found there,
    ``records`` each array file's size and digests (``arrays``)."""
    sequence, gt, gt_source = inputs.sequence, inputs.gt, inputs.gt_source
    return {
        "version": CACHE_VERSION,
        "name": name,
        "sequence": sequence.name,
        "input_hash": digest,
        "hash_method": "sha256: parameters, text/pose/prior files by content, images by path+size+mtime",
        "parameters": parameters,
        "sources": {
            **sequence.images.locations(),
            "files": [str(Path(p).resolve()) for p in sequence.sources],
            "prior": "array" if isinstance(prior, np.ndarray) else str(Path(prior).resolve()),
            "ground_truth": (
                None if gt is None else "array" if isinstance(gt_source, np.ndarray)
                else str(Path(gt_source).resolve()) if gt_source is not None else "sequence poses"
            ),
        },
        "source_image_size": list(sequence.image_size),
        "n_frames": int(kept.size),
        "n_source_frames": len(sequence),
        "image_size": list(size),
        "baseline": float(sequence.baseline),
        "K": K.tolist(),
        "has_gt": gt is not None,
        "flows": [k for k, f in FLOW_FILES.items() if (tmp / f).exists()],
        "flow_step": flow_step(size),
        "stereo_depth": (tmp / DISPARITY_FILE).exists(),
        "arrays": dict(sorted(records.items())),
    }


def _load_ground_truth(source: str | Path | np.ndarray, n: int) -> np.ndarray:
    if isinstance(source, np.ndarray):
        label = "ground-truth array"
        poses = validate_poses(source, label)
    else:
        label = str(source)
        poses = read_ground_truth(source)
    if poses.shape[0] != n:
        raise ValueError(
            f"{label}: {poses.shape[0]} ground-truth poses for {n} frames; expected one per frame"
        )
    return poses
