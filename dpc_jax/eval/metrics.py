"""Trajectory error metrics (docs/method.md §5, §7): pure, vectorised, jit-compiled ``jnp``.

Inputs are trajectories ``[N, 4, 4]`` of camera-to-world poses ``T_w_c`` — ground truth ``G`` and
estimate ``E`` of the same frames, the estimate already re-anchored to the first ground-truth pose
(see :mod:`dpc_jax.eval.evaluation`). Every function is dtype-preserving (float64 in, float64 out) and
equals a plain float64 loop over poses and segments (:mod:`dpc_jax.eval.reference_metrics`) to rounding.
Rotation errors are reported in degrees, translations in metres, segment errors in % and °/100 m.

Definitions:

* **m-ATE** (ss-DPC-Net): the mean over i of ``‖trans(inv(E_i) G_i)‖`` (m) and of
  ``‖Log(rot(inv(E_i) G_i))‖`` (°). **c-ATE** (Zhang et al. eq. 15): their cumulative sums.
* **Segment errors** (pyslam ``TrajectoryMetrics.segment_errors``, used for the ss-DPC-Net and
  Stereo-DPC tables): ``c`` is the cumulative ground-truth path length (``c_0 = 0``,
  ``c_k = c_{k-1} + ‖p_k − p_{k-1}‖``). For every length L and **every** start frame i the
  segment ends at the first j with ``c_j − c_i > L``; starts with no such j are skipped. The
  error ``Log(inv(inv(E_i) E_j) · inv(G_i) G_j) = [ρ, φ]`` gives ``‖ρ‖ / L`` and ``‖φ‖ / L``.
  Each length's errors are averaged, then the per-length means are averaged (lengths without a
  single segment are left out of that mean and reported as NaN; pyslam would return NaN).
* **KITTI devkit** (``evaluate_odometry.cpp``, ``calcSequenceErrors``): start frames 0, 10,
  20, …; ``dist`` the same cumulative length; the segment ends at the first frame ``j ≥ i`` with
  ``dist_j > dist_i + L``; the error matrix is the same product, but translation is ``‖t‖`` of its
  3×4 form and rotation is ``acos(clip((tr R − 1) / 2, −1, 1))``; all segments of all lengths are
  pooled into one mean (the devkit computes in float32; we compute in the input dtype).
* **ATE** (Zhang eq. 17): RMSE of position differences, after an optional Umeyama alignment of
  the estimate positions onto the ground truth (``se3``: rotation and translation; ``sim3``: with
  scale), as ``evo_ape -a`` / ``-as``.
* **RPE** (Zhang eq. 18–19): RMSE over i of the translation (m) and rotation angle (°) of
  ``inv(inv(G_i) G_{i+Δ}) · inv(E_i) E_{i+Δ}``.
* **Loop closures** (ss-DPC-Net §IV epoch selection, docs/method.md §5): see :func:`count_loop_closures`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from dpc_jax.geometry.lie import se3_inverse, se3_log, so3_log

SEGMENT_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
ALIGNMENTS = ("none", "se3", "sim3")


class SegmentErrors(NamedTuple):
    """Segment errors (pyslam / ss-DPC-Net definition). Scalars are 0-d arrays."""

    trans_pct: Array  # mean of the per-length means, %
    rot_deg_per_100m: Array  # mean of the per-length means, °/100 m
    lengths: Array  # [L] m
    per_length_trans_pct: Array  # [L], NaN where no segment exists
    per_length_rot_deg_per_100m: Array  # [L]
    counts: Array  # [L] int, number of segments per length


class DevkitErrors(NamedTuple):
    """KITTI devkit segment errors: all segments pooled."""

    trans_pct: Array
    rot_deg_per_100m: Array
    count: Array  # number of segments (int)


def _check_pair(gt: Array, est: Array) -> tuple[Array, Array]:
    gt, est = jnp.asarray(gt), jnp.asarray(est)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or gt.shape != est.shape:
        raise ValueError(f"gt and est must both have shape [N, 4, 4]; got {gt.shape} and {est.shape}")
    return gt, est


def _rotation_angle(rotation: Array) -> Array:
    """Angle (rad) of rotations ``[..., 3, 3]``, via the SO(3) log (accurate at small angles)."""
    return jnp.linalg.norm(so3_log(rotation), axis=-1)


@jax.jit
def path_length(trajectory: Array) -> Array:
    """Cumulative path length ``[N]`` (m): ``c_0 = 0``, ``c_k = c_{k-1} + ‖p_k − p_{k-1}‖``.

    Accumulated sequentially (``lax.scan``), bit-for-bit the running sum of a plain loop, so that
    segment end frames agree exactly with the reference implementations.
    """
    positions = trajectory[:, :3, 3]
    steps = jnp.linalg.norm(positions[1:] - positions[:-1], axis=-1)
    zero = jnp.zeros((), positions.dtype)
    _, cumulative = jax.lax.scan(lambda c, s: (c + s, c + s), zero, steps)
    return jnp.concatenate([zero[None], cumulative])


@jax.jit
def pose_errors(gt: Array, est: Array) -> tuple[Array, Array]:
    """Per-pose absolute errors of ``inv(E_i) G_i``: translation ``[N]`` (m), rotation ``[N]`` (rad)."""
    gt, est = _check_pair(gt, est)
    error = se3_inverse(est) @ gt
    return jnp.linalg.norm(error[:, :3, 3], axis=-1), _rotation_angle(error[:, :3, :3])


@jax.jit
def step_corrections(gt: Array, est: Array) -> Array:
    """The correction each step of ``est`` needs: ``Log(G_{k+1,k} · inv(E_{k+1,k}))`` → ``[N-1, 6]``.

    ``[ρ (m), φ (rad)]`` with ``X_{k+1,k} = inv(X_{k+1}) X_k``, so that ``Exp(ξ_k) · E_{k+1,k} =
    G_{k+1,k}`` — the ξ_corr a perfect network would output (docs/method.md §1). Its mean over a
    sequence is the estimate's systematic error per step, its spread the random part.
    """
    gt, est = _check_pair(gt, est)
    g = se3_inverse(gt[1:]) @ gt[:-1]
    e = se3_inverse(est[1:]) @ est[:-1]
    return se3_log(g @ se3_inverse(e))


@jax.jit
def m_ate(gt: Array, est: Array) -> tuple[Array, Array]:
    """Mean absolute trajectory error (ss-DPC-Net): ``(translation m, rotation °)``."""
    trans, rot = pose_errors(gt, est)
    return jnp.mean(trans), jnp.degrees(jnp.mean(rot))


@jax.jit
def c_ate(gt: Array, est: Array) -> tuple[Array, Array]:
    """Cumulative absolute trajectory error (Zhang eq. 15): ``([N] m, [N] °)``."""
    trans, rot = pose_errors(gt, est)
    return jnp.cumsum(trans), jnp.degrees(jnp.cumsum(rot))


def _first_index(predicate: Callable[[Array], Array], shape: tuple[int, ...], n: int) -> Array:
    """Smallest k in ``[0, n]`` with ``predicate(k)`` true, elementwise over ``shape`` (int32).

    ``predicate(k)`` (k an int array of ``shape``, values in ``[0, n)``) must be monotone in k
    (false … false true … true); index ``n`` stands for "none". A vectorised bisection, so the
    result is exactly the index a linear scan with the same float comparison finds.
    """
    lo = jnp.zeros(shape, jnp.int32)
    hi = jnp.full(shape, n, jnp.int32)

    def step(_: int, bounds: tuple[Array, Array]) -> tuple[Array, Array]:
        lo, hi = bounds
        mid = (lo + hi) // 2
        go_left = predicate(jnp.minimum(mid, n - 1))
        active = lo < hi
        return jnp.where(active & ~go_left, mid + 1, lo), jnp.where(active & go_left, mid, hi)

    lo, _ = jax.lax.fori_loop(0, max(n, 1).bit_length() + 1, step, (lo, hi))
    return lo


def _segment_deltas(gt: Array, est: Array, starts: Array, ends: Array) -> Array:
    """``inv(inv(E_i) E_j) · inv(G_i) G_j`` for index arrays of equal shape -> ``[..., 4, 4]``."""
    delta_gt = se3_inverse(gt[starts]) @ gt[ends]
    delta_est = se3_inverse(est[starts]) @ est[ends]
    return se3_inverse(delta_est) @ delta_gt


@functools.partial(jax.jit, static_argnames="lengths")
def segment_error_matrix(
    gt: Array, est: Array, lengths: tuple[float, ...] = SEGMENT_LENGTHS
) -> tuple[Array, Array, Array, Array]:
    """Every segment of the pyslam definition: ``(trans [N, L], rot [N, L], end [N, L], valid [N, L])``.

    Row i, column l: the segment of length ``lengths[l]`` (m) starting at frame i; ``trans`` is
    ``‖ρ‖ / L`` (unitless), ``rot`` is ``‖φ‖ / L`` (rad/m), ``end`` the end frame; entries with
    ``valid`` false (no end frame) are 0 and their ``end`` is N.
    """
    gt, est = _check_pair(gt, est)
    n = gt.shape[0]
    c = path_length(gt)
    length = jnp.asarray(lengths, c.dtype)
    start = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None], (n, len(lengths)))
    # pyslam: searchsorted(c − c[i], L, side="right"), i.e. the first j with c_j − c_i > L.
    end = _first_index(lambda k: c[k] - c[start] > length, start.shape, n)
    valid = end < n
    xi = se3_log(_segment_deltas(gt, est, start, jnp.minimum(end, n - 1)))
    trans = jnp.where(valid, jnp.linalg.norm(xi[..., :3], axis=-1) / length, 0.0)
    rot = jnp.where(valid, jnp.linalg.norm(xi[..., 3:], axis=-1) / length, 0.0)
    return trans, rot, end, valid


@functools.partial(jax.jit, static_argnames="lengths")
def segment_errors(gt: Array, est: Array, lengths: tuple[float, ...] = SEGMENT_LENGTHS) -> SegmentErrors:
    """Segment errors, pyslam / ss-DPC-Net definition (every start frame; see the module docstring)."""
    trans, rot, _, valid = segment_error_matrix(gt, est, lengths)
    return _aggregate_segments(trans, rot, valid, jnp.asarray(lengths, trans.dtype))


def _aggregate_segments(trans: Array, rot: Array, valid: Array, length: Array) -> SegmentErrors:
    """Per-length means of ``[N, L]`` segment errors (zero where invalid), then their mean."""
    counts = jnp.sum(valid, axis=0)
    per_trans = 100.0 * jnp.sum(trans, axis=0) / counts
    per_rot = 100.0 * jnp.degrees(jnp.sum(rot, axis=0) / counts)
    present = counts > 0
    used = jnp.sum(present)
    return SegmentErrors(
        trans_pct=jnp.sum(jnp.where(present, per_trans, 0.0)) / used,
        rot_deg_per_100m=jnp.sum(jnp.where(present, per_rot, 0.0)) / used,
        lengths=length,
        per_length_trans_pct=per_trans,
        per_length_rot_deg_per_100m=per_rot,
        counts=counts,
    )


@functools.partial(jax.jit, static_argnames=("lengths", "step"))
def kitti_devkit_errors(
    gt: Array, est: Array, lengths: tuple[float, ...] = SEGMENT_LENGTHS, step: int = 10
) -> DevkitErrors:
    """Segment errors of the KITTI devkit (start every ``step``-th frame, pooled mean; module docstring)."""
    gt, est = _check_pair(gt, est)
    n = gt.shape[0]
    dist = path_length(gt)
    length = jnp.asarray(lengths, dist.dtype)
    first = jnp.arange(0, n, step, dtype=jnp.int32)
    first = jnp.broadcast_to(first[:, None], (first.shape[0], len(lengths)))
    # lastFrameFromSegmentLength: the first i ≥ first with dist[i] > dist[first] + len.
    last = _first_index(lambda k: dist[k] > dist[first] + length, first.shape, n)
    valid = last < n
    error = _segment_deltas(gt, est, first, jnp.minimum(last, n - 1))
    cos = 0.5 * (jnp.trace(error[..., :3, :3], axis1=-2, axis2=-1) - 1.0)
    r_err = jnp.arccos(jnp.clip(cos, -1.0, 1.0)) / length
    t_err = jnp.linalg.norm(error[..., :3, 3], axis=-1) / length
    count = jnp.sum(valid)
    return DevkitErrors(
        trans_pct=100.0 * jnp.sum(jnp.where(valid, t_err, 0.0)) / count,
        rot_deg_per_100m=100.0 * jnp.degrees(jnp.sum(jnp.where(valid, r_err, 0.0)) / count),
        count=count,
    )


@functools.partial(jax.jit, static_argnames="with_scale")
def umeyama_alignment(source: Array, target: Array, with_scale: bool = False) -> tuple[Array, Array, Array]:
    """Least-squares ``target ≈ s R source + t`` (Umeyama 1991) for points ``[N, 3]``.

    Returns ``(R [3, 3], t [3], s)`` with ``s = 1`` unless ``with_scale``. ``det R = +1`` always.
    """
    mu_s, mu_t = jnp.mean(source, axis=0), jnp.mean(target, axis=0)
    xs, xt = source - mu_s, target - mu_t
    covariance = xt.T @ xs / source.shape[0]
    u, d, vt = jnp.linalg.svd(covariance)
    sign = jnp.where(jnp.linalg.det(u) * jnp.linalg.det(vt) < 0.0, -1.0, 1.0).astype(source.dtype)
    fix = jnp.stack([jnp.ones_like(sign), jnp.ones_like(sign), sign])
    rotation = (u * fix) @ vt
    if with_scale:
        scale = jnp.sum(d * fix) / jnp.mean(jnp.sum(xs * xs, axis=-1))
    else:
        scale = jnp.ones((), source.dtype)
    return rotation, mu_t - scale * rotation @ mu_s, scale


@functools.partial(jax.jit, static_argnames="align")
def ate(gt: Array, est: Array, align: str = "none") -> Array:
    """Absolute trajectory error (m): RMSE of positions, ``align`` in ``none | se3 | sim3``."""
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    gt, est = _check_pair(gt, est)
    p_gt, p_est = gt[:, :3, 3], est[:, :3, 3]
    if align != "none":
        rotation, translation, scale = umeyama_alignment(p_est, p_gt, with_scale=align == "sim3")
        p_est = scale * p_est @ rotation.T + translation
    return jnp.sqrt(jnp.mean(jnp.sum((p_gt - p_est) ** 2, axis=-1)))


@functools.partial(jax.jit, static_argnames="delta")
def rpe(gt: Array, est: Array, delta: int = 1) -> tuple[Array, Array]:
    """Relative pose error over ``delta`` frames: RMSE of translation (m) and rotation (°)."""
    gt, est = _check_pair(gt, est)
    if not 1 <= delta < gt.shape[0]:
        raise ValueError(f"delta must be in [1, N − 1] = [1, {gt.shape[0] - 1}], got {delta}")
    n = gt.shape[0] - delta
    delta_gt = se3_inverse(gt[:n]) @ gt[delta:]
    delta_est = se3_inverse(est[:n]) @ est[delta:]
    error = se3_inverse(delta_gt) @ delta_est
    trans = jnp.linalg.norm(error[:, :3, 3], axis=-1)
    rot = jnp.degrees(_rotation_angle(error[:, :3, :3]))
    return jnp.sqrt(jnp.mean(trans**2)), jnp.sqrt(jnp.mean(rot**2))


@functools.partial(
    jax.jit, static_argnames=("stride", "max_distance", "max_angle_deg", "min_travel", "batch_size")
)
def count_loop_closures(
    trajectory: Array,
    stride: int = 8,
    max_distance: float = 7.0,
    max_angle_deg: float = 8.5,
    min_travel: float = 10.0,
    batch_size: int = 64,
) -> Array:
    """Number of loop-closure events of a trajectory ``[N, 4, 4]`` (int32 scalar).

    An event is a pair of frames ``(t, s)`` with ``t`` a multiple of ``stride`` and ``s > t``
    such that the trajectory's own path length from t to s is at least ``min_travel`` (m), the
    positions are within ``max_distance`` (m), and the relative rotation ``R_tᵀ R_s`` has an angle
    of at most ``max_angle_deg`` (°), i.e. ``(tr(R_tᵀ R_s) − 1) / 2 ≥ cos(max_angle_deg)``.

    This is ss-DPC-Net's criterion for epoch selection without ground truth (its code counts the
    same pairs, starts every 8th frame, 7 m, 10 m of travel, and a heading test of 0.15 rad ≈
    8.5°). Two deliberate differences: the angle is that of the full relative rotation (frame
    independent) rather than a difference of absolute yaws, and revisits in the opposite
    direction do not count (the published yaw test accepted them through an operator-precedence
    slip). Counting pairs rather than start frames makes the count grow with how long and how
    tightly the trajectory re-traverses places it visited, so a better-closing trajectory scores
    higher. Memory is bounded by ``batch_size × N``.
    """
    trajectory = jnp.asarray(trajectory)
    n = trajectory.shape[0]
    c = path_length(trajectory)
    positions, rotations = trajectory[:, :3, 3], trajectory[:, :3, :3]
    cos_max = jnp.cos(jnp.radians(jnp.asarray(max_angle_deg, positions.dtype)))
    frames = jnp.arange(n)

    def events(t: Array) -> Array:
        later = frames > t
        travelled = c - c[t] >= min_travel
        near = jnp.linalg.norm(positions - positions[t], axis=-1) <= max_distance
        cos = 0.5 * (jnp.einsum("ij,nij->n", rotations[t], rotations) - 1.0)
        return jnp.sum(later & travelled & near & (cos >= cos_max), dtype=jnp.int32)

    starts = jnp.arange(0, n, stride)
    return jnp.sum(jax.lax.map(events, starts, batch_size=batch_size), dtype=jnp.int32)


@functools.partial(
    jax.jit, static_argnames=("align", "rpe_delta", "lengths", "devkit_step", "loop_stride")
)
def trajectory_metrics(
    gt: Array,
    est: Array,
    align: str = "none",
    rpe_delta: int = 1,
    lengths: tuple[float, ...] = SEGMENT_LENGTHS,
    devkit_step: int = 10,
    loop_stride: int = 8,
) -> dict[str, Array]:
    """Every metric of this module in one compiled call (what :mod:`dpc_jax.eval.evaluation` reports).

    Keys: ``m_ate_trans_m, m_ate_rot_deg, seg_trans_pct, seg_rot_deg_per_100m, kitti_trans_pct,
    kitti_rot_deg_per_100m, ate_m, rpe_trans_m, rpe_rot_deg, loop_closures`` (scalars) and
    ``seg_lengths_m, seg_per_length_trans_pct, seg_per_length_rot_deg_per_100m, seg_counts``
    ``[L]`` and ``c_ate_trans_m, c_ate_rot_deg`` ``[N]``; each the value of the function named.
    """
    gt, est = _check_pair(gt, est)
    n = gt.shape[0]
    if n < 2:
        raise ValueError(f"a trajectory needs at least 2 poses, got {n}")
    if not 1 <= rpe_delta < n:
        raise ValueError(f"rpe_delta must be in [1, N − 1] = [1, {n - 1}], got {rpe_delta}")
    m_ate_trans, m_ate_rot = m_ate(gt, est)
    c_ate_trans, c_ate_rot = c_ate(gt, est)
    seg = segment_errors(gt, est, lengths)
    devkit = kitti_devkit_errors(gt, est, lengths, devkit_step)
    rpe_trans, rpe_rot = rpe(gt, est, rpe_delta)
    return {
        "m_ate_trans_m": m_ate_trans,
        "m_ate_rot_deg": m_ate_rot,
        "seg_trans_pct": seg.trans_pct,
        "seg_rot_deg_per_100m": seg.rot_deg_per_100m,
        "kitti_trans_pct": devkit.trans_pct,
        "kitti_rot_deg_per_100m": devkit.rot_deg_per_100m,
        "ate_m": ate(gt, est, align),
        "rpe_trans_m": rpe_trans,
        "rpe_rot_deg": rpe_rot,
        "loop_closures": count_loop_closures(est, stride=loop_stride),
        "seg_lengths_m": seg.lengths,
        "seg_per_length_trans_pct": seg.per_length_trans_pct,
        "seg_per_length_rot_deg_per_100m": seg.per_length_rot_deg_per_100m,
        "seg_counts": seg.counts,
        "c_ate_trans_m": c_ate_trans,
        "c_ate_rot_deg": c_ate_rot,
    }
