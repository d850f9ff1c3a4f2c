"""Corrected visual odometry live: each pose corrected as its stereo pair arrives (docs/method.md §8).

A :class:`LiveCorrector` is built once from a trained run and the camera's calibration; each call
takes one stereo pair as the camera gives it (full size, uint8, grey or colour) and the prior's pose
of that frame, or no prior and it runs dpc_jax's own stereo VO, and returns the frame's corrected
pose (:class:`LiveFrame`). Per frame:

1. The pair is prepared as ``dpc-jax prepare`` prepares a frame (``dpc_jax.data.preparation``).
2. The previous frame and this one form a two-frame sequence in memory, on which the network predicts
   ξ for the pair and the measurement gives Δ of its parts, through ``correct``'s functions.
3. The one decision of ``correct`` (``dpc_jax.correction.decision.Decision``), sequential: the parts
   of ξ it consults (in its order: the full correction and its rotation, each whole with its mean
   tested apart or without its trailing mean over the last pairs; a rotation narrowed to the axes
   whose own tests accept, which it then tests itself) are measured on the pair and their tests
   fed (``dpc_jax.correction.acceptance.SequentialTest``: a false acceptance stays below α however
   long it runs, and an accepted part is withdrawn when the evidence turns); the pair gets the part
   the decision applies after it, or nothing.
4. With a *judge* (``judge_size``, as ``correct``'s judge: the same frames at a larger size, StereoSGBM
   depth, no network), the parts the decision consults there (what the network's size would apply,
   its mean, its scales) are measured on the pair at the judge's size: a part is applied only once its
   tests there have accepted too (at 64×96 the images of a real drive can favour a rotation the
   ground truth does not, ``docs/method.md`` §8), at the judge's scale.
5. ``T_w_k = T_w_{k-1} · inv(Exp(ξ_applied) · T_vo_{k,k-1})``: a pose once returned is never changed.

With ``behind`` the measurement of steps 3–4 leaves the pose's path, so that both cores serve the pose:
the pair is prepared on a worker thread while the prior's pose is computed (our VO, or the function
given as the prior), the pose is corrected with the decision of the pairs measured before it, and the
pair's own Δ are measured on the worker after the pose is returned; they inform the next frames (fed
to the decision when the next frame arrives). With ``skip`` a pair that arrives while the measurement
of an earlier one is still running is not measured: the sequential tests are valid on any subset of
pairs chosen without their Δ, so the guarantee holds on the pairs measured; without ``skip`` each frame
waits for the previous pair's measurement, and the decision is the synchronous one shifted by one pair.

Kept between frames: the previous prepared frame and poses, the tests' running statistics, the last
pairs' corrections (the trailing mean), with a judge the previous pair at full size: no more.
"""

from __future__ import annotations

import gc
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from dpc_jax.correction.acceptance import DEFAULT_ALPHA
from dpc_jax.correction.corrector import default_acceptance_depth
from dpc_jax.correction.decision import COMPONENTS, DEFAULT_MEAN_TEST, MEAN_TESTS, NETWORK, Decision, MeanTest
from dpc_jax.correction.inference import TrainedRun, load_run
from dpc_jax.correction.judge import judge_rule, judge_size_problem
from dpc_jax.correction.live_measure import ChildMeasure, Frame, Measured, PairMeasure
from dpc_jax.correction.measure import PADDED
from dpc_jax.correction.parts import MEAN_WINDOW, Part
from dpc_jax.data.calibration import Calibration
from dpc_jax.data.preparation import as_rgb, prepared_pair, resized_intrinsics
from dpc_jax.geometry.poses import validate_poses

# A frame's prior: its pose ``[4, 4]`` (or ``[3, 4]``), a function that gives it, or None (our VO).
Prior = np.ndarray | Callable[[], np.ndarray] | None


def _rigid(pose: Any, source: str) -> np.ndarray:
    """``pose`` (``[4, 4]``, or ``[3, 4]``: a KITTI row) as ``[4, 4]`` float64, checked rigid (its values
    as given); ``ValueError`` naming ``source`` otherwise. The same rule for every pose, from frame 0."""
    pose = np.asarray(pose, np.float64)
    validate_poses(pose[None], source)
    return np.vstack([pose, [0.0, 0.0, 0.0, 1.0]]) if pose.shape == (3, 4) else pose


