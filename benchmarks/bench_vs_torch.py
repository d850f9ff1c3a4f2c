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

from machine import this_cpu

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


def config_name(variant: str, mode: str, batch: int) -> str:
    return f"{variant}-{mode}-{batch}"


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
              "jax": jax.__version__, "compile_s": time.perf_counter() - began}
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


def _json_line(command: list[str], env: dict[str, str], what: str) -> dict:
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
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


def torch_run(args: argparse.Namespace, variant: str, mode: str, batch: int, reps: int) -> tuple[Run, dict]:
    env = dict(os.environ, BENCH_H=str(args.size[0]), BENCH_W=str(args.size[1]))
    command = [args.torch_python, str(args.torch_bench), variant, mode, str(batch), str(reps),
               str(args.warmup)]
    load = os.getloadavg()[0]
    record = _json_line(command, env, f"PyTorch {config_name(variant, mode, batch)}")
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
    parser.add_argument("--reps", type=int, help="timed calls per run (default: 20 inference, 5 training)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls per run after the first")
    parser.add_argument("--only", nargs="+", choices=names, metavar="NAME",
                        help=f"configurations to run (default all: {' '.join(names)})")
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

    chosen = [c for c in CONFIGURATIONS if args.only is None or config_name(*c) in args.only]
    print(f"`python benchmarks/bench_vs_torch.py {' '.join(sys.argv[1:])}`: {this_cpu()}, "
          f"{args.size[0]}×{args.size[1]}, {args.pairs} alternating pairs, "
          f"{time.strftime('%Y-%m-%d %H:%M')}", flush=True)
    rows, versions = [], {}
    for variant, mode, batch in chosen:
        reps = args.reps or DEFAULT_REPS[mode]
        pairs = []
        try:
            for _ in range(args.pairs):
                wait_until_quiet(args.wait_quiet, 0.2)
                theirs, torch_record = torch_run(args, variant, mode, batch, reps)
                wait_until_quiet(args.wait_quiet, 0.2)
                ours, our_record = our_run(args, variant, mode, batch, reps)
                pairs.append((theirs, ours))
        except BenchError as error:
            print(f"bench_vs_torch: {error}", file=sys.stderr)
            return 1
        versions = {"torch": torch_record["torch"], "threads": torch_record["threads"],
                    "jax": our_record["jax"]}
        label = f"{NAMES[variant]} {'inference' if mode == 'infer' else 'train step'}, b{batch}"
        rows.append(table_row(label, pairs, args.max_foreign))
        print(f"  {rows[-1]}", file=sys.stderr, flush=True)
    print(f"PyTorch {versions['torch']} ({versions['threads']} threads), jax {versions['jax']}; "
          f"median step time of each run ({args.reps or '20 inference / 5 training'} timed calls, "
          f"{args.warmup} warm-up); "
          "ratio = PyTorch time / ours (> 1: dpc_jax faster)\n")
    print(TABLE_HEADER)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    if "--ours" in sys.argv:
        from dpc_jax.hugepages import reexec_with_huge_pages

        reexec_with_huge_pages()
    raise SystemExit(main())
