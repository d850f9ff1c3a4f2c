"""The whole pipeline on the real KITTI raw excerpt (smoke test); see configs/kitti_raw_excerpt.py.

    python experiments/protocols/kitti_raw_excerpt.py --workdir runs/kitti_raw_excerpt
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax.pipelines import protocol as P
from dpc_jax.report.pages import check_results_page
from dpc_jax.report.protocol_report import write_fold_results
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

HERE = Path(__file__).resolve().parent

CONFIG = HERE / "configs" / "kitti_raw_excerpt.py"
DEFAULT_ROOT = HERE.parents[2] / "shared" / "data" / "kitti-raw"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--kitti-raw", type=P.path_argument, default=DEFAULT_ROOT, metavar="ROOT",
                        help="raw root holding DATE/ and libviso2/")
    P.add_common_arguments(parser, CONFIG)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from dpc_jax.data.kitti import open_raw

    progress = not args.no_progress and sys.stderr.isatty()
    try:
        base, protocol = P.load_protocol(args.config)
        check_results_page(args.results_page)
        if protocol.train_frames is None or protocol.validation_frames is None:
            raise ValueError(f"{args.config}: PROTOCOL names no train_frames or validation_frames")
        (t0, t1), (v0, v1) = protocol.train_frames, protocol.validation_frames
        libviso2 = args.kitti_raw / protocol.libviso2
        sequence = open_raw(args.kitti_raw, protocol.date, protocol.drive, poses=libviso2)
        P.claim_workdir(args.workdir, [("--kitti-raw", args.kitti_raw), ("--config", args.config)],
                        files=[("--results-page", args.results_page)])
        fold = P.Fold("excerpt", tuple(base.train_sequences), base.validation_sequences[0],
                      tuple(base.test_sequences))
        cache_root = args.workdir / "cache"
        config = P.fold_config(base, fold, cache_root, P.overrides_from(args))
        record = P.vo_prior(sequence, args.workdir / "priors" / "vo.txt", progress)
        vo = Path(record["path"])
        # The colour pair's calibration residual, as our VO's online estimate measures it (no ground
        # truth): the network's images are rectified by it (see configs/kitti_raw_excerpt.py).
        offset = record["disparity_offset_median_px"] if protocol.rectify_offset else 0.0
        jobs = {
            fold.train[0]: (vo, protocol.train_frames),
            fold.validation: (vo, protocol.validation_frames),
            "vo": (vo, None),
            "libviso2": (libviso2, None),
        }
        for name, (prior, frames) in jobs.items():
            P.prepare(sequence, prior, cache_root, config, name=name, frames=frames, disparity_offset=offset,
                      progress=progress)
        # Every acceptance test is measured on the test priors' frames prepared at judge_size.
        judge_size = protocol.judge_size
        judges = {name: P.prepare_judge(sequence, jobs[name][0], cache_root, config, judge_size, name=name,
                                        disparity_offset=offset, progress=progress)
                  for name in fold.test}
        run_dir = args.workdir / "runs" / fold.name
        P.train_fold(config, run_dir, progress)
        select = args.select or protocol.select
        results = [
            P.correct_and_evaluate(fold.name, run_dir, cache_root / name, args.workdir, protocol,
                                   select=select, prior_label=name, judge=judges[name], progress=progress)
            for name in fold.test
        ]
    except (OSError, ValueError, KeyError) as error:
        print(f"kitti_raw_excerpt: error: {error}", file=sys.stderr)
        return 2
    size = config.resolved_image_size
    notes = [f"Real KITTI raw {sequence.name} ({len(sequence)} frames); Stereo DPC trained on frames "
             f"{t0}–{t1 - 1} with our VO prior, validated on {v0}–{v1 - 1}; network images rectified by the "
             f"disparity offset our VO measured ({offset:+.3f} px); the whole drive corrected by the network "
             f"as trained and by the network adapted to each prior ({protocol.adapt_steps} steps), each "
             f"behind its acceptance test (depth {config.acceptance_depth}) measured at "
             + (f"{judge_size[0]}×{judge_size[1]} (the drive prepared at that size, not at the network's "
                f"{size[0]}×{size[1]}); " if judge_size is not None else
                f"the network's {size[0]}×{size[1]} only (no judge); ")
             + f"epoch selection: {select}; "
             f"{'rotation only' if protocol.rotation_only else 'full correction'} applied. "
             f"Not a reproduction: the trained network has seen frames "
             f"{t0}–{t1 - 1}, and 108 frames give only a handful of 100 m segments."
             + (" SMOKE RUN (1 epoch of 2 steps)." if args.smoke else "")]
    table = write_fold_results(args.workdir, results, "Pipeline on the real KITTI raw excerpt", notes)
    P.print_results(table, args.results_page, Path(__file__))
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(main())
