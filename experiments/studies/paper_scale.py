"""The papers' scale on a synthetic stand-in: what each stage costs (configs/paper_scale.py).

Renders sequences with the lengths of KITTI odometry 00–10 (scaled to ``--frames``), runs our VO,
prepares both methods' caches (ss-DPC-Net's with flow augmentation), trains each method, corrects
the longest sequence, and writes ``WORKDIR/scale.md`` and ``WORKDIR/scale.csv``: per stage and
method, wall and CPU time, the share of the cores it kept busy, frames or samples per second, peak
resident memory (all of it, and the anonymous part: what the process allocated, without the
file pages it mapped or wrote, which are the page cache's) and bytes on disk. Every stage is a command
started as its own process and measured from outside (``dpc_jax.experiments.scale``); all but rendering
are the `dpc-jax` commands a user runs. A finished stage is recorded in ``WORKDIR/stages/NAME.json`` and
reused by a rerun with the same settings. ``--planted-bias`` also writes, per sequence, a second prior:
the ground truth with a planted per-step rotation error (``WORKDIR/planted/XX.txt``).

``--docs`` puts the table's rows into the "Scale" table of docs/performance.md (replacing the rows
of the same run: profile, frames and size) with the machine, commit and date.
"""

from __future__ import annotations

import os
import runpy
import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax.experiments import scale
from dpc_jax.experiments import script as kit
from dpc_jax.experiments.script import interruptible
from dpc_jax.pipelines.protocol import path_argument

CONFIG = Path(__file__).resolve().parent / "configs" / "paper_scale.py"
DOCS = Path(__file__).resolve().parents[2] / "docs" / "performance.md"


def main(argv: Sequence[str] | None = None) -> int:
    parser = kit.new_parser(__doc__)
    parser.add_argument("--workdir", type=path_argument,
                        help="work folder (made if missing; a rerun reuses its stages)")
    parser.add_argument("--config", type=path_argument, default=CONFIG, help="the experiment's config file")
    parser.add_argument("--frames", type=int, metavar="N", help="total frames (default: KITTI's 23,201)")
    parser.add_argument("--size", metavar="HxW", help="image size (default: the config's, 240x376)")
    parser.add_argument("--profile", choices=("cpu", "gpu"), default="cpu",
                        help="training length: cpu = a few steps at batch 8, gpu = 2 epochs at batch 32")
    parser.add_argument("--methods", nargs="+", choices=("stereo_dpc", "ss_dpc"),
                        default=["stereo_dpc", "ss_dpc"])
    parser.add_argument("--planted-bias", type=float, nargs=3, metavar=("PX", "PY", "PZ"),
                        help="also write priors with this per-step rotation bias (mrad, camera x y z)")
    parser.add_argument("--planted-noise", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                        metavar=("SX", "SY", "SZ"),
                        help="per-step rotation noise of the planted priors (mrad, standard deviation)")
    parser.add_argument("--docs", action="store_true",
                        help="put the rows into docs/performance.md's Scale table")
    args = parser.parse_args(argv)
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
        if args.docs:  # before hours of stages, not after
            from dpc_jax.report.pages import read_block

            read_block(DOCS, "scale")
        workdir = kit.claim(args.workdir, [("--config", args.config)],
                            files=[("--docs", DOCS if args.docs else None)], script=__file__)
        assert workdir is not None  # a work folder was given
    except (ValueError, KeyError, OSError) as error:
        return kit.refuse("paper_scale", error)
    settings = scale.Settings(scale.lengths(config["KITTI_LENGTHS"], args.frames), size, args.profile,
                              config["PROFILES"][args.profile], config["SCALE"],
                              None if args.planted_bias is None else tuple(args.planted_bias),
                              tuple(args.planted_noise))
    from dpc_jax.experiments.process import Stages
    from dpc_jax.experiments.stamp import stamp

    try:
        # Each stage records the code and machine that ran it: a rerun may reuse stages of another commit.
        records = scale.run_stages(Stages(workdir, stamp()), settings, args.methods, config["METHODS"])
        if settings.planted_bias is not None:
            scale.plant(workdir, settings)
    except (RuntimeError, OSError, ValueError) as error:
        return kit.refuse("paper_scale", error, 1)
    from dpc_jax._io import atomic_write
    from dpc_jax.report.tables import csv_text, table

    run = f"{args.profile} profile, {sum(settings.frames.values())} frames, {size[0]}×{size[1]}"
    rows = scale.rows(run, records, os.cpu_count() or 1, (config["PAPER_PAIRS"], config["PAPER_EPOCHS"]))
    options = "".join(f" --{k} {v}" for k, v in (("frames", args.frames), ("size", args.size))
                      if v is not None)
    text = "\n".join([
        f"# The papers' scale: {run}", "",
        "Each row names the machine and commit that measured it (a rerun reuses finished stages); "
        f"`python experiments/studies/paper_scale.py --workdir {workdir}{options} --profile {args.profile}`.",
        f"Sequences (frames): {', '.join(f'{k} ({v})' for k, v in settings.frames.items())}; "
        f"training: {settings.training}; corrected: {settings.scale['test']}.", "",
        table(scale.HEADER, rows)])
    atomic_write(workdir / "scale.md", text)
    atomic_write(workdir / "scale.csv", csv_text(scale.HEADER, rows))
    if args.docs:
        kit.replace_rows(DOCS, "scale", scale.HEADER, rows, run)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(interruptible(main, __file__))
