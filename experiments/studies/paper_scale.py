"""The papers' scale on a synthetic stand-in: what each stage costs (configs/paper_scale.py).

Renders sequences with the lengths of KITTI odometry 00–10 (scaled to ``--frames``), runs our VO,
prepares both methods' caches (ss-DPC-Net's with flow augmentation), trains each method, corrects
the longest sequence, and writes ``WORKDIR/scale.md`` and ``WORKDIR/scale.csv``: per stage and
method, wall and CPU time, the share of the cores it kept busy, frames or samples per second, peak
resident memory (all of it, and the anonymous part: what the process allocated, without the
file pages it mapped or wrote, which are the page cache's) and bytes on disk. Every stage but
rendering is the `dpc-jax` command a user runs, started as its own process and measured from
outside (``os.wait4`` for times and the kernel's peak, ``/proc/PID/status`` sampled every 50 ms for
the anonymous part). A finished stage is recorded in ``WORKDIR/stages/NAME.json`` and reused by a
rerun with the same settings. ``--planted-bias`` also writes, per sequence, a second prior: the
ground truth with a planted per-step rotation error (``dpc_jax.synth.planted_prior``).

``--docs`` puts the table's rows into the "Scale" table of docs/performance.md (replacing the rows
of the same run: profile, frames and size) with the machine, commit and date.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import json
import os
import re
import runpy
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# This checkout's dpc_jax, here and in the stages' processes (`python -m dpc_jax` from ROOT), whatever
# else is installed: the table's commit is the code that ran.
sys.path.insert(0, str(ROOT))
DPC_JAX = [sys.executable, "-m", "dpc_jax"]
CONFIG = ROOT / "experiments" / "studies" / "configs" / "paper_scale.py"
DOCS = ROOT / "docs" / "performance.md"
MB = 1e6


@dataclasses.dataclass
class Measured:
    """What one process (or a list of them, added up) cost."""

    wall_s: float = 0.0
    cpu_s: float = 0.0
    peak_rss_mb: float = 0.0  # the kernel's high-water mark, file pages included
    peak_anon_mb: float = 0.0  # sampled peak of RssAnon: the process's own allocations
    others_cpu_s: float = 0.0  # CPU time the rest of the machine used meanwhile (its load)

    def add(self, other: Measured) -> Measured:
        return Measured(
            self.wall_s + other.wall_s,
            self.cpu_s + other.cpu_s,
            max(self.peak_rss_mb, other.peak_rss_mb),
            max(self.peak_anon_mb, other.peak_anon_mb),
        )


def _anon_mb(pid: int) -> float | None:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    match = re.search(r"^RssAnon:\s+(\d+) kB", text, re.MULTILINE)
    return None if match is None else int(match.group(1)) / 1000


def _busy_cpu_s() -> float:
    """CPU seconds the whole machine has spent busy since boot (``/proc/stat``), 0 where unknown."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return 0.0
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in fields[:8])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def measure(command: Sequence[str], log: Path, env: dict[str, str] | None = None) -> Measured:
    """Run ``command`` (its output into ``log``) and measure it; ``RuntimeError`` naming the log
    when it fails."""
    peak = [0.0]
    with log.open("w") as out:
        start, busy = time.perf_counter(), _busy_cpu_s()
        process = subprocess.Popen(
            list(command), stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, env={**os.environ, **(env or {})}
        )
        done = threading.Event()

        def sample() -> None:
            while not done.wait(0.05):
                value = _anon_mb(process.pid)
                if value is not None:
                    peak[0] = max(peak[0], value)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        try:
            _, status, usage = os.wait4(process.pid, 0)
        except BaseException:
            process.kill()
            process.wait()
            raise
        finally:
            done.set()
            sampler.join()
        wall, busy = time.perf_counter() - start, _busy_cpu_s() - busy
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode != 0:
        tail = log.read_text(errors="replace").strip().splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(
            f"{' '.join(command[:3])} ... failed (exit {process.returncode}; {log}): {tail[0]}"
        )
    cpu = usage.ru_utime + usage.ru_stime
    return Measured(wall, cpu, usage.ru_maxrss / 1000, peak[0], max(0.0, busy - cpu))


