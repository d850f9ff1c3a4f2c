"""numpy input pipeline: prepared caches → fixed-shape :class:`~dpc_jax.nn.batch.Batch` es.

A *sample* is an ordered frame pair ``(i, j)`` of one cached sequence: the network reconstructs
frame j from frame i, its prior is ``T_vo_{j,i} = inv(T_vo_j) T_vo_i`` and, when ground truth is
known, ``xi_gt = Log(T_gt_{j,i})`` (reporting only). Pair kinds:

* ``forward``: ``(k, k+1)``, the consecutive pairs of the sequence;
* ``skip`` (augmentation, on by default for training): ``(k, k+2)`` for every k, i.e. the
  every-second-frame copies of the sequence starting at frame 0 and at frame 1 (faster motion);
  the prior is the composition of the two prior steps, the ground truth likewise;
* ``reverse`` / ``skip_reverse`` (optional augmentation): ``(k+1, k)`` / ``(k+2, k)``, the
  sequences played backwards, with inverted priors.

The caches are read with :func:`~dpc_jax.data.sequence_cache.load_cache`, which checks them.
Flow, when used, is read from the cache (``flow_augment`` at prepare time is needed for the
augmented kinds). ``xi_vo``/``xi_gt`` of every sample are computed once when a loader is built.

Training (:class:`TrainLoader`): shuffled from ``(seed, epoch)`` only, so an epoch is
reproducible and independent of the number of workers; batches have exactly ``batch_size``
samples and **the last partial batch of an epoch is dropped** (a different subset each epoch).
Evaluation (:func:`iterate_sequence`): the forward pairs of one sequence in order; **the last
batch is padded to ``batch_size`` with copies of the last pair whose ``weight`` is 0**.

Batches are assembled by background threads (:func:`prefetch`): a bounded number of batches in
flight, order preserved, a worker's exception re-raised in the consumer, workers stopped when
the consumer stops iterating (the generator is closed or garbage collected). ``put`` (of
:meth:`TrainLoader.epoch` and :func:`iterate_sequence`) runs in the same threads on each assembled
batch, e.g. a transfer to the device (``dpc_jax.engine.parallel.shard_batch``): the batches then
reach the device ahead of the step that uses them, and the step's thread never copies one.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Generator, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.data.holdout import touches
from dpc_jax.data.sequence_cache import PAIR_KINDS, SequenceCache, StereoDepth, load_cache
from dpc_jax.data.splits import training_names
from dpc_jax.geometry.poses import invert_poses, log_poses
from dpc_jax.nn.batch import Batch


def _as_caches(caches: Sequence[SequenceCache | str | Path]) -> list[SequenceCache]:
    return [c if isinstance(c, SequenceCache) else load_cache(c) for c in caches]


def pair_indices(n_frames: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Source and target frame indices ``(i [M], j [M])`` of the pairs of one kind."""
    step, backward = PAIR_KINDS[kind]
    first = np.arange(n_frames - step)
    return (first + step, first) if backward else (first, first + step)


