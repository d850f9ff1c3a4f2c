"""The whole pipeline on the real KITTI raw excerpt (smoke test); see configs/kitti_raw_excerpt.py.

    python experiments/protocols/kitti_raw_excerpt.py --workdir runs/kitti_raw_excerpt
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax.experiments.folds import Context, FoldRun, Plan, Test, add_protocol_arguments, run_protocol
from dpc_jax.experiments.script import add_kitti_raw_option, data_given, interruptible, new_parser
from dpc_jax.pipelines import protocol as P
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

CONFIG = Path(__file__).resolve().parent / "configs" / "kitti_raw_excerpt.py"


def build_parser() -> argparse.ArgumentParser:
    parser = new_parser(__doc__)
    add_kitti_raw_option(parser)
    add_protocol_arguments(parser, CONFIG)
    return parser


def plan(context: Context) -> Plan:
    """One fold: trained on the drive's first frames with our VO's prior, validated on the next; the whole
    drive corrected with each prior, every test also measured at the protocol's judge size."""
    from dpc_jax.data.kitti import open_raw

    args, protocol = context.args, context.protocol
    if protocol.train_frames is None or protocol.validation_frames is None:
        raise ValueError(f"{args.config}: PROTOCOL names no train_frames or validation_frames")
    (t0, t1), (v0, v1) = protocol.train_frames, protocol.validation_frames
    raw = data_given(args.kitti_raw, "--kitti-raw")
    libviso2 = raw / protocol.libviso2
    sequence = open_raw(raw, protocol.date, protocol.drive, poses=libviso2)
    context.claim([("--kitti-raw", raw)])
    base = context.base
    fold = P.Fold("excerpt", tuple(base.train_sequences), base.validation_sequences[0],
                  tuple(base.test_sequences))
    config = P.fold_config(base, fold, context.cache_root, context.overrides)
    record = P.vo_prior(sequence, context.workdir / "priors" / "vo.txt", context.progress)
    vo = Path(record["path"])
    # The colour pair's calibration residual, as our VO's online estimate measures it (no ground
    # truth): the network's images are rectified by it (see configs/kitti_raw_excerpt.py).
    offset = record["disparity_offset_median_px"] if protocol.rectify_offset else 0.0
    jobs = {fold.train[0]: (vo, protocol.train_frames), fold.validation: (vo, protocol.validation_frames),
            "vo": (vo, None), "libviso2": (libviso2, None)}
    for name, (prior, frames) in jobs.items():
        P.prepare(sequence, prior, context.cache_root, config, name=name, frames=frames,
                  disparity_offset=offset, progress=context.progress)
    # Every acceptance test is measured on the test priors' frames prepared at judge_size.
    judge_size = protocol.judge_size
    tests = tuple(Test(context.cache_root / name, name, P.prepare_judge(
        sequence, jobs[name][0], context.cache_root, config, judge_size, name=name, disparity_offset=offset,
        progress=context.progress)) for name in fold.test)
    size = config.resolved_image_size
    measured = (f"{judge_size[0]}×{judge_size[1]} (the drive prepared at that size, not at the network's "
                f"{size[0]}×{size[1]})" if judge_size is not None else
                f"the network's {size[0]}×{size[1]} only (no judge)")
    notes = (f"Real KITTI raw {sequence.name} ({len(sequence)} frames); Stereo DPC trained on frames "
             f"{t0}–{t1 - 1} with our VO prior, validated on {v0}–{v1 - 1}; network images rectified by "
             f"the disparity offset our VO measured ({offset:+.3f} px); the whole drive corrected by the "
             f"network as trained and by the network adapted to each prior ({protocol.adapt_steps} steps), "
             f"each behind its acceptance test (depth {config.acceptance_depth}) measured at {measured}; "
             f"epoch selection: {context.select}; "
             f"{'rotation only' if protocol.rotation_only else 'full correction'} applied. Not a "
             f"reproduction: the trained network has seen frames {t0}–{t1 - 1}, and 108 frames give only a "
             "handful of 100 m segments.")
    return Plan([FoldRun(fold, config, tests)], "Pipeline on the real KITTI raw excerpt", notes)


def main(argv: Sequence[str] | None = None) -> int:
    return run_protocol(__file__, build_parser(), plan, argv)


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
