"""Bias recovery: can self-supervised training remove a systematic yaw bias from the VO prior?

The scientific check of self-supervision. Synthetic stereo sequences (``dpc_jax.synth``) are rendered in the
KITTI odometry layout; each sequence's prior is its true trajectory with every relative pose
perturbed as ``T_vo = [[Exp(φ_bias + φ_noise), ρ_noise], [0, 1]] · T_gt_{t+1,t}``, where
``φ_bias`` is a yaw (rotation about the camera's y axis) of ``--bias-deg`` per frame and the
noise is Gaussian (``--rot-noise-deg`` per axis, ``--trans-noise`` m per axis). Stereo DPC with
the ``small`` preset is trained on the training sequences (config
``experiments/studies/configs/bias_recovery.py``), the epoch is selected by the validation gradient loss
(no ground truth), and the held-out test sequence is corrected. Pass: the rotational segment
error of the corrected test trajectory is at least 50 % lower than the prior's.

    python experiments/studies/bias_recovery.py                # render, prepare, train, evaluate
    python experiments/studies/bias_recovery.py --resume       # continue an interrupted training

Writes ``OUT/data`` (rendered layout), ``OUT/cache`` (prepared caches, whatever the config's
``cache_root``), ``OUT/run`` (the training run) and ``OUT/result.json``, ``OUT`` being ``--out DIR``
(default ``runs/bias_recovery`` in the current folder); prints a table. Exit status 0 when the check
passes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from dpc_jax import config as config_lib
from dpc_jax.experiments import script as kit
from dpc_jax.experiments.script import interruptible
from dpc_jax.experiments.world import World
from dpc_jax.geometry.poses import compose, relative_poses
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.report.tables import change_pct, table
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

ROOT = Path(__file__).resolve().parents[2]


def biased_prior(
    gt: np.ndarray, bias_deg: float, rot_noise_deg: float, trans_noise: float, seed: int
) -> np.ndarray:
    """The true trajectory with each relative pose perturbed on the left by bias and noise."""
    rng = np.random.default_rng(seed)
    relative = relative_poses(gt)
    n = relative.shape[0]
    rotvec = np.radians(rng.normal(0.0, rot_noise_deg, (n, 3)))
    rotvec[:, 1] += np.radians(bias_deg)
    perturbation = np.tile(np.eye(4), (n, 1, 1))
    perturbation[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    perturbation[:, :3, 3] = rng.normal(0.0, trans_noise, (n, 3))
    return compose(perturbation @ relative, gt[0])


def make_data(out: Path, config: Any, args: argparse.Namespace) -> None:
    """Render every sequence of the split (sequence i seeded 100 + i, at twice the network's size) and
    prepare its cache with the biased prior."""
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import open_odometry
    from dpc_jax.synth import sequence_poses

    names = [*config.train_sequences, *config.validation_sequences, *config.test_sequences]
    world = World((2 * config.image_size[0], 2 * config.image_size[1]), seed=100)
    world.render(out / "data", {name: (args.frames, i) for i, name in enumerate(names)})
    for i, name in enumerate(names):
        began = time.perf_counter()
        gt = sequence_poses(world.config(args.frames, i))[0]  # exact, as rendered
        prior = biased_prior(gt, args.bias_deg, args.rot_noise_deg, args.trans_noise, seed=200 + i)
        sequence = open_odometry(out / "data", name)
        prepare_sequence(sequence, prior, out / "cache", size=config.image_size, progress=False)
        print(f"{name}: {args.frames} frames, {trajectory_length(gt):.0f} m, "
              f"{time.perf_counter() - began:.0f} s", flush=True)


def trajectory_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def evaluate_test(config: Any, workdir: Path, selection: str) -> dict[str, float]:
    """Correct the test sequence with the epoch chosen by ``selection`` (acceptance test on its own
    images); prior vs corrected."""
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.inference import load_run
    from dpc_jax.eval import metrics

    run = load_run(workdir, selection)
    [name] = config.test_sequences
    correction = correct_cache(run, Path(config.cache_root) / name)
    prior, gt, corrected = correction.prior, correction.ground_truth, correction.corrected
    result = {"selection": selection, "epoch": run.epoch, "applied": correction.part}
    for label, estimate in (("prior", prior), ("network", correction.proposed), ("corrected", corrected)):
        errors = metrics.segment_errors(gt, estimate)
        result[f"{label}_r_err"] = float(errors.rot_deg_per_100m)
        result[f"{label}_t_err"] = float(errors.trans_pct)
    truth, vo = relative_poses(gt), relative_poses(prior)
    needed = Rotation.from_matrix(truth[:, :3, :3] @ np.swapaxes(vo[:, :3, :3], 1, 2))
    result["mean_yaw_needed_deg"] = float(np.degrees(needed.as_rotvec()[:, 1].mean()))
    result["mean_yaw_correction_deg"] = float(np.degrees(correction.xi_corr[:, 4].mean()))
    result["r_err_reduction_pct"] = -change_pct(result["prior_r_err"], result["corrected_r_err"])
    return result


def main(argv: list[str] | None = None) -> int:
    parser = kit.new_parser(__doc__)
    parser.add_argument("--config", type=path_argument,
                        default=ROOT / "experiments/studies/configs/bias_recovery.py")
    parser.add_argument("--out", type=path_argument, default=Path("runs/bias_recovery"), metavar="DIR",
                        help="everything goes here (default: runs/bias_recovery in the current folder)")
    parser.add_argument("--frames", type=int, default=200, help="frames per synthetic sequence")
    parser.add_argument("--bias-deg", type=float, default=0.15, help="yaw bias per frame (°)")
    parser.add_argument("--rot-noise-deg", type=float, default=0.01, help="rotation noise per axis (°)")
    parser.add_argument("--trans-noise", type=float, default=0.005, help="translation noise per axis (m)")
    parser.add_argument("--resume", action="store_true", help="continue the training run in OUT/run")
    args = parser.parse_args(argv)

    from dpc_jax.training.loop import train
    from dpc_jax.training.train_config import TrainConfig

    try:
        config = config_lib.load_file(args.config, TrainConfig)
        kit.claim(args.out, [("--config", args.config)], option="--out", script=__file__)
    except (OSError, ValueError) as error:  # a ConfigError is a ValueError
        return kit.refuse("bias_recovery", error)
    # The script makes the caches it trains on, in OUT/cache: the config's cache_root is not read.
    cache_root = (args.out / "cache").resolve()
    config = config_lib.from_dict(TrainConfig, {**config_lib.to_dict(config), "cache_root": str(cache_root)})

    make_data(args.out, config, args)
    began = time.perf_counter()
    summary = train(config, args.out / "run", resume=args.resume)
    minutes = (time.perf_counter() - began) / 60
    results = [evaluate_test(config, args.out / "run", s) for s in ("delta", "last")]
    print(f"\ntraining: {config.epochs} epochs, {summary['step']} steps, {minutes:.1f} min")
    header = ["selection", "epoch", "applied", "r_err prior (°/100m)", "r_err network", "r_err corrected",
              "reduction", "t_err prior (%)", "t_err corrected", "mean yaw needed (°)",
              "mean yaw correction (°)"]
    print(table(header, ([
        r["selection"], str(r["epoch"]), r["applied"], f"{r['prior_r_err']:.3f}",
        f"{r['network_r_err']:.3f}", f"{r['corrected_r_err']:.3f}", f"{r['r_err_reduction_pct']:.1f} %",
        f"{r['prior_t_err']:.2f}", f"{r['corrected_t_err']:.2f}", f"{r['mean_yaw_needed_deg']:.4f}",
        f"{r['mean_yaw_correction_deg']:.4f}",
    ] for r in results)), end="")
    passed = results[0]["r_err_reduction_pct"] >= 50.0
    record = {"passed": passed, "training_minutes": minutes, "results": results,
              "args": {k: str(v) for k, v in vars(args).items()}, "config": config_lib.to_dict(config)}
    config_lib.save_json(args.out / "result.json", record)
    print(("PASS" if passed else "FAIL") + ": the corrected test trajectory's rotational segment error is "
          f"{results[0]['r_err_reduction_pct']:.1f} % lower than the prior's (needed: >= 50 %)")
    return 0 if passed else 1


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