def folder_bytes(path: Path) -> int:
    """Bytes of the regular files under ``path`` (their sizes, as a user's disk fills)."""
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


def lengths(kitti: dict[str, int], frames: int | None) -> dict[str, int]:
    """Each sequence's frames: KITTI's, or scaled so they add up to about ``frames`` (at least 8)."""
    if frames is None:
        return dict(kitti)
    total = sum(kitti.values())
    return {name: max(8, round(n * frames / total)) for name, n in kitti.items()}


@dataclasses.dataclass(frozen=True)
class Settings:
    """One run of the stand-in: what its stages depend on (recorded with each stage)."""

    frames: dict[str, int]
    size: tuple[int, int]
    profile: str
    training: dict[str, object]
    scale: dict[str, object]
    planted_bias: tuple[float, float, float] | None
    planted_noise: tuple[float, float, float]


class Stages:
    """Runs and records stages under ``workdir/stages``; a stage recorded with the same key is reused."""

    def __init__(self, workdir: Path, stamp: dict[str, str]) -> None:
        self.folder = workdir / "stages"
        self.logs = workdir / "logs"
        self.stamp = stamp  # machine, commit and date of the code that runs the stages now
        self.folder.mkdir(parents=True, exist_ok=True)
        self.logs.mkdir(parents=True, exist_ok=True)

    def done(self, name: str, key: dict) -> dict | None:
        path = self.folder / f"{name}.json"
        if not path.is_file():
            return None
        record = json.loads(path.read_text())
        return record if record.get("key") == key else None

    def record(self, name: str, key: dict, measured: Measured, **facts: object) -> dict:
        from dpc_jax._io import atomic_write

        record = {"key": key, **dataclasses.asdict(measured), **facts, **self.stamp}
        atomic_write(self.folder / f"{name}.json", json.dumps(record, indent=2))
        return record


def _json_key(settings: Settings, *fields: str) -> dict:
    return json.loads(json.dumps({f: getattr(settings, f) for f in fields}))


def render(stages: Stages, workdir: Path, settings: Settings) -> dict:
    key = _json_key(settings, "frames", "size", "scale")
    record = stages.done("render", key)
    if record is None:
        command = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--render-into",
            str(workdir / "data"),
            "--render-settings",
            json.dumps(key),
        ]
        measured = measure(command, stages.logs / "render.log")
        total = sum(settings.frames.values())
        record = stages.record(
            "render", key, measured, count=total, unit="frames", bytes=folder_bytes(workdir / "data")
        )
    return record


def _render_worker(out: Path, key: dict) -> None:
    """Render every sequence of ``key`` not yet complete under ``out`` (the render stage's process)."""
    from dpc_jax.synth import SynthConfig, write_sequence

    scale, size = key["scale"], key["size"]
    for index, (name, n) in enumerate(key["frames"].items()):
        if (out / "sequences" / name / "synth.json").is_file() and (out / "poses" / f"{name}.txt").is_file():
            continue
        config = SynthConfig(
            frames=n,
            height=size[0],
            width=size[1],
            seed=int(scale["seed"]) + index,
            moving_objects=int(scale["moving_objects"]),
            illumination_drift=float(scale["illumination_drift"]),
            noise=float(scale["noise"]),
        )
        write_sequence(out, name, config, overwrite=True)
        print(f"rendered {name}: {n} frames", flush=True)


def vo(stages: Stages, workdir: Path, settings: Settings) -> dict:
    key = _json_key(settings, "frames", "size", "scale")
    record = stages.done("vo", key)
    if record is None:
        measured = Measured()
        (workdir / "vo").mkdir(exist_ok=True)
        for name in settings.frames:
            command = [
                *DPC_JAX,
                "vo",
                "--kitti-odometry",
                str(workdir / "data"),
                "--sequence",
                name,
                "--out",
                str(workdir / "vo" / f"{name}.txt"),
                "--no-progress",
            ]
            measured = measured.add(measure(command, stages.logs / f"vo_{name}.log"))
        record = stages.record("vo", key, measured, count=sum(settings.frames.values()), unit="frames")
    return record


