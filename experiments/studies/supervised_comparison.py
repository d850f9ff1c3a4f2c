"""The papers' comparison on what we can run: prior → supervised linear baseline → supervised network →
self-supervised network (configs/supervised_comparison.py: the data, the networks, the command).

    python experiments/studies/supervised_comparison.py --workdir runs/supervised_comparison
    python experiments/studies/supervised_comparison.py --workdir /tmp/smoke --smoke --seeds 0  # wiring

Per test (the demo's held-out sequence per seed, each real KITTI raw drive corrected by networks of the
other) the rows: the prior; the rotation-only linear baseline and its constant term alone (fit on the
training sequences' ground truth: **supervised**); Stereo DPC trained with DPC-Net's supervised loss and
the same network trained self-supervised, each as trained, adapted and final, with its acceptance test.
The demo runs into ``WORKDIR/seed_K`` and ``WORKDIR/supervised/seed_K``, the drives
(``dpc_jax.experiments.drives``) into ``WORKDIR/drives`` and ``WORKDIR/supervised/drives``; a supervised
folder links the self-supervised one's inputs. A rerun reuses a finished demo of the same config and
finished drives of the same arguments and config. Writes ``comparison.md`` and ``comparison.csv``.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import logging
import runpy
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dpc_jax._io import atomic_write
from dpc_jax.experiments import comparison as table
from dpc_jax.experiments import drives
from dpc_jax.experiments import script as kit
from dpc_jax.experiments.baselines import linear_baselines
from dpc_jax.experiments.demos import demo_config, finished_demo, share
from dpc_jax.experiments.folds import finished_protocol
from dpc_jax.experiments.script import interruptible
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "configs" / "supervised_comparison.py"
DRIVES = HERE.parent / "protocols" / "kitti_raw_drives.py"


def baselines(train_caches: Sequence[Path], test_cache: Path) -> dict[str, table.Metrics]:
    """The rotation-only linear baseline (``linear``) and its constant term alone (``constant``, a per-axis
    bias), fit on ``train_caches``' ground truth and prior, on ``test_cache``."""
    from dpc_jax.data.sequence_cache import load_cache

    caches = [load_cache(path) for path in (*train_caches, test_cache)]
    if any(cache.gt is None for cache in caches):
        raise ValueError(f"{test_cache.parent}: a cache without ground truth (the baseline needs it)")
    *train, (gt, prior) = [(cache.gt, cache.prior) for cache in caches]
    fits = {"linear": {"rotation_only": True}, "constant": {"rotation_only": True, "constant_only": True}}
    return {kind: table.metrics_of(m) for kind, m in linear_baselines(train, gt, prior, fits).items()}


def run_seed(seed: int, args: argparse.Namespace, namespace: Mapping[str, Any],
             say: Callable[[str], None]) -> list[table.Row]:
    """Demo seed ``seed`` with either network, and the baselines: its rows."""
    own_dir, other_dir = args.workdir / f"seed_{seed}", args.workdir / "supervised" / f"seed_{seed}"
    smoke = namespace["SMOKE_DEMO"] if args.smoke else None
    configs = {kind: demo_config(Path(path), seed, smoke) for kind, path in namespace["DEMO"].items()}
    progress = kit.progress_flag(args.no_progress)
    own = finished_demo(configs["self"], own_dir, say, progress)
    share(own_dir, other_dir, ("data", "vo", "cache"))
    other = finished_demo(configs["supervised"], other_dir, say, progress)
    train = [name for name, role in configs["self"].sequences.items() if role == "train"]
    return table.rows_of(f"demo seed {seed}", ", ".join(train), table.metrics_of(own.test["prior"]),
                         baselines([own_dir / "cache" / n for n in train], own_dir / "cache" / "test"),
                         {"supervised": table.demo_stages(other), "self": table.demo_stages(own)})


