"""Live and offline on the same frames: does the live corrector end where ``correct`` does?

For each case, the same trained network corrects the same prior twice, from the same prepared frames
(the case's disparity offset, the network's size; no adaptation, as the live corrector runs; the judge of
``correct``'s rule, as ``dpc-jax vo --correct`` and ``dpc-jax live`` take it, or none with
``--no-judge``): offline (``correct_cache``: the tests decide once, over the whole sequence) and live
(``LiveCorrector``: frame by frame, each part applied from the pair its sequential test, and its
judge's, accepts at). The table gives the
prior, the offline final and the live final against the ground truth (segment errors, rotational
m-ATE), the offline decision, the frames the live corrector spent in each state, and where the two
differ. Cases: the demo's test sequence with the demo's network; each real drive with the network
trained on the other drive for our VO's and libviso2-s's prior (``kitti_raw_drives.py``'s runs); and
each real drive's libviso2-s prior with the demo's network, trained on the synthetic world (a network
the offline tests refuse there).

    python experiments/studies/live_agreement.py --demo runs/demo_seeds/seed_0 \\
        --drives runs/kitti_raw_drives --workdir runs/live_agreement --results-page docs/results/live.md
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dpc_jax.correction.stream import frame_state
from dpc_jax.data.sequence_cache import read_manifest
from dpc_jax.experiments.script import (
    Clock,
    add_kitti_raw_option,
    add_results_page,
    claim,
    data_given,
    interruptible,
    new_parser,
    publish,
    refuse,
)
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.results.demo import SUMMARY

HERE = Path(__file__).resolve().parent
DATE = "2011_09_26"
MATS = {"0001": "libviso2/stereo_2011_09_26_drive_0001.mat",
        "0005": "libviso2/stereo_2011_09_26_drive_0005.mat"}
METRICS = ("seg_trans_pct", "seg_rot_deg_per_100m", "m_ate_rot_deg")


def cases(demo: Path, drives: Path, raw: Path) -> list[dict[str, Any]]:
    """Each case: its name, run folder, sequence opener, prior and ground truth, offset and rotation rule."""
    from dpc_jax.data.kitti import open_odometry, open_raw
    from dpc_jax.data.poses_io import read_kitti_poses, read_trajectory

    def offset(cache: Path) -> float:
        return float(read_manifest(cache)["parameters"]["disparity_offset"])

    test = open_odometry(demo / "data", "test")
    out = [{"name": "demo test sequence, demo network", "run": demo / "run", "sequence": test,
            "prior": read_kitti_poses(demo / "vo" / "test.txt"), "gt": test.poses,
            "offset": offset(demo / "cache" / "test"), "rotation_only": None}]
    for drive, other in (("0001", "0005"), ("0005", "0001")):
        sequence = open_raw(raw, DATE, drive)
        n = len(sequence)
        gt = read_trajectory(raw / MATS[drive], mat_key="poses_gt")[:n]
        priors = {"vo": read_kitti_poses(drives / "priors" / f"{drive}_vo.txt"),
                  "libviso2": read_trajectory(raw / MATS[drive], mat_key="poses_est")[:n]}
        for prior, trained_on in (("vo", "vo"), ("libviso2", "libviso2")):
            out.append({"name": f"drive {drive}, {prior} prior, network of drive {other}'s {trained_on}",
                        "run": drives / "runs" / f"train{other}_{trained_on}", "sequence": sequence,
                        "prior": priors[prior], "gt": gt, "rotation_only": True,
                        "offset": offset(drives / "cache" / f"{drive}_{prior}")})
        out.append({"name": f"drive {drive}, libviso2 prior, demo network (synthetic)", "run": demo / "run",
                    "sequence": sequence, "prior": priors["libviso2"], "gt": gt, "rotation_only": True,
                    "offset": offset(drives / "cache" / f"{drive}_libviso2")})
    return out


def run_case(case: dict[str, Any], cache: Path, judged: bool) -> dict[str, Any]:
    """Offline and live on one case (its frames prepared into ``cache``, and at the judge's size beside
    it when ``judged`` and the rule gives one) → its row."""
    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.inference import load_run
    from dpc_jax.correction.judge import judge_rule
    from dpc_jax.correction.live import Calibration, LiveCorrector
    from dpc_jax.data.cache import prepare_sequence
    from dpc_jax.data.kitti import load_image
    from dpc_jax.eval.evaluation import evaluate

    run = load_run(case["run"], "delta")
    sequence, prior, gt = case["sequence"], case["prior"], case["gt"]
    prepared = prepare_sequence(sequence, prior, cache.parent, size=run.image_size, ground_truth=gt,
                                disparity_offset=case["offset"], name=cache.name, progress=False)
    judge_size = judge_rule(run.config.method, run.image_size, sequence.image_size) if judged else None
    judge = None if judge_size is None else prepare_sequence(
        sequence, prior, cache.parent, size=judge_size, ground_truth=gt, disparity_offset=case["offset"],
        name=f"{cache.name}_judge", progress=False)
    offline = correct_cache(run, prepared, rotation_only=case["rotation_only"], judge=judge)
    live = LiveCorrector(run, Calibration.of(sequence), rotation_only=case["rotation_only"],
                         first_pose=gt[0], disparity_offset=case["offset"], judge_size=judge_size)
    files = sequence.images
    frames = [live(load_image(left), load_image(right), prior[k])
              for k, (left, right) in enumerate(zip(files.left_paths, files.right_paths, strict=True))]
    poses = np.stack([f.pose for f in frames])
    summary = evaluate(gt, {"prior": offline.prior, "offline": offline.corrected, "live": poses}).estimates
    states = Counter(frame_state(f) for f in frames[1:])
    applied = [frame_state(f) not in ("prior", "start") for f in frames]
    longest = max((len(r) for r in "".join("1" if a else "0" for a in applied).split("0")), default=0)
    differed = [f.index for f in frames[1:] if f.part.split(" ")[0] != offline.acceptance.component]
    judge_ms = [1e3 * f.seconds["judge"] for f in frames if "judge" in f.seconds]
    return {"case": case["name"], "frames": len(frames),
            "judge": "none" if judge_size is None else "{}x{}".format(*judge_size),
            "judge_ms": float(np.median(judge_ms)) if judge_ms else None, "offline": offline.acceptance.part,
            "states": dict(states), "applied_frames": int(sum(applied)), "longest_run": longest,
            "differed": len(differed), "events": [(f.index, e) for f in frames for e in f.events],
            **{f"{k}_{m}": summary[k][m] for k in ("prior", "offline", "live") for m in METRICS}}


def markdown(rows: list[dict[str, Any]], minutes: float) -> str:
    from dpc_jax.report.tables import number, table

    def change(row: dict[str, Any], which: str, metric: str) -> str:
        a, b = row[f"offline_{metric}"], row[f"{which}_{metric}"]
        return "n/a" if a is None or b is None or not a else f"{100 * (b / a - 1):+.1f} %"

    def triple(row: dict[str, Any], metric: str) -> str:
        return " / ".join(number(row[f"{k}_{metric}"]) for k in ("prior", "offline", "live"))

    body = table(["case", "frames", "judge (live p50 ms)", "offline applies", "live: frames per state",
                  "seg. t % (prior / offline / live)", "seg. r °/100 m", "rot. m-ATE °",
                  "live vs offline (t, r, m-ATE r)", "frames deciding otherwise"],
                 ([r["case"], str(r["frames"]), r["judge"] + ("" if r["judge_ms"] is None
                                                             else f" ({r['judge_ms']:.0f})"), r["offline"],
                   ", ".join(f"{s} {n}" for s, n in r["states"].items()), triple(r, "seg_trans_pct"),
                   triple(r, "seg_rot_deg_per_100m"), triple(r, "m_ate_rot_deg"),
                   ", ".join(change(r, "live", m) for m in METRICS), str(r["differed"])] for r in rows))
    events = [f"- {r['case']}: " + ("; ".join(f"frame {i}: {e}" for i, e in r["events"])
                                    or "no test accepted") for r in rows]
    return "\n".join(["# Live and offline on the same frames", "",
                      f"{minutes:.1f} min. Offline: `correct_cache` (no adaptation; the judge of the "
                      "column, as `correct` takes it); live: `LiveCorrector` on the same prepared frames, "
                      "prior and first pose, with the same judge. A frame decides otherwise when the part "
                      "live applies to its pair is not the component offline applies.",
                      "", body, "",
                      "When the live tests changed state:", *events, ""])


def main(argv: Sequence[str] | None = None) -> int:
    parser = new_parser(__doc__)
    parser.add_argument("--demo", type=path_argument, required=True, help="a finished demo folder")
    parser.add_argument("--drives", type=path_argument, required=True,
                        help="a finished kitti_raw_drives folder")
    add_kitti_raw_option(parser)
    parser.add_argument("--workdir", type=path_argument, required=True, help="caches and the table go here")
    parser.add_argument("--no-judge", action="store_true",
                        help="decide at the network's size alone, offline and live (no judge)")
    add_results_page(parser)
    args = parser.parse_args(argv)
    from dpc_jax._io import atomic_write

    try:
        # The inputs are read (and named as the options give them) before the work folder is made.
        for option, folder, marker, what in (
                ("--demo", args.demo, SUMMARY, "a finished `dpc-jax demo --out` folder"),
                ("--drives", args.drives, "results.json", "a finished kitti_raw_drives.py work folder")):
            if not (folder / marker).is_file():
                raise ValueError(f"{option} {folder}: not {what} (no {marker})")
        raw = data_given(args.kitti_raw, "--kitti-raw")
        todo = cases(args.demo, args.drives, raw)
        workdir = claim(args.workdir, [("--demo", args.demo), ("--drives", args.drives),
                                       ("--kitti-raw", raw)], script=__file__,
                        page=args.results_page)
        assert workdir is not None
    except (OSError, ValueError, KeyError) as error:
        return refuse("live_agreement", error)
    clock = Clock()
    rows = []
    for k, case in enumerate(todo):
        rows.append(run_case(case, workdir / "cache" / f"case{k}", not args.no_judge))
        clock.say(f"{rows[-1]['case']}: offline {rows[-1]['offline']}, live {rows[-1]['states']}")
    text = markdown(rows, clock.minutes)
    atomic_write(workdir / "live_agreement.md", text)
    publish(text, args.results_page, __file__)
    return 0


if __name__ == "__main__":
    sys.exit(interruptible(main, __file__))
