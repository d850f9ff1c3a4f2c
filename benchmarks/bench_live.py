"""Latency of the live correction per frame, as Stereo DPC's paper measures it: from the stereo pair to
the corrected pose.

    python benchmarks/bench_live.py                      # both methods at 64x96, 120x188 and 240x376
    python benchmarks/bench_live.py --quick              # the small preset at 64x96, 16 frames: a check
    python benchmarks/bench_live.py --write-docs         # and the rows into docs/performance.md ("Live")
    python benchmarks/bench_live.py --profile            # and a cProfile of the first configuration's frames
    python benchmarks/bench_live.py --realtime 10        # paced at 10 Hz, the tests measured behind the poses

Each frame of the real drive (KITTI raw 2011_09_26, drive 0001, 1242×375 colour pairs, from
``../shared/data/kitti-raw``; ``--frames`` beyond its 108 play it back and forth; synthetic frames of
the same size with ``--synthetic`` or without the drive) is timed in four ways, one after the other:

* **VO**: our stereo VO (``dpc_jax.vo.StereoVO``) on the grey pair in memory;
* **correction**: ``dpc_jax.correction.live.LiveCorrector`` on the colour pair in memory with the VO's
  pose: the pair prepared as ``prepare`` does (resized, StereoSGBM; the optical flow for ss-DPC-Net),
  the network's forward pass (what the paper's 9.53 ms measures), Δ of the parts for the sequential
  tests, the tests and the composed pose; its stages ``prepare``, ``network`` and ``measure`` are also
  given apart;
* **VO + correction**: both, the pair in memory: what the paper's 42.73 ms (libviso2-s + correction)
  measures;
* **from PNG**: decoding the pair's four images (colour for the network, grey for the VO, two at a time,
  as ``dpc-jax vo --correct`` does) and both.

With ``--realtime HZ`` the frames come at HZ (frame k due k/HZ s after the first) and the corrector
measures the tests' Δ behind the poses, skipping the pairs that come while it is busy (``dpc-jax vo
--correct … --realtime``): our VO runs as the prior's function while the pair is prepared on the other
core, so **VO** is its own time, **VO + correction** the call (VO and preparation side by side, the
network, the composed pose), **correction** what the call adds to the VO, **from PNG** the latency from
the frame's due time to its pose (decoding included), and the row says how many pairs were measured
and how many frames missed their deadline (a pose after the next frame is due); ``measure`` is then
the measurement's own time, off the pose's path.

p50, p99 and max are over the frames after ``--warmup`` frames; the compile time (the corrector's
construction: the network restored for the backend and compiled, before the first frame) is apart.
The networks are untrained, the method's model of ``--preset`` initialised from a seed as
``tests/support.py`` builds one: the latency does not depend on the weights. The table names the
device, the CPU, the commit and the load; ``--write-docs`` puts its rows between the ``live`` markers
of ``docs/performance.md``, replacing the rows of the same machine, method, size and preset and
keeping the others.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime
import io
import math
import os
import pstats
import sys
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dpc_jax.runtime.hugepages import reexec_with_huge_pages
from dpc_jax.runtime.machine import this_cpu
from dpc_jax.runtime.versions import versions_line

ROOT = Path(__file__).resolve().parents[1]
DRIVE = ROOT.parent / "shared" / "data" / "kitti-raw"
DOCS = ROOT / "docs" / "performance.md"
BLOCK = "live"  # docs/performance.md: <!-- live:begin --> … <!-- live:end -->
QUICK = ", quick"  # after the date of a row measured with --quick
SIZES = ("64x96", "120x188", "240x376")
METHODS = ("stereo_dpc", "ss_dpc")
NAMES = {"stereo_dpc": "Stereo DPC", "ss_dpc": "ss-DPC-Net"}
TIMED = ("vo", "correction", "both", "png")
STAGES = ("prepare", "network", "measure")
HEADER = ("method", "size", "preset", "tests measured", "compile s", "VO ms p50 / p99 / max", "correction",
          "VO + correction", "from PNG", "correction's stages, p50 ms: prepare / network / measure",
          "command", "machine", "libraries", "commit", "date")
# The libraries column came on 2026-12-07: a row of an older table says so.
UNRECORDED = "not recorded"
# Before --realtime every row measured the tests' Δ in the frame's own call.
INLINE = "inline"


@dataclass(frozen=True)
class Frames:
    """Where the frames come from: ``paths`` (left, right) per frame, or None for synthetic frames;
    ``K``, ``baseline``, ``image_size`` of the camera; ``name`` for the header."""

    paths: list[tuple[Path, Path]] | None
    K: np.ndarray
    baseline: float
    image_size: tuple[int, int]
    name: str


def source(synthetic: bool) -> Frames:
    """The real drive, or the synthetic stand-in when asked or when the drive is not there."""
    from dpc_jax.data.kitti import open_raw

    if not synthetic and (DRIVE / "2011_09_26").is_dir():
        sequence = open_raw(DRIVE, "2011_09_26", "0001")
        paths = list(zip(sequence.images.left_paths, sequence.images.right_paths, strict=True))
        return Frames(paths, sequence.K, sequence.baseline, sequence.image_size,
                      f"KITTI raw 2011_09_26 drive 0001 ({sequence.image_size[1]}x{sequence.image_size[0]})")
    K = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
    return Frames(None, K, 0.5372, (375, 1242), "synthetic frames (1242x375, KITTI's colour intrinsics)")


def _texture(size: tuple[int, int], seed: int = 0) -> np.ndarray:
    """A random colour texture with corners for the VO's FAST detector, wider than the frames (they
    slide over it)."""
    rng = np.random.default_rng(seed)
    h, w = size
    noise = rng.integers(0, 256, (h // 3, (w + 500) // 3, 3), np.uint8)
    return cv2.resize(cv2.GaussianBlur(noise, (3, 3), 0.8), (w + 500, h), interpolation=cv2.INTER_LINEAR)


def frames(where: Frames, count: int) -> Iterator[tuple[int, tuple[Path, Path] | None]]:
    """``count`` frame numbers, the drive played forward and back again as often as it takes."""
    n = len(where.paths) if where.paths is not None else 108  # as many as the drive; the texture fits them
    cycle = list(range(n)) + list(range(n - 2, 0, -1))
    for k in range(count):
        index = cycle[k % len(cycle)]
        yield index, None if where.paths is None else where.paths[index]


def decode(pool: ThreadPoolExecutor, where: Frames, index: int, paths: tuple[Path, Path] | None,
           texture: np.ndarray) -> list[np.ndarray]:
    """The frame's four images: colour left, right, grey left, right (decoded two at a time, as
    ``dpc-jax vo --correct`` does; synthetic: cut from the texture)."""
    from dpc_jax.data.kitti import load_image

    if paths is not None:
        jobs = [pool.submit(load_image, path, grey) for grey in (False, True) for path in paths]
        return [job.result() for job in jobs]
    h, w = where.image_size
    # A ground-plane-like scene seen by a camera moving sideways: the disparity grows from 5 px at the top
    # row to 35 px at the bottom, and each row moves by 2 px per frame at 20 px of disparity.
    disparity = np.round(5 + 30 * np.arange(h) / h).astype(int)
    moved = np.round(index * 2 * disparity / 20).astype(int)
    rows, columns = np.arange(h)[:, None], np.arange(w)[None, :]
    left = texture[rows, moved[:, None] + columns]
    right = texture[rows, (moved + disparity)[:, None] + columns]
    return [left, right, cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)]


def untrained_run(method: str, preset: str, size: tuple[int, int]):  # -> TrainedRun
    """The method's network of ``preset`` at ``size``, initialised from seed 0, as a restored run."""
    from flax import nnx

    from dpc_jax.correction.inference import TrainedRun
    from dpc_jax.nn.models import create_model
    from dpc_jax.training.train_config import REFERENCE, TrainConfig

    config = TrainConfig(method=method, preset=preset, image_size=size, **REFERENCE, cache_root="unused",
                         train_sequences=("00",), validation_sequences=("01",))
    model = create_model(method, config.model_config(), 0)
    model.eval()
    graphdef, state = nnx.split(model)
    return TrainedRun(Path(f"<untrained {method}>"), config, "last", 0, graphdef, state)


