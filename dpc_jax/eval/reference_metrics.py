"""Plain float64 numpy reference implementations (loops) of the trajectory metrics.

Written straight from the definitions of docs/method.md §5–§7 and the published code they describe
(pyslam ``TrajectoryMetrics.segment_errors``, the KITTI devkit ``evaluate_odometry.cpp``,
ss-DPC-Net's static-frame loop), one pose or one segment at a time, with scipy's rotation
vector as an independent SO(3) log: the reference the compiled metrics (:mod:`dpc_jax.eval.metrics`) are
tested against to 1e-9 and timed against (``benchmarks/bench_metrics.py``, ``bench_cli.py``). Its numpy
SE(3) functions (``so3_hat``, ``se3_exp``, ``se3_log``, ``se3_logm``) are the tests' references for the
Lie algebra too. Numpy and scipy only: no JAX.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.spatial.transform import Rotation

LENGTHS = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)


def inv(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T)


def so3_log(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def so3_hat(phi: np.ndarray) -> np.ndarray:
    """The skew matrix ``φ^`` with ``φ^ v = φ × v``."""
    return np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """``Exp([ρ, φ])`` as scipy's matrix exponential of the se(3) matrix (an independent reference)."""
    twist = np.zeros((4, 4))
    twist[:3, :3] = so3_hat(xi[3:])
    twist[:3, 3] = xi[:3]
    return scipy.linalg.expm(twist)


def se3_log(T: np.ndarray) -> np.ndarray:
    """``[ρ, φ]`` with ``ρ = J⁻¹(φ) t`` (Barfoot's closed form)."""
    phi = so3_log(T[:3, :3])
    theta = np.linalg.norm(phi)
    hat = so3_hat(phi)
    if theta < 1e-6:
        j_inv = np.eye(3) - 0.5 * hat + hat @ hat / 12.0
    else:
        j_inv = (
            np.eye(3) - 0.5 * hat
            + (1.0 / theta**2 - (1.0 + np.cos(theta)) / (2.0 * theta * np.sin(theta))) * hat @ hat
        )
    return np.concatenate([j_inv @ T[:3, 3], phi])


def se3_logm(T: np.ndarray) -> np.ndarray:
    """``[ρ, φ]`` of a rigid transform read off scipy's general matrix logarithm ``[[φ^, ρ], [0, 0]]``."""
    log = np.real(scipy.linalg.logm(T))
    return np.array([log[0, 3], log[1, 3], log[2, 3], log[2, 1], log[0, 2], log[1, 0]])


def remove_static_frames(prior: np.ndarray, trans: float = 1.5, rot: float = 0.007) -> np.ndarray:
    """The ss-DPC-Net loop: drop frame i of even pairs (i, i+1) that barely move; repeat."""
    kept = list(range(prior.shape[0]))
    while True:
        drop = []
        for i in range(0, len(kept) - 1, 2):
            xi = se3_log(inv(prior[kept[i + 1]]) @ prior[kept[i]])
            if np.linalg.norm(xi[:3]) < trans and np.linalg.norm(xi[3:]) < rot:
                drop.append(kept[i])
        if not drop:
            return np.array(kept)
        kept = [k for k in kept if k not in set(drop)]


def cumulative_distance(traj: np.ndarray) -> np.ndarray:
    steps = [0.0] + [float(np.linalg.norm(traj[i, :3, 3] - traj[i - 1, :3, 3])) for i in range(1, len(traj))]
    return np.cumsum(steps)


