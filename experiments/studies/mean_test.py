"""The test of a correction's mean on real pairs: how often a wrong mean gets through, how often a right one.

A correction that fits each step's error well passes the per-pair test whatever small mean it carries;
the mean is what drifts a trajectory, so ``dpc_jax.correction.decision`` tests it on its own (``mean of
X``: ``Δ(whole) − Δ(whole − mean)`` below zero). This study measures that test where it matters, on the
real drives' images, with planted errors whose truth is known:

* The images' motion is libviso2-s's (the excerpt's images side with the VOs over the GPS/IMU poses:
  ``docs/results/excerpt_ground_truth.md``); each trial plants a per-step rotation error ``n_k`` of
  libviso2-s's spread (the detection-limit study's ×1, zero mean over the drive) on it.
* **A wrong mean** (the false acceptance): the prior carries ``n_k`` alone and the correction is
  ``n_k + m``, right about every step and with a mean ``m`` of size s in a random direction, which can
  only harm. The earlier decision (whole parts only) applies it whenever the whole passes; the mean test
  should refuse it.
* **A right mean** (the power): the prior carries ``n_k + m`` and the correction is ``n_k + m``.

Per drive, network size (64×96, and the judge's 240×376) and s (×1 and ×3 libviso2-s's rotation bias),
the table gives the share of trials in which the whole passed (what the earlier decision applied), in
which the mean passed its own test, and in which the whole was applied under the new decision (both).
Δ with StereoSGBM depth on each size's prepared frames, no network: what the acceptance test measures.

    python experiments/studies/mean_test.py --workdir runs/mean_test --results-page docs/results/mean_test.md
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dpc_jax.experiments.script import (
    Clock,
    add_kitti_raw_option,
    add_results_page,
    claim,
    data_given,
    interruptible,
    new_parser,
    publish,
    refuse,
)
from dpc_jax.pipelines.protocol import path_argument

if TYPE_CHECKING:
    from dpc_jax.data.sequence_cache import SequenceCache

HERE = Path(__file__).resolve().parent
DATE = "2011_09_26"
DRIVES = {"0001": "libviso2/stereo_2011_09_26_drive_0001.mat",
          "0005": "libviso2/stereo_2011_09_26_drive_0005.mat"}
SIZES = ((64, 96), (240, 376))
# libviso2-s's per-step rotation error on KITTI 00, 02, 05-10 (median of `evaluate --diagnose`, mrad,
# camera x, y, z): its spread, and the norm of its mean (the detection-limit study's ×1).
SPREAD_MRAD = (0.57, 0.87, 0.59)
BIAS_MRAD = 0.259
SCALES = (1.0, 3.0)


def planted(prior: np.ndarray, error: np.ndarray) -> np.ndarray:
    """The trajectory ``[N, 4, 4]`` whose steps are ``prior``'s with the rotation error ``error`` ``[N-1, 6]``
    planted: ``T'_{k+1,k} = Exp(−e_k) · T_{k+1,k}`` (so ``ξ_k = e_k`` corrects it exactly)."""
    from dpc_jax.geometry.lie import se3_exp
    from dpc_jax.geometry.poses import compose, relative_poses

    steps = np.asarray(se3_exp(-error), np.float64) @ relative_poses(prior)
    return compose(steps, prior[0])


def trial(cache: SequenceCache, seed: int, size_mrad: float, right: bool) -> tuple[bool, bool]:
    """One trial on ``cache`` (a prepared drive): ``(whole passed, mean passed)``."""
    from dpc_jax.correction.acceptance import paired_test
    from dpc_jax.engine.predict import measure_effects
    from dpc_jax.nn.model_config import StereoDPCLossConfig

    rng = np.random.default_rng(seed)
    pairs = len(cache) - 1
    noise = np.zeros((pairs, 6))
    noise[:, 3:] = rng.normal(size=(pairs, 3)) * 1e-3 * np.asarray(SPREAD_MRAD)
    noise -= noise.mean(axis=0)
    direction = rng.normal(size=3)
    mean = np.zeros(6)
    mean[3:] = size_mrad * 1e-3 * direction / np.linalg.norm(direction)
    proposal = noise + mean
    prior = planted(np.asarray(cache.prior, np.float64), proposal if right else noise)
    tested = dataclasses.replace(cache, prior=prior)
    remainder = proposal - proposal.mean(axis=0)
    delta = measure_effects(tested, np.stack([proposal, remainder]), StereoDPCLossConfig(rotation_only=True),
                            batch_size=8, stereo_depth=tested.stereo_depth)["delta"]
    return paired_test("whole", delta[0]).passed, paired_test("mean", delta[0] - delta[1]).passed