@dataclass(frozen=True)
class LiveFrame:
    """One frame's output.

    ``index``: the frame's number (0: the first); ``pose``: ``[4, 4]`` float64 corrected
    camera-to-world pose; ``prior``: the prior's pose (composed from the same first pose);
    ``proposal``: ``[6]`` the network's ξ for the pair ending at this frame (None for frame 0);
    ``part``: the part of it applied, by its one name (``rotation_xz − mean``; ``none``: the prior's
    step, at frame 0, before a part is accepted or once withdrawn); ``correction``: ``[6]`` that part
    (zeros for none); ``forced``: applied whatever the tests say; ``events``: tests accepted or
    withdrawn at this pair; ``seconds``: time per stage: ``vo`` (our VO, or the check of
    the given prior), ``prepare`` (the pair resized and matched; then the two frames made a batch on
    the device, with their optical flow for a network that reads flow), ``network`` (its forward pass),
    ``measure`` (Δ of the parts for the tests), ``judge`` (with a judge, while a part is accepted: the
    pair prepared at its size and Δ of that part there), ``total`` (the call); frame 0 has no
    ``network`` and no ``measure``.
    """

    index: int
    time: float | None
    pose: np.ndarray
    prior: np.ndarray
    proposal: np.ndarray | None
    correction: np.ndarray
    part: str
    forced: bool = False
    events: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)
    measured: bool = True


@dataclass
class _Previous:
    """What the next frame needs of this one."""

    frame: Frame  # prepared (with the pair as given only for a judge)
    raw: np.ndarray  # the prior's camera-to-world pose as given (or as our VO composed it)
    prior: np.ndarray  # the prior's pose composed from the first pose
    pose: np.ndarray  # the corrected one


