"""Run the headline benchmarks and write their figures as a Markdown table into the docs and the README.

    python benchmarks/performance_table.py                        # every benchmark, full settings
    python benchmarks/performance_table.py --quick                # few repeats, small shapes: a check
    python benchmarks/performance_table.py --only bench_core bench_data

Each benchmark of :data:`BENCHMARKS` runs as its own process (the way a reader reproduces a row:
the table's command column is that exact command line); the figures are read from its output,
JSON where the benchmark writes it (``bench_vs_torch.py --ours``, ``bench_train_loop.py --json``),
its printed table otherwise. The full table, with the CPU that ``dpc_jax.runtime.machine`` names, the
library versions (``dpc_jax.runtime.versions``), the commit (``git rev-parse --short HEAD``, ``-dirty``
when tracked files differ from it) and the date of each row, goes into ``docs/performance.md`` between
``<!-- performance:begin -->`` and ``<!-- performance:end -->``; a short table (what, shape, figure,
command) of the rows measured in full into the README's Performance section between the same markers
(quick rows say nothing of speed, so the README never shows them). Both files are rewritten atomically,
and only between their markers. Rows of benchmarks not run this time (``--only``) are kept from the
previous table, so one benchmark can be re-measured alone.

``--quick`` runs every benchmark with few repeats and, where it takes them, small shapes and short
sequences: its figures check that the benchmarks still run and say little about speed; the block's
heading says when any row is from a quick run. Nothing here judges a figure: a slow row is
printed like a fast one.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import re
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dpc_jax.report.pages import commit, read_block, replace_block
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.runtime.versions import versions_line

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs" / "performance.md"
README = ROOT / "README.md"
BLOCK = "performance"  # docs/performance.md and the README: <!-- performance:begin --> … :end -->
QUICK = ", quick"  # after the date of a row measured with --quick


@dataclass(frozen=True)
class Row:
    """One line of the table: what was timed, at which shape, the figure, and its provenance."""

    what: str
    shape: str
    figure: str
    command: str = ""
    machine: str = ""
    libraries: str = ""
    commit: str = ""
    date: str = ""
    quick: bool = False


Parser = Callable[[str], list[Row]]


@dataclass(frozen=True)
class Benchmark:
    """A benchmark script, its arguments in full and in quick mode, and how to read its output."""

    name: str
    full: tuple[str, ...]
    quick: tuple[str, ...]
    parse: Parser | None  # None: bench_vs_torch, run once per model configuration (run_models)


class OutputError(RuntimeError):
    """A benchmark's output lacks a line this script reads (its format changed)."""


def _find(pattern: str, text: str, name: str) -> re.Match[str]:
    found = re.search(pattern, text, re.MULTILINE)
    if found is None:
        raise OutputError(f"{name}: no line matching {pattern!r} in its output")
    return found


