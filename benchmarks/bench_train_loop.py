"""Loop efficiency: the real training epoch and correction against their isolated jitted steps.

    python benchmarks/bench_train_loop.py              # both methods, reference preset, 240x376, batch 8
    python benchmarks/bench_train_loop.py --method ss_dpc --steps 10 --rounds 2
    python benchmarks/bench_train_loop.py --cache ROOT --train 00 --validation 01 --correct 02 --json out.json

Training: samples/s of one epoch as ``dpc-jax train`` runs it (``dpc_jax.training.loop``: the
prepared cache read by ``TrainLoader`` with its background workers, frame-skip augmentation on, flow
for ss-DPC-Net, the per-step metrics fetched, checked and logged to TensorBoard), against samples/s
of the same jitted train step called back to back on the same epoch's batches already on the device
(the most the loop could reach: the step over the same data, nothing feeding it). Both run on the
same state, alternating epoch and isolated steps ``--rounds`` times after a warm-up; the medians and
their ratio (the loop efficiency) are printed; the whole epoch's wall time counts (its start:
threads, the first batch), and beside it the rate the loop itself reports (``samples_per_s`` of
``metrics.csv``: from its first step's end to its last). Validation and checkpoints are not part of
the epoch measured.

Correction: frames/s of ``dpc_jax.correction.corrector.correct_cache`` over a whole sequence (reading the
cache, the prediction, Δ — for Stereo DPC with the StereoSGBM depth prepared with the cache, as ``dpc-jax
prepare`` writes it — the acceptance test, the trajectories and their evaluation) against frames/s
of the isolated inference step over the sequence's batches, all on the device before the clock
starts, alternating likewise: the prediction step as the correction runs it (the network, ``L(0)``
and Δ of its correction and of its rotation; not the training loss, which only validation reads),
frames counted as the sequence's pairs in both. And batches/s of the input pipeline alone (the
training loader with its transfer to the device, nothing consuming): what it could feed a faster
device.

Without ``--cache`` the script writes a synthetic cache (random frames and flow with the layout of
a prepared one) in a temporary folder, sized for ``--steps`` steps per epoch, with a sequence of
``--correct-frames`` frames to correct (a correction's fixed costs, the evaluation of its
trajectories above all, weigh on a short sequence), and removes it at the end. The network is the
preset's with the training defaults. The device and the CPU are named in the header; ``--json
FILE`` (``-``: stdout) writes the figures as one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import jax
from bench_data import write_random_cache
from bench_train import SMOKE_LABEL

from dpc_jax.correction.acceptance import DEFAULT_ALPHA
from dpc_jax.runtime.hugepages import reexec_with_huge_pages
from dpc_jax.runtime.machine import this_cpu

METHODS = ("stereo_dpc", "ss_dpc")


def synthetic_root(
    root: Path, steps: int, batch: int, size: tuple[int, int], flow: bool, correct_frames: int
) -> Path:
    """Training sequence ``00`` with enough pairs (forward and frame-skip) for ``steps`` batches, a
    short validation sequence ``01`` and the sequence ``02`` of ``correct_frames`` frames to correct."""
    kinds = ("forward", "skip") if flow else ()
    # forward + skip pairs of n frames: 2n - 3 samples.
    frames = math.ceil((steps * batch + 3) / 2)
    write_random_cache(root / "00", frames, size, kinds, seed=0)
    write_random_cache(root / "01", 4, size, kinds, seed=1)
    write_random_cache(root / "02", correct_frames, size, kinds[:1], seed=2)
    return root


def median_rate(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def bench_method(
    args: argparse.Namespace, method: str, root: Path, train: str, validation: str, corrected: str
) -> dict[str, Any]:
    from flax import nnx

    from dpc_jax.correction.corrector import correct_cache, default_acceptance_depth
    from dpc_jax.correction.inference import TrainedRun
    from dpc_jax.data.pipeline import iterate_sequence
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.engine import parallel
    from dpc_jax.engine.backend import prepare_for_backend
    from dpc_jax.engine.predict import predict_step, stereo_depth_of
    from dpc_jax.pipelines.protocol import SMOKE
    from dpc_jax.training import loop
    from dpc_jax.training.steps import make_train_step
    from dpc_jax.training.train_config import TrainConfig

    config = TrainConfig(
        method=method, preset=args.preset, image_size=args.size, batch_size=args.batch,
        cache_root=str(root), train_sequences=(train,), validation_sequences=(validation,),
        steps_per_epoch=args.steps, epochs=args.rounds + 1,
        model=SMOKE["model"] if args.smoke_network else {},
    )
    data = loop.open_data(config, workers=args.workers)
    mesh = parallel.make_mesh()
    _, graphdef, state = loop._initial_state(config, data, mesh)
    train_step = make_train_step(config.loss_config(), config.warmup_steps(data.steps_per_epoch), mesh)
    steps = data.steps_per_epoch
    record: dict[str, Any] = {"method": method, "steps_per_epoch": steps}
    with tempfile.TemporaryDirectory(prefix="dpc_loop_log_") as logdir:
        log = loop.MetricsLog(Path(logdir), 0, 0, enabled=True)
        # Isolated: the batches of epoch 0, on the device before the clock starts (distinct batches:
        # a step's gathers run faster over one batch repeated, whose data stays in the CPU's
        # caches); keys made before the clock starts too.
        with contextlib.closing(data.loader.epoch(0)) as stream:
            batches = [parallel.shard_batch(b, mesh) for b in itertools.islice(stream, steps)]
        batch = batches[0]
        base = jax.random.key(config.seed)
        keys = [jax.random.fold_in(base, s) for s in range(steps)]
        # The step as the loop runs it: graph definition bound, state as its flat list of arrays.
        leaves, treedef = jax.tree.flatten(state)
        bound = train_step.bind(graphdef, treedef)
        began = time.perf_counter()
        leaves, metrics = bound(leaves, batch, keys[0])
        jax.block_until_ready(metrics)
        record["compile_s"] = time.perf_counter() - began
        state = jax.tree.unflatten(treedef, leaves)

        def isolated(state: Any) -> tuple[Any, float]:
            leaves = jax.tree.leaves(state)
            began = time.perf_counter()
            for key, resident in zip(keys, batches, strict=True):
                leaves, metrics = bound(leaves, resident, key)
            jax.block_until_ready((leaves, metrics))
            rate = steps * args.batch / (time.perf_counter() - began)
            return jax.tree.unflatten(treedef, leaves), rate

        steady: list[float] = []

        def epoch(state: Any, number: int, data: Any = data) -> tuple[Any, float]:
            began = time.perf_counter()
            state, means = loop._train_epoch(
                number, graphdef, state, train_step, data, config, mesh, 0, log, False
            )
            jax.block_until_ready(state)
            steady.append(means["samples_per_s"])
            return state, data.steps_per_epoch * args.batch / (time.perf_counter() - began)

        def pipeline(number: int) -> float:
            """Batches/s of the input side alone: the loader's epoch with the transfer to the device."""
            share = parallel.process_slice(config.batch_size)

            def put(batch: Any) -> Any:
                return parallel.shard_batch(jax.tree.map(lambda x: x[share], batch), mesh)

            began = time.perf_counter()
            for batch in data.loader.epoch(number, put=put):
                jax.block_until_ready(batch)
            return len(data.loader) / (time.perf_counter() - began)

        pipeline(0)
        record["pipeline_batches_s"] = [pipeline(r + 1) for r in range(args.rounds)]
        record["pipeline_median"] = median_rate(record["pipeline_batches_s"])
        print(f"  {method}: input pipeline alone {record['pipeline_median']:.1f} batches/s "
              f"({args.workers} workers)", file=sys.stderr, flush=True)
        # Warm-up: a short epoch (threads, files, logging) and a few isolated steps.
        state, _ = epoch(state, 0, dataclasses.replace(data, steps_per_epoch=min(2, steps)))
        steady.clear()
        leaves = jax.tree.leaves(state)
        for _ in range(min(2, steps)):
            leaves, metrics = bound(leaves, batch, keys[0])
        state = jax.block_until_ready(jax.tree.unflatten(treedef, leaves))
        loop_rates, step_rates = [], []
        for r in range(args.rounds):
            state, rate = epoch(state, r + 1)
            loop_rates.append(rate)
            state, rate = isolated(state)
            step_rates.append(rate)
            print(f"  {method} round {r + 1}: epoch {loop_rates[-1]:.2f} (as the loop reports it "
                  f"{steady[-1]:.2f}), isolated step {step_rates[-1]:.2f} samples/s",
                  file=sys.stderr, flush=True)
        log.close()
    record["train"] = {"loop_samples_s": loop_rates, "step_samples_s": step_rates,
                       "loop_median": median_rate(loop_rates), "step_median": median_rate(step_rates),
                       "loop_reported_samples_s": steady, "loop_reported_median": median_rate(steady)}
    record["train"]["efficiency"] = record["train"]["loop_median"] / record["train"]["step_median"]

    # Correction: the trained state as a restored run would hold it (model only, evaluation mode).
    model, _ = nnx.merge(graphdef, state)
    model.eval()
    run_graphdef, run_state = nnx.split(model)
    del state
    run = TrainedRun(root, config, "last", 1, run_graphdef, run_state)
    cache = load_cache(root / corrected)
    pairs = len(cache) - 1
    size = min(args.batch, pairs)
    prepared_graphdef, prepared_state = prepare_for_backend(run_graphdef, run_state)
    prepared_leaves, treedef = jax.tree.flatten(prepared_state)
    # The prediction as the correction runs it: the network and Δ of its correction, no training loss.
    predict = predict_step(None, prepared_graphdef, treedef, config.loss_config(), loss=False)
    # The same inputs the correction's step gets: the cache's stereo depth where its test uses it.
    stereo = stereo_depth_of(cache, default_acceptance_depth(run))
    # The sequence's batches, on the device before the clock starts.
    resident = [jax.device_put(b) for b in iterate_sequence(cache, size, flow=config.use_flow,
                                                            stereo_depth=stereo)]

    def predict_isolated() -> float:
        began = time.perf_counter()
        out = None
        for batch in resident:
            out = predict(prepared_leaves, batch)
        jax.block_until_ready(out)
        # The sequence's pairs, as the correction counts them (the last batch's padding is no frame).
        return pairs / (time.perf_counter() - began)

    decisions: list[str] = []

    def correct_whole() -> float:
        began = time.perf_counter()
        correction = correct_cache(run, cache, batch_size=args.batch, alpha=args.alpha)
        rate = pairs / (time.perf_counter() - began)
        decisions.append(correction.part)
        return rate

    correct_whole()  # warm-up: compiles the prediction and the evaluation
    predict_isolated()
    correct_rates, infer_rates = [], []
    for r in range(args.rounds):
        correct_rates.append(correct_whole())
        infer_rates.append(predict_isolated())
        print(f"  {method} round {r + 1}: correct {correct_rates[-1]:.2f}, isolated inference "
              f"{infer_rates[-1]:.2f} frames/s", file=sys.stderr, flush=True)
    record["correct"] = {"pairs": pairs, "loop_frames_s": correct_rates, "step_frames_s": infer_rates,
                         "loop_median": median_rate(correct_rates), "step_median": median_rate(infer_rates),
                         # What the correction decided sets its extra work (a narrowed rotation
                         # measures Δ of the axes kept, another pass over the sequence).
                         "decisions": sorted(set(decisions))}
    record["correct"]["efficiency"] = record["correct"]["loop_median"] / record["correct"]["step_median"]
    return record


def parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size: expected HxW (e.g. 240x376), got {text!r}") from None
    return h, w


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--preset", default="reference", choices=("reference", "small"))
    parser.add_argument("--smoke-network", action="store_true",
                        help="the protocols' two-block --smoke network on the preset: checks that every step "
                             "runs (gpu_check.sh's quick mode); its figures mean nothing")
    parser.add_argument("--size", type=parse_size, default=(240, 376), metavar="HxW")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=12, help="steps per measured epoch (default 12)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating measurements (default 3)")
    parser.add_argument("--workers", type=int, default=2, help="data-loading threads, as dpc-jax train")
    parser.add_argument("--cache", type=Path, help="a cache root with --train and --validation sequences")
    parser.add_argument("--train", default="00")
    parser.add_argument("--validation", default="01")
    parser.add_argument("--correct", default="02", help="the sequence corrected (default 02)")
    parser.add_argument("--alpha", type=float, default=DEFAULT_ALPHA,
                        help="the acceptance tests' level (default %(default)s); 1e-300 refuses every "
                             "part: the worst case, every part measured that a refusal needs")
    parser.add_argument("--correct-frames", type=int, default=200,
                        help="frames of the synthetic sequence corrected (default 200)")
    parser.add_argument("--json", metavar="FILE", help="write the figures as JSON (- for stdout)")
    args = parser.parse_args()
    devices = jax.devices()
    header = {
        "device": f"{len(devices)} x {devices[0].device_kind} ({jax.default_backend()})",
        "cpu": this_cpu(),
        "jax": jax.__version__,
        "preset": args.preset, "smoke_network": args.smoke_network, "size": list(args.size),
        "batch": args.batch,
        "load_start": os.getloadavg()[0],
    }
    print(f"device: {header['device']}, {header['cpu']}, jax {jax.__version__}, "
          f"load average {header['load_start']:.1f} at start", flush=True)
    records = []
    temporary = None
    try:
        for method in args.method:
            if args.cache is not None:
                root = args.cache
            else:
                temporary = Path(tempfile.mkdtemp(prefix="dpc_loop_cache_"))
                root = synthetic_root(temporary, args.steps, args.batch, args.size, method == "ss_dpc",
                                      args.correct_frames)
            records.append(bench_method(args, method, root, args.train, args.validation, args.correct))
            if temporary is not None:
                shutil.rmtree(temporary)
                temporary = None
    finally:
        if temporary is not None:
            shutil.rmtree(temporary, ignore_errors=True)
    h, w = args.size
    network = SMOKE_LABEL if args.smoke_network else ""
    print(f"\npreset {args.preset}{network}, {h}x{w}, batch {args.batch}; "
          f"medians of {args.rounds} alternating rounds")
    print("| method | what | real loop | isolated step | efficiency |")
    print("|---|---|---|---|---|")
    for r in records:
        print(f"| {r['method']} | input pipeline alone ({args.workers} workers), batches/s | "
              f"{r['pipeline_median']:.1f} | | |")
    for r in records:
        t, c = r["train"], r["correct"]
        print(f"| {r['method']} | train ({r['steps_per_epoch']} steps/epoch), samples/s | "
              f"{t['loop_median']:.2f} | "
              f"{t['step_median']:.2f} | {t['efficiency']:.3f} |")
        print(f"| {r['method']} | train, the loop's own samples/s (after its first step) | "
              f"{t['loop_reported_median']:.2f} | {t['step_median']:.2f} | "
              f"{t['loop_reported_median'] / t['step_median']:.3f} |")
        print(f"| {r['method']} | correct ({c['pairs']} pairs; decided {', '.join(c['decisions'])}), "
              f"frames/s | {c['loop_median']:.2f} | "
              f"{c['step_median']:.2f} | {c['efficiency']:.3f} |")
    header["load_end"] = os.getloadavg()[0]
    print(f"load average {header['load_end']:.1f} at end", flush=True)
    if args.json:
        text = json.dumps({**header, "results": records}, indent=2) + "\n"
        if args.json == "-":
            sys.stdout.write(text)
        else:
            Path(args.json).write_text(text)


if __name__ == "__main__":
    reexec_with_huge_pages()
    main()