@dataclass
class Result:
    """One configuration's figures: seconds per timed frame of each of :data:`TIMED`, of the
    correction's ``prepare`` and ``network`` stages, and the compile time."""

    method: str
    size: tuple[int, int]
    compile_s: float
    seconds: dict[str, list[float]]
    mode: str = INLINE

    def ms(self, name: str) -> tuple[float, float, float]:
        values = 1e3 * np.asarray(self.seconds[name])
        values = values[np.isfinite(values)]  # behind, a frame whose pair's measurement was not fed
        if not len(values):
            return math.nan, math.nan, math.nan
        p50, p99 = np.percentile(values, [50, 99])
        return float(p50), float(p99), float(values.max())


def measure(where: Frames, method: str, preset: str, size: tuple[int, int], count: int, warmup: int,
            profile: cProfile.Profile | None, hz: float | None = None) -> Result:
    """Time ``count`` frames of one configuration (the module docstring), the first ``warmup`` apart;
    ``hz``: paced, measured behind the poses."""
    from dpc_jax.correction.live import Calibration, LiveCorrector
    from dpc_jax.vo import StereoVO

    run = untrained_run(method, preset, size)
    began = time.perf_counter()
    # Forced, so that every pair composes a corrected pose; the tests run as they would anyway.
    live = LiveCorrector(run, Calibration(where.K, where.baseline, where.image_size), force=True,
                         behind=hz is not None, skip=hz is not None)
    compile_s = time.perf_counter() - began
    vo = StereoVO(where.K, where.baseline)
    texture = _texture(where.image_size)
    seconds: dict[str, list[float]] = {name: [] for name in (*TIMED, *STAGES)}
    pose = np.eye(4)
    late = measured = pairs = 0
    started = time.perf_counter()
    with ThreadPoolExecutor(2) as pool:
        for k, (index, paths) in enumerate(frames(where, count)):
            timed = k >= warmup
            if k == warmup:  # paced from the first timed frame: the warm-up's compilation is not a deadline
                started = time.perf_counter() - k / (hz or 1.0)
            due = started + k / hz if hz is not None else time.perf_counter()
            time.sleep(max(0.0, due - time.perf_counter()))
            live.hold()  # arrived: the measurement behind the poses stops for it (as dpc-jax vo does)
            t0 = time.perf_counter()
            left, right, grey_left, grey_right = decode(pool, where, index, paths, texture)
            if timed and profile is not None:  # the VO and the correction, not the decoding threads
                profile.enable()
            if hz is None:
                t1 = time.perf_counter()
                estimate = vo.process(grey_left, grey_right)
                if estimate is not None:
                    pose = pose @ np.linalg.inv(estimate.relative)
                t2 = time.perf_counter()
                frame = live(left, right, pose)
            else:
                def prior(pair: tuple[np.ndarray, np.ndarray] = (grey_left, grey_right)) -> np.ndarray:
                    nonlocal pose
                    estimate = vo.process(*pair)
                    pose = pose if estimate is None else pose @ np.linalg.inv(estimate.relative)
                    return pose

                t1 = time.perf_counter()
                frame = live(left, right, prior)
                t2 = t1 + frame.seconds["vo"]
                t0 = due
            t3 = time.perf_counter()
            if profile is not None:
                profile.disable()
            if timed and frame.proposal is not None:
                pairs += 1
                measured += frame.measured
                late += hz is not None and t3 > started + (k + 1) / hz
                for name, value in (("vo", t2 - t1), ("correction", t3 - t2), ("both", t3 - t1),
                                    ("png", t3 - t0),
                                    *((stage, frame.seconds.get(stage, np.nan)) for stage in STAGES)):
                    seconds[name].append(value)
    live.close()
    mode = INLINE if hz is None else (f"behind, {hz:g} Hz: {measured} of {pairs} pairs measured, {late} "
                                      "missed")
    return Result(method, size, compile_s, seconds, mode)


