"""Benchmark the networks: inference latency and a full training step (docs/method.md §3, issue 7).

Usage::

    python benchmarks/bench_models.py [--preset reference] [--height 240 --width 376]
        [--methods ss_dpc stereo_dpc] [--infer-batches 1 8] [--train-batches 4 8]
        [--repeats 10] [--breakdown] [--profile DIR] [--smoke-network]

* ``inference``: jitted eval-mode forward of a batch by the model prepared once
  (``dpc_jax.engine.backend.prepare_for_backend``), as ``dpc_jax.engine.predict.predict_sequence`` runs one.
* ``train step``: the library's own jitted, state-donating step (``dpc_jax.training.steps``, the
  ``REFERENCE`` settings, as ``bench_train.py`` runs it): train-mode forward, the loss with its
  warps, backward, the optimizer update, new parameters and BatchNorm statistics.
* ``--breakdown`` adds rows that split the training step: the forward alone, the loss alone on
  fixed network outputs, and the loss's forward+backward.
* ``--profile DIR`` writes a ``jax.profiler`` trace of a few training steps (TensorBoard /
  Perfetto). Eigen convolutions run asynchronously: their trace events cover only the launch.

The script restarts itself with glibc's huge-page malloc (``dpc_jax.runtime.hugepages``), as the
``dpc-jax`` command does; ``DPC_JAX_HUGE_PAGES=0`` measures without it.

Every function is compiled and called once more before timing; the table reports the median, mean
and min wall time of ``--repeats`` calls, each blocked until ready, and the median CPU time of the
process per call. The load average is printed before and after, because wall times mean little
on a busy machine.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from bench_train import SMOKE_LABEL, published_config, train_step_runner
from flax import nnx

from dpc_jax.engine.backend import compiler_options, prepare_for_backend
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.losses import ss_dpc_loss, stereo_dpc_loss
from dpc_jax.nn.model_config import PRESETS, SSDPCLossConfig, StereoDPCLossConfig
from dpc_jax.nn.models import create_model
from dpc_jax.pipelines.protocol import SMOKE
from dpc_jax.runtime.hugepages import reexec_with_huge_pages
from dpc_jax.runtime.machine import this_cpu


def timeit(fn: Callable[..., object], args: tuple, repeats: int) -> tuple[float, float, float, float]:
    """Median, mean and min wall time and median process CPU time (all threads), in milliseconds,
    of ``fn(*args)`` after compilation and one warm-up call. The mean is the throughput figure
    when consecutive calls alternate between fast and slow (Stereo DPC steps with huge pages do).

    On a busy machine the wall time mostly measures the other processes; the CPU time is less
    sensitive to them (on an idle machine with P cores, wall ≥ CPU / P).
    """
    jax.block_until_ready(fn(*args))
    jax.block_until_ready(fn(*args))
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall.append((time.perf_counter() - start) * 1e3)
        cpu.append((time.process_time() - start_cpu) * 1e3)
    return statistics.median(wall), statistics.fmean(wall), min(wall), statistics.median(cpu)


def make_batch(b: int, h: int, w: int, seed: int = 0) -> Batch:
    """Random images and flow, a small prior, KITTI-like intrinsics at ``h × w``."""
    r = np.random.default_rng(seed)
    k = np.array([[0.58 * w, 0, w / 2], [0, 1.9 * h, h / 2], [0, 0, 1]], np.float32)
    return Batch(
        left=r.integers(0, 256, (b, 2, h, w, 3), dtype=np.uint8),
        right=r.integers(0, 256, (b, 2, h, w, 3), dtype=np.uint8),
        xi_vo=np.tile(np.array([0.0, 0.0, 1.0, 0.0, 0.01, 0.0], np.float32), (b, 1)),
        intrinsics=np.tile(k, (b, 1, 1)),
        baseline=np.full(b, 0.54, np.float32),
        weight=np.ones(b, np.float32),
        flow=r.normal(size=(b, 2, h, w, 2)).astype(np.float32),
    )


def loss_fn(method: str) -> Callable:
    if method == "ss_dpc":
        config = SSDPCLossConfig()
        return lambda outputs, batch: ss_dpc_loss(outputs, batch, config)
    config = StereoDPCLossConfig()
    return lambda outputs, batch: stereo_dpc_loss(outputs, batch, config)


def build(
    method: str, preset: str, hw: tuple[int, int], model_overrides: dict[str, Any] | None = None
) -> dict[str, Callable]:
    """Jitted inference and the breakdown functions of the training step for one model (the preset's
    network with ``model_overrides``, as a TrainConfig's ``model``), the one the train step rows run."""
    config = published_config(method, preset, image_size=hw, model=model_overrides).model_config()
    model = create_model(method, config, seed=0)
    graphdef, params, stats = nnx.split(model, nnx.Param, ...)
    loss = loss_fn(method)
    # The library's jitted inference and training step compile the network with these options too.
    jit = functools.partial(jax.jit, compiler_options=compiler_options(method, training=True))

    # As dpc_jax.engine.predict runs a sequence: the model prepared once, its state passed as its
    # flat list of arrays, then batches.
    inference_graphdef, prepared_state = prepare_for_backend(graphdef, nnx.merge_state(params, stats))
    prepared, treedef = jax.tree.flatten(prepared_state)

    @functools.partial(jax.jit, compiler_options=compiler_options(method, training=False))
    def infer(prepared: list[jax.Array], batch: Batch):
        return nnx.merge(inference_graphdef, jax.tree.unflatten(treedef, prepared))(batch)

    @jit
    def forward_train(params: nnx.State, stats: nnx.State, batch: Batch, key: jax.Array):
        m = nnx.merge(graphdef, params, stats)
        m.train()
        return m(batch, key=key)

    @jit
    def loss_only(outputs, batch: Batch):
        return loss(outputs, batch)[0]

    @jit
    def loss_grad(outputs, batch: Batch):
        return jax.grad(lambda o: loss(o, batch)[0])(outputs)

    @jit
    def grad_only(params: nnx.State, stats: nnx.State, batch: Batch, key: jax.Array):
        # As the library's step differentiates: with respect to the merged model, in train mode.
        m = nnx.merge(graphdef, params, stats)
        m.train()
        return nnx.grad(lambda m: loss(m(batch, key=key), batch)[0])(m)

    return {
        "state": (params, stats),
        "prepared": prepared,
        "infer": infer,
        "forward_train": forward_train,
        "loss_only": loss_only,
        "loss_grad": loss_grad,
        "grad_only": grad_only,
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="reference", choices=sorted(PRESETS))
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--width", type=int, default=376)
    parser.add_argument("--methods", nargs="+", default=["ss_dpc", "stereo_dpc"])
    parser.add_argument("--infer-batches", nargs="*", type=int, default=[1, 8])
    parser.add_argument("--train-batches", nargs="*", type=int, default=[4, 8])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--breakdown", action="store_true", help="also time parts of the training step")
    parser.add_argument("--smoke-network", action="store_true",
                        help="the protocols' two-block --smoke network on the preset: checks that every row "
                             "runs; its figures mean nothing")
    parser.add_argument("--profile", help="write a jax.profiler trace of training steps to this folder")
    args = parser.parse_args(argv)

    hw = (args.height, args.width)
    device = jax.devices()[0]
    print(
        f"device: {device.platform} ({device.device_kind}), {this_cpu()}, jax {jax.__version__}, "
        f"float32, preset {args.preset}{SMOKE_LABEL if args.smoke_network else ''}, {hw[0]}x{hw[1]}, "
        f"{args.repeats} repeats"
    )
    model = SMOKE["model"] if args.smoke_network else {}
    env = {name: os.environ.get(name, "") for name in ("XLA_FLAGS", "GLIBC_TUNABLES")}
    print(", ".join(f"{name}={value!r}" for name, value in env.items()))
    print("load average before: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    header = ("model", "what", "batch", "median ms", "mean ms", "min ms", "CPU ms")
    print("| {:<10} | {:<30} | {:>5} | {:>9} | {:>9} | {:>9} | {:>9} |".format(*header))
    print(f"|{'-' * 12}|{'-' * 32}|{'-' * 7}|{'-' * 11}|{'-' * 11}|{'-' * 11}|{'-' * 11}|")

    def row(method: str, what: str, b: int, fn: Callable[..., object], *fn_args: object) -> None:
        median, mean, best, cpu = timeit(fn, fn_args, args.repeats)
        times = " | ".join(f"{t:>9.1f}" for t in (median, mean, best, cpu))
        cells = f"| {method:<10} | {what:<30} | {b:>5} | {times} |"
        print(cells, flush=True)

    key = jax.random.key(0)
    for method in args.methods:
        fns = build(method, args.preset, hw, model)
        params, stats = fns["state"]
        for b in args.infer_batches:
            batch = jax.device_put(make_batch(b, *hw))
            row(method, "inference (eval)", b, fns["infer"], fns["prepared"], batch)
        for b in args.train_batches:
            batch = jax.device_put(make_batch(b, *hw))
            if args.breakdown:
                outputs = fns["forward_train"](params, stats, batch, key)
                row(method, "forward (train mode)", b, fns["forward_train"], params, stats, batch, key)
                row(method, "loss fwd (fixed outputs)", b, fns["loss_only"], outputs, batch)
                row(method, "loss fwd+bwd (fixed outputs)", b, fns["loss_grad"], outputs, batch)
                row(method, "forward+loss+backward", b, fns["grad_only"], params, stats, batch, key)
            step, _ = train_step_runner(method, args.preset, b, hw, model)
            row(method, "train step (fwd+loss+bwd+Adam)", b, step)
            if args.profile:
                with jax.profiler.trace(os.path.join(args.profile, f"{method}_b{b}")):
                    for _ in range(3):
                        jax.block_until_ready(step())
    print("load average after: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    raise SystemExit(main())
