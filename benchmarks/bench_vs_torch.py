"""dpc_jax against the PyTorch reference, side by side: the only comparison this machine allows.

Runs ``../shared/bench/torch_reference/bench_torch.py`` (under ``--torch-python``, an environment
with PyTorch; that folder's README says how to make one) and the same configuration of ours as
separate processes, alternating PyTorch, ours, PyTorch, ours, ... (``--pairs`` pairs), and prints
a Markdown table: each pair's median step times, the per-pair ratio PyTorch time / our time
(> 1: we are faster), the median ratio, and the machine's load during each run.

    python benchmarks/bench_vs_torch.py --torch-python ../.venv-torch/bin/python
    python benchmarks/bench_vs_torch.py --torch-python PY --only mono-train-8 stereo-train-8 --pairs 3

Both sides run the published architecture at the same image size and batch: ``infer`` is the
eval-mode forward with pose, inverse depth and masks (ours: by the model prepared once,
``dpc_jax.nn.models.prepare_inference``, as ``dpc-jax correct`` runs a sequence); ``train`` is the
train-mode forward (dropout 0.5), the method's loss, backward and an Adam step (ours: the
``dpc-jax train`` step, ``dpc_jax.training.steps``, with the ``REFERENCE`` settings, as ``bench_train.py``
runs it). Our process restarts itself with huge pages as ``dpc-jax`` does; PyTorch uses
``TORCH_THREADS`` (default 2) threads. Load: ``foreign`` is the share of the machine's CPU time
that other processes used while a run was timing (each side measures its own, from ``/proc/stat``),
``load`` the 1-minute load average when the run started. A ratio from a run with much foreign load
mostly measures the other processes (PyTorch's OpenMP threads suffer far more from a stolen core
than ours): such pairs are marked ``*`` and left out of the median. Before each run the script
waits (``--wait-quiet``) for the other processes to go quiet.

On a GPU machine (``--torch-device cuda``; JAX takes its default device, the GPU) each PyTorch
step is synchronised; ``--torch-variants eager compiled`` also times PyTorch with ``torch.compile``
(``TORCH_COMPILE=1``; its compilation happens in the warm-up steps, bounded by ``--torch-timeout``)
and adds a summary table: each configuration's median PyTorch eager, PyTorch compiled and dpc_jax
times, and the ratio to the faster PyTorch. On a GPU the foreign CPU share says little; pass
``--wait-quiet 0`` there.

    python benchmarks/bench_vs_torch.py --torch-python python3 --torch-device cuda --wait-quiet 0 \
        --torch-variants eager compiled --pairs 1 --reps 20 --warmup 3

``--only`` takes any ``VARIANT-MODE-BATCH`` (e.g. ``stereo-train-32``), not only the defaults.

``--ours VARIANT MODE BATCH REPS WARMUP`` is the worker: one configuration of ours in this process,
one JSON line on stdout, the interface of ``bench_torch.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from dpc_jax.runtime.machine import this_cpu

ROOT = Path(__file__).resolve().parents[1]
TORCH_BENCH = ROOT.parent / "shared" / "bench" / "torch_reference" / "bench_torch.py"
METHODS = {"mono": "ss_dpc", "stereo": "stereo_dpc"}
NAMES = {"mono": "ss-DPC-Net", "stereo": "Stereo DPC"}
# (variant, mode, batch): inference at batch 1 and 8, training at 4 and 8, both models (issue 18).
CONFIGURATIONS = [
    (variant, mode, batch)
    for mode, batches in (("infer", (1, 8)), ("train", (4, 8)))
    for variant in ("mono", "stereo")
    for batch in batches
]
DEFAULT_REPS = {"infer": 20, "train": 5}
TORCH_VARIANTS = ("eager", "compiled")


def config_name(variant: str, mode: str, batch: int) -> str:
    return f"{variant}-{mode}-{batch}"


def parse_config_name(name: str) -> tuple[str, str, int]:
    """``VARIANT-MODE-BATCH`` (e.g. ``stereo-train-32``) as its parts; ValueError with one line."""
    parts = name.split("-")
    if (len(parts) != 3 or parts[0] not in METHODS or parts[1] not in DEFAULT_REPS
            or not parts[2].isdigit() or int(parts[2]) < 1):
        raise ValueError(f"configuration {name!r}: expected VARIANT-MODE-BATCH with VARIANT in "
                         f"{sorted(METHODS)}, MODE in {sorted(DEFAULT_REPS)}, BATCH ≥ 1")
    return parts[0], parts[1], int(parts[2])


# ------------------------------------------------------------------------------------------ worker


def _busy_s() -> float:
    """Machine-wide busy CPU seconds, all cores (as ``bench_torch.py`` measures them)."""
    with open("/proc/stat") as f:
        ticks = [int(x) for x in f.readline().split()[1:]]
    return (sum(ticks[:8]) - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK")


def _own_s() -> float:
    t = os.times()
    return t.user + t.system


def time_calls(fn: Callable[[], object], reps: int, warmup: int) -> dict[str, object]:
    """Wall time of ``reps`` calls after ``warmup`` (each blocked until ready) and the CPU time
    other processes used meanwhile; the fields of ``bench_torch.py`` that the table reads."""
    import jax

    for _ in range(warmup):
        jax.block_until_ready(fn())
    times, foreign = [], []
    for _ in range(reps):
        busy, own = _busy_s(), _own_s()
        began = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - began)
        foreign.append(max(0.0, (_busy_s() - busy) - (_own_s() - own)))
    return {
        "median_s": statistics.median(times),
        "min_s": min(times),
        "times_s": times,
        "foreign_cpu_frac": sum(foreign) / ((os.cpu_count() or 1) * sum(times)),
    }


def run_ours(variant: str, mode: str, batch: int, reps: int, warmup: int, size: tuple[int, int]) -> dict:
    """One configuration of ours, timed in this process; the JSON record of ``--ours``."""
    import bench_models
    import bench_train
    import jax

    method = METHODS[variant]
    began = time.perf_counter()
    if mode == "train":
        fn, _ = bench_train.train_step_runner(method, "reference", batch, size)
    else:
        fns = bench_models.build(method, "reference", size)
        inputs = jax.device_put(bench_models.make_batch(batch, *size))
        fn = lambda: fns["infer"](fns["prepared"], inputs)
    jax.block_until_ready(fn())
    record = {"variant": variant, "mode": mode, "batch": batch, "reps": reps, "warmup": warmup,
              "jax": jax.__version__, "device": jax.devices()[0].device_kind,
              "compile_s": time.perf_counter() - began}
    record.update(time_calls(fn, reps, warmup))
    return record


# ------------------------------------------------------------------------------------------ driver


@dataclass
class Run:
    """One timed process: its median step time and the load around it."""

    median_ms: float
    foreign: float
    load: float


class BenchError(RuntimeError):
    """A run failed; the message is one line for the user."""


class BenchTimeout(BenchError):
    """A run outlasted its time limit (``--torch-timeout``)."""


def _json_line(command: list[str], env: dict[str, str], what: str, timeout_s: float | None = None) -> dict:
    try:
        done = subprocess.run(command, env=env, capture_output=True, text=True, check=False,
                              timeout=timeout_s)
    except subprocess.TimeoutExpired as error:
        raise BenchTimeout(f"{what} did not finish within {timeout_s:g} s") from error
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise BenchError(f"{what} failed (exit {done.returncode}): {tail}")
    return json.loads(lines[-1])


def check_torch_python(torch_python: str | None) -> str | None:
    """None if ``torch_python`` runs and imports torch, else a one-line reason."""
    hint = f"a Python with PyTorch (see {TORCH_BENCH.parent / 'README.md'})"
    if not torch_python:
        return f"--torch-python PATH is required: {hint}"
    try:
        done = subprocess.run([torch_python, "-c", "import torch"], capture_output=True, text=True,
                              timeout=120, check=False)
    except OSError as error:
        return f"--torch-python {torch_python} cannot be run ({error.strerror}): {hint}"
    except subprocess.TimeoutExpired:
        return f"--torch-python {torch_python} did not import torch within 120 s"
    if done.returncode != 0:
        reason = (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
        return f"--torch-python {torch_python} cannot import torch ({reason}): {hint}"
    return None


def torch_run(args: argparse.Namespace, variant: str, mode: str, batch: int, reps: int,
              torch_variant: str = "eager") -> tuple[Run, dict]:
    env = dict(os.environ, BENCH_H=str(args.size[0]), BENCH_W=str(args.size[1]),
               TORCH_DEVICE=args.torch_device, TORCH_COMPILE="1" if torch_variant == "compiled" else "0")
    command = [args.torch_python, str(args.torch_bench), variant, mode, str(batch), str(reps),
               str(args.warmup)]
    load = os.getloadavg()[0]
    record = _json_line(command, env, f"PyTorch {torch_variant} {config_name(variant, mode, batch)}",
                        args.torch_timeout)
    return Run(1e3 * record["median_s"], record["foreign_cpu_frac"], load), record


def our_run(args: argparse.Namespace, variant: str, mode: str, batch: int, reps: int) -> tuple[Run, dict]:
    command = [sys.executable, str(Path(__file__).resolve()), "--ours", variant, mode, str(batch), str(reps),
               str(args.warmup), "--size", *map(str, args.size)]
    load = os.getloadavg()[0]
    record = _json_line(command, dict(os.environ), f"dpc_jax {config_name(variant, mode, batch)}")
    return Run(1e3 * record["median_s"], record["foreign_cpu_frac"], load), record


def table_row(label: str, pairs: Sequence[tuple[Run, Run]], max_foreign: float) -> str:
    """One Markdown row: each pair's PyTorch and our times, ratios (``*``: a pair in which either
    run had a foreign CPU share above ``max_foreign``), the median ratio of the other pairs (of
    all pairs, marked "loaded", when every pair was loaded), and the load."""
    ratios = [theirs.median_ms / ours.median_ms for theirs, ours in pairs]
    loaded = [max(t.foreign, o.foreign) > max_foreign for t, o in pairs]
    clean = [r for r, bad in zip(ratios, loaded, strict=True) if not bad]
    median = f"**{statistics.median(clean):.2f}×**" if clean else f"{statistics.median(ratios):.2f}× (loaded)"

    def joined(values: Sequence[float], fmt: str) -> str:
        return ", ".join(format(v, fmt) for v in values)

    runs = [run for pair in pairs for run in pair]
    theirs, ours = [t.median_ms for t, _ in pairs], [o.median_ms for _, o in pairs]
    marked = ", ".join(f"{r:.2f}{'*' if bad else ''}" for r, bad in zip(ratios, loaded, strict=True))
    return (
        f"| {label} | {joined(theirs, '.1f')} | {joined(ours, '.1f')} "
        f"| {marked} | {median} "
        f"| {joined([t.foreign for t, _ in pairs], '.2f')} / {joined([o.foreign for _, o in pairs], '.2f')} "
        f"| {min(r.load for r in runs):.1f}–{max(r.load for r in runs):.1f} |"
    )


TABLE_HEADER = (
    "| configuration | PyTorch ms | dpc_jax ms | ratio per pair | median ratio "
    "| foreign CPU (PyTorch / ours) | load avg |\n|---|---|---|---|---|---|---|"
)
SUMMARY_HEADER = (
    "| configuration | PyTorch eager ms | PyTorch compiled ms | dpc_jax ms | ratio to the faster PyTorch |"
    "\n|---|---|---|---|---|"
)


def summary_row(label: str, eager: Sequence[Run], compiled: Sequence[Run] | None, ours: Sequence[Run],
                compiled_note: str = "—") -> str:
    """One row of the summary table: the median of each side's runs and the ratio of the faster
    PyTorch variant to ours (``compiled_note`` stands where the compiled variant gave no time)."""
    eager_ms = statistics.median(r.median_ms for r in eager)
    ours_ms = statistics.median(r.median_ms for r in ours)
    compiled_ms = statistics.median(r.median_ms for r in compiled) if compiled else None
    faster = min(eager_ms, compiled_ms) if compiled_ms is not None else eager_ms
    which = "compiled" if compiled_ms is not None and compiled_ms < eager_ms else "eager"
    compiled_cell = f"{compiled_ms:.2f}" if compiled_ms is not None else compiled_note
    return (f"| {label} | {eager_ms:.2f} | {compiled_cell} | {ours_ms:.2f} "
            f"| **{faster / ours_ms:.2f}×** ({which}) |")


def wait_until_quiet(limit_s: float, max_busy: float) -> None:
    """Wait, at most ``limit_s``, until the other processes use at most ``max_busy`` cores' worth
    of CPU over one second (nothing of ours runs meanwhile)."""
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        began = _busy_s()
        time.sleep(1.0)
        if _busy_s() - began <= max_busy:
            return


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    names = [config_name(*c) for c in CONFIGURATIONS]
    parser.add_argument("--torch-python", help="Python of an environment with PyTorch (required)")
    parser.add_argument("--torch-bench", type=Path, default=TORCH_BENCH, help="bench_torch.py to run")
    parser.add_argument("--pairs", type=int, default=2, help="alternating PyTorch/ours pairs per row")
    parser.add_argument("--torch-device", choices=("cpu", "cuda"), default="cpu",
                        help="PyTorch's device (TORCH_DEVICE; default cpu); ours: JAX's default device")
    parser.add_argument("--torch-variants", nargs="+", choices=TORCH_VARIANTS, default=["eager"],
                        help="PyTorch variants timed in each pair (default eager; compiled: torch.compile)")
    parser.add_argument("--compiled-only", nargs="+", metavar="NAME",
                        help="with --torch-variants compiled: time the compiled variant only for these "
                             "configurations (default: all chosen)")
    parser.add_argument("--torch-timeout", type=float, metavar="SECONDS",
                        help="give up on a PyTorch run after this long (its cell then says so)")
    parser.add_argument("--reps", type=int, help="timed calls per run (default: 20 inference, 5 training)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls per run after the first")
    parser.add_argument("--only", nargs="+", metavar="NAME",
                        help=f"configurations VARIANT-MODE-BATCH to run (default: {' '.join(names)})")
    parser.add_argument("--max-foreign", type=float, default=0.1,
                        help="foreign CPU share above which a pair counts as loaded (default 0.1)")
    parser.add_argument("--wait-quiet", type=float, default=120, metavar="SECONDS",
                        help="before each run, wait up to this long for the other processes to go "
                             "quiet (default 120; 0: never wait)")
    parser.add_argument("--size", nargs=2, type=int, default=(240, 376), metavar=("H", "W"))
    parser.add_argument("--ours", nargs=5, metavar=("VARIANT", "MODE", "BATCH", "REPS", "WARMUP"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.pairs < 1 or (args.reps is not None and args.reps < 1) or args.warmup < 0:
        parser.error("--pairs and --reps must be at least 1, --warmup at least 0")
    try:
        args.configurations = ([parse_config_name(n) for n in args.only] if args.only
                               else list(CONFIGURATIONS))
    except ValueError as error:
        parser.error(f"--only: {error}")
    if "eager" not in args.torch_variants:
        parser.error("--torch-variants: eager is always timed (the per-pair table); add compiled")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.ours:
        variant, mode, batch, reps, warmup = args.ours
        record = run_ours(variant, mode, int(batch), int(reps), int(warmup), tuple(args.size))
        print(json.dumps(record), flush=True)
        return 0
    problem = check_torch_python(args.torch_python)
    if problem is None and not args.torch_bench.is_file():
        problem = f"{args.torch_bench} not found (the PyTorch reference; see --torch-bench)"
    if problem:
        print(f"bench_vs_torch: {problem}", file=sys.stderr)
        return 2

    print(f"`python benchmarks/bench_vs_torch.py {' '.join(sys.argv[1:])}`: {this_cpu()}, "
          f"{args.size[0]}×{args.size[1]}, {args.pairs} alternating pairs, "
          f"{time.strftime('%Y-%m-%d %H:%M')}", flush=True)
    rows, summary, versions = [], [], {}
    for variant, mode, batch in args.configurations:
        reps = args.reps or DEFAULT_REPS[mode]
        label = f"{NAMES[variant]} {'inference' if mode == 'infer' else 'train step'}, b{batch}"
        pairs, compiled_runs, compiled_note = [], [], "—"
        if args.compiled_only and config_name(variant, mode, batch) not in args.compiled_only:
            compiled_note = "not run"
        try:
            for _ in range(args.pairs):
                wait_until_quiet(args.wait_quiet, 0.2)
                theirs, torch_record = torch_run(args, variant, mode, batch, reps)
                if "compiled" in args.torch_variants and compiled_note == "—":  # not given up on
                    wait_until_quiet(args.wait_quiet, 0.2)
                    try:
                        compiled_runs.append(torch_run(args, variant, mode, batch, reps, "compiled")[0])
                    except BenchTimeout:
                        compiled_note = f"did not compile within {args.torch_timeout:g} s"
                    except BenchError as error:
                        compiled_note = "failed"
                        print(f"bench_vs_torch: {error}", file=sys.stderr, flush=True)
                wait_until_quiet(args.wait_quiet, 0.2)
                ours, our_record = our_run(args, variant, mode, batch, reps)
                pairs.append((theirs, ours))
        except BenchError as error:
            print(f"bench_vs_torch: {error}", file=sys.stderr)
            return 1
        versions = {"torch": torch_record["torch"], "threads": torch_record["threads"],
                    "jax": our_record["jax"], "torch_device": torch_record.get("device", args.torch_device),
                    "our_device": our_record.get("device", "?")}
        rows.append(table_row(label, pairs, args.max_foreign))
        print(f"  {rows[-1]}", file=sys.stderr, flush=True)
        if "compiled" in args.torch_variants:
            summary.append(summary_row(label, [t for t, _ in pairs], compiled_runs, [o for _, o in pairs],
                                       compiled_note))
            print(f"  {summary[-1]}", file=sys.stderr, flush=True)
    print(f"PyTorch {versions['torch']} on {versions['torch_device']} ({versions['threads']} threads), "
          f"jax {versions['jax']} on {versions['our_device']}; "
          f"median step time of each run ({args.reps or '20 inference / 5 training'} timed calls, "
          f"{args.warmup} warm-up); "
          "ratio = PyTorch time / ours (> 1: dpc_jax faster)\n")
    print(TABLE_HEADER)
    print("\n".join(rows))
    if summary:
        print("\nMedians over the pairs; PyTorch compiled: `torch.compile` of the forward and loss.\n")
        print(SUMMARY_HEADER)
        print("\n".join(summary))
    return 0


if __name__ == "__main__":
    if "--ours" in sys.argv:
        from dpc_jax.runtime.hugepages import reexec_with_huge_pages

        reexec_with_huge_pages()
    raise SystemExit(main())