def _json_object(text: str, name: str) -> Any:
    """The JSON object a benchmark printed after its table: from the first line that is ``{``."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.rstrip() == "{":
            return json.loads("\n".join(lines[i:]))
    raise OutputError(f"{name}: no JSON object in its output")


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def _table_row(text: str, first: str, name: str) -> list[str]:
    """The cells of the printed Markdown-style row whose first cell is ``first``."""
    for line in text.splitlines():
        if line.lstrip().startswith("|") and _cells(line)[0] == first:
            return _cells(line)
    raise OutputError(f"{name}: no table row {first!r} in its output")


def _option(args: Sequence[str], flag: str, default: str) -> str:
    return args[args.index(flag) + 1] if flag in args else default


def parse_synth(text: str) -> list[Row]:
    size = _find(r"image (\d+)x(\d+), (\d+) moving cars", text, "bench_synth")
    shape = f"{size[1]}×{size[2]} stereo, {size[3]} moving cars"
    render = _table_row(text, "render (stereo)", "bench_synth")
    figure = f"{float(render[3]):.1f} stereo frames/s rendering"
    if "render + write" in text:
        written = _table_row(text, "render + write", "bench_synth")
        figure += f", {float(written[3]):.1f} with PNG writing"
    return [Row("synthetic renderer", shape, figure)]


def parse_vo(text: str) -> list[Row]:
    size = _find(r"stereo VO, (\d+) frames of (\d+)x(\d+) grey pairs", text, "bench_vo")
    vo = _find(r"frames/s \(VO only\): ([\d.]+)", text, "bench_vo")
    decoding = _find(r"with decoding ([\d.]+) frames/s", text, "bench_vo")
    return [Row("classical stereo VO", f"{size[2]}×{size[3]} grey pairs, KITTI excerpt ({size[1]} frames)",
                f"{vo[1]} frames/s ({decoding[1]} with PNG decoding)")]


def parse_bag(text: str) -> list[Row]:
    size = _find(r"decoded to colour, (\d+) frames of (\d+)x(\d+)", text, "bench_bag")
    rates = {name: _table_row(text, name, "bench_bag")[1]
             for name in ("KITTI PNG files", "MCAP, rgb8", "MCAP, PNG-compressed", "ROS 1 bag, rgb8")}
    return [Row("a recording's stereo pairs read and decoded",
                f"{size[2]}×{size[3]} colour, {size[1]} frames",
                f"{rates['MCAP, rgb8']} frames/s from MCAP (rgb8), {rates['MCAP, PNG-compressed']} (PNG), "
                f"{rates['ROS 1 bag, rgb8']} from a ROS 1 bag; KITTI's PNG files {rates['KITTI PNG files']}")]


def parse_metrics(text: str) -> list[Row]:
    poses = _find(r"N = (\d+) poses", text, "bench_metrics")
    found = _find(r"^trajectory_metrics \(all\)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)×", text,
                  "bench_metrics")
    return [Row("all trajectory metrics", f"{poses[1]} poses, float64",
                f"{float(found[2]):.0f} ms ({found[4]}× the float64 loop)")]


def parse_cli(text: str) -> list[Row]:
    poses = _find(r": (\d+) poses;", text, "bench_cli")

    def seconds(title: str) -> float:
        return float(_find(rf"^{re.escape(title)}\s+([\d.]+)", text, "bench_cli")[1])

    cold = seconds("dpc-jax evaluate (empty compilation cache)")
    warm = seconds("dpc-jax evaluate (cache filled)")
    loop = seconds("float64 loop (dpc_jax.eval.reference_metrics)")
    return [Row("`dpc-jax evaluate --mat … --json -` as a whole process", f"{poses[1]} poses",
                f"{warm:.2f} s with the compilation cache filled, {cold:.2f} s the first time; "
                f"the float64 loop {loop:.2f} s")]


def parse_core(text: str) -> list[Row]:
    def median(function: str) -> tuple[str, float]:
        cells = _table_row(text, function, "bench_core")
        return cells[1], float(cells[2])

    exp_shape, exp_ms = median("se3_exp")
    _, log_ms = median("se3_log")
    warp_shape, warp_ms = median("inverse_warp fwd+bwd")
    _, ssim_ms = median("ssim_loss fwd+bwd")
    poses = exp_shape.strip("[]").split(",")[0]
    return [
        Row("`se3_exp` / `se3_log`", f"{poses} poses, float32", f"{exp_ms:.1f} ms / {log_ms:.1f} ms"),
        Row("`inverse_warp` fwd+bwd / `ssim_loss` fwd+bwd", warp_shape.strip("[]").replace(", ", "×"),
            f"{warp_ms:.1f} ms / {ssim_ms:.1f} ms"),
    ]


def parse_data(text: str) -> list[Row]:
    def rate(label: str) -> float:
        return float(_find(rf"^{re.escape(label)}\s.*?\s([\d.]+)\s+\d+\s+[\d.]+$", text, "bench_data")[1])

    batch = _find(r"^inline \(workers=0\)\s+\((\d+), 2, (\d+), (\d+)", text, "bench_data")
    return [Row("input pipeline", f"{batch[1]} stereo pairs + flow, {batch[2]}×{batch[3]}",
                f"{rate('inline (workers=0)'):.0f} batches/s inline, "
                f"{rate('prefetch (4 threads, depth 8)'):.0f} with 4 threads")]


def parse_train_loop(text: str) -> list[Row]:
    record = _json_object(text, "bench_train_loop")
    h, w = record["size"]
    rows = []
    for result in record["results"]:
        train, correct = result["train"], result["correct"]
        rows.append(Row(
            f"{result['method']} training loop / correction against the isolated step",
            f"batch {record['batch']}, {h}×{w}, {record['preset']} preset",
            f"train {train['loop_median']:.1f} samples/s (efficiency {train['efficiency']:.3g}); "
            f"correct {correct['loop_median']:.1f} frames/s (efficiency {correct['efficiency']:.3g})",
            machine=f"{record['device']}, {record['cpu']}",
        ))
    return rows


NETWORKS = {"mono": "ss-DPC-Net", "stereo": "Stereo DPC"}
# The model rows: inference at batch 1 and a training step at batch 8, each network, as the
# dpc_jax side of bench_vs_torch.py measures them (one process per configuration).
MODEL_RUNS = (("mono", "infer", 1), ("mono", "train", 8), ("stereo", "infer", 1), ("stereo", "train", 8))


def parse_models(records: Sequence[dict[str, Any]], size: tuple[int, int]) -> list[Row]:
    rows = []
    for variant in NETWORKS:
        infer = next(r for r in records if r["variant"] == variant and r["mode"] == "infer")
        train = next(r for r in records if r["variant"] == variant and r["mode"] == "train")
        rows.append(Row(
            f"{NETWORKS[variant]} inference / train step",
            f"batch {infer['batch']} / batch {train['batch']}, {size[0]}×{size[1]}",
            f"{1e3 * infer['median_s']:.1f} ms / {1e3 * train['median_s']:.1f} ms",
        ))
    return rows


BENCHMARKS = {
    b.name: b
    for b in (
        Benchmark("bench_synth", ("--write",),
                  ("--write", "--frames", "4", "--size", "64x96", "--repeats", "1"), parse_synth),
        Benchmark("bench_vo", (), ("--frames", "12", "--repeats", "1"), parse_vo),
        Benchmark("bench_bag", (), ("--frames", "12", "--repeats", "1"), parse_bag),
        Benchmark("bench_metrics", (), ("--repeats", "2"), parse_metrics),
        Benchmark("bench_cli", (), ("--repeats", "1"), parse_cli),
        Benchmark("bench_core", (),
                  ("--repeats", "3", "--poses", "10000", "--batch", "2", "--height", "64", "--width", "96"),
                  parse_core),
        Benchmark("bench_data", (),
                  ("--frames", "24", "--size", "64x96", "--batch", "8", "--repeats", "1"), parse_data),
        Benchmark("bench_vs_torch", ("--size", "240", "376"), ("--size", "64", "96"), None),
        Benchmark("bench_train_loop", ("--json", "-"),
                  ("--json", "-", "--preset", "small", "--size", "64x96", "--batch", "2", "--steps", "2",
                   "--rounds", "1", "--correct-frames", "8"),
                  parse_train_loop),
    )
}
MODEL_REPS = {"infer": ("20", "2"), "train": ("5", "2")}
QUICK_MODEL_REPS = ("2", "1")


def command_line(name: str, args: Sequence[str]) -> str:
    return " ".join(["python", f"benchmarks/{name}.py", *args])


def run(name: str, args: Sequence[str]) -> str:
    """The benchmark's standard output; its standard error passes through as progress."""
    began = time.perf_counter()
    print(f"$ {command_line(name, args)}", file=sys.stderr, flush=True)
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / f"{name}.py"), *args], cwd=ROOT,
                          stdout=subprocess.PIPE, text=True, check=False)
    if done.returncode != 0:
        raise OutputError(f"{name} failed (exit {done.returncode})")
    print(f"  {name}: {time.perf_counter() - began:.0f} s", file=sys.stderr, flush=True)
    return done.stdout