def _three(values: tuple[float, float, float]) -> str:
    return " / ".join(f"{v:.1f}" for v in values)


def rows(results: Sequence[Result], preset: str, command: str, machine: str, commit: str, date: str
         ) -> list[list[str]]:
    """The table's rows (:data:`HEADER`)."""
    out = []
    for r in results:
        stages = " / ".join(f"{r.ms(stage)[0]:.1f}" for stage in STAGES)
        out.append([NAMES[r.method], f"{r.size[0]}×{r.size[1]}", preset, r.mode, f"{r.compile_s:.1f}",
                    *(_three(r.ms(name)) for name in TIMED), stages, f"`{command}`", machine, versions_line(),
                    commit, date])
    return out


def table(lines: Sequence[Sequence[str]]) -> str:
    cells = [list(HEADER), ["---"] * len(HEADER), *lines]
    return "\n".join("| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in cells)


def block(lines: Sequence[Sequence[str]]) -> str:
    """What goes between the markers: the table, under a warning when a row is from ``--quick``."""
    quick = [row for row in lines if row[-1].endswith(QUICK)]
    warning = ("Rows dated *quick* are from `--quick` (the small preset, 16 frames): they show that the "
               "benchmark runs, not how fast.\n\n" if quick else "")
    return warning + table(lines)


def parse_table(text: str) -> list[list[str]]:
    """The rows of a table :func:`table` wrote (to keep the rows not measured again)."""
    found = []
    for line in text.splitlines():
        if not line.startswith("|"):
            continue
        cells = [c.strip().replace("\\|", "|") for c in line.strip().strip("|").split(" | ")]
        if len(cells) == len(HEADER) - 2:  # a table from before the libraries and tests columns
            at = HEADER.index("libraries") - 1
            cells = [*cells[:at], UNRECORDED, *cells[at:]]
        if len(cells) == len(HEADER) - 1:  # a table from before the tests column
            at = HEADER.index("tests measured")
            cells = [*cells[:at], INLINE, *cells[at:]]
        if len(cells) == len(HEADER) and cells[0] != HEADER[0] and set(cells[0]) != {"-"}:
            found.append(cells)
    return found


def merge(previous: Sequence[list[str]], measured: Sequence[list[str]]) -> list[list[str]]:
    """The measured rows, and the previous rows of other machines, methods, sizes or presets."""
    def key(row: Sequence[str]) -> tuple[str, ...]:
        return row[0], row[1], row[2], row[3], row[HEADER.index("machine")]

    fresh = {key(row) for row in measured}
    return [*[row for row in previous if key(row) not in fresh], *measured]


def device() -> str:
    import jax

    devices = jax.devices()
    if jax.default_backend() == "cpu":
        return this_cpu()
    return f"{len(devices)} x {devices[0].device_kind} ({jax.default_backend()}), {this_cpu()}"


def print_profile(profile: cProfile.Profile, result: Result) -> None:
    """The functions that took the most time over the profiled frames, and the split of a frame's time."""
    text = io.StringIO()
    stats = pstats.Stats(profile, stream=text)
    stats.sort_stats("tottime").print_stats(18)
    print(f"\ncProfile of {NAMES[result.method]} at {result.size[0]}x{result.size[1]}, the timed frames "
          "(own time per function):")
    print("\n".join(line for line in text.getvalue().splitlines() if line.strip())[:6000])
    both, vo, correction = (result.ms(name)[0] for name in ("both", "vo", "correction"))
    prepare, network, measure = (result.ms(stage)[0] for stage in STAGES)
    rest = correction - prepare - network - measure
    print(f"\nsplit of the median frame (ms): VO {vo:.1f}; correction {correction:.1f}: preparation "
          f"{prepare:.1f}, network {network:.1f}, measurement of Δ {measure:.1f}, the rest (tests, "
          f"composition, bookkeeping) {rest:.1f}; VO + correction {both:.1f}")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="the small preset at 64x96, 16 frames after 4 of warm-up: checks that it runs")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--sizes", nargs="+", default=None, metavar="HxW",
                        help=f"network input sizes (default: {' '.join(SIZES)}; --quick: 64x96)")
    parser.add_argument("--preset", choices=("reference", "small"), default=None,
                        help="the networks' preset (default: reference; --quick: small)")
    parser.add_argument("--frames", type=int, default=None, help="frames timed (default: 300; --quick: 16)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="frames before the timed ones (default: 8; --quick: 4)")
    parser.add_argument("--synthetic", action="store_true", help="synthetic frames instead of the drive")
    parser.add_argument("--realtime", type=float, default=None, metavar="HZ",
                        help="frames paced at HZ, the tests measured behind the poses (module docstring)")
    parser.add_argument("--profile", action="store_true",
                        help="cProfile the timed frames of the first configuration; print what took the time")
    parser.add_argument("--write-docs", action="store_true",
                        help=f"write the rows into {DOCS.relative_to(ROOT)} (between the live markers)")
    args = parser.parse_args(argv)
    sizes = args.sizes or (["64x96"] if args.quick else list(SIZES))
    preset = args.preset or ("small" if args.quick else "reference")
    count = args.frames or (16 if args.quick else 300)
    warmup = 4 if args.quick and args.warmup is None else (8 if args.warmup is None else args.warmup)
    try:
        shapes = [(int(h), int(w)) for h, w in (size.lower().split("x") for size in sizes)]
    except ValueError:
        parser.error(f"--sizes: expected HxW such as 64x96, got {sizes}")
    if args.write_docs:
        from dpc_jax.report.pages import read_block

        try:  # before minutes of timing, not after
            previous = parse_table(read_block(DOCS, BLOCK))
        except (OSError, ValueError) as error:
            raise SystemExit(f"bench_live: {error}") from None

    from dpc_jax.report.pages import commit

    where = source(args.synthetic)
    machine, version = device(), commit(ROOT)
    print(f"live correction per frame, {where.name}, {count} frames timed after {warmup} of warm-up, "
          f"{preset} preset, untrained networks")
    print(f"device: {machine}, OpenCV {cv2.__version__} with {cv2.getNumThreads()} threads, commit "
          f"{version}, load average {' '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)
    results: list[Result] = []
    profile = cProfile.Profile() if args.profile else None
    for method in args.methods:
        for size in shapes:
            first = not results
            results.append(measure(where, method, preset, size, count + warmup, warmup,
                                   profile if first else None, args.realtime))
            if first and profile is not None:
                print_profile(profile, results[0])
            r = results[-1]
            print(f"  {NAMES[method]} {size[0]}x{size[1]}: VO + correction p50 {r.ms('both')[0]:.1f} ms "
                  f"(compiled in {r.compile_s:.1f} s)", file=sys.stderr, flush=True)
    date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d") + (QUICK if args.quick else "")
    command = " ".join(["python", "benchmarks/bench_live.py", *(argv if argv is not None else sys.argv[1:])])
    command = command.replace(" --write-docs", "").replace(" --profile", "")
    measured = rows(results, preset, command, machine, version, date)
    print(table(measured))
    print("the papers: Stereo DPC's correction 9.53 ms, libviso2-s + correction 42.73 ms per frame (one RTX "
          "3070); ORB-SLAM2 37.2 ms, SfMLearner 83.26 ms; KITTI's cameras: 100 ms per frame")
    if args.write_docs:
        from dpc_jax.report.pages import replace_block

        replace_block(DOCS, BLOCK, block(merge(previous, measured)))
        print(f"wrote the rows into {DOCS}")
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    raise SystemExit(main())