def pose_errors(gt: np.ndarray, est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose ‖trans(inv(E_i) G_i)‖ (m) and ‖Log rot(inv(E_i) G_i)‖ (rad)."""
    trans, rot = [], []
    for i in range(len(gt)):
        err = inv(est[i]) @ gt[i]
        trans.append(np.linalg.norm(err[:3, 3]))
        rot.append(np.linalg.norm(so3_log(err[:3, :3])))
    return np.array(trans), np.array(rot)


def m_ate(gt: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    trans, rot = pose_errors(gt, est)
    return float(np.mean(trans)), float(np.degrees(np.mean(rot)))


def c_ate(gt: np.ndarray, est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    trans, rot = pose_errors(gt, est)
    return np.cumsum(trans), np.degrees(np.cumsum(rot))


def segment_error(gt: np.ndarray, est: np.ndarray, start: int, length: float) -> tuple[float, float] | None:
    """pyslam: end = searchsorted(c − c[start], L, 'right'); (‖ρ‖/L, ‖φ‖/L) or None."""
    c = cumulative_distance(gt)
    stop = int(np.searchsorted(c - c[start], length, side="right"))
    if stop >= len(gt):
        return None
    delta_gt = inv(gt[start]) @ gt[stop]
    delta_est = inv(est[start]) @ est[stop]
    xi = se3_log(inv(delta_est) @ delta_gt)
    return float(np.linalg.norm(xi[:3]) / length), float(np.linalg.norm(xi[3:]) / length)


def segment_errors(
    gt: np.ndarray, est: np.ndarray, lengths: tuple[float, ...] = LENGTHS
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """(trans %, rot °/100 m, per-length trans %, per-length rot °/100 m, counts): every start frame."""
    c = cumulative_distance(gt)
    per_t: list[float] = []
    per_r: list[float] = []
    counts = []
    for length in lengths:
        errs = []
        for start in range(len(gt)):
            stop = int(np.searchsorted(c - c[start], length, side="right"))
            if stop < len(gt):
                xi = se3_log(inv(inv(est[start]) @ est[stop]) @ (inv(gt[start]) @ gt[stop]))
                errs.append((np.linalg.norm(xi[:3]) / length, np.linalg.norm(xi[3:]) / length))
        counts.append(len(errs))
        if errs:
            per_t.append(100.0 * float(np.mean([e[0] for e in errs])))
            per_r.append(100.0 * float(np.degrees(np.mean([e[1] for e in errs]))))
        else:
            per_t.append(np.nan)
            per_r.append(np.nan)
    t, r = np.array(per_t), np.array(per_r)
    return float(np.nanmean(t)), float(np.nanmean(r)), t, r, np.array(counts)


def kitti_devkit_errors(
    gt: np.ndarray, est: np.ndarray, lengths: tuple[float, ...] = LENGTHS, step: int = 10
) -> tuple[float, float, int]:
    """evaluate_odometry.cpp calcSequenceErrors + the pooled mean: (trans %, rot °/100 m, count)."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[i - 1] + float(np.linalg.norm(gt[i - 1, :3, 3] - gt[i, :3, 3])))
    t_errs, r_errs = [], []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = -1
            for i in range(first, len(gt)):
                if dist[i] > dist[first] + length:
                    last = i
                    break
            if last == -1:
                continue
            err = inv(inv(est[first]) @ est[last]) @ (inv(gt[first]) @ gt[last])
            d = 0.5 * (err[0, 0] + err[1, 1] + err[2, 2] - 1.0)
            r_errs.append(np.arccos(max(min(d, 1.0), -1.0)) / length)
            t_errs.append(np.linalg.norm(err[:3, 3]) / length)
    return 100.0 * float(np.mean(t_errs)), 100.0 * float(np.degrees(np.mean(r_errs))), len(t_errs)


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """``target ≈ s R source + t`` in the least-squares sense (Umeyama 1991)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    cov = sum(np.outer(y - mu_t, x - mu_s) for x, y in zip(source, target, strict=True)) / len(source)
    u, d, vt = np.linalg.svd(cov)
    s_fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_fix[2, 2] = -1.0
    rot = u @ s_fix @ vt
    var_s = np.mean(np.sum((source - mu_s) ** 2, axis=1))
    scale = float(np.trace(np.diag(d) @ s_fix) / var_s) if with_scale else 1.0
    return rot, mu_t - scale * rot @ mu_s, scale


def ate(gt: np.ndarray, est: np.ndarray, align: str = "none") -> float:
    p_gt, p_est = gt[:, :3, 3], est[:, :3, 3]
    if align != "none":
        rot, t, s = umeyama(p_est, p_gt, with_scale=align == "sim3")
        p_est = np.array([s * rot @ p + t for p in p_est])
    return float(np.sqrt(np.mean([np.sum((a - b) ** 2) for a, b in zip(p_gt, p_est, strict=True)])))


def rpe(gt: np.ndarray, est: np.ndarray, delta: int = 1) -> tuple[float, float]:
    trans, rot = [], []
    for i in range(len(gt) - delta):
        err = inv(inv(gt[i]) @ gt[i + delta]) @ (inv(est[i]) @ est[i + delta])
        trans.append(np.linalg.norm(err[:3, 3]) ** 2)
        rot.append(np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) ** 2)
    return float(np.sqrt(np.mean(trans))), float(np.sqrt(np.mean(rot)))


def count_loop_closures(
    traj: np.ndarray, stride: int = 8, max_distance: float = 7.0, max_angle_deg: float = 8.5,
    min_travel: float = 10.0,
) -> int:
    """Pairs (t, s), t on the stride, s > t: travelled ≥ min_travel, within the distance and angle.

    A loop over start frames t (inner comparisons vectorised over s, as ss-DPC-Net's own code).
    """
    c = cumulative_distance(traj)
    cos_max = np.cos(np.radians(max_angle_deg))
    count = 0
    for t in range(0, len(traj), stride):
        later = traj[t + 1 :]
        travelled = c[t + 1 :] - c[t] >= min_travel
        near = np.linalg.norm(later[:, :3, 3] - traj[t, :3, 3], axis=1) <= max_distance
        cos = 0.5 * (np.einsum("ij,nij->n", traj[t, :3, :3], later[:, :3, :3]) - 1.0)
        count += int(np.sum(travelled & near & (cos >= cos_max)))
    return count
