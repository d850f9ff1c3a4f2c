"""Speed of the jitted trajectory metrics against their plain float64 loops.

    python benchmarks/bench_metrics.py [--mat PATH] [--repeats 7] [--reference-repeats 1]

Uses the libviso2-s estimate of KITTI 00 (4541 poses) by default. Our times are the median of
``--repeats`` calls after a warm-up call (compilation excluded; compile time is printed apart);
the reference loops (``dpc_jax.eval.reference_metrics``) run ``--reference-repeats`` times.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from dpc_jax.data.poses_io import read_mat  # noqa: E402
from dpc_jax.eval import metrics  # noqa: E402
from dpc_jax.eval import reference_metrics as ref  # noqa: E402
from dpc_jax.runtime.hugepages import reexec_with_huge_pages  # noqa: E402
from dpc_jax.runtime.machine import this_cpu  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MAT = ROOT.parent / "shared" / "data" / "kitti-libviso2" / "stereo_00.mat"


def median_time(function: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mat", type=Path, default=DEFAULT_MAT)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--reference-repeats", type=int, default=1)
    args = parser.parse_args()
    if not args.mat.is_file():  # one line before any work, not a traceback from deep inside
        raise SystemExit(f"bench_metrics: error: --mat {args.mat}: no such file (expected libviso2-s's "
                         "stereo_XX.mat with ground truth, as in ../shared/data/kitti-libviso2/)")

    gt, est = read_mat(args.mat)
    n = gt.shape[0]
    cases: list[tuple[str, Callable[[], object], Callable[[], object]]] = [
        ("m_ate", lambda: metrics.m_ate(gt, est), lambda: ref.m_ate(gt, est)),
        ("segment_errors", lambda: metrics.segment_errors(gt, est), lambda: ref.segment_errors(gt, est)),
        ("kitti_devkit_errors", lambda: metrics.kitti_devkit_errors(gt, est),
         lambda: ref.kitti_devkit_errors(gt, est)),
        ("ate (sim3)", lambda: metrics.ate(gt, est, "sim3"), lambda: ref.ate(gt, est, "sim3")),
        ("rpe", lambda: metrics.rpe(gt, est), lambda: ref.rpe(gt, est)),
        ("count_loop_closures (gt)", lambda: metrics.count_loop_closures(gt),
         lambda: ref.count_loop_closures(gt)),
    ]
    references = [reference for _, _, reference in cases]
    cases.append((
        "trajectory_metrics (all)",
        lambda: metrics.trajectory_metrics(gt, est, align="sim3"),
        lambda: [reference() for reference in references],
    ))

    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), {this_cpu()}, float64, "
          f"trajectory {args.mat.name}: N = {n} poses, 8 segment lengths")
    print(f"{'metric':<26} {'compile s':>10} {'ours ms':>10} {'loop s':>10} {'speed-up':>10}")
    for name, ours, reference in cases:
        start = time.perf_counter()
        jax.block_until_ready(ours())
        compile_s = time.perf_counter() - start
        ours_s = median_time(ours, args.repeats)
        ref_s = median_time(reference, args.reference_repeats)
        print(f"{name:<26} {compile_s:>10.2f} {1e3 * ours_s:>10.2f} {ref_s:>10.2f} {ref_s / ours_s:>9.0f}×")


if __name__ == "__main__":
    reexec_with_huge_pages()
    main()
