"""ss-DPC-Net on KITTI odometry, libviso2 priors (Wagstaff et al.); see configs/kitti_ss_dpc.py.

    python experiments/protocols/kitti_ss_dpc.py --kitti-odometry ROOT --priors DIR --fold NAME|all \
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

CONFIG = HERE / "configs" / "kitti_ss_dpc.py"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--kitti-odometry", required=True, type=P.path_argument, metavar="ROOT",
                        help="odometry root (sequences/XX/, poses/XX.txt)")
    parser.add_argument("--priors", required=True, metavar="DIR|vo",
                        help="folder with stereo_XX.mat and mono_XX.mat (libviso2 release); 'vo' = our "
                        "stereo VO for the stereo folds")
    parser.add_argument("--fold", default="all", metavar="NAME|all",
                        help="stereo_val05, stereo_val00, mono, or all")
    parser.add_argument("--sequences", nargs="+", metavar="XX",
                        help="odometry sequences available (default: the config's 00 02 05-10); training "
                        "uses those of them that are not the fold's validation or test sequences")
    P.add_common_arguments(parser, CONFIG)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from dpc_jax.data.kitti import open_odometry

    progress = not args.no_progress and sys.stderr.isatty()
    try:
        base, protocol = P.load_protocol(args.config)
        check_results_page(args.results_page)
        overrides = P.overrides_from(args)
        sequences = tuple(args.sequences or protocol.sequences)
        specs = protocol.folds
        if args.fold != "all" and args.fold not in specs:
            raise ValueError(f"--fold {args.fold!r}: expected one of {', '.join(specs)} or all")
        names = list(specs) if args.fold == "all" else [args.fold]
        folds, configs = [], {}
        for name in names:
            spec = specs[name]
            held_out = (spec.validation, *spec.test)
            missing = [s for s in held_out if s not in sequences]
            if missing:
                raise ValueError(f"fold {name} needs sequence(s) {missing}, not among {list(sequences)}")
            fold = P.Fold(name, training_names(sequences, held_out), spec.validation, spec.test)
            folds.append((fold, spec.prior))
            cache_root = args.workdir / "cache" / spec.prior
            configs[name] = P.fold_config(base, fold, cache_root, {**spec.overrides, **overrides})
        # Every sequence opened and every prior found before the first is used.
        needed = {(kind, name): fold for fold, kind in folds
                  for name in (*fold.train, fold.validation, *fold.test)}
        opened = {name: open_odometry(args.kitti_odometry, name) for _, name in needed}
        for kind, name in needed:
            if args.priors == "vo" and kind != "stereo":
                raise ValueError(f"--priors vo gives stereo priors only; the {kind} priors of fold "
                                 f"{needed[kind, name].name} need a folder")
            if args.priors != "vo":
                P.find_prior(Path(args.priors), name, kind)
        P.claim_workdir(args.workdir, [("--kitti-odometry", args.kitti_odometry),
                                       ("--priors", None if args.priors == "vo" else args.priors),
                                       ("--config", args.config)],
                        files=[("--results-page", args.results_page)])
        prepared: set[tuple[str, str]] = set()
        for fold, kind in folds:
            config = configs[fold.name]
            for name in (*fold.train, fold.validation, *fold.test):
                if (kind, name) in prepared:
                    continue
                sequence = opened[name]
                prior = P.prior_source(args.priors, kind, sequence, args.workdir, progress)
                P.prepare(sequence, prior, Path(config.cache_root), config, mono_rescale=kind == "mono",
                          progress=progress)
                prepared.add((kind, name))
        select = args.select or protocol.select
        results = []
        for fold, kind in folds:
            run_dir = args.workdir / "runs" / fold.name
            P.train_fold(configs[fold.name], run_dir, progress)
            for test in fold.test:
                results.append(P.correct_and_evaluate(
                    fold.name, run_dir, Path(configs[fold.name].cache_root) / test, args.workdir, protocol,
                    select=select, prior_label=f"libviso2-{kind[0]}" if args.priors != "vo" else "vo",
                    progress=progress,
                ))
    except (OSError, ValueError, KeyError) as error:
        print(f"kitti_ss_dpc: error: {error}", file=sys.stderr)
        return 2
    notes = [f"ss-DPC-Net (Wagstaff et al.); folds {', '.join(names)}; priors: {args.priors} "
             f"(mono rescaled to the ground-truth step length); stereo: rotation-only correction; "
             f"epoch selection: {select}."
             + (" SMOKE RUN (1 epoch of 2 steps): the numbers mean nothing." if args.smoke else "")]
    table = write_fold_results(args.workdir, results, "ss-DPC-Net on KITTI odometry", notes)
    P.print_results(table, args.results_page, Path(__file__))
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(main())
