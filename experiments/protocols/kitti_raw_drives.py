"""Two real KITTI raw drives, cross-drive: train on one, correct the other (configs/kitti_raw_drives.py).

    python experiments/protocols/kitti_raw_drives.py --workdir runs/kitti_raw_drives
    python experiments/protocols/kitti_raw_drives.py --workdir /tmp/drives_smoke --smoke   # wiring, minutes

Writes ``WORKDIR/results.md`` (the table, with what each row was trained on) and ``WORKDIR/results.csv``
(long form: one row per test drive, prior, training prior and estimate ∈ prior, trained, adapted, final;
segment errors empty where the drive is shorter than 100 m; RPE over one frame).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax._io import atomic_write
from dpc_jax.pipelines import protocol as P
from dpc_jax.report.pages import check_results_page
from dpc_jax.report.tables import EMPTY, csv_text, number, table
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

HERE = Path(__file__).resolve().parent

CONFIG = HERE / "configs" / "kitti_raw_drives.py"
DEFAULT_ROOT = HERE.parents[2] / "shared" / "data" / "kitti-raw"

CSV_COLUMNS = ("drive", "prior", "trained_on", "estimate", "decision", "seg_trans_pct",
               "seg_rot_deg_per_100m", "m_ate_trans_m", "m_ate_rot_deg", "ate_m", "rpe_trans_m",
               "rpe_rot_deg")
METRICS = CSV_COLUMNS[5:]
TITLES = ("seg. t (%)", "seg. r (°/100 m)", "m-ATE (m)", "m-ATE (°)", "ATE (m)", "RPE t (m)", "RPE r (°)")
PRIOR_NAMES = {"vo": "our VO", "libviso2": "libviso2-s"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kitti-raw", type=P.path_argument, default=DEFAULT_ROOT, metavar="ROOT",
                        help="raw root holding DATE/ and libviso2/")
    parser.add_argument("--test-drives", nargs="+", metavar="NNNN",
                        help="only these test drives (default: both; e.g. two work folders run side by side)")
    P.add_common_arguments(parser, CONFIG)
    return parser


def _value(summary: dict[str, Any], key: str) -> float | None:
    value = summary.get(key)
    return None if value is None or (isinstance(value, float) and math.isnan(value)) else float(value)


def long_rows(drive: str, prior: str, trained_on: str, result: P.Result) -> list[dict[str, Any]]:
    """The rows (prior, trained, adapted, final, and the final of the earlier decision when the protocol
    asks for it) of one correction, for ``results.csv``."""
    rows = [("prior", "", result.metrics["prior"])]
    rows += [(label, result.decisions[label], result.stages[label]) for label in ("trained", "adapted")
             if label in result.stages]
    rows.append(("final", result.applied, result.metrics["corrected"]))
    if result.earlier is not None:
        rows.append(("final, earlier decision", result.earlier["applied"], result.earlier["metrics"]))
    return [{"drive": drive, "prior": prior, "trained_on": trained_on, "estimate": estimate,
             "decision": decision, **{k: _value(summary, k) for k in METRICS}}
            for estimate, decision, summary in rows]


def results_csv(rows: Sequence[dict[str, Any]]) -> str:
    return csv_text(CSV_COLUMNS, ([row[c] for c in CSV_COLUMNS] for row in rows))


def results_markdown(rows: Sequence[dict[str, Any]], notes: Sequence[str]) -> str:
    body = table(["test drive", "prior", "trained on", "estimate", "decision", *TITLES],
                 ([r["drive"], PRIOR_NAMES[r["prior"]], r["trained_on"], r["estimate"], r["decision"],
                   *(number(r[k]) for k in METRICS)] for r in rows))
    return "\n".join([
        "# Two real KITTI raw drives, cross-drive", "", *notes, "", body,
        "estimate: prior = the prior itself; trained = the network as trained applied (whatever its test "
        "said), decision = its acceptance test; adapted = the same network adapted to the test drive's "
        "images (no ground truth) applied; final = what the acceptance tests and the choice keep; final, "
        "earlier decision = the same networks decided without testing the correction's mean apart. Segment "
        f"errors: {EMPTY} where the drive is shorter than 100 m. RPE over one frame."]) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from dpc_jax.data.kitti import open_raw
    from dpc_jax.data.poses_io import read_trajectory

    progress = not args.no_progress and sys.stderr.isatty()
    began = time.perf_counter()
    rows: list[dict[str, Any]] = []
    try:
        base, protocol = P.load_protocol(args.config)
        check_results_page(args.results_page)
        drives = protocol.drives
        if len(drives) != 2:
            raise ValueError(f"{args.config}: PROTOCOL['drives'] must name two drives, got {list(drives)}")
        cache_root = args.workdir / "cache"
        overrides = P.overrides_from(args)
        adapt_steps = 2 if args.smoke else protocol.adapt_steps
        judge_size = protocol.judge_size
        unknown = [d for d in args.test_drives or () if d not in drives]
        if unknown:
            raise ValueError(f"--test-drives {unknown[0]}: not a drive of {args.config} "
                             f"({', '.join(drives)})")
        sequences, libviso2, priors, offsets = {}, {}, {}, {}
        for drive, spec in drives.items():
            mat = args.kitti_raw / spec.libviso2
            gt_all = read_trajectory(mat, mat_key="poses_gt")
            est_all = read_trajectory(mat, mat_key="poses_est")
            probe = open_raw(args.kitti_raw, protocol.date, drive)
            n = len(probe)
            if gt_all.shape[0] < n:
                raise ValueError(f"{mat}: {gt_all.shape[0]} poses for the {n} frames of drive {drive}")
            # The .mat may cover the whole drive; its first n poses belong to the images (the data README).
            sequences[drive] = open_raw(args.kitti_raw, protocol.date, drive, poses=gt_all[:n])
            libviso2[drive] = est_all[:n]
        P.claim_workdir(args.workdir, [("--kitti-raw", args.kitti_raw), ("--config", args.config)],
                        files=[("--results-page", args.results_page)])
        for drive, sequence in sequences.items():
            record = P.vo_prior(sequence, args.workdir / "priors" / f"{drive}_vo.txt", progress)
            priors[drive] = {"vo": Path(record["path"]), "libviso2": libviso2[drive]}
            offsets[drive] = record["disparity_offset_median_px"] if protocol.rectify_offset else 0.0
        config0 = P.fold_config(base, P.Fold("prepare", ("x",), "y", ()), cache_root, overrides)
        for drive, sequence in sequences.items():
            spec = drives[drive]
            for prior, source in priors[drive].items():
                jobs = {f"{drive}_{prior}_train": spec.train_frames,
                        f"{drive}_{prior}_validation": spec.validation_frames,
                        f"{drive}_{prior}": None}
                for name, frames in jobs.items():
                    P.prepare(sequence, source, cache_root, config0, name=name, frames=frames,
                              disparity_offset=offsets[drive], progress=progress)
                P.prepare_judge(sequence, source, cache_root, config0, judge_size, name=f"{drive}_{prior}",
                                disparity_offset=offsets[drive], progress=progress)
        select = args.select or protocol.select
        for test_drive in args.test_drives or drives:
            train_drive = next(d for d in drives if d != test_drive)
            for prior, trained_on in protocol.tests:
                # One network per training drive and prior corrects every test prior it is paired with.
                tested = tuple(f"{test_drive}_{p}" for p, t in protocol.tests if t == trained_on)
                fold = P.Fold(f"train{train_drive}_{trained_on}", (f"{train_drive}_{trained_on}_train",),
                              f"{train_drive}_{trained_on}_validation", tested)
                config = P.fold_config(base, fold, cache_root, overrides)
                run_dir = args.workdir / "runs" / fold.name
                P.train_fold(config, run_dir, progress)
                result = P.correct_and_evaluate(
                    fold.name, run_dir, cache_root / f"{test_drive}_{prior}", args.workdir, protocol,
                    select=select, prior_label=prior, adapt_steps=adapt_steps, progress=progress,
                    judge=None if judge_size is None else cache_root / f"{test_drive}_{prior}_judge")
                rows += long_rows(test_drive, prior, f"{train_drive} {PRIOR_NAMES[trained_on]}", result)
                print(f"[{(time.perf_counter() - began) / 60:.1f} min] test {test_drive}, prior {prior}, "
                      f"trained on {train_drive} {trained_on}: final {result.applied}", flush=True)
    except (OSError, ValueError, KeyError) as error:
        print(f"kitti_raw_drives: error: {error}", file=sys.stderr)
        return 2
    minutes = (time.perf_counter() - began) / 60
    described = "; ".join(
        f"{s.name}: {len(s)} frames, {'grey' if s.left_paths[0].parts[-3] == 'image_00' else 'colour'} pair, "
        f"trained on frames {drives[d].train_frames[0]}–{drives[d].train_frames[1] - 1}, validated on "
        f"{drives[d].validation_frames[0]}–{drives[d].validation_frames[1] - 1}, images rectified by "
        f"{offsets[d]:+.3f} px" for d, s in sequences.items())
    notes = [f"Real KITTI raw drives ({described}). Each test drive is corrected by networks trained on the "
             f"other drive (trained on: drive and training prior), epoch by {select}, adapted "
             f"{adapt_steps} steps to the test drive, acceptance depth {base.acceptance_depth}"
             + (f" measured at {judge_size[0]}×{judge_size[1]} (the scale of an accepted correction chosen "
                "there)" if judge_size is not None else "") + ", "
             f"{'rotation only' if protocol.rotation_only else 'full correction'} applied. "
             f"{minutes:.1f} minutes." + (" SMOKE RUN (1 epoch of 2 steps, 2 adaptation steps)." if args.smoke
                                          else "")]
    args.workdir.mkdir(parents=True, exist_ok=True)
    atomic_write(args.workdir / "results.csv", results_csv(rows))
    atomic_write(args.workdir / "results.md", results_markdown(rows, notes))
    P.print_results(args.workdir / "results.md", args.results_page, Path(__file__))
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(main())