def planted(workdir: Path, settings: Settings) -> None:
    """Write ``WORKDIR/planted/XX.txt``: each sequence's ground truth with the planted rotation error."""
    import numpy as np

    from dpc_jax._io import atomic_write
    from dpc_jax.data.kitti import read_ground_truth
    from dpc_jax.synth.planted_prior import planted_prior

    assert settings.planted_bias is not None
    out = workdir / "planted"
    out.mkdir(exist_ok=True)
    bias = np.asarray(settings.planted_bias) * 1e-3
    noise = np.asarray(settings.planted_noise) * 1e-3
    for index, name in enumerate(settings.frames):
        gt = read_ground_truth(workdir / "data" / "poses" / f"{name}.txt")
        prior = planted_prior(gt, bias, noise, seed=index)
        atomic_write(
            out / f"{name}.txt", "".join(" ".join(f"{v:.9e}" for v in p[:3].ravel()) + "\n" for p in prior)
        )


def prepare(stages: Stages, workdir: Path, settings: Settings, method: str) -> dict:
    key = _json_key(settings, "frames", "size", "scale")
    name = f"prepare_{method}"
    record = stages.done(name, key)
    if record is None:
        out = workdir / "cache" / method
        command = [
            *DPC_JAX,
            "prepare",
            "--kitti-odometry",
            str(workdir / "data"),
            "--sequence",
            *settings.frames,
            "--prior",
            str(workdir / "vo" / "{seq}.txt"),
            "--out",
            str(out),
            "--size",
            f"{settings.size[0]}x{settings.size[1]}",
            "--no-progress",
        ]
        if method == "ss_dpc":
            command.append("--flow-augment")
        measured = measure(command, stages.logs / f"{name}.log")
        total = sum(settings.frames.values())
        record = stages.record(name, key, measured, count=total, unit="frames", bytes=folder_bytes(out))
    return record


def training_config(workdir: Path, settings: Settings, method: str, base: dict) -> dict:
    scale = settings.scale
    return {
        **base,
        **settings.training,
        "image_size": tuple(settings.size),
        "cache_root": str(workdir / "cache" / method),
        "train_sequences": tuple(s for s in settings.frames if s not in (scale["test"], scale["validation"])),
        "validation_sequences": (scale["validation"],),
        "test_sequences": (scale["test"],),
    }


def train(stages: Stages, workdir: Path, settings: Settings, method: str, base: dict) -> dict:
    config = training_config(workdir, settings, method, base)
    key = {**_json_key(settings, "frames", "size", "scale"), "config": json.loads(json.dumps(config))}
    name = f"train_{method}"
    record = stages.done(name, key)
    if record is None:
        from dpc_jax._io import atomic_write

        run = workdir / "runs" / method
        if run.exists():
            raise RuntimeError(f"{run} holds a run of other settings; remove it to train again")
        config_file = workdir / "configs" / f"{method}.py"
        config_file.parent.mkdir(exist_ok=True)
        atomic_write(config_file, f"CONFIG = {config!r}\n")
        command = [*DPC_JAX, "train", "--config", str(config_file), "--workdir", str(run), "--no-progress"]
        measured = measure(command, stages.logs / f"{name}.log")
        with (run / "metrics.csv").open() as f:
            epochs = list(csv.DictReader(f))
        record = stages.record(
            name,
            key,
            measured,
            unit="samples",
            count=int(epochs[-1]["step"]) * config["batch_size"],
            samples_per_s=[float(e["samples_per_s"]) for e in epochs],
            batch_size=config["batch_size"],
        )
    return record


def correct(stages: Stages, workdir: Path, settings: Settings, method: str) -> dict:
    key = _json_key(settings, "frames", "size", "scale", "training")
    name = f"correct_{method}"
    record = stages.done(name, key)
    if record is None:
        test = str(settings.scale["test"])
        command = [
            *DPC_JAX,
            "correct",
            "--checkpoint",
            str(workdir / "runs" / method),
            "--select",
            "last",
            "--data",
            str(workdir / "cache" / method / test),
            "--out",
            str(workdir / "corrected" / method / f"{test}.txt"),
            "--report",
            str(workdir / "reports" / method / test),
            "--no-progress",
        ]
        measured = measure(command, stages.logs / f"{name}.log")
        record = stages.record(name, key, measured, count=settings.frames[test], unit="frames")
    return record