def markdown(rows: list[dict[str, Any]], trials: int, minutes: float) -> str:
    from dpc_jax.report.tables import table

    def share(value: float) -> str:
        return f"{100 * value:.0f} %"

    body = table(
        ["drive", "size", "pairs", "mean (mrad)", "wrong mean: whole passed (earlier decision applies it)",
         "wrong mean: mean passed", "wrong mean: applied now", "right mean: whole passed",
         "right mean: mean passed", "right mean: applied now"],
        ([str(r["drive"]), str(r["size"]), str(r["pairs"]), f"{r['mrad']:.2f}", share(r["wrong_whole"]),
          share(r["wrong_mean"]), share(r["wrong_applied"]), share(r["right_whole"]), share(r["right_mean"]),
          share(r["right_applied"])] for r in rows))
    worst = max(float(r["wrong_applied"]) for r in rows)
    bound = 3 * math.sqrt(0.01 * 0.99 / trials)
    return "\n".join([
        "# The test of a correction's mean on real pairs", "",
        f"{trials} trials per row (each a planted per-step rotation error of libviso2-s's spread and a mean "
        f"in a random direction); level 0.01; {minutes:.0f} min. Wrong mean: the correction is right about "
        "every step and its mean can only harm; right mean: the prior carries that mean.", "",
        body, "",
        f"Largest share of wrong means applied now: {100 * worst:.1f} % (the test's nominal rate is 1 %; "
        f"with {trials} trials a share up to {100 * (0.01 + bound):.1f} % is within three standard errors of "
        "it).", ""])


def main(argv: Sequence[str] | None = None) -> int:
    parser = new_parser(__doc__)
    parser.add_argument("--workdir", type=path_argument, required=True, help="caches go here")
    add_kitti_raw_option(parser)
    parser.add_argument("--trials", type=int, default=40, metavar="N", help="trials per row")
    add_results_page(parser)
    args = parser.parse_args(argv)
    from dpc_jax._io import atomic_write

    try:
        if args.trials < 1:
            raise ValueError(f"--trials {args.trials}: expected 1 or more")
        raw = data_given(args.kitti_raw, "--kitti-raw")
        workdir = claim(args.workdir, [("--kitti-raw", raw)], script=__file__,
                        page=args.results_page)
        assert workdir is not None
        from dpc_jax.data.cache import prepare_sequence
        from dpc_jax.data.kitti import open_raw
        from dpc_jax.data.poses_io import read_trajectory
        from dpc_jax.data.sequence_cache import load_cache

        caches = {}
        for drive, mat in DRIVES.items():
            sequence = open_raw(raw, DATE, drive)
            prior = read_trajectory(raw / mat, mat_key="poses_est")[:len(sequence)]
            for size in SIZES:
                path = prepare_sequence(sequence, prior, workdir / "cache" / f"{size[0]}x{size[1]}",
                                        size=size, progress=False)
                caches[drive, size] = load_cache(path)
    except (OSError, ValueError) as error:
        return refuse("mean_test", error)
    clock = Clock()
    rows = []
    for (drive, size), cache in caches.items():
        for scale in SCALES:
            mrad = scale * BIAS_MRAD
            counts = {}
            for right in (False, True):
                outcomes = np.array([trial(cache, seed, mrad, right) for seed in range(args.trials)])
                key = "right" if right else "wrong"
                counts |= {f"{key}_whole": outcomes[:, 0].mean(), f"{key}_mean": outcomes[:, 1].mean(),
                           f"{key}_applied": (outcomes[:, 0] & outcomes[:, 1]).mean()}
            rows.append({"drive": drive, "size": f"{size[0]}×{size[1]}", "pairs": len(cache) - 1,
                         "mrad": mrad, **counts})
            clock.say(str(rows[-1]))
    text = markdown(rows, args.trials, clock.minutes)
    atomic_write(workdir / "mean_test.md", text)
    publish(text, args.results_page, __file__)
    return 0


if __name__ == "__main__":
    sys.exit(interruptible(main, __file__))