def run_models(quick: bool) -> list[Row]:
    """The dpc_jax side of bench_vs_torch.py: one ``--ours`` process per :data:`MODEL_RUNS` entry."""
    spec = BENCHMARKS["bench_vs_torch"]
    size_args = spec.quick if quick else spec.full
    size = (int(size_args[1]), int(size_args[2]))
    records, commands = [], []
    for variant, mode, batch in MODEL_RUNS:
        reps, warmup = QUICK_MODEL_REPS if quick else MODEL_REPS[mode]
        args = ("--ours", variant, mode, str(batch), reps, warmup, *size_args)
        output = run("bench_vs_torch", args)
        lines = [line for line in output.splitlines() if line.startswith("{")]
        if not lines:
            raise OutputError("bench_vs_torch --ours: no JSON line in its output")
        records.append(json.loads(lines[-1]))
        commands.append(command_line("bench_vs_torch", args))
    rows = parse_models(records, size)
    by_variant = {variant: [c for c, (v, _, _) in zip(commands, MODEL_RUNS, strict=True) if v == variant]
                  for variant in NETWORKS}
    device = records[0].get("device", "")
    machine = this_cpu() if device.lower() == "cpu" else f"{device}, {this_cpu()}"
    return [dataclasses.replace(row, command=" ; ".join(by_variant[variant]), machine=machine)
            for row, variant in zip(rows, NETWORKS, strict=True)]


