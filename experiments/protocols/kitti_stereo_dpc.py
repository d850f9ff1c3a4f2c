r"""Stereo DPC on KITTI odometry, leave-one-out (Zhang et al.); see configs/kitti_stereo_dpc.py.

    python experiments/protocols/kitti_stereo_dpc.py --kitti-odometry ROOT --priors DIR|vo --test XX|all \
        --workdir DIR
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax.data.splits import training_names
from dpc_jax.experiments.folds import Context, FoldRun, Plan, Test, add_protocol_arguments, run_protocol
from dpc_jax.experiments.script import interruptible, new_parser
from dpc_jax.pipelines import protocol as P
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

CONFIG = Path(__file__).resolve().parent / "configs" / "kitti_stereo_dpc.py"


def build_parser() -> argparse.ArgumentParser:
    parser = new_parser(__doc__)
    parser.add_argument("--kitti-odometry", required=True, type=P.path_argument, metavar="ROOT",
                        help="odometry root (sequences/XX/, poses/XX.txt)")
    parser.add_argument("--priors", required=True, type=P.priors_argument, metavar="DIR|vo",
                        help="folder of priors (stereo_XX.mat, XX.mat or XX.txt) or 'vo' for our stereo VO")
    parser.add_argument("--test", default="all", metavar="XX|all", help="the fold's test sequence, or all")
    parser.add_argument("--sequences", nargs="+", metavar="XX",
                        help="odometry sequences of the protocol (default: the config's 00 02 05-10)")
    parser.add_argument("--kitti-raw", type=P.path_argument, metavar="ROOT",
                        help="raw root for extra training drives")
    parser.add_argument("--raw-drive", nargs="+", default=[], metavar="DATE_drive_NNNN",
                        help="extra training drives, e.g. 2011_09_26_drive_0001 (priors from --priors)")
    add_protocol_arguments(parser, CONFIG)
    return parser


def plan(context: Context) -> Plan:
    """One fold per test sequence: validated on the protocol's validation sequence for it, trained on the
    others (and the extra raw drives); every sequence prepared once."""
    from dpc_jax.data.kitti import open_odometry, open_raw

    args, protocol = context.args, context.protocol
    sequences = tuple(args.sequences or protocol.sequences)
    tests = sequences if args.test == "all" else (args.test,)
    unknown = [t for t in tests if t not in sequences]
    if unknown:
        raise ValueError(f"--test {unknown[0]} is not one of the sequences {list(sequences)}")
    if args.raw_drive and args.kitti_raw is None:
        raise ValueError("--raw-drive needs --kitti-raw ROOT")
    opened = {name: open_odometry(args.kitti_odometry, name) for name in sequences}
    for drive in args.raw_drive:
        date, _, number = drive.partition("_drive_")
        if drive in P.ODOMETRY_DRIVES.values():
            raise ValueError(f"--raw-drive {drive} is an odometry sequence's drive (test data leak)")
        opened[drive] = open_raw(args.kitti_raw, date, number)
    folds = []
    for test in tests:
        validation = protocol.validation.get(test, protocol.validation["default"])
        if validation not in sequences or validation == test:
            validation = next(s for s in sequences if s != test)
        folds.append(P.Fold(f"test_{test}", training_names(tuple(opened), (test, validation)), validation,
                            (test,)))
    if args.priors != "vo":
        for sequence in opened.values():  # every prior found before the first is used
            P.find_prior(Path(args.priors), sequence.name, "stereo")
    context.claim([("--kitti-odometry", args.kitti_odometry), ("--kitti-raw", args.kitti_raw),
                   ("--priors", None if args.priors == "vo" else args.priors)])
    configs = {f.name: P.fold_config(context.base, f, context.cache_root, context.overrides) for f in folds}
    first = next(iter(configs.values()))
    for sequence in opened.values():
        prior = P.prior_source(args.priors, "stereo", sequence, context.workdir, context.progress)
        P.prepare(sequence, prior, context.cache_root, first, progress=context.progress)
    label = Path(args.priors).name if args.priors != "vo" else "vo"
    return Plan([FoldRun(f, configs[f.name], tuple(Test(context.cache_root / t, label) for t in f.test))
                 for f in folds], "Stereo DPC on KITTI odometry",
                f"Stereo DPC (Zhang et al.), leave-one-out; validation per fold as in {args.config.name}; "
                f"priors: {args.priors}; epoch selection: {context.select}.")


def main(argv: Sequence[str] | None = None) -> int:
    return run_protocol(__file__, build_parser(), plan, argv)


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
