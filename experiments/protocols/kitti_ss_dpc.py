r"""ss-DPC-Net on KITTI odometry, libviso2 priors (Wagstaff et al.); see configs/kitti_ss_dpc.py.

    python experiments/protocols/kitti_ss_dpc.py --kitti-odometry ROOT --priors DIR --fold NAME|all \
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

CONFIG = Path(__file__).resolve().parent / "configs" / "kitti_ss_dpc.py"


def build_parser() -> argparse.ArgumentParser:
    parser = new_parser(__doc__)
    parser.add_argument("--kitti-odometry", required=True, type=P.path_argument, metavar="ROOT",
                        help="odometry root (sequences/XX/, poses/XX.txt)")
    parser.add_argument("--priors", required=True, type=P.priors_argument, metavar="DIR|vo",
                        help="folder with stereo_XX.mat and mono_XX.mat (libviso2 release); 'vo' = our "
                        "stereo VO for the stereo folds")
    parser.add_argument("--fold", default="all", metavar="NAME|all",
                        help="stereo_val05, stereo_val00, mono, or all")
    parser.add_argument("--sequences", nargs="+", metavar="XX",
                        help="odometry sequences available (default: the config's 00 02 05-10); training "
                        "uses those of them that are not the fold's validation or test sequences")
    add_protocol_arguments(parser, CONFIG)
    return parser


def plan(context: Context) -> Plan:
    """The protocol's named folds, each with its prior kind (stereo, mono) and cache; every sequence opened
    and every prior found before the first is prepared."""
    from dpc_jax.data.kitti import open_odometry

    args, specs = context.args, context.protocol.folds
    sequences = tuple(args.sequences or context.protocol.sequences)
    if args.fold != "all" and args.fold not in specs:
        raise ValueError(f"--fold {args.fold!r}: expected one of {', '.join(specs)} or all")
    names = list(specs) if args.fold == "all" else [args.fold]
    runs = []
    for name in names:
        spec = specs[name]
        held_out = (spec.validation, *spec.test)
        missing = [s for s in held_out if s not in sequences]
        if missing:
            raise ValueError(f"fold {name} needs sequence(s) {missing}, not among {list(sequences)}")
        fold = P.Fold(name, training_names(sequences, held_out), spec.validation, spec.test)
        cache_root = context.cache_root / spec.prior
        config = P.fold_config(context.base, fold, cache_root, {**spec.overrides, **context.overrides})
        label = f"libviso2-{spec.prior[0]}" if args.priors != "vo" else "vo"
        runs.append(FoldRun(fold, config, tuple(Test(cache_root / t, label) for t in fold.test)))
    needed = {(specs[run.fold.name].prior, name): run.fold
              for run in runs for name in (*run.fold.train, run.fold.validation, *run.fold.test)}
    opened = {name: open_odometry(args.kitti_odometry, name) for _, name in needed}
    for kind, name in needed:
        if args.priors == "vo" and kind != "stereo":
            raise ValueError(f"--priors vo gives stereo priors only; the {kind} priors of fold "
                             f"{needed[kind, name].name} need a folder")
        if args.priors != "vo":
            P.find_prior(Path(args.priors), name, kind)
    context.claim([("--kitti-odometry", args.kitti_odometry),
                   ("--priors", None if args.priors == "vo" else args.priors)])
    prepared: set[tuple[str, str]] = set()
    for run in runs:
        kind = specs[run.fold.name].prior
        for name in (*run.fold.train, run.fold.validation, *run.fold.test):
            if (kind, name) not in prepared:
                prior = P.prior_source(args.priors, kind, opened[name], context.workdir, context.progress)
                P.prepare(opened[name], prior, Path(run.config.cache_root), run.config,
                          mono_rescale=kind == "mono", progress=context.progress)
                prepared.add((kind, name))
    return Plan(runs, "ss-DPC-Net on KITTI odometry",
                f"ss-DPC-Net (Wagstaff et al.); folds {', '.join(names)}; priors: {args.priors} (mono "
                f"rescaled to the ground-truth step length); stereo: rotation-only correction; epoch "
                f"selection: {context.select}.")


def main(argv: Sequence[str] | None = None) -> int:
    return run_protocol(__file__, build_parser(), plan, argv)


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
