"""The cross-drive protocol on two real KITTI raw drives (``experiments/protocols/kitti_raw_drives.py``;
``experiments/studies/supervised_comparison.py`` runs it too): every test drive is corrected by networks
trained on the other drive, with each (test prior, training prior) pair of the protocol's ``tests``.

Its table is long form: one row per test drive, prior, training prior and estimate (prior, the networks
as trained and adapted, the final trajectory, and the final of each decision the protocol asks for; the
page shows those in a table of their own, ``dpc_jax.report.protocol_report.decisions_markdown``).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax.experiments.detection_answer import TOLERANCE_PCT
from dpc_jax.experiments.folds import Context, FoldRun, Plan, Tables, Test, add_protocol_arguments
from dpc_jax.experiments.script import add_kitti_raw_option, data_given, new_parser
from dpc_jax.pipelines import protocol as P
from dpc_jax.report.protocol_report import decisions_markdown
from dpc_jax.report.tables import EMPTY, csv_text, number, table
from dpc_jax.results.fold import FoldResult

CSV_COLUMNS = ("drive", "prior", "trained_on", "estimate", "decision", "seg_trans_pct",
               "seg_rot_deg_per_100m", "m_ate_trans_m", "m_ate_rot_deg", "ate_m", "rpe_trans_m",
               "rpe_rot_deg")
METRICS = CSV_COLUMNS[5:]
TITLES = ("seg. t (%)", "seg. r (°/100 m)", "m-ATE (m)", "m-ATE (°)", "ATE (m)", "RPE t (m)", "RPE r (°)")
PRIOR_NAMES = {"vo": "our VO", "libviso2": "libviso2-s"}


def build_parser(doc: str | None, config: Path) -> argparse.ArgumentParser:
    """The protocol's options (``config``: the default ``--config``)."""
    parser = new_parser(doc)
    add_kitti_raw_option(parser)
    parser.add_argument("--test-drives", nargs="+", metavar="NNNN",
                        help="only these test drives (default: both; e.g. two work folders run side by side)")
    add_protocol_arguments(parser, config)
    return parser


def plan(context: Context) -> Plan:
    """Both drives opened with both priors (our VO run on each, libviso2-s from its ``.mat``), every cache
    prepared (training, validation and whole-drive frames, and the judge's), one fold per training drive
    and training prior correcting the other drive's test priors."""
    from dpc_jax.data.kitti import open_raw
    from dpc_jax.data.poses_io import read_trajectory

    args, protocol = context.args, context.protocol
    drives = protocol.drives
    if len(drives) != 2:
        raise ValueError(f"{args.config}: PROTOCOL['drives'] must name two drives, got {list(drives)}")
    unknown = [d for d in args.test_drives or () if d not in drives]
    if unknown:
        raise ValueError(f"--test-drives {unknown[0]}: not a drive of {args.config} ({', '.join(drives)})")
    raw = data_given(args.kitti_raw, "--kitti-raw")
    sequences, libviso2 = {}, {}
    for drive, spec in drives.items():
        mat = raw / spec.libviso2
        gt_all, est_all = (read_trajectory(mat, mat_key=key) for key in ("poses_gt", "poses_est"))
        n = len(open_raw(raw, protocol.date, drive))
        if gt_all.shape[0] < n:
            raise ValueError(f"{mat}: {gt_all.shape[0]} poses for the {n} frames of drive {drive}")
        # The .mat may cover the whole drive; its first n poses belong to the images (the data README).
        sequences[drive] = open_raw(raw, protocol.date, drive, poses=gt_all[:n])
        libviso2[drive] = est_all[:n]
    context.claim([("--kitti-raw", raw)])
    root, progress = context.cache_root, context.progress
    config0 = P.fold_config(context.base, P.Fold("prepare", ("x",), "y", ()), root, context.overrides)
    offsets = {}
    for drive, sequence in sequences.items():
        record = P.vo_prior(sequence, context.workdir / "priors" / f"{drive}_vo.txt", progress)
        offsets[drive] = record["disparity_offset_median_px"] if protocol.rectify_offset else 0.0
        spec = drives[drive]
        priors: dict[str, Any] = {"vo": Path(record["path"]), "libviso2": libviso2[drive]}
        for prior, source in priors.items():
            jobs = {f"{drive}_{prior}_train": spec.train_frames,
                    f"{drive}_{prior}_validation": spec.validation_frames, f"{drive}_{prior}": None}
            for name, frames in jobs.items():
                P.prepare(sequence, source, root, config0, name=name, frames=frames,
                          disparity_offset=offsets[drive], progress=progress)
            P.prepare_judge(sequence, source, root, config0, protocol.judge_size, name=f"{drive}_{prior}",
                            disparity_offset=offsets[drive], progress=progress)
    runs, trained_on = [], {}
    for test_drive in args.test_drives or drives:
        train_drive = next(d for d in drives if d != test_drive)
        # One network per training drive and prior corrects every test prior it is paired with.
        for kind in dict.fromkeys(t for _, t in protocol.tests):
            tested = [p for p, t in protocol.tests if t == kind]
            fold = P.Fold(f"train{train_drive}_{kind}", (f"{train_drive}_{kind}_train",),
                          f"{train_drive}_{kind}_validation", tuple(f"{test_drive}_{p}" for p in tested))
            trained_on[fold.name] = f"{train_drive} {PRIOR_NAMES[kind]}"
            judged = protocol.judge_size is not None
            tests = tuple(Test(root / name, prior, root / f"{name}_judge" if judged else None)
                          for name, prior in zip(fold.test, tested, strict=True))
            runs.append(FoldRun(fold, P.fold_config(context.base, fold, root, context.overrides), tests))
    return Plan(runs, "Two real KITTI raw drives, cross-drive", _notes(context, sequences, offsets),
                adapt_steps=2 if args.smoke else protocol.adapt_steps, tables=_tables(trained_on))