def accelerator(text: str) -> str:
    """The JAX device a benchmark's ``device:`` header names, when it is not the CPU; else ``""``."""
    found = re.search(r"^device: ([^,]*)", text, re.MULTILINE)
    if found and re.search(r"\b(gpu|cuda|rocm|tpu)\b", found[1], re.IGNORECASE):
        return found[1].strip()
    return ""


def measure(names: Sequence[str], quick: bool) -> list[Row]:
    """The rows of the chosen benchmarks, in :data:`BENCHMARKS` order."""
    rows: list[Row] = []
    for name, spec in BENCHMARKS.items():
        if name not in names:
            continue
        if spec.parse is None:
            found = run_models(quick)
        else:
            args = spec.quick if quick else spec.full
            output = run(name, args)
            device = accelerator(output)
            machine = f"{device}, {this_cpu()}" if device else this_cpu()
            command = command_line(name, args)
            found = [dataclasses.replace(row, command=command, machine=row.machine or machine)
                     for row in spec.parse(output)]
        rows += [dataclasses.replace(row, quick=quick) for row in found]
    return rows


# ------------------------------------------------------------------------------------------ tables

FULL_HEADER = ("what", "shape", "figure", "command", "machine", "libraries", "commit", "date")
# The libraries column came on 2026-12-07: a row of an older table says so.
UNRECORDED = "not recorded"
SHORT_HEADER = ("what", "shape", "figure", "command")


