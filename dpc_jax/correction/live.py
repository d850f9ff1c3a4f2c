"""Corrected visual odometry live: each pose corrected as its stereo pair arrives (docs/method.md §8).

A :class:`LiveCorrector` is built once from a trained run and the camera's calibration; each call
takes one stereo pair as the camera gives it (full size, uint8, grey or colour) and the prior's pose
of that frame, or no prior and it runs dpc_jax's own stereo VO, and returns the frame's corrected
pose (:class:`LiveFrame`). Per frame:

1. The pair is prepared exactly as ``dpc-jax prepare`` prepares a frame
   (``dpc_jax.data.preparation``): resized, matched with StereoSGBM.
2. The previous frame and this one form a two-frame sequence held in memory, on which the network
   predicts ξ for the pair and the measurement gives Δ of its parts, through the same functions as
   ``dpc-jax correct`` (``dpc_jax.engine.predict``): the network was compiled for it before the first
   frame.
3. The parts of ξ (the full correction and its rotation, each whole and without its running mean over
   the last pairs, the rotation also about each camera axis alone)
   are tested sequentially on their Δ (``dpc_jax.correction.acceptance.SequentialTest``: a false
   acceptance stays below α however long it runs, and an accepted part is withdrawn when the evidence
   turns); the pair gets the largest part accepted, in the order of the offline decision
   (``dpc_jax.correction.decision``), or nothing.
4. With a *judge* (``judge_size``, as ``correct``'s judge: the same frames at a larger size, StereoSGBM
   depth, no network), the part the tests would apply is also measured there, and it is applied only
   once its own sequential test at the judge's size has accepted too: at 64×96 the images of a real
   drive can favour a rotation the ground truth does not (``docs/method.md`` §8). The judge's work is
   done only while a part is accepted at the network's size.
5. ``T_w_k = T_w_{k-1} · inv(Exp(ξ_applied) · T_vo_{k,k-1})``: a pose once returned is never changed.

What is kept between frames is what the next frame needs: the previous prepared frame and poses, the
tests' running statistics and the corrections of the last pairs (for the running mean), and with a judge
the previous pair at full size; memory does not grow with the frames.
"""

from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from dpc_jax.correction.acceptance import DEFAULT_ALPHA, SequentialTest
from dpc_jax.correction.corrector import default_acceptance_depth
from dpc_jax.correction.decision import (
    AXES,
    COMPONENTS,
    MEAN_WINDOW,
    Part,
    component_mask,
    part_of,
    rotation_component,
)
from dpc_jax.correction.inference import TrainedRun, load_run
from dpc_jax.correction.judge import judge_rule
from dpc_jax.data.calibration import Calibration
from dpc_jax.data.preparation import as_rgb, prepared_pair, resized_intrinsics
from dpc_jax.data.sequence_cache import (
    SequenceCache,
    decode_flow,
    encode_flow,
    flow_step,
    stereo_depth_views,
)
from dpc_jax.geometry.poses import validate_poses


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
    ``applied``: ``[6]`` the part of it applied (zeros when none); ``state``: which state produced
    the pose: ``start``, ``prior`` (no part accepted yet, or withdrawn), ``forced``, or the part
    applied (``rotation``, ``rotation − mean``, ``full``, ``full − mean``); ``events``: tests
    accepted or withdrawn at this pair; ``seconds``: time per stage: ``vo`` (our VO, or the check of
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
    applied: np.ndarray
    state: str
    events: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)


@dataclass
class _Previous:
    """What the next frame needs of this one."""

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray | None
    raw: np.ndarray  # the prior's camera-to-world pose as given (or as our VO composed it)
    prior: np.ndarray  # the prior's pose composed from the first pose
    pose: np.ndarray  # the corrected one
    full: tuple[np.ndarray, np.ndarray] | None = None  # the pair as given, kept only for a judge
    judged: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None  # prepared at the judge's size