class LiveCorrector:
    """Correct a VO's poses as the frames arrive (module docstring).

    ``run``: a trained run (:class:`~dpc_jax.correction.inference.TrainedRun`, or its folder with
    ``select`` the epoch criterion); ``calibration``: the camera's; ``rotation_only``: None = the
    run's; ``alpha``: the level of the sequential tests; ``mean_test``: test the correction's mean
    apart (False: whole parts only); ``mean``: where and how (``MEAN_TESTS``, as ``correct --decision``);
    ``force``: apply the correction to every pair whatever the
    tests say; ``first_pose``: ``[4, 4]`` the pose of frame 0 (default: the prior's first pose, or
    the identity for our VO); ``disparity_offset``: px, the rig's calibration residual the images
    are rectified by (``dpc_jax.data.cache.prepare_sequence``); ``vo``: the configuration of our VO
    when no prior is given (``dpc_jax.vo.VOConfig``); ``judge_size``: ``(H, W)`` px, the size the part to
    apply is judged at as well (module docstring; a Stereo DPC run, no smaller than the run's images
    and no larger than the camera's), None: no judge, or ``"rule"`` (the default): the judge
    ``dpc-jax live`` and ``correct`` use by default (``dpc_jax.correction.judge.judge_rule``: a Stereo
    DPC run smaller than 240×376 is judged at 240×376, no larger than the camera's images), so that the
    API and the command line decide alike; ``behind``, ``skip``: the measurement off the pose's path,
    and pairs skipped while it is busy (module docstring; :attr:`skipped` counts them, :meth:`finish`
    feeds the last pair's Δ); ``ahead``: every program compiled before the first frame (False: the
    measurement's programs when a pair first needs them, which delays that pair: a replay without
    deadlines). Poses (``first_pose``, each prior) are ``[4, 4]`` or
    ``[3, 4]`` (a KITTI row), rigid; a returned pose is ``[4, 4]``. :attr:`decision` is the one decision
    (``dpc_jax.correction.decision.Decision``, sequential, trailing mean), its tests by name in
    ``decision.tests``.
    """

    def __init__(
        self,
        run: TrainedRun | str | os.PathLike,
        calibration: Calibration,
        *,
        select: str = "delta",
        rotation_only: bool | None = None,
        alpha: float = DEFAULT_ALPHA,
        mean_test: bool = True,
        mean: MeanTest = MEAN_TESTS[DEFAULT_MEAN_TEST],
        force: bool = False,
        first_pose: np.ndarray | None = None,
        disparity_offset: float = 0.0,
        vo: Any = None,
        judge_size: tuple[int, int] | Literal["rule"] | None = "rule",
        behind: bool = False,
        skip: bool = False,
        ahead: bool = True,
    ) -> None:
        self.run = run if isinstance(run, TrainedRun) else load_run(run, select)
        self.calibration = calibration
        rotation_only = self.run.config.rotation_only if rotation_only is None else bool(rotation_only)
        self.components = ("rotation",) if rotation_only else COMPONENTS
        self.mean_test, self.force = bool(mean_test), bool(force)
        self.depth = default_acceptance_depth(self.run)
        self.size = self.run.image_size
        (h, w), (ch, cw) = self.size, calibration.image_size
        if h > ch or w > cw:
            raise ValueError(f"calibration: the network takes {h}x{w} images, larger than the camera's "
                             f"{ch}x{cw}; a frame is not upsampled: use a run trained at {ch}x{cw} or less")
        self.K = resized_intrinsics(calibration.K, calibration.image_size, self.size)
        self.disparity_offset = float(disparity_offset)
        self.first_pose = None if first_pose is None else _rigid(first_pose, "first_pose")
        self.alpha = float(alpha)
        self._judge_K = self.K
        if judge_size == "rule":
            judge_size = judge_rule(self.run.config.method, self.size, calibration.image_size)
        self.judge_size = None if judge_size is None or self.force else self._checked_judge(judge_size)
        # The one decision of ``correct``, sequential, with the mean of the pairs seen.
        self.decision = Decision(components=self.components, alpha=self.alpha,
                                 judge=self.judge_size is not None, mean_test=self.mean_test, mean=mean,
                                 trailing=True, force=self.force, sequential=True)
        self._vo_config = vo
        self._vo: Any = None
        self._previous: _Previous | None = None
        # The corrections of the last pairs: the trailing mean a remainder removes (its window as offline).
        self._recent: deque[np.ndarray] = deque(maxlen=MEAN_WINDOW - 1)
        self._pairs = 0
        self.behind, self.skip, self.ahead = bool(behind), bool(skip), bool(ahead)
        self._measure = PairMeasure(self.run, self.K, calibration.baseline, depth=self.depth,
                                    flow=self.run.use_flow, judge_size=self.judge_size, judge_K=self._judge_K,
                                    disparity_offset=self.disparity_offset)
        # Behind: threads prepare the pair (a camera's matching each) while the prior is computed; the
        # measurement runs on a thread, or skipping on a CPU in a child process at the lowest priority
        # (live_measure).
        self._pool = ThreadPoolExecutor(3, thread_name_prefix="live") if self.behind else None
        # Measured in a child process, the pair's StereoSGBM is matched there too, off the pose's path (the
        # network does not read it); the pairs the child skips are never matched.
        import jax

        self._apart = self.skip and self.behind and jax.default_backend() == "cpu"
        self._child: ChildMeasure | None = None
        self._pending: Future[Measured] | None = None
        self.skipped = 0
        self._compile()

    def _checked_judge(self, size: tuple[int, int]) -> tuple[int, int]:
        """``size`` checked as ``dpc-jax live`` checks ``--judge-size``
        (``dpc_jax.correction.judge.judge_size_problem``), and wide enough for StereoSGBM."""
        from dpc_jax.data.stereo_depth import sgbm_fits

        h, w = (int(x) for x in size)
        if self.run.config.method != "stereo_dpc":
            raise ValueError(f"judge {h}x{w}: a judge measures Δ with stereo depth; the run is "
                             f"{self.run.config.method}")
        problem = judge_size_problem((h, w), self.size, self.calibration.image_size)
        if problem is not None:
            raise ValueError(problem)
        K = resized_intrinsics(self.calibration.K, self.calibration.image_size, (h, w))
        if not sgbm_fits(w, float(K[0, 0]), self.calibration.baseline):
            raise ValueError(f"judge {h}x{w}: too narrow for StereoSGBM to match the camera's disparities")
        self._judge_K = K
        return h, w

    def _compile(self) -> None:
        """Predict, measure and compose once on a blank pair, for every number of parts a pair can
        measure (``dpc_jax.correction.measure.PADDED``; forced, the first component and its remainder
        only), so that no frame compiles anything (the composition's compilation alone took 0.4 s);
        not ``ahead``, the prediction and the composition only. A child process of the measurement
        compiles the first pairs' programs before the first frame and any other between frames."""

        h, w = self.size
        blank = np.zeros((h, w, 3), np.uint8)
        _, _, disparity = prepared_pair(blank, blank, self.size, self.K, self.calibration.baseline,
                                        match=self.depth == "sgbm" and not self._apart)
        full = (np.zeros((*self.calibration.image_size, 3), np.uint8),) * 2 if self.judge_size else None
        frame = Frame(0, blank, blank, disparity, full)
        self._predict((frame, frame), np.stack([np.eye(4)] * 2), {})
        self._compose(_Previous(frame, np.eye(4), np.eye(4), np.eye(4)), np.eye(4), np.zeros(6))
        if self._apart:
            # The first pairs' programs before the first frame; any other when a pair first needs it.
            first = sum(size == NETWORK for size, _ in self.decision.needs())
            self._child = ChildMeasure(self._measure, frame, [min(n for n in PADDED if n >= first)]
                                       if self.ahead else [])
        elif self.ahead:
            self._measure.compile(frame, PADDED[:1] if self.force else PADDED)
        if self.skip:
            # What restoring and compiling left is collected once now and never walked again: a full
            # collection of it in the middle of a frame made that frame miss its deadline.
            gc.collect()
            gc.freeze()

    def _predict(self, frames: tuple[Frame, Frame], prior: np.ndarray,
                 seconds: dict[str, float]) -> tuple[np.ndarray, Any]:
        """ξ ``[6]`` of the pair (``dpc_jax.engine.predict.xi_step``: the forward pass alone) and the pair
        as a batch on the device, assembled once for the network and the measurement → ``(ξ, batch)``;
        ``seconds`` gets the batch's time (with its optical flow, added to ``prepare``) and ``network``."""
        began = time.perf_counter()
        batch = self._measure.batch(frames, prior, depth=not self._apart)
        assembled = time.perf_counter()
        seconds["prepare"] = seconds.get("prepare", 0.0) + assembled - began
        model = self._measure.model
        xi = np.asarray(model.xi_step(self.run.config.method)(model.leaves, batch), np.float64)[0]
        seconds["network"] = time.perf_counter() - assembled
        return xi, batch

    def _collect(self, wait: bool, seconds: dict[str, float]) -> tuple[str, ...]:
        """Behind: the pending pair's Δ fed to the decision once measured (``wait``: waiting for it) →
        the tests accepted or withdrawn; its ``measure`` and ``judge`` seconds into ``seconds``."""
        pending = self._pending
        if pending is None or not (wait or pending.done()):
            return ()
        self._pending = None
        measured = pending.result()
        seconds.update(measured.seconds)
        return self.decision.update(measured.network, measured.judge)

    def hold(self) -> None:
        """A frame has arrived: the measurement in a child process stops until this frame's pose is
        given (:class:`~dpc_jax.correction.live_measure.ChildMeasure`), so that the frame's work,
        reading its images included, has both cores. :meth:`__call__` holds it too."""
        if self._child is not None:
            self._child.hold()

    def close(self) -> None:
        """End a child process of the measurement (:meth:`finish` first for the last pair's Δ)."""
        if self._child is not None:
            self._child.close()

    def finish(self) -> tuple[str, ...]:
        """Behind: wait for the last pair's measurement and feed it to the decision (what the tests say
        after every pair measured, :attr:`decision`) → the tests accepted or withdrawn there."""
        return self._collect(True, {})

    def _vectors(self, xi: np.ndarray, parts: Sequence[Part | None]) -> np.ndarray:
        """``parts`` of this pair's ``xi`` ``[6]`` (a remainder without the trailing mean of the last
        pairs, this one the last) → ``[K, 6]``; zeros for None."""
        recent = np.stack([*self._recent, xi])
        return np.stack([np.zeros(6) if p is None else p.of(recent)[-1] for p in parts]).reshape(-1, 6)

    def __call__(
        self, left: np.ndarray, right: np.ndarray, prior: Prior = None, *, time_s: float | None = None,
        grey: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> LiveFrame:
        """Correct the next frame (module docstring).

        ``left``, ``right``: the stereo pair at the calibration's size (uint8, ``[H, W]`` grey or
        ``[H, W, 3]`` RGB); ``prior``: ``[4, 4]`` the prior VO's camera-to-world pose of this frame, a
        function that gives it (called once; behind, while the pair is prepared), or None to run our VO
        (on ``grey``, the pair as grey images, when given: e.g. decoded in grey as ``dpc-jax vo`` does;
        else converted here); ``time_s``: the frame's time, reported.
        """
        began = time.perf_counter()
        self.hold()
        try:
            return self._corrected(left, right, prior, time_s, grey, began)
        finally:
            if self._child is not None:
                self._child.release()

    def _corrected(self, left: np.ndarray, right: np.ndarray, prior: Prior, time_s: float | None,
                   grey: tuple[np.ndarray, np.ndarray] | None, began: float) -> LiveFrame:
        seconds: dict[str, float] = {}
        left, right = as_rgb(left, "left"), as_rgb(right, "right")
        if left.shape[:2] != tuple(self.calibration.image_size) or right.shape != left.shape:
            h, w = self.calibration.image_size
            index = self._pairs + (self._previous is not None)
            raise ValueError(f"frame {index}: images of {left.shape[:2]} and {right.shape[:2]}, expected "
                             f"both {h}x{w} (the calibration's)")
        current = self._arrived(left, right, prior, grey, seconds)
        prior_pose = current.raw
        previous = self._previous
        if previous is None:
            start = prior_pose if self.first_pose is None else self.first_pose
            current.pose = current.prior = start
            self._previous = current
            seconds["total"] = time.perf_counter() - began
            return LiveFrame(0, time_s, start.copy(), current.prior.copy(), None, np.zeros(6), "none",
                             self.force, (), seconds)
        frames, poses = (previous.frame, current.frame), np.stack([previous.raw, prior_pose])
        # What is measured is chosen from the tests of the pairs before this one (a choice made after
        # seeing this pair's Δ would select the pairs that favour it).
        measured = True
        if self._pool is not None:
            events = self._collect(not self.skip, seconds)
            xi, batch = self._predict(frames, poses, seconds)
            if self._pending is None:
                needs = self.decision.needs()
                vectors = self._vectors(xi, [p for _, p in needs])
                self._pending = (
                    self._child.submit(frames, poses, needs, vectors) if self._child is not None
                    else self._pool.submit(self._measure.deltas, frames, poses, needs, vectors, batch))
            else:
                measured = False
                self.skipped += 1
        else:
            needs = self.decision.needs()
            xi, batch = self._predict(frames, poses, seconds)
            done = self._measure.deltas(frames, poses, needs, self._vectors(xi, [p for _, p in needs]), batch)
            seconds.update(done.seconds)
            events = self.decision.update(done.network, done.judge)
        part = self.decision.outcome.part
        correction = self._vectors(xi, [part])[0]
        self._recent.append(xi)
        self._pairs += 1
        current.pose, current.prior = self._compose(previous, prior_pose, correction)
        self._previous = current
        seconds["total"] = time.perf_counter() - began
        return LiveFrame(self._pairs, time_s, current.pose.copy(), current.prior.copy(), xi, correction,
                         "none" if part is None else part.name, self.force, events, seconds, measured)

    def _arrived(self, left: np.ndarray, right: np.ndarray, prior: Prior,
                 grey: tuple[np.ndarray, np.ndarray] | None, seconds: dict[str, float]) -> _Previous:
        """This frame: the pair prepared at the network's size, with the prior's pose (``raw``); behind,
        the pair is prepared on a worker while the prior's pose is computed. ``seconds`` gets ``vo`` and
        ``prepare``."""
        def prepare() -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
            t = time.perf_counter()
            prepared = prepared_pair(left, right, self.size, self.K, self.calibration.baseline,
                                     self.disparity_offset, match=self.depth == "sgbm" and not self._apart,
                                     pool=self._pool)
            seconds["prepare"] = time.perf_counter() - t
            return prepared

        aside = self._pool is not None and (prior is None or callable(prior))
        job = self._pool.submit(prepare) if aside and self._pool is not None else None
        t = time.perf_counter()
        prior_pose = self._prior_pose(left, right, prior, grey)
        seconds["vo"] = time.perf_counter() - t
        small_left, small_right, disparity = prepare() if job is None else job.result()
        frame = Frame(self._pairs + (self._previous is not None), small_left, small_right, disparity,
                      (left, right) if self.judge_size is not None else None)
        return _Previous(frame, prior_pose, prior_pose, prior_pose)

    def _prior_pose(self, left: np.ndarray, right: np.ndarray, prior: Prior,
                    grey: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """The prior's pose of this frame: given (or by the function given; checked rigid), or our VO's
        from the previous one."""
        index = self._pairs + (self._previous is not None)
        if callable(prior):
            prior = prior()
        if prior is not None:
            return _rigid(prior, f"prior pose of frame {index}")
        import cv2

        from dpc_jax.vo import StereoVO

        if self._vo is None:
            self._vo = StereoVO(self.calibration.K, self.calibration.baseline, self._vo_config)
        pair = grey if grey is not None else tuple(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (left, right))
        estimate = self._vo.process(*pair)
        if estimate is None:
            return np.eye(4) if self.first_pose is None else self.first_pose
        assert self._previous is not None
        return self._previous.raw @ np.linalg.inv(estimate.relative)

    def _compose(self, previous: _Previous, prior_pose: np.ndarray,
                 applied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The corrected pose and the prior's (both from the same first pose) of this frame."""
        from dpc_jax.geometry.pose_correction import corrected_trajectory

        step_prior = np.stack([previous.raw, prior_pose])
        corrected = corrected_trajectory(applied[None], step_prior, previous.pose)[1]
        prior_from_start = corrected_trajectory(np.zeros((1, 6)), step_prior, previous.prior)[1]
        return corrected, prior_from_start
