"""Training throughput: samples/s of the jitted train step (forward, loss, backward, Adam update).

For each method and model preset at the preset's image size, one batch of random images (and
flow for ss-DPC-Net) is placed on the device mesh once; the step is compiled, warmed up, then
timed ``--repeats`` times (each call blocked on its result). Reported: compile time, median
and spread of the step time, samples/s = batch / median. The input pipeline is not included
(``benchmarks/bench_data.py`` shows it is much faster than the step).

    python benchmarks/bench_train.py                         # both presets, both methods, batch 8
    python benchmarks/bench_train.py --preset small --batch 4 16 --repeats 20
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from dpc_jax.engine import parallel
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.model_config import PRESETS
from dpc_jax.nn.models import create_model
from dpc_jax.runtime.hugepages import reexec_with_huge_pages
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.training.optim import create_train_state, make_optimizer
from dpc_jax.training.steps import make_train_step
from dpc_jax.training.train_config import REFERENCE, TrainConfig


def random_batch(batch: int, size: tuple[int, int], flow: bool, seed: int = 0) -> Batch:
    rng = np.random.default_rng(seed)
    h, w = size
    K = np.array([[0.6 * w, 0, w / 2], [0, 0.6 * w, h / 2], [0, 0, 1]], np.float32)
    return Batch(
        left=rng.integers(0, 256, (batch, 2, h, w, 3), dtype=np.uint8),
        right=rng.integers(0, 256, (batch, 2, h, w, 3), dtype=np.uint8),
        xi_vo=(rng.normal(size=(batch, 6)) * [0.02, 0.02, 1.0, 0.002, 0.01, 0.002]).astype(np.float32),
        intrinsics=np.tile(K, (batch, 1, 1)),
        baseline=np.full(batch, 0.54, np.float32),
        weight=np.ones(batch, np.float32),
        flow=rng.normal(size=(batch, 2, h, w, 2)).astype(np.float32) if flow else None,
    )


SMOKE_LABEL = " (the --smoke network: figures that mean nothing)"
"""What a benchmark's table says of rows measured with ``--smoke-network``."""


def published_config(
    method: str, preset: str, batch_size: int = 8, image_size: tuple[int, int] | None = None,
    model: dict[str, Any] | None = None,
) -> TrainConfig:
    """The run config of the published architecture (the ``REFERENCE`` settings: the papers' pose head,
    comparable with the PyTorch reference) on ``preset``'s network, with ``model`` overrides of it."""
    return TrainConfig(method=method, preset=preset, batch_size=batch_size, validation_sequences=("v",),
                       image_size=image_size, model=model or {}, **REFERENCE)


def train_step_runner(
    method: str, preset: str, batch_size: int, image_size: tuple[int, int] | None = None,
    model: dict[str, Any] | None = None,
) -> tuple[Callable[[], object], tuple[int, int]]:
    """``(run, (H, W))``: ``run()`` performs one training step of the published architecture
    (the papers' pose head, comparable with the PyTorch reference; ``model``: overrides of the
    preset's network) on a fixed random batch and returns its metrics (not blocked on). The state
    is donated and kept between calls."""
    config = published_config(method, preset, batch_size, image_size, model)
    mesh = parallel.make_mesh()
    model_config = config.model_config()
    graphdef, state = create_train_state(
        create_model(method, model_config, 0), make_optimizer(config, 100), mesh
    )
    step = make_train_step(config.loss_config(), 0, mesh)
    batch = parallel.shard_batch(random_batch(batch_size, model_config.image_size, method == "ss_dpc"), mesh)
    key = jax.random.key(0)
    # As the training loop runs it: graph definition bound, state carried as its flat arrays.
    leaves, treedef = jax.tree.flatten(state)
    bound = step.bind(graphdef, treedef)
    live = [leaves]

    def run() -> object:
        live[0], metrics = bound(live[0], batch, key)
        return metrics

    return run, tuple(model_config.image_size)


def bench(method: str, preset: str, batch_size: int, warmup: int, repeats: int) -> dict[str, float]:
    run, size = train_step_runner(method, preset, batch_size)
    began = time.perf_counter()
    jax.block_until_ready(run())
    compile_s = time.perf_counter() - began
    for _ in range(warmup):
        jax.block_until_ready(run())
    times = []
    for _ in range(repeats):
        began = time.perf_counter()
        jax.block_until_ready(run())
        times.append(time.perf_counter() - began)
    median = statistics.median(times)
    return {
        "size": size,
        "compile_s": compile_s,
        "median_ms": 1e3 * median,
        "min_ms": 1e3 * min(times),
        "max_ms": 1e3 * max(times),
        "samples_s": batch_size / median,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    methods = ["stereo_dpc", "ss_dpc"]
    parser.add_argument("--method", nargs="+", default=methods, choices=methods)
    parser.add_argument("--preset", nargs="+", default=["small", "reference"], choices=sorted(PRESETS))
    parser.add_argument("--batch", nargs="+", type=int, default=[8])
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    devices = jax.devices()
    print(f"device: {len(devices)} x {devices[0].device_kind} ({jax.default_backend()}), "
          f"{this_cpu()}, load average {os.getloadavg()[0]:.1f} at start")
    print("| method | preset | image HxW | batch | compile (s) | step median (ms) | min–max (ms) "
          "| samples/s |")
    print("|---|---|---|---|---|---|---|---|")
    for method in args.method:
        for preset in args.preset:
            for batch in args.batch:
                r = bench(method, preset, batch, args.warmup, args.repeats)
                h, w = r["size"]
                print(f"| {method} | {preset} | {h}x{w} | {batch} | {r['compile_s']:.1f} | "
                      f"{r['median_ms']:.0f} | {r['min_ms']:.0f}–{r['max_ms']:.0f} | {r['samples_s']:.1f} |",
                      flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at end")


if __name__ == "__main__":
    reexec_with_huge_pages()
    main()