def _left_folder(sequence: Any) -> str:
    """The camera folder of a raw drive's left images (``image_00``: grey; ``image_02``: colour)."""
    return Path(sequence.images.locations()["left_images"]).parts[-2]


def _notes(context: Context, sequences: dict[str, Any], offsets: dict[str, float]) -> str:
    protocol, judge_size = context.protocol, context.protocol.judge_size
    drives = protocol.drives
    described = "; ".join(
        f"{s.name}: {len(s)} frames, {'grey' if _left_folder(s) == 'image_00' else 'colour'} pair, "
        f"trained on frames {drives[d].train_frames[0]}–{drives[d].train_frames[1] - 1}, validated on "
        f"{drives[d].validation_frames[0]}–{drives[d].validation_frames[1] - 1}, images rectified by "
        f"{offsets[d]:+.3f} px" for d, s in sequences.items())
    return (f"Real KITTI raw drives ({described}). Each test drive is corrected by networks trained on the "
            f"other drive (trained on: drive and training prior), epoch by {context.select}, adapted "
            f"{2 if context.args.smoke else protocol.adapt_steps} steps to the test drive, acceptance depth "
            f"{context.base.acceptance_depth}"
            + (f" measured at {judge_size[0]}×{judge_size[1]} (the scale of an accepted correction chosen "
               "there)" if judge_size is not None else "")
            + f", {'rotation only' if protocol.rotation_only else 'full correction'} applied.")


def _value(summary: dict[str, Any], key: str) -> float | None:
    value = summary.get(key)
    return None if value is None or (isinstance(value, float) and math.isnan(value)) else float(value)


def drive_of(result: FoldResult) -> str:
    """The drive a result's test sequence (``NNNN_PRIOR``) belongs to."""
    return result.sequence.removesuffix(f"_{result.prior_label}")


def long_rows(result: FoldResult, trained_on: str, *, decided: bool = True) -> list[dict[str, Any]]:
    """The rows (prior, trained, adapted, final, and with ``decided`` the final of each decision the
    protocol asks for, ``final, NAME``) of one correction, for ``results.csv``."""
    rows = [("prior", "", result.metrics["prior"])]
    rows += [(label, result.decisions[label], result.stages[label]) for label in ("trained", "adapted")
             if label in result.stages]
    rows.append(("final", result.applied, result.metrics["corrected"]))
    if decided:
        rows += [(f"final, {name}", final.applied, final.metrics) for name, final in result.decided.items()]
    return [{"drive": drive_of(result), "prior": result.prior_label, "trained_on": trained_on,
             "estimate": estimate, "decision": decision, **{k: _value(summary, k) for k in METRICS}}
            for estimate, decision, summary in rows]


def _tables(trained_on: dict[str, str]) -> Tables:
    def tables(results: Sequence[FoldResult], notes: Sequence[str]) -> tuple[str, str]:
        shown = [row for r in results for row in long_rows(r, trained_on[r.fold], decided=False)]
        body = table(["test drive", "prior", "trained on", "estimate", "decision", *TITLES],
                     ([r["drive"], PRIOR_NAMES[r["prior"]], r["trained_on"], r["estimate"], r["decision"],
                       *(number(r[k]) for k in METRICS)] for r in shown))
        lines = [
            "# Two real KITTI raw drives, cross-drive", "", *notes, "", body,
            "estimate: prior = the prior itself; trained = the network as trained applied (whatever its test "
            "said), decision = its acceptance test; adapted = the same network adapted to the test drive's "
            "images (no ground truth) applied; final = what the acceptance tests and the choice keep. "
            f"Segment errors: {EMPTY} where the drive is shorter than 100 m. RPE over one frame."]
        if any(r.decided for r in results):
            names = ["test drive", "prior", "trained on"], lambda r: [
                drive_of(r), PRIOR_NAMES[r.prior_label], trained_on[r.fold]]
            lines += ["", decisions_markdown(results, *names, TOLERANCE_PCT).rstrip()]
        rows = [row for r in results for row in long_rows(r, trained_on[r.fold])]
        return "\n".join(lines) + "\n", csv_text(CSV_COLUMNS, ([row[c] for c in CSV_COLUMNS] for row in rows))
    return tables
