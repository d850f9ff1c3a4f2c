"""Stereo DPC on KITTI odometry, leave-one-out (Zhang et al.); see configs/kitti_stereo_dpc.py.

    python experiments/protocols/kitti_stereo_dpc.py --kitti-odometry ROOT --priors DIR|vo --test XX|all \
        --workdir DIR
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax.data.splits import training_names
from dpc_jax.pipelines import protocol as P
from dpc_jax.report.pages import check_results_page
from dpc_jax.report.protocol_report import write_fold_results
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

HERE = Path(__file__).resolve().parent

CONFIG = HERE / "configs" / "kitti_stereo_dpc.py"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--kitti-odometry", required=True, type=P.path_argument, metavar="ROOT",
                        help="odometry root (sequences/XX/, poses/XX.txt)")
    parser.add_argument("--priors", required=True, metavar="DIR|vo",
                        help="folder of priors (stereo_XX.mat, XX.mat or XX.txt) or 'vo' for our stereo VO")
    parser.add_argument("--test", default="all", metavar="XX|all", help="the fold's test sequence, or all")
    parser.add_argument("--sequences", nargs="+", metavar="XX",
                        help="odometry sequences of the protocol (default: the config's 00 02 05-10)")
    parser.add_argument("--kitti-raw", type=P.path_argument, metavar="ROOT",
                        help="raw root for extra training drives")
    parser.add_argument("--raw-drive", nargs="+", default=[], metavar="DATE_drive_NNNN",
                        help="extra training drives, e.g. 2011_09_26_drive_0001 (priors from --priors)")
    P.add_common_arguments(parser, CONFIG)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from dpc_jax.data.kitti import open_odometry, open_raw

    progress = not args.no_progress and sys.stderr.isatty()
    try:
        base, protocol = P.load_protocol(args.config)
        check_results_page(args.results_page)
        overrides = P.overrides_from(args)
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
            train = training_names(tuple(opened), (test, validation))
            folds.append(P.Fold(f"test_{test}", train, validation, (test,)))
        if args.priors != "vo":
            for sequence in opened.values():  # every prior found before the first is used
                P.find_prior(Path(args.priors), sequence.name, "stereo")
        inputs = [("--kitti-odometry", args.kitti_odometry), ("--kitti-raw", args.kitti_raw),
                  ("--priors", None if args.priors == "vo" else args.priors), ("--config", args.config)]
        P.claim_workdir(args.workdir, inputs, files=[("--results-page", args.results_page)])
        cache_root = args.workdir / "cache"
        configs = {f.name: P.fold_config(base, f, cache_root, overrides) for f in folds}
        first = next(iter(configs.values()))
        for sequence in opened.values():
            P.prepare(sequence, P.prior_source(args.priors, "stereo", sequence, args.workdir, progress),
                      cache_root, first, progress=progress)
        select = args.select or protocol.select
        results = []
        for fold in folds:
            run_dir = args.workdir / "runs" / fold.name
            P.train_fold(configs[fold.name], run_dir, progress)
            for test in fold.test:
                results.append(P.correct_and_evaluate(
                    fold.name, run_dir, cache_root / test, args.workdir, protocol, select=select,
                    prior_label=Path(args.priors).name if args.priors != "vo" else "vo", progress=progress,
                ))
    except (OSError, ValueError, KeyError) as error:
        print(f"kitti_stereo_dpc: error: {error}", file=sys.stderr)
        return 2
    notes = [f"Stereo DPC (Zhang et al.), leave-one-out; validation per fold as in {args.config.name}; "
             f"priors: {args.priors}; epoch selection: {select}."
             + (" SMOKE RUN (1 epoch of 2 steps): the numbers mean nothing." if args.smoke else "")]
    table = write_fold_results(args.workdir, results, "Stereo DPC on KITTI odometry", notes)
    P.print_results(table, args.results_page, Path(__file__))
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(main())
