"""Whole-process time of ``dpc-jax evaluate``, first and repeated, against the plain float64 loops.

    python benchmarks/bench_cli.py [--mat PATH] [--repeats 3]

Three commands, each run as a new process and timed by the wall clock from start to exit:

* ``dpc-jax evaluate --mat FILE --json -`` with an empty compilation cache (``cold``: the first run);
* the same with the cache the cold run filled (``warm``: every later run;
  ``dpc_jax.runtime.compilation_cache``);
* the same metrics by the float64 loops of ``dpc_jax.eval.reference_metrics`` (``float64 loop``), this
  script run with ``--reference-loop FILE``: it reads the file, re-anchors the estimate as
  ``evaluate`` does and prints the same JSON summary, without JAX.

One unmeasured round first (it fills the operating system's file cache), then ``--repeats`` rounds of
cold, warm, loop in turn, so that drift in the machine's speed reaches all three alike; the table gives
the medians. The numbers must agree: cold and warm print the same bytes, the loop the same values to
1e-9. Uses the libviso2-s estimate of KITTI 00 (4541 poses) by default.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dpc_jax.runtime.machine import this_cpu

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MAT = ROOT.parent / "shared" / "data" / "kitti-libviso2" / "stereo_00.mat"


def reference_loop(mat: Path) -> str:
    """The JSON summary of ``dpc-jax evaluate --mat mat --json -``, computed by the float64 loops."""
    import numpy as np

    from dpc_jax.data.poses_io import read_mat
    from dpc_jax.eval import reference_metrics as ref
    from dpc_jax.eval.evaluation import SUMMARY_KEYS

    gt, est = read_mat(mat)
    est = gt[0] @ np.linalg.inv(est[0]) @ est
    seg = ref.segment_errors(gt, est)
    values = [*ref.m_ate(gt, est), seg[0], seg[1], *ref.kitti_devkit_errors(gt, est)[:2], ref.ate(gt, est),
              *ref.rpe(gt, est), ref.count_loop_closures(est)]
    summary = dict(zip(SUMMARY_KEYS, values, strict=True))
    return json.dumps({"num_poses": int(gt.shape[0]), "estimates": {"est": summary}}, indent=2) + "\n"


def timed(command: list[str], env: dict[str, str]) -> tuple[float, str]:
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=env, check=True)
    return time.perf_counter() - start, done.stdout


def agree(ours: str, loop: str) -> bool:
    a, b = (json.loads(text)["estimates"]["est"] for text in (ours, loop))
    return a.keys() == b.keys() and all(
        a[k] == b[k] if isinstance(b[k], int) else math.isclose(a[k], b[k], rel_tol=1e-9, abs_tol=1e-12)
        for k in a
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mat", type=Path, default=DEFAULT_MAT)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reference-loop", type=Path, metavar="FILE", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if not args.mat.is_file():  # one line before any work, not a traceback from deep inside
        raise SystemExit(f"bench_cli: error: --mat {args.mat}: no such file (expected libviso2-s's "
                         "stereo_XX.mat with ground truth, as in ../shared/data/kitti-libviso2/)")
    if args.reference_loop is not None:
        sys.stdout.write(reference_loop(args.reference_loop))
        return

    evaluate = [sys.executable, "-m", "dpc_jax", "evaluate", "--mat", str(args.mat), "--json", "-"]
    loop = [sys.executable, __file__, "--reference-loop", str(args.mat)]
    base = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    times: dict[str, list[float]] = {"cold": [], "warm": [], "loop": []}
    outputs: dict[str, set[str]] = {"cold": set(), "warm": set(), "loop": set()}
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory(prefix="bench-cli-") as tmp:
        for round_ in range(args.repeats + 1):
            env = {**base, "DPC_JAX_COMPILATION_CACHE": str(Path(tmp) / str(round_))}  # empty
            for name, command in (("cold", evaluate), ("warm", evaluate), ("loop", loop)):
                seconds, stdout = timed(command, env)
                outputs[name].add(stdout)
                if round_ > 0:
                    times[name].append(seconds)
            load.append(os.getloadavg()[0])

    import jax

    ours, loops = outputs["cold"] | outputs["warm"], outputs["loop"]
    same = len(ours) == 1 and len(loops) == 1 and agree(next(iter(ours)), next(iter(loops)))
    n = json.loads(next(iter(ours)))["num_poses"]
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), {this_cpu()}, "
          f"load average {min(load):.1f}-{max(load):.1f}; {args.mat.name}: {n} poses; "
          f"median of {args.repeats} rounds after one unmeasured round, whole processes")
    print(f"{'command':<44} {'wall s':>8} {'runs':>28} {'vs loop':>8}")
    loop_s = statistics.median(times["loop"])
    for name, title in (("cold", "dpc-jax evaluate (empty compilation cache)"),
                        ("warm", "dpc-jax evaluate (cache filled)"),
                        ("loop", "float64 loop (dpc_jax.eval.reference_metrics)")):
        median = statistics.median(times[name])
        runs = " ".join(f"{t:.2f}" for t in times[name])
        print(f"{title:<44} {median:>8.2f} {runs:>28} {loop_s / median:>7.1f}×")
    print(f"numbers: cold and warm {'identical' if len(ours) == 1 else 'DIFFER'}, "
          f"float64 loop {'agrees to 1e-9' if same else 'DISAGREES'}")


if __name__ == "__main__":
    main()
