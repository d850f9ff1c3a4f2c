"""Benchmark the differentiable core: se3_exp/se3_log, inverse_warp forward+backward, SSIM.

Usage: ``python benchmarks/bench_core.py [--repeats N] [--batch B] [--poses N]``.
Every function is jitted; the first call (compilation) and one more warm-up call are excluded,
then the median and min of ``--repeats`` timed calls are reported, each call blocked until ready.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dpc_jax.geometry.lie import se3_exp, se3_log
from dpc_jax.geometry.ssim import ssim_loss
from dpc_jax.geometry.warp import inverse_warp
from dpc_jax.runtime.hugepages import reexec_with_huge_pages
from dpc_jax.runtime.machine import this_cpu


def timeit(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(median, min) wall time in milliseconds after compilation and one warm-up call."""
    jax.block_until_ready(fn())
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), min(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--width", type=int, default=376)
    parser.add_argument("--poses", type=int, default=100_000)
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    b, h, w = args.batch, args.height, args.width
    xi = jnp.asarray(rng.normal(scale=0.5, size=(args.poses, 6)), jnp.float32)
    T = jax.jit(se3_exp)(xi)

    source = jnp.asarray(rng.random((b, h, w, 3)), jnp.float32)
    target = jnp.asarray(rng.random((b, h, w, 3)), jnp.float32)
    depth = jnp.asarray(rng.uniform(2.0, 50.0, (b, h, w)), jnp.float32)
    K = jnp.asarray(np.broadcast_to([[0.5 * w, 0, 0.5 * w], [0, 0.5 * w, 0.5 * h], [0, 0, 1]], (b, 3, 3)),
                    jnp.float32)
    xi_warp = jnp.asarray(rng.normal(scale=0.02, size=(b, 6)), jnp.float32)

    def photometric(d: jax.Array, x: jax.Array) -> jax.Array:
        recon, valid = inverse_warp(source, d, se3_exp(x), K)
        return jnp.sum(jnp.abs(recon - target).mean(-1) * valid) / jnp.maximum(jnp.sum(valid), 1)

    exp_fn = jax.jit(se3_exp)
    log_fn = jax.jit(se3_log)
    warp_fwd = jax.jit(lambda: inverse_warp(source, depth, se3_exp(xi_warp), K))
    warp_bwd = jax.jit(jax.value_and_grad(photometric, argnums=(0, 1)))
    ssim_fwd = jax.jit(ssim_loss)
    ssim_bwd = jax.jit(jax.grad(lambda x: jnp.mean(ssim_loss(x, target))))

    rows = [
        ("se3_exp", f"[{args.poses}, 6]", lambda: exp_fn(xi)),
        ("se3_log", f"[{args.poses}, 4, 4]", lambda: log_fn(T)),
        ("inverse_warp fwd", f"[{b}, {h}, {w}, 3]", warp_fwd),
        ("inverse_warp fwd+bwd", f"[{b}, {h}, {w}, 3]", lambda: warp_bwd(depth, xi_warp)),
        ("ssim_loss fwd", f"[{b}, {h}, {w}, 3]", lambda: ssim_fwd(source, target)),
        ("ssim_loss fwd+bwd", f"[{b}, {h}, {w}, 3]", lambda: ssim_bwd(source)),
    ]
    device = jax.devices()[0]
    print(f"device: {device.platform} ({device.device_kind}), {this_cpu()}, jax {jax.__version__}, float32, "
          f"{args.repeats} repeats")
    print(f"| {'function':<22} | {'shape':<18} | {'median ms':>10} | {'min ms':>10} |")
    print(f"|{'-' * 24}|{'-' * 20}|{'-' * 12}|{'-' * 12}|")
    for name, shape, fn in rows:
        median, best = timeit(fn, args.repeats)
        print(f"| {name:<22} | {shape:<18} | {median:>10.2f} | {best:>10.2f} |")
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    raise SystemExit(main())