def run_drives(args: argparse.Namespace, namespace: Mapping[str, Any],
               say: Callable[[str], None]) -> list[table.Row]:
    """Both drives with either network, and the baselines: their rows (our VO's prior only)."""
    from dpc_jax import config as config_lib
    from dpc_jax.pipelines.protocol import load_protocol

    base, protocol = load_protocol(args.config)
    record = {"config": config_lib.to_dict(base), "protocol": config_lib.to_dict(protocol)}
    common = ["--config", str(args.config), "--kitti-raw", str(args.kitti_raw), *["--smoke"] * args.smoke,
              *["--no-progress"] * args.no_progress]
    supervised = [f"--set={key}={json.dumps(value)}" for key, value in namespace["SUPERVISED"].items()]
    own_dir, other_dir = args.workdir / "drives", args.workdir / "supervised" / "drives"
    parser = drives.build_parser(None, args.config)
    say("drives, self-supervised networks")
    own = finished_protocol(DRIVES, parser, drives.plan, own_dir, common, record, say)
    share(own_dir, other_dir, ("priors", "cache"))
    say("drives, supervised networks")
    other = finished_protocol(DRIVES, parser, drives.plan, other_dir, common + supervised, record, say)
    rows = []
    for test, train in itertools.permutations(protocol.drives):
        first, end = protocol.drives[train].train_frames
        [mine], [theirs] = ([r for r in results if drives.drive_of(r) == test and r.prior_label == "vo"]
                            for results in (own, other))
        cache = own_dir / "cache"
        rows += table.rows_of(f"drive {test}", f"drive {train}, frames {first}–{end - 1}",
                              table.metrics_of(mine.metrics["prior"]),
                              baselines([cache / f"{train}_vo_train"], cache / f"{test}_vo"),
                              {"supervised": table.fold_stages(theirs), "self": table.fold_stages(mine)})
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = kit.new_parser(__doc__)
    parser.add_argument("--workdir", required=True, type=path_argument, metavar="DIR",
                        help="everything goes here")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], metavar="K",
                        help="demo seeds (default: %(default)s)")
    parser.add_argument("--skip-drives", action="store_true", help="the demo seeds only")
    parser.add_argument("--config", type=path_argument, default=CONFIG, metavar="FILE",
                        help="comparison config")
    kit.add_kitti_raw_option(parser)
    parser.add_argument("--smoke", action="store_true", help="wiring check: tiny demo (the config's "
                        "SMOKE_DEMO) and kitti_raw_drives.py --smoke")
    kit.add_no_progress(parser)
    kit.add_results_page(parser)
    args = parser.parse_args(argv)
    try:
        namespace = runpy.run_path(str(args.config))
    except Exception as error:  # the config file's own code failed
        return kit.refuse("supervised_comparison", f"{args.config}: {type(error).__name__}: {error}")
    try:
        if not args.skip_drives and not (kit.data_given(args.kitti_raw, "--kitti-raw") / "libviso2").is_dir():
            raise ValueError(f"--kitti-raw {args.kitti_raw}: no libviso2/ folder (or give --skip-drives)")
        kit.claim(args.workdir, [("--config", args.config), ("--kitti-raw", None if args.skip_drives
                                                              else args.kitti_raw)], script=__file__,
                  page=args.results_page)
    except (OSError, ValueError) as error:
        return kit.refuse("supervised_comparison", error)
    logging.getLogger("absl").setLevel(logging.ERROR)
    clock = kit.Clock()
    tests: list[tuple[str, Callable[[], list[table.Row]]]] = [
        (f"demo seed {seed}", functools.partial(run_seed, seed, args, namespace, clock.say))
        for seed in args.seeds]
    if not args.skip_drives:
        tests.append(("drives", functools.partial(run_drives, args, namespace, clock.say)))
    notes = [namespace["NOTES"], *["SMOKE RUN (tiny demo, one epoch of two steps, two adaptation steps): the "
                                   "numbers mean nothing."] * args.smoke]
    rows: list[table.Row] = []
    try:
        for name, run in tests:
            clock.say(f"{name}: start")
            rows += run()
            atomic_write(args.workdir / "comparison.csv", table.comparison_csv(rows))
            text = table.comparison_markdown(rows, [*notes, f"{clock.minutes:.1f} minutes."])
            atomic_write(args.workdir / "comparison.md", text)
            clock.say(f"{name}: done; {args.workdir / 'comparison.md'}")
    except (OSError, ValueError, KeyError, RuntimeError) as error:
        return kit.refuse("supervised_comparison", error, 1)
    kit.publish(text, args.results_page, __file__)
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
