"""Δ of a live pair's parts for the sequential tests (``dpc_jax.correction.live``): measured in the
corrector's process, or behind the poses in a child process at the lowest CPU priority.

Why a process: on a CPU the measurement of Δ is most of a frame's work at the papers' size, and the pose
does not need it. On a thread beside the pose's own work (decoding, our VO, StereoSGBM, the network) it
takes the cores the pose needs and slows every stage of it (``benchmarks/bench_live.py --realtime``); a
child process at nice 19 gets the CPU when the pose's work leaves a core idle, and the operating system
hands the core back as soon as a frame arrives. On an accelerator the device does the work, so a thread
is enough (and a second process would claim the device's memory again).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import signal
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any

import numpy as np

from dpc_jax.correction.decision import JUDGE, NETWORK
from dpc_jax.correction.inference import TrainedRun
from dpc_jax.correction.measure import pair_deltas
from dpc_jax.correction.parts import Part
from dpc_jax.data.preparation import matched_pair, pair_cache, prepared_pair

# The child's priority: the lowest, so that the pose's work always comes first.
CHILD_NICE = 19
# The longest a child is held (s): far beyond a frame's work.
HOLD_S = 2.0


@dataclass(frozen=True)
class Frame:
    """A live frame as prediction and measurement read it: its ``index`` (from 0), the pair prepared at
    the network's size (``left``, ``right`` ``[H, W, 3]`` uint8, ``disparity`` ``[H, W]`` px or None) and,
    with a judge, the pair as given (``full``)."""

    index: int
    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray | None
    full: tuple[np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True)
class Measured:
    """Δ of a pair's parts at the network's size and at the judge's, and the seconds they took
    (``measure``, ``judge``)."""

    network: dict[Part, float]
    judge: dict[Part, float]
    seconds: dict[str, float]


class PairMeasure:
    """Δ of named corrections on one pair of frames (:meth:`deltas`), at the network's size and, with
    ``judge_size``, at the judge's: what a live corrector's measurement needs, picklable (the prepared
    model and the frames prepared at the judge's size are made again where it is unpickled).

    ``K``: ``[3, 3]`` at the network's size; ``judge_K``: at the judge's; ``depth``: the acceptance
    depth (``dpc_jax.correction.corrector.default_acceptance_depth``); ``flow``: the network reads
    optical flow; ``disparity_offset``: px, as the frames are prepared.
    """

    def __init__(self, run: TrainedRun, K: np.ndarray, baseline: float, *, depth: str, flow: bool,
                 judge_size: tuple[int, int] | None, judge_K: np.ndarray, disparity_offset: float) -> None:
        self.run, self.K, self.baseline, self.depth, self.flow = run, K, float(baseline), depth, flow
        self.judge_size, self.judge_K, self.disparity_offset = judge_size, judge_K, float(disparity_offset)
        self._judged: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}
        self._matched: dict[int, np.ndarray | None] = {}

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_judged": {}, "_matched": {}}

    @property
    def model(self) -> Any:
        """The run prepared for the backend (``dpc_jax.engine.predict.PreparedModel``), once."""
        return self.run.prepared

    def batch(self, frames: tuple[Frame, Frame], prior: np.ndarray, depth: bool = True) -> Any:
        """The pair (with the prior's poses ``[2, 4, 4]``) as a batch on the device, with its optical flow
        for a network that reads it and (``depth``) the acceptance depth: StereoSGBM's of a frame prepared
        without it is matched here, as ``prepare`` matches it (each frame once: the last two kept)."""
        from dpc_jax.engine.predict import pair_batch, stereo_depth_of

        if depth and self.depth == "sgbm":
            frames = (self._with_disparity(frames[0]), self._with_disparity(frames[1]))
        window = pair_cache(tuple((f.left, f.right, f.disparity if depth else None) for f in frames), self.K,
                            self.baseline, prior, flow=self.flow)
        return pair_batch(window, self.flow, stereo_depth_of(window, self.depth) if depth else None)

    def _with_disparity(self, frame: Frame) -> Frame:
        if frame.disparity is not None:
            return frame
        if frame.index not in self._matched:
            self._matched = {k: v for k, v in self._matched.items() if k == frame.index - 1}
            self._matched[frame.index] = matched_pair(frame.left, frame.right, self.K, self.baseline)
        return dataclasses.replace(frame, disparity=self._matched[frame.index])

    def deltas(self, frames: tuple[Frame, Frame], prior: np.ndarray, needs: Sequence[tuple[str, Part]],
               vectors: np.ndarray, batch: Any = None) -> Measured:
        """Δ of the parts ``needs`` (``(size, part)``), ``vectors`` ``[K, 6]`` of the pair ``frames`` with
        the prior's poses ``prior`` ``[2, 4, 4]``, at the network's size (on ``batch`` when given, else the
        pair's, ``dpc_jax.correction.measure.pair_deltas``) and at the judge's."""
        seconds: dict[str, float] = {}
        found: dict[str, dict[Part, float]] = {NETWORK: {}, JUDGE: {}}
        for size, stage in ((NETWORK, "measure"), (JUDGE, "judge")):
            chosen = [k for k, (s, _) in enumerate(needs) if s == size]
            if not chosen:
                continue
            t = time.perf_counter()
            if size == NETWORK:
                batch = self.batch(frames, prior) if batch is None else batch
                delta = pair_deltas(self.run, batch, vectors[chosen], model=self.model)
            else:
                delta = self._at_judge(frames, prior, vectors[chosen])
            found[size] = {needs[k][1]: float(d) for k, d in zip(chosen, delta, strict=True)}
            seconds[stage] = time.perf_counter() - t
        return Measured(found[NETWORK], found[JUDGE], seconds)

    def _at_judge(self, frames: tuple[Frame, Frame], prior: np.ndarray,
                  corrections: np.ndarray) -> np.ndarray:
        """Δ ``[K]`` of ``corrections`` ``[K, 6]`` on the pair at the judge's size (each frame prepared
        there once: the last two kept)."""
        from dpc_jax.engine.predict import pair_batch

        assert self.judge_size is not None
        for frame in frames:
            if frame.index not in self._judged:
                assert frame.full is not None
                self._judged[frame.index] = prepared_pair(*frame.full, self.judge_size, self.judge_K,
                                                          self.baseline, self.disparity_offset)
        self._judged = {k: v for k, v in self._judged.items() if k >= frames[0].index}
        window = pair_cache(tuple(self._judged[f.index] for f in frames), self.judge_K, self.baseline, prior)
        return pair_deltas(self.run, pair_batch(window, False, window.stereo_depth), corrections)

    def compile(self, frame: Frame, counts: Sequence[int], judge: bool = True) -> None:
        """The measurement's programs for each of ``counts`` parts (``PADDED``), at the network's size and
        (``judge``) the judge's, on the blank ``frame``, so that no pair compiles them."""
        prior = np.stack([np.eye(4)] * 2)
        for count in counts:
            needs = [(NETWORK, Part("full"))] * count
            if judge and self.judge_size is not None:
                needs += [(JUDGE, Part("full"))] * count
            self.deltas((frame, frame), prior, needs, np.zeros((len(needs), 6)))
        # The blank frame's index is a real frame's too: nothing of it is kept for that frame.
        self._judged, self._matched = {}, {}


# The child's measurement, set by _start.
_CHILD: PairMeasure | None = None


def _lowest() -> None:
    """Every thread of this process at :data:`CHILD_NICE`: a priority is a thread's on Linux, and the
    threads JAX starts need not descend from the thread that lowered its own."""
    tasks = "/proc/self/task"
    for task in os.listdir(tasks) if os.path.isdir(tasks) else ():
        try:
            os.setpriority(os.PRIO_PROCESS, int(task), CHILD_NICE)
        except OSError:  # a thread that has ended since
            continue


def _start(measure: bytes, frame: Frame, counts: Sequence[int]) -> None:
    """The child's start: lowest priority, then the measurement (pickled, so that JAX starts after) and
    its programs for ``counts`` parts at the network's size compiled on ``frame``."""
    global _CHILD
    os.nice(CHILD_NICE)
    _CHILD = pickle.loads(measure)
    _CHILD.compile(frame, counts, judge=False)


def _measure_in_child(frames: tuple[Frame, Frame], prior: np.ndarray, needs: Sequence[tuple[str, Part]],
                      vectors: np.ndarray) -> Measured:
    assert _CHILD is not None, "started by _start"
    _lowest()
    return _CHILD.deltas(frames, prior, needs, vectors)


class ChildMeasure:
    """A :class:`PairMeasure` run in a child process at nice :data:`CHILD_NICE` (module docstring),
    started with its programs for ``counts`` parts at the network's size compiled on ``frame`` (what the
    first pairs need); it compiles any other when a pair first needs it, off the pose's path. :meth:`hold`
    stops it (``SIGSTOP``) until :meth:`release`: on two cores even a child at the lowest priority
    slowed every stage of the pose (the cores' caches, the machine's scheduler), so the corrector holds
    it while a frame is worked on and it runs between frames."""

    def __init__(self, measure: PairMeasure, frame: Frame, counts: Sequence[int]) -> None:
        # Spawned, not forked: a fork of a process whose JAX runtime has started threads can hang.
        self._pool: Executor = ProcessPoolExecutor(1, mp_context=get_context("spawn"), initializer=_start,
                                                   initargs=(pickle.dumps(measure), frame, tuple(counts)))
        self._pid = self._pool.submit(os.getpid).result()
        self._timer: threading.Timer | None = None

    def submit(self, frames: tuple[Frame, Frame], prior: np.ndarray, needs: Sequence[tuple[str, Part]],
               vectors: np.ndarray) -> Future[Measured]:
        return self._pool.submit(_measure_in_child, frames, prior, needs, vectors)

    def hold(self) -> None:
        """Stop the child until :meth:`release`, or :data:`HOLD_S` at most (a frame that never comes
        to its pose, an error, must not leave it stopped: the interpreter's exit waits for it)."""
        if self._timer is None and hasattr(signal, "SIGSTOP"):
            os.kill(self._pid, signal.SIGSTOP)
            self._timer = threading.Timer(HOLD_S, self.release)
            self._timer.daemon = True
            self._timer.start()

    def release(self) -> None:
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()
            os.kill(self._pid, signal.SIGCONT)

    def close(self) -> None:
        """End the child now: a pair it is measuring has no next frame to inform."""
        self.release()
        self._pool.shutdown(wait=False, cancel_futures=True)
        try:
            os.kill(self._pid, signal.SIGTERM)
        except ProcessLookupError:
            return