HEADER = [
    "run",
    "stage",
    "method",
    "count",
    "wall (s)",
    "CPU (s)",
    "cores busy",
    "others' load",
    "rate",
    "peak RSS (MB)",
    "peak anon (MB)",
    "disk (MB)",
    "disk per frame (MB)",
    "30 epochs × 46k pairs",
    "machine",
    "commit",
    "date",
]


def _rows(run: str, records: dict[str, dict], cores: int, paper: tuple[int, int]) -> list[list[str]]:
    from dpc_jax.report.tables import EMPTY

    rows = []
    for stage, record in records.items():
        kind, _, method = stage.partition("_")
        if kind == "train":
            rates = record["samples_per_s"]
            rate = rates[-1] if rates else float("nan")
            rate_text = f"{rate:.2f} samples/s (batch {record['batch_size']}, after the first step)"
            pairs, epochs = paper
            extrapolated = f"{pairs * epochs / rate / 3600:.1f} h" if rate > 0 else ""
        else:
            rate = record["count"] / record["wall_s"] if record["count"] else float("nan")
            rate_text, extrapolated = f"{rate:.1f} {record['unit']}/s", ""
        count = "" if record.get("count") is None else f"{record['count']} {record['unit']}"
        disk = record.get("bytes")
        rows.append(
            [
                run,
                kind,
                method or EMPTY,
                count,
                f"{record['wall_s']:.1f}",
                f"{record['cpu_s']:.1f}",
                f"{record['cpu_s'] / record['wall_s'] / cores:.2f}",
                "not recorded"
                if "others_cpu_s" not in record
                else f"{record['others_cpu_s'] / record['wall_s'] / cores:.2f}",
                rate_text,
                f"{record['peak_rss_mb']:.0f}",
                f"{record['peak_anon_mb']:.0f}",
                "" if disk is None else f"{disk / MB:.0f}",
                "" if disk is None else f"{disk / MB / record['count']:.3f}",
                extrapolated,
                *(record.get(field, "not recorded") for field in ("machine", "commit", "date")),
            ]
        )
    return rows


def _machine() -> str:
    """The CPU (benchmarks/machine.py's description) and the accelerator JAX sees, if any."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from machine import this_cpu

    code = "import jax; d = jax.devices()[0]; print(d.platform, d.device_kind)"
    found = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    platform_name, _, kind = found.stdout.strip().partition(" ")
    return this_cpu() + ("" if platform_name in ("cpu", "") else f", {kind}")


def write_docs(rows: list[list[str]], run: str) -> None:
    """Replace the rows of ``run`` in docs/performance.md's Scale table (its ``scale`` block)."""
    from dpc_jax.report.pages import read_block, replace_block
    from dpc_jax.report.tables import row as md_row
    from dpc_jax.report.tables import table

    kept = [
        line
        for line in read_block(DOCS, "scale").strip().splitlines()[2:]
        if line.startswith("| ") and not line.startswith(md_row([run]).removesuffix(" |") + " |")
    ]
    body = table(HEADER, []).rstrip("\n") + "\n" + "\n".join([*kept, *(md_row(cells) for cells in rows)])
    replace_block(DOCS, "scale", body)