class LiveCorrector:
    """Correct a VO's poses as the frames arrive (module docstring).

    ``run``: a trained run (:class:`~dpc_jax.correction.inference.TrainedRun`, or its folder with
    ``select`` the epoch criterion); ``calibration``: the camera's; ``rotation_only``: None = the
    run's; ``alpha``: the level of the sequential tests; ``mean_test``: test the correction's mean
    apart (False: whole parts only); ``force``: apply the correction to every pair whatever the
    tests say; ``first_pose``: ``[4, 4]`` the pose of frame 0 (default: the prior's first pose, or
    the identity for our VO); ``disparity_offset``: px, the rig's calibration residual the images
    are rectified by (``dpc_jax.data.cache.prepare_sequence``); ``vo``: the configuration of our VO
    when no prior is given (``dpc_jax.vo.VOConfig``); ``judge_size``: ``(H, W)`` px, the size the part to
    apply is judged at as well (module docstring; a Stereo DPC run, no smaller than the run's images
    and no larger than the camera's), None: no judge, or ``"rule"`` (the default): the judge
    ``dpc-jax live`` and ``correct`` use by default (``dpc_jax.correction.judge.judge_rule``: a Stereo
    DPC run smaller than 240×376 is judged at 240×376, no larger than the camera's images), so that the
    API and the command line decide alike. Poses (``first_pose``, each prior) are ``[4, 4]`` or
    ``[3, 4]`` (a KITTI row), rigid; a returned pose is ``[4, 4]``.
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
        force: bool = False,
        first_pose: np.ndarray | None = None,
        disparity_offset: float = 0.0,
        vo: Any = None,
        judge_size: tuple[int, int] | Literal["rule"] | None = "rule",
    ) -> None:
        from dpc_jax.engine.predict import PreparedModel

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
        self.tests = {name: SequentialTest(name, alpha) for name in self._test_names()}
        self._judge_K = self.K
        if judge_size == "rule":
            judge_size = judge_rule(self.run.config.method, self.size, calibration.image_size)
        self.judge_size = None if judge_size is None or self.force else self._checked_judge(judge_size)
        # One test per part judged, made when the part is first to be applied.
        self.judge_tests: dict[str, SequentialTest] = {}
        self._vo_config = vo
        self._vo: Any = None
        self._previous: _Previous | None = None
        # The corrections of the last pairs: the running mean a remainder removes (its window as offline).
        self._recent: deque[np.ndarray] = deque(maxlen=MEAN_WINDOW)
        self._pairs = 0
        self._loss = self.run.config.loss_config()
        self._flow = self.run.use_flow
        # Prepared for the backend once; compiled below, before the first frame.
        self._model = PreparedModel(self.run.graphdef, self.run.state)
        self._compile()

    def _checked_judge(self, size: tuple[int, int]) -> tuple[int, int]:
        from dpc_jax.data.stereo_depth import sgbm_fits

        h, w = (int(x) for x in size)
        (ch, cw), (nh, nw) = self.calibration.image_size, self.size
        if self.run.config.method != "stereo_dpc":
            raise ValueError(f"judge {h}x{w}: a judge measures Δ with stereo depth; the run is "
                             f"{self.run.config.method}")
        if not (nh <= h <= ch and nw <= w <= cw):
            raise ValueError(f"judge {h}x{w}: expected a size between the run's {nh}x{nw} and the camera's "
                             f"{ch}x{cw}")
        K = resized_intrinsics(self.calibration.K, self.calibration.image_size, (h, w))
        if not sgbm_fits(w, float(K[0, 0]), self.calibration.baseline):
            raise ValueError(f"judge {h}x{w}: too narrow for StereoSGBM to match the camera's disparities")
        self._judge_K = K
        return h, w

    def _test_names(self) -> list[str]:
        names = []
        for component in self.components:
            names.append(component)
            if self.mean_test:
                names += [f"mean of {component}", f"{component} − mean"]
        return names + [part.name for part in self._singles()]

    def _singles(self) -> list[Part]:
        """The rotation about each camera axis alone, whole and without its mean: the axis split of the
        offline decision (an accepted rotation is applied about the axes whose own test has accepted)."""
        if "rotation" not in self.components:
            return []
        return [Part(rotation_component(a), remainder) for remainder in ((False, True) if self.mean_test
                                                                          else (False,)) for a in AXES]

    def _compile(self) -> None:
        """Predict, measure and compose once on a blank pair, so that the first frame compiles nothing
        (the composition's compilation alone took 0.4 s)."""
        h, w = self.size
        blank = np.zeros((h, w, 3), np.uint8)
        _, _, disparity = prepared_pair(blank, blank, self.size, self.K, self.calibration.baseline,
                                        match=self.depth == "sgbm")
        frame = _Previous(blank, blank, disparity, np.eye(4), np.eye(4), np.eye(4))
        self._correction_of(self._window(frame, frame, np.eye(4)))
        self._compose(frame, np.eye(4), np.zeros(6))
        if self.judge_size is not None:
            h, w = self.calibration.image_size
            full = np.zeros((h, w, 3), np.uint8)
            judged = _Previous(blank, blank, disparity, np.eye(4), np.eye(4), np.eye(4), (full, full))
            self._judged_delta(judged, judged, np.eye(4), np.zeros(6))

    def _window(self, previous: _Previous, current: _Previous, prior_pose: np.ndarray) -> SequenceCache:
        """The two frames as a cache in memory: what prediction and measurement read."""
        flows: dict[str, Any] = {}
        if self._flow:
            from dpc_jax.data.cache_products import farneback_flow, grey

            step = flow_step(self.size)
            pair = np.stack([farneback_flow(grey(a), grey(b)) for a, b in
                             ((previous.left, current.left), (previous.right, current.right))])
            flows["forward"] = decode_flow(encode_flow(pair, step)[None], step)
        return self._pair_cache(((previous.left, previous.right, previous.disparity),
                                 (current.left, current.right, current.disparity)),
                                self.K, np.stack([previous.raw, prior_pose]), flows)

    def _pair_cache(self, frames: tuple[tuple[np.ndarray, np.ndarray, np.ndarray | None], ...],
                    K: np.ndarray, prior: np.ndarray, flows: dict[str, Any]) -> SequenceCache:
        """Two prepared frames ``(left, right, disparity)`` at the size of ``K``, with the prior's poses
        ``[2, 4, 4]``, as a cache in memory."""
        (left0, right0, disparity0), (left1, right1, disparity1) = frames
        depth = None
        if disparity0 is not None and disparity1 is not None:
            depth = stereo_depth_views(np.stack([disparity0, disparity1]),
                                       float(K[0, 0]) * self.calibration.baseline)
        return SequenceCache(
            path=Path("<live>"), name="live", left=np.stack([left0, left1]), right=np.stack([right0, right1]),
            prior=prior, gt=None, K=K, baseline=self.calibration.baseline, indices=np.arange(2),
            times=np.zeros(2), flows=flows, manifest={}, stereo_depth=depth)

    def _judged_delta(self, previous: _Previous, current: _Previous, prior_pose: np.ndarray,
                      correction: np.ndarray) -> float:
        """Δ of ``correction`` ``[6]`` on the pair at the judge's size (each frame prepared there once)."""
        import jax.numpy as jnp

        from dpc_jax.engine.predict import effects_step, pair_batch

        assert self.judge_size is not None
        for frame in (previous, current):
            if frame.judged is None:
                assert frame.full is not None
                frame.judged = prepared_pair(*frame.full, self.judge_size, self._judge_K,
                                             self.calibration.baseline, self.disparity_offset)
        window = self._pair_cache((previous.judged, current.judged), self._judge_K,  # type: ignore[arg-type]
                                  np.stack([previous.raw, prior_pose]), {})
        batch = pair_batch(window, False, window.stereo_depth)
        candidates = jnp.asarray(correction[None, None], jnp.float32)
        effects = effects_step(None, None, self._loss)(None, batch, candidates, None)
        return float(np.asarray(effects["delta"], np.float64)[0, 0])

    def _correction_of(self, window: SequenceCache,
                       seconds: dict[str, float] | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """ξ ``[6]`` of the window's pair and Δ of each part (running mean included) → ``(ξ, Δ)``;
        ``seconds`` gets the time of the batch's assembly and transfer (added to ``prepare``), of the
        network (``network``) and of the measurement (``measure``).

        The steps of ``correct`` on one pair, assembled and moved to the device once for both: the
        network's forward pass (``dpc_jax.engine.predict.xi_step``; ``correct``'s prediction also
        computes the training loss and Δ of the whole correction, which this does not need), then Δ of
        the parts with the same measurement as ``correct`` (``effects_step``: the stereo depth and no
        network, else the network's depth), L(0) included.
        """
        import jax.numpy as jnp

        from dpc_jax.engine.predict import effects_step, pair_batch, stereo_depth_of

        seconds = {} if seconds is None else seconds
        began = time.perf_counter()
        stereo = stereo_depth_of(window, self.depth)
        batch = pair_batch(window, self._flow, stereo)
        assembled = time.perf_counter()
        seconds["prepare"] = seconds.get("prepare", 0.0) + assembled - began
        xi = np.asarray(self._model.xi_step(self.run.config.method)(self._model.leaves, batch), np.float64)[0]
        predicted = time.perf_counter()
        seconds["network"] = predicted - assembled
        mean = self._running_mean(xi)
        remainders = (False, True) if self.mean_test else (False,)
        measured = [Part(c, r) for c in self.components for r in remainders]
        parts = {part.name: self._vector(xi, part, mean) for part in [*measured, *self._singles()]}
        candidates = jnp.asarray(np.stack(list(parts.values()))[:, None], jnp.float32)
        if stereo is not None and not self.run.config.learn_ssim_weight:
            effects = effects_step(None, None, self._loss)(None, batch, candidates, None)
        else:
            effects = self._model.effects_step(self._loss)(self._model.leaves, batch, candidates, None)
        delta = np.asarray(effects["delta"], np.float64)[:, 0]
        seconds["measure"] = time.perf_counter() - predicted
        return xi, {name: float(delta[i]) for i, name in enumerate(parts)}

    def _running_mean(self, xi: np.ndarray) -> np.ndarray:
        """The mean ``[6]`` of the corrections of the last pairs, ``xi`` (this pair's) the last of them."""
        return np.mean([*self._recent, xi][-MEAN_WINDOW:], axis=0)

    def _vector(self, xi: np.ndarray, part: Part | None, mean: np.ndarray) -> np.ndarray:
        """``part`` of this pair's ``xi`` ``[6]`` (without the running ``mean`` for a remainder); zeros:
        None."""
        if part is None:
            return np.zeros(6)
        if part.remainder:
            return self._remainder(xi, part.component, mean)
        return part_of(xi[None], part.component)[0]

    @staticmethod
    def _remainder(xi: np.ndarray, component: str, mean: np.ndarray) -> np.ndarray:
        """``component`` of ``xi`` ``[6]`` without the same entries of the running ``mean`` ``[6]``."""
        return part_of(xi[None], component, True, mean=mean * component_mask(component))[0]

    def _part(self) -> Part | None:
        """The largest part whose tests have accepted, in the offline decision's order; an accepted
        rotation about the axes whose own test has accepted, when some but not all have."""
        if self.force:
            return Part(self.components[0])
        for component in self.components:
            mean_accepted = not self.mean_test or self.tests[f"mean of {component}"].accepted
            rest_accepted = self.mean_test and self.tests[f"{component} − mean"].accepted
            for remainder, accepted in ((False, self.tests[component].accepted and mean_accepted),
                                        (True, rest_accepted)):
                if not accepted:
                    continue
                if component != "rotation":
                    return Part(component, remainder)
                axes = "".join(a for a in AXES
                               if self.tests[Part(rotation_component(a), remainder).name].accepted)
                return Part(rotation_component(axes) if axes else component, remainder)
        return None

    @property
    def state(self) -> str:
        """``forced``, the part now applied, or ``prior``."""
        if self.force:
            return "forced"
        part = self._judged(self._part())
        return "prior" if part is None else part.name

    def _judged(self, part: Part | None) -> Part | None:
        """``part`` when there is no judge or its test at the judge's size has accepted it, else None."""
        if part is None or self.judge_size is None:
            return part
        test = self.judge_tests.get(part.name)
        return part if test is not None and test.accepted else None

    def __call__(
        self, left: np.ndarray, right: np.ndarray, prior: np.ndarray | None = None, *,
        time_s: float | None = None, grey: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> LiveFrame:
        """Correct the next frame (module docstring).

        ``left``, ``right``: the stereo pair at the calibration's size (uint8, ``[H, W]`` grey or
        ``[H, W, 3]`` RGB); ``prior``: ``[4, 4]`` the prior VO's camera-to-world pose of this frame,
        or None to run our VO (on ``grey``, the pair as grey images, when given: e.g. decoded in
        grey as ``dpc-jax vo`` does; else converted here); ``time_s``: the frame's time, reported.
        """
        began = time.perf_counter()
        seconds: dict[str, float] = {}
        left, right = as_rgb(left, "left"), as_rgb(right, "right")
        if left.shape[:2] != tuple(self.calibration.image_size) or right.shape != left.shape:
            h, w = self.calibration.image_size
            index = self._pairs + (self._previous is not None)
            raise ValueError(f"frame {index}: images of {left.shape[:2]} and {right.shape[:2]}, expected "
                             f"both {h}x{w} (the calibration's)")
        t = time.perf_counter()
        prior_pose = self._prior_pose(left, right, prior, grey)
        seconds["vo"] = time.perf_counter() - t
        t = time.perf_counter()
        small_left, small_right, disparity = prepared_pair(
            left, right, self.size, self.K, self.calibration.baseline, self.disparity_offset,
            match=self.depth == "sgbm")
        current = _Previous(small_left, small_right, disparity, prior_pose, prior_pose, prior_pose,
                            (left, right) if self.judge_size is not None else None)
        seconds["prepare"] = time.perf_counter() - t
        previous = self._previous
        if previous is None:
            start = prior_pose if self.first_pose is None else self.first_pose
            current.pose = current.prior = start
            self._previous = current
            seconds["total"] = time.perf_counter() - began
            return LiveFrame(0, time_s, start.copy(), current.prior.copy(), None, np.zeros(6), "start",
                             (), seconds)
        t = time.perf_counter()
        window = self._window(previous, current, prior_pose)  # with its optical flow, for ss-DPC-Net
        seconds["prepare"] += time.perf_counter() - t
        # What the judge measures is chosen from the tests of the pairs before this one (a choice made
        # after seeing this pair's Δ would select the pairs that favour it).
        candidate = None if self.judge_size is None else self._part()
        xi, delta = self._correction_of(window, seconds)
        events = self._update_tests(delta)
        if candidate is not None:
            t = time.perf_counter()
            judged = self._judged_delta(previous, current, prior_pose,
                                        self._vector(xi, candidate, self._running_mean(xi)))
            test = self.judge_tests.setdefault(candidate.name,
                                               SequentialTest(f"judge: {candidate.name}", self.alpha))
            change = test.update(judged)
            events += () if change is None else (f"{test.name} {change}",)
            seconds["judge"] = time.perf_counter() - t
        applied = self._vector(xi, self._judged(self._part()), self._running_mean(xi))
        self._recent.append(xi)
        self._pairs += 1
        current.pose, current.prior = self._compose(previous, prior_pose, applied)
        self._previous = current
        seconds["total"] = time.perf_counter() - began
        return LiveFrame(self._pairs, time_s, current.pose.copy(), current.prior.copy(), xi, applied,
                         self.state, events, seconds)

    def _prior_pose(self, left: np.ndarray, right: np.ndarray, prior: np.ndarray | None,
                    grey: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """The prior's pose of this frame: given (checked rigid), or our VO's from the previous one."""
        index = self._pairs + (self._previous is not None)
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

    def _update_tests(self, delta: dict[str, float]) -> tuple[str, ...]:
        events = []
        for component in self.components:
            differences = {component: delta[component]}
            if self.mean_test:
                rest = delta[f"{component} − mean"]
                differences |= {f"mean of {component}": delta[component] - rest, f"{component} − mean": rest}
            for name, value in differences.items():
                change = self.tests[name].update(value)
                if change is not None:
                    events.append(f"{name} {change}")
        for single in self._singles():
            change = self.tests[single.name].update(delta[single.name])
            if change is not None:
                events.append(f"{single.name} {change}")
        return tuple(events)

    def _compose(self, previous: _Previous, prior_pose: np.ndarray,
                 applied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The corrected pose and the prior's (both from the same first pose) of this frame."""
        from dpc_jax.geometry.pose_correction import corrected_trajectory

        step_prior = np.stack([previous.raw, prior_pose])
        corrected = corrected_trajectory(applied[None], step_prior, previous.pose)[1]
        prior_from_start = corrected_trajectory(np.zeros((1, 6)), step_prior, previous.prior)[1]
        return corrected, prior_from_start