def _line(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |"


def _code(command: str) -> str:
    return " ; ".join(f"`{part}`" for part in command.split(" ; "))


def full_table(rows: Sequence[Row]) -> str:
    lines = [_line(FULL_HEADER), "|" + "---|" * len(FULL_HEADER)]
    for r in rows:
        date = r.date + QUICK if r.quick else r.date
        lines.append(_line((r.what, r.shape, r.figure, _code(r.command), r.machine, r.libraries or UNRECORDED,
                            r.commit, date)))
    return "\n".join(lines)


def readme_block(rows: Sequence[Row]) -> str:
    """The README's block: the rows measured in full, under their heading; none when all are quick."""
    full = [r for r in rows if not r.quick]
    if not full:
        return ("No figures measured in full yet (only `--quick` rows, which show that the benchmarks run, "
                "not how fast: [docs/performance.md](docs/performance.md)); `python "
                "benchmarks/performance_table.py` measures them.")
    return f"{heading(full)}\n\n{short_table(full)}"


def short_table(rows: Sequence[Row]) -> str:
    lines = [_line(SHORT_HEADER), "|" + "---|" * len(SHORT_HEADER)]
    lines += [_line((r.what, r.shape, r.figure, _code(r.command))) for r in rows]
    return "\n".join(lines)


def heading(rows: Sequence[Row]) -> str:
    """One line naming the machines, commits and dates of the rows, and whether any is quick."""
    def distinct(values: Sequence[str]) -> str:
        return "; ".join(dict.fromkeys(values))

    machines, commits = distinct([r.machine for r in rows]), distinct([r.commit for r in rows])
    text = (f"Generated by `python benchmarks/performance_table.py` on {machines}, commit {commits}, "
            f"{distinct([r.date for r in rows])}.")
    quick = [r for r in rows if r.quick]
    if not quick:
        return text
    which = ("All rows are" if len(quick) == len(rows)
             else f"The rows of {distinct([benchmark_of(r) for r in quick])} are")
    return (f"{which} **quick-mode figures** (`--quick`: few repeats, small shapes): they show that "
            f"the benchmarks run, not how fast; the script without `--quick` gives the real table. "
            f"{text}")


def parse_full_table(block: str) -> list[Row]:
    """The rows of a table :func:`full_table` wrote (to keep those not measured again)."""
    rows = []
    for line in block.splitlines():
        cells = _cells(line) if line.startswith("|") else []
        if len(cells) == len(FULL_HEADER) - 1:  # a table from before the libraries column
            cells = [*cells[:5], UNRECORDED, *cells[5:]]
        if len(cells) != len(FULL_HEADER) or cells[0] == FULL_HEADER[0] or set(cells[0]) <= {"-"}:
            continue
        what, shape, figure, command, machine, libraries, commit, date = (
            c.replace("\\|", "|") for c in cells)
        plain = " ; ".join(part.strip("`") for part in command.split(" ; "))
        rows.append(Row(what, shape, figure, plain, machine, libraries, commit, date.removesuffix(QUICK),
                        quick=date.endswith(QUICK)))
    return rows


def benchmark_of(row: Row) -> str:
    found = re.search(r"benchmarks/(\w+)\.py", row.command)
    return found[1] if found else ""


def merge(previous: Sequence[Row], measured: Sequence[Row]) -> list[Row]:
    """The new rows, with the previous rows of benchmarks not run this time, in benchmark order."""
    fresh = {benchmark_of(r) for r in measured}
    kept = [r for r in previous if benchmark_of(r) not in fresh]
    order = list(BENCHMARKS)
    return sorted([*kept, *measured],
                  key=lambda r: order.index(benchmark_of(r)) if benchmark_of(r) in order else len(order))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="few repeats and small shapes: checks that the benchmarks run, in minutes")
    parser.add_argument("--only", nargs="+", metavar="NAME", choices=list(BENCHMARKS),
                        help=f"benchmarks to run (default: all of {' '.join(BENCHMARKS)})")
    parser.add_argument("--docs", type=Path, default=DOCS, help="the full table's file (%(default)s)")
    parser.add_argument("--readme", type=Path, default=README, help="the short table's file (%(default)s)")
    args = parser.parse_args(argv)
    try:  # before minutes of benchmarks, not after
        previous = read_block(args.docs, BLOCK)
        read_block(args.readme, BLOCK)
    except ValueError as error:
        raise SystemExit(f"performance_table: {error}") from None

    names = args.only or list(BENCHMARKS)
    try:
        measured = measure(names, args.quick)
    except OutputError as error:
        print(f"performance_table: {error}", file=sys.stderr)
        return 1
    provenance = {"commit": commit(ROOT), "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
                  "libraries": versions_line()}
    measured = [dataclasses.replace(row, **provenance) for row in measured]
    rows = merge(parse_full_table(previous), measured)
    replace_block(args.docs, BLOCK, f"{heading(rows)}\n\n{full_table(rows)}")
    replace_block(args.readme, BLOCK, readme_block(rows))
    print(full_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