def _relative_poses(poses: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``inv(T_j) T_i`` for index arrays i, j → float64 ``[M, 4, 4]``.

    Formed in float64 numpy: world coordinates reach kilometres, where float32 would cost
    0.1 mm per step.
    """
    poses = np.asarray(poses, np.float64)
    return invert_poses(poses[j]) @ poses[i]


@dataclass(frozen=True)
class _SampleTable:
    """All samples of a loader: which cache, which frames, which flow slot, and their ξ."""

    cache: np.ndarray  # int [S]
    source: np.ndarray  # int [S]
    target: np.ndarray  # int [S]
    kind: np.ndarray  # int [S], index into PAIR_KINDS order
    flow_slot: np.ndarray  # int [S], index into the kind's flow array
    xi_vo: np.ndarray  # float32 [S, 6]
    xi_gt: np.ndarray | None  # float32 [S, 6]

    def __len__(self) -> int:
        return int(self.cache.shape[0])


_KIND_NAMES = tuple(PAIR_KINDS)


def _build_table(
    caches: list[SequenceCache], kinds: Sequence[str], use_flow: bool,
    held_out: Sequence[np.ndarray] | None = None, ground_truth: bool | None = None,
) -> _SampleTable:
    """The samples of ``kinds`` of every cache; ``held_out[c]``: consecutive pairs ``(k, k+1)`` of
    cache ``c`` (by ``k``) kept out with every sample that reaches one of their frames
    (``dpc_jax.data.holdout``). ``ground_truth``: see :class:`TrainLoader`."""
    keys = ("cache", "source", "target", "kind", "slot", "vo", "gt")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    with_gt = all(c.gt is not None for c in caches) if ground_truth is None else ground_truth
    if ground_truth:
        lacking = [str(c.path) for c in caches if c.gt is None]
        if lacking:
            raise ValueError(f"{lacking[0]}: no ground truth in the cache; the supervised loss needs it "
                             "for every training sequence")
    for c_id, cache in enumerate(caches):
        for kind in kinds:
            if use_flow and kind not in cache.flows:
                how = "flow (--flow)" if kind == "forward" else "flow_augment (--flow-augment)"
                raise ValueError(
                    f"{cache.path}: no {kind} flow in the cache; prepare it with {how}, "
                    f"or use the pairs without flow"
                )
            i, j = pair_indices(len(cache), kind)
            if held_out is not None:
                keep = ~touches(np.minimum(i, j), np.maximum(i, j), held_out[c_id])
                i, j = i[keep], j[keep]
            if i.size == 0:
                continue
            parts["cache"].append(np.full(i.size, c_id))
            parts["source"].append(i)
            parts["target"].append(j)
            parts["kind"].append(np.full(i.size, _KIND_NAMES.index(kind)))
            parts["slot"].append(np.minimum(i, j))
            parts["vo"].append(_relative_poses(cache.prior, i, j))
            if with_gt:
                assert cache.gt is not None  # with_gt: every cache has ground truth
                parts["gt"].append(_relative_poses(cache.gt, i, j))
    if not parts["cache"]:
        raise ValueError("no frame pairs: every sequence is too short for the requested pair kinds")
    cat = {k: np.concatenate(v) for k, v in parts.items() if v}
    # One logarithm call for every pair of every sequence (a single compilation).
    relative = cat["vo"] if not with_gt else np.concatenate([cat["vo"], cat["gt"]])
    xi = log_poses(relative).astype(np.float32)
    count = cat["vo"].shape[0]
    return _SampleTable(
        cache=cat["cache"], source=cat["source"], target=cat["target"], kind=cat["kind"],
        flow_slot=cat["slot"], xi_vo=xi[:count], xi_gt=xi[count:] if with_gt else None,
    )


def _check_compatible(caches: list[SequenceCache]) -> None:
    sizes = {c.image_size for c in caches}
    if len(sizes) != 1:
        raise ValueError(f"caches have different image sizes {sorted(sizes)}; prepare them with one --size")


def _assemble(
    caches: list[SequenceCache], table: _SampleTable, rows: np.ndarray, weight: np.ndarray, use_flow: bool,
    stereo_depth: StereoDepth | None = None,
) -> Batch:
    """Gather the samples ``rows`` of ``table`` into one Batch of numpy arrays; ``stereo_depth``:
    ``(inverse depth, valid)`` ``[N, camera, H, W]`` of every frame of a single cache, gathered into
    ``Batch.stereo_depth`` for the samples' two frames."""
    b = rows.size
    h, w = caches[0].image_size
    left = np.empty((b, 2, h, w, 3), np.uint8)
    right = np.empty((b, 2, h, w, 3), np.uint8)
    flow = np.empty((b, 2, h, w, 2), np.float32) if use_flow else None
    intrinsics = np.empty((b, 3, 3), np.float32)
    baseline = np.empty(b, np.float32)
    for n, r in enumerate(rows):
        cache = caches[table.cache[r]]
        i, j = table.source[r], table.target[r]
        left[n, 0], left[n, 1] = cache.left[i], cache.left[j]
        right[n, 0], right[n, 1] = cache.right[i], cache.right[j]
        if flow is not None:
            flow[n] = cache.flows[_KIND_NAMES[table.kind[r]]][table.flow_slot[r]]
        intrinsics[n] = cache.K
        baseline[n] = cache.baseline
    return Batch(
        left=left,
        right=right,
        xi_vo=table.xi_vo[rows],
        intrinsics=intrinsics,
        baseline=baseline,
        weight=weight.astype(np.float32),
        flow=flow,
        xi_gt=None if table.xi_gt is None else table.xi_gt[rows],
        stereo_depth=None if stereo_depth is None else _pair_depth(stereo_depth, table, rows),
    )


def _pair_depth(
    stereo_depth: StereoDepth, table: _SampleTable, rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The frames ``(source, target)`` of samples ``rows`` → ``[B, camera, frame, H, W]`` each."""
    frames = np.stack([table.source[rows], table.target[rows]], axis=1)  # [B, frame]
    inverse, valid = stereo_depth
    return np.moveaxis(inverse[frames], 1, 2), np.moveaxis(valid[frames], 1, 2)


def _identity(batch: Batch) -> Batch:
    return batch


def prefetch(
    tasks: Iterator[Callable[[], Any]], depth: int = 4, workers: int = 2
) -> Generator[Any, None, None]:
    """Run ``tasks`` (callables) on ``workers`` threads, yielding their results in order.

    At most ``depth`` tasks are in flight (bounded memory). An exception of a task is raised in
    the consumer at its position. When the consumer stops (closes the generator, or drops it),
    the pending tasks are cancelled and the threads joined. ``workers=0`` runs inline.
    """
    if workers == 0:
        for task in tasks:
            yield task()
        return
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dpc-data")
    pending: deque[Future] = deque()
    try:
        for task in tasks:
            pending.append(pool.submit(task))
            if len(pending) >= depth:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()
        pool.shutdown(wait=True, cancel_futures=True)


class TrainLoader:
    """Shuffled, fixed-shape training batches over several cached sequences.

    ``caches``: cache folders or loaded :class:`SequenceCache` s (same image size).
    ``frame_skip`` adds the ``(k, k+2)`` pairs, ``reverse`` the reversed pairs of every kind in
    use. ``flow``: include flow (None → when every cache holds the flow of every pair kind in
    use; True → an error names a cache that lacks one). ``ground_truth``: True → batches hold
    ``xi_gt`` (an error names a cache without ground truth; the supervised loss); False → they
    never do (self-supervised training: no ground truth reaches a batch); None → only when every
    sequence has ground truth (for reporting), so the batch structure is the same for every batch.

    ``held_out``: per cache, the consecutive pairs ``(k, k+1)`` (by ``k``) to keep out, together
    with every sample (any kind, both directions) whose frames reach frame ``k`` or ``k+1``: the
    neighbouring pairs share an image with a held-out pair and a frame-skip pair ``(k-1, k+1)``
    contains its motion, so a network fitted to them has seen what the held-out pair is judged on.

    ``len(loader)`` is the number of batches per epoch, ``floor(samples / batch_size)``: the
    last partial batch is dropped. ``epoch(e)`` shuffles with ``numpy.random.default_rng((seed,
    e))`` and yields batches prepared by ``workers`` background threads (``workers=0``:
    inline) with at most ``depth`` batches in flight (each ~80 MB at batch 32, 240×376, with
    flow). Assembly is a memory-bound copy: one thread keeps up with the train step (see
    ``benchmarks/bench_data.py``); more threads help only on machines with idle cores.
    """

    def __init__(
        self,
        caches: Sequence[SequenceCache | str | Path],
        batch_size: int,
        *,
        seed: int = 0,
        frame_skip: bool = True,
        reverse: bool = False,
        flow: bool | None = None,
        shuffle: bool = True,
        held_out: Sequence[np.ndarray] | None = None,
        ground_truth: bool | None = None,
        workers: int = 1,
        depth: int = 3,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.caches = _as_caches(caches)
        if not self.caches:
            raise ValueError("TrainLoader needs at least one cache")
        _check_compatible(self.caches)
        kinds = ["forward"] + (["skip"] if frame_skip else [])
        if reverse:
            kinds += ["reverse"] + (["skip_reverse"] if frame_skip else [])
        self.kinds = tuple(kinds)
        if flow is None:
            flow = all(kind in c.flows for c in self.caches for kind in self.kinds)
        self.use_flow = flow
        self.table = _build_table(self.caches, self.kinds, self.use_flow, held_out, ground_truth)
        self.batch_size = batch_size
        self.seed = seed
        self.shuffle = shuffle
        self.workers = workers
        self.depth = depth
        if len(self) == 0:
            raise ValueError(f"{len(self.table)} samples are fewer than one batch of {batch_size}")

    @property
    def num_samples(self) -> int:
        return len(self.table)

    def __len__(self) -> int:
        return self.num_samples // self.batch_size

    def order(self, epoch: int) -> np.ndarray:
        """Sample order of epoch ``epoch`` (a permutation, or the identity without shuffling)."""
        if not self.shuffle:
            return np.arange(self.num_samples)
        return np.random.default_rng((self.seed, epoch)).permutation(self.num_samples)

    def epoch(self, epoch: int, put: Callable[[Batch], Any] | None = None) -> Generator[Any, None, None]:
        """The ``len(self)`` batches of epoch ``epoch``, prefetched in the background; with ``put``,
        ``put(batch)`` of each, computed in the background threads too (module docstring)."""
        order = self.order(epoch)
        ones = np.ones(self.batch_size, np.float32)
        finish = put or _identity

        def tasks() -> Iterator[Callable[[], Any]]:
            for b in range(len(self)):
                rows = order[b * self.batch_size:(b + 1) * self.batch_size]

                def task(rows: np.ndarray = rows) -> Any:
                    return finish(_assemble(self.caches, self.table, rows, ones, self.use_flow))

                yield task

        return prefetch(tasks(), self.depth, self.workers)


def iterate_sequence(
    cache: SequenceCache | str | Path,
    batch_size: int,
    *,
    flow: bool | None = None,
    workers: int = 1,
    depth: int = 4,
    put: Callable[[Batch], Any] | None = None,
    stereo_depth: StereoDepth | None = None,
    ground_truth: bool | None = None,
) -> Generator[Any, None, None]:
    """The forward pairs ``(k, k+1)``, k = 0 … N-2, of one sequence in order, in fixed-size batches.

    The last batch is padded with copies of the final pair whose ``weight`` is 0, so every batch
    has ``batch_size`` samples; ``ceil((N-1) / batch_size)`` batches in all. ``put``: as in
    :meth:`TrainLoader.epoch`. ``stereo_depth``: ``(inverse depth, valid)`` ``[N, camera, H, W]``
    of every frame, gathered into each batch's ``stereo_depth`` by the data threads (so ``put``
    moves it to the device with the images). ``ground_truth``: as in :class:`TrainLoader`.
    """
    finish = put or _identity
    [loaded] = _as_caches([cache])
    use_flow = bool(loaded.flows) if flow is None else flow
    table = _build_table([loaded], ["forward"], use_flow, ground_truth=ground_truth)
    n = len(table)
    if stereo_depth is not None and any(a.shape[:1] != (len(loaded),) for a in stereo_depth):
        raise ValueError(f"{loaded.path}: the stereo depth must hold its {len(loaded)} frames, got "
                         f"{[a.shape for a in stereo_depth]}")

    def tasks() -> Iterator[Callable[[], Any]]:
        for start in range(0, n, batch_size):
            real = np.arange(start, min(start + batch_size, n))
            rows = np.concatenate([real, np.full(batch_size - real.size, n - 1)])
            weight = (np.arange(batch_size) < real.size).astype(np.float32)

            def task(rows: np.ndarray = rows, weight: np.ndarray = weight) -> Any:
                return finish(_assemble([loaded], table, rows, weight, use_flow, stereo_depth))

            yield task

    # A sequence of one batch has nothing to overlap its assembly with: assembled inline, no thread.
    return prefetch(tasks(), depth, workers if n > batch_size else 0)


@dataclass(frozen=True)
class Split:
    """Sequence names for training, validation (epoch selection) and test."""

    train: tuple[str, ...]
    validation: str | None
    test: str | None


def leave_one_out(
    names: Sequence[str],
    *,
    test: str | None,
    validation: str | None = None,
    train: Sequence[str] | None = None,
) -> Split:
    """Leave-one-out split: train on every sequence of ``names`` but the validation and test ones.

    An explicit ``train`` list is checked instead: it must not hold the validation or the test
    sequence. Raises ``ValueError`` for unknown names, validation == test, or overlap.
    """
    known = list(dict.fromkeys(names))
    for role, value in (("test", test), ("validation", validation)):
        if value is not None and value not in known:
            raise ValueError(f"{role} sequence {value!r} is not one of {known}")
    if test is not None and test == validation:
        raise ValueError(f"sequence {test!r} cannot be both the validation and the test sequence")
    held_out = [n for n in (test, validation) if n is not None]
    chosen = training_names(known, held_out, None if train is None else list(dict.fromkeys(train)))
    if train is not None:
        unknown = [n for n in chosen if n not in known]
        if unknown:
            raise ValueError(f"training sequences {unknown} are not among {known}")
        overlap = [n for n in chosen if n in held_out]
        if overlap:
            role = "validation" if validation in overlap else "test"
            raise ValueError(f"sequence {overlap[0]!r} is the {role} sequence and cannot also be in training")
    if not chosen:
        raise ValueError("no training sequence left after removing the validation and test sequences")
    return Split(train=chosen, validation=validation, test=test)
