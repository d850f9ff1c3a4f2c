"""Speed of the synthetic world renderer: stereo frames per second, and time per stage.

    python benchmarks/bench_synth.py [--frames 40] [--size 240x376] [--moving-objects 4] [--write]

Frames are rendered after a warm-up sequence (compilation excluded); the table reports the median
over repeats of wall time and of process CPU time (the latter is robust when other jobs load the
machine), and the load average at the start, so that figures from a busy machine can be judged.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from dpc_jax.runtime.hugepages import reexec_with_huge_pages
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.synth import SynthConfig, iter_frames, write_sequence
from dpc_jax.synth import render as R
from dpc_jax.synth.sequence import _plan, frame_scene, kitti_intrinsics


def _timed(fn, repeats: int) -> tuple[float, float]:
    walls, cpus = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return float(np.median(walls)), float(np.median(cpus))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="240x376")
    parser.add_argument("--moving-objects", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--write", action="store_true", help="also time rendering + writing PNG/NPY files")
    args = parser.parse_args()
    h, w = (int(v) for v in args.size.split("x"))
    config = SynthConfig(frames=args.frames, height=h, width=w, seed=0, moving_objects=args.moving_objects)
    load = os.getloadavg()[0]

    for _ in iter_frames(SynthConfig(frames=2, height=h, width=w, moving_objects=args.moving_objects)):
        pass  # compile

    rows = []
    wall, cpu = _timed(lambda: [None for _ in iter_frames(config)], args.repeats)
    rows.append(("render (stereo)", wall / args.frames, cpu / args.frames))
    if args.write:
        with tempfile.TemporaryDirectory() as tmp:
            counter = iter(range(10**9))
            wall, cpu = _timed(lambda: write_sequence(tmp, f"{next(counter):02d}", config), args.repeats)
        rows.append(("render + write", wall / args.frames, cpu / args.frames))

    plan = _plan(config)
    K = kitti_intrinsics(h, w)
    scene = R.FrameScene(*(jnp.asarray(t) for t in frame_scene(plan, args.frames // 2, K, (h, w), 0.54)))
    pose = jnp.asarray(plan.world_poses[args.frames // 2], jnp.float32)
    K32, b, zero = jnp.asarray(K, jnp.float32), jnp.float32(0.54), jnp.float32(0.0)
    hits = R.nearest_hits(scene, pose, K32, b, zero, height=h, width=w)
    surf = R.surface_attributes(scene, hits, pose, K32, b, zero, height=h, width=w)
    ppm, noise = R._noise(surf.u, surf.v, surf.seed)
    stages = {
        "  visibility": lambda: jax.block_until_ready(
            R.nearest_hits(scene, pose, K32, b, zero, height=h, width=w)),
        "  attributes": lambda: jax.block_until_ready(
            R.surface_attributes(scene, hits, pose, K32, b, zero, height=h, width=w)),
        "  noise": lambda: jax.block_until_ready(R._noise(surf.u, surf.v, surf.seed)),
        "  shading": lambda: jax.block_until_ready(
            R._shade(surf, ppm, noise, scene.layers, scene.sun, jnp.float32(1), jnp.float32(1),
                     apply_gamma=False)),
    }
    for name, fn in stages.items():
        fn()
        wall, cpu = _timed(fn, 5 * args.repeats)
        rows.append((name, wall, cpu))

    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), {this_cpu()}, "
          f"load average {load:.1f}; image {h}x{w}, {args.moving_objects} moving cars, "
          f"{args.frames} frames x {args.repeats} repeats (median)")
    print(f"| {'stage':<18} | {'wall ms/frame':>13} | {'CPU ms/frame':>12} | {'frames/s (wall)':>15} |")
    print(f"|{'-' * 20}|{'-' * 15}|{'-' * 14}|{'-' * 17}|")
    for name, wall, cpu in rows:
        print(f"| {name:<18} | {wall * 1e3:13.1f} | {cpu * 1e3:12.1f} | {1.0 / wall:15.1f} |")


if __name__ == "__main__":
    reexec_with_huge_pages()
    main()