def build_parser() -> argparse.ArgumentParser:
    # Imported here, not at the top: this checkout's dpc_jax is put first on the path above.
    from dpc_jax.pipelines.protocol import path_argument

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--workdir", type=path_argument, help="work folder (made if missing; a rerun reuses its stages)"
    )
    parser.add_argument("--config", type=path_argument, default=CONFIG, help="the experiment's config file")
    parser.add_argument("--frames", type=int, metavar="N", help="total frames (default: KITTI's 23,201)")
    parser.add_argument("--size", metavar="HxW", help="image size (default: the config's, 240x376)")
    parser.add_argument(
        "--profile",
        choices=("cpu", "gpu"),
        default="cpu",
        help="training length: cpu = a few steps at batch 8, gpu = 2 epochs at batch 32",
    )
    parser.add_argument(
        "--methods", nargs="+", choices=("stereo_dpc", "ss_dpc"), default=["stereo_dpc", "ss_dpc"]
    )
    parser.add_argument(
        "--planted-bias",
        type=float,
        nargs=3,
        metavar=("PX", "PY", "PZ"),
        help="also write priors with this per-step rotation bias (mrad, camera x y z)",
    )
    parser.add_argument(
        "--planted-noise",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 0.0),
        metavar=("SX", "SY", "SZ"),
        help="per-step rotation noise of the planted priors (mrad, standard deviation)",
    )
    parser.add_argument(
        "--docs", action="store_true", help="put the rows into docs/performance.md's Scale table"
    )
    parser.add_argument("--render-into", type=Path, help=argparse.SUPPRESS)  # the render stage's own process
    parser.add_argument("--render-settings", help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.render_into is not None:
        _render_worker(args.render_into, json.loads(args.render_settings))
        return 0
    try:
        if args.workdir is None:
            raise ValueError("--workdir is required (a folder to make, or one this experiment made)")
        config = runpy.run_path(str(args.config))
        size = tuple(config["SCALE"]["size"])
        if args.size:
            h, _, w = args.size.partition("x")
            size = (int(h), int(w))
        if args.frames is not None and args.frames < 8 * len(config["KITTI_LENGTHS"]):
            raise ValueError(f"--frames {args.frames}: expected at least {8 * len(config['KITTI_LENGTHS'])}")
        from dpc_jax.pipelines.protocol import claim_workdir

        if args.docs:  # before hours of stages, not after
            from dpc_jax.report.pages import read_block

            read_block(DOCS, "scale")
        workdir = claim_workdir(args.workdir, [("--config", args.config)],
                                files=[("--docs", DOCS if args.docs else None)])
        assert workdir is not None  # a work folder was given
    except (ValueError, KeyError, OSError) as error:
        print(f"paper_scale: error: {error}", file=sys.stderr)
        return 2
    settings = Settings(
        frames=lengths(config["KITTI_LENGTHS"], args.frames),
        size=size,
        profile=args.profile,
        training=config["PROFILES"][args.profile],
        scale=config["SCALE"],
        planted_bias=None if args.planted_bias is None else tuple(args.planted_bias),
        planted_noise=tuple(args.planted_noise),
    )
    from dpc_jax.report.pages import commit

    # Each stage records the code and machine that ran it: a rerun may reuse stages of another commit.
    stages = Stages(
        workdir, {"machine": _machine(), "commit": commit(ROOT), "date": datetime.date.today().isoformat()}
    )
    records: dict[str, dict] = {}
    try:
        records["render"] = render(stages, workdir, settings)
        records["vo"] = vo(stages, workdir, settings)
        if settings.planted_bias is not None:
            planted(workdir, settings)
        for method in args.methods:
            records[f"prepare_{method}"] = prepare(stages, workdir, settings, method)
        for method in args.methods:
            records[f"train_{method}"] = train(stages, workdir, settings, method, config["METHODS"][method])
            records[f"correct_{method}"] = correct(stages, workdir, settings, method)
    except (RuntimeError, OSError, ValueError) as error:
        print(f"paper_scale: error: {error}", file=sys.stderr)
        return 1
    from dpc_jax._io import atomic_write
    from dpc_jax.report.tables import csv_text, table

    total = sum(settings.frames.values())
    run = f"{args.profile} profile, {total} frames, {size[0]}×{size[1]}"
    rows = _rows(run, records, os.cpu_count() or 1, (config["PAPER_PAIRS"], config["PAPER_EPOCHS"]))
    lines = [
        f"# The papers' scale: {run}",
        "",
        "Each row names the machine and commit that measured it (a rerun reuses finished stages); "
        f"`python experiments/studies/paper_scale.py --workdir {workdir}"
        + ("" if args.frames is None else f" --frames {args.frames}")
        + ("" if args.size is None else f" --size {args.size}")
        + f" --profile {args.profile}`.",
        f"Sequences (frames): {', '.join(f'{k} ({v})' for k, v in settings.frames.items())}; "
        f"training: {settings.training}; corrected: {settings.scale['test']}.",
        "",
        table(HEADER, rows),
    ]
    atomic_write(workdir / "scale.md", "\n".join(lines))
    atomic_write(workdir / "scale.csv", csv_text(HEADER, rows))
    if args.docs:
        write_docs(rows, run)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
