"""Which depth should the acceptance test measure Δ with: the network's own, or OpenCV's StereoSGBM?

The test (``dpc_jax.correction.acceptance``) decides without ground truth; this experiment checks its
decisions against the ground truth on the demo's test sequences. For every demo output folder given
(``dpc-jax demo`` or ``experiments/studies/demo_seeds.py`` layout: ``run/``, ``adapted/``, ``cache/test``)
and every network in it — the epochs kept by each selection criterion and the adapted network — the
test runs twice, with the network's depth and with the SGBM depth, and the full correction is scored
against the ground truth: *helps* (both test segment errors lower), *hurts* (either one more than
2 % higher) or neither. A good test accepts what helps and rejects what hurts. Writes
``OUT/acceptance_depth.md`` (table per network, and the counts).

    python experiments/studies/acceptance_depth.py runs/demo_seeds/seed_* --out runs/acceptance_depth
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax.experiments import script as kit
from dpc_jax.experiments.script import interruptible
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.report.tables import change_pct, table
from dpc_jax.results.demo import SUMMARY
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

DEPTHS = ("network", "sgbm")
SEG = ("seg_trans_pct", "seg_rot_deg_per_100m")


def _outcome(prior: dict[str, Any], corrected: dict[str, Any]) -> str:
    change = [change_pct(prior[k], corrected[k]) for k in SEG]
    if all(c < 0 for c in change):
        return "helps"
    return "hurts" if max(change) > 2 else "neutral"


def evaluate_folder(folder: Path) -> list[dict[str, Any]]:
    """The test's decisions with both depths for every network of one demo folder, and the truth."""
    import numpy as np

    from dpc_jax.correction.corrector import correct_cache
    from dpc_jax.correction.inference import load_run
    from dpc_jax.data.sequence_cache import load_cache

    cache = load_cache(folder / "cache" / "test")
    networks: dict[str, Any] = {}
    for select in ("delta", "gradient", "loop", "last"):
        run = load_run(folder / "run", select)
        if run.improves_on_prior or select != "delta":
            networks.setdefault(f"trained, epoch {run.epoch}", (run, None))
    adapted = folder / "adapted"
    held_out = None
    if (adapted / "adapt.json").is_file():
        import json

        held_out = np.asarray(json.loads((adapted / "adapt.json").read_text())["held_out_pairs"])
        networks["adapted"] = (load_run(adapted, "last"), held_out)
    rows = []
    for label, (run, pairs) in networks.items():
        row: dict[str, Any] = {"folder": folder.name, "label": label, "decision": {}}
        for depth in DEPTHS:
            correction = correct_cache(run, cache, acceptance_depth=depth, held_out=pairs, force=False)
            assert correction.evaluation is not None  # the demo's test sequence has its ground truth
            estimates = correction.evaluation.estimates
            applied = correction.part
            row["decision"][depth] = applied if applied == "none" else (
                f"{applied}: {_outcome(estimates['prior'], estimates['corrected'])}")
            row["truth"] = _outcome(estimates["prior"], estimates["network"])
            row["change"] = tuple(change_pct(estimates["prior"][k], estimates["network"][k]) for k in SEG)
        rows.append(row)
    return rows


def report(rows: list[dict[str, Any]]) -> str:
    counts = []
    for depth in DEPTHS:
        accepted = [r for r in rows if r["decision"][depth] != "none"]
        rejected = [r for r in rows if r["decision"][depth] == "none"]
        counts.append([depth, *(str(n) for n in (
            sum(r["decision"][depth].endswith("helps") for r in accepted),
            sum(r["decision"][depth].endswith("hurts") for r in accepted),
            sum(r["truth"] == "helps" for r in rejected),
            sum(r["truth"] == "hurts" for r in rejected),
        ))])
    return "\n".join([
        "# Acceptance test: network depth against SGBM depth",
        "",
        "Each row: one network on its demo's test sequence. truth: what its full correction does to the "
        "test segment errors (helps: both lower; hurts: one more than 2 % higher). The test's decision "
        "with each depth: none (prior kept), or full / rotation (only the rotation applied) with what the "
        "applied correction did. Counts: accepted corrections by what they did, rejected ones by what the "
        "full correction would have done.",
        "",
        table(["demo", "network", "change t / r", "truth", "network depth", "SGBM depth"],
              ([r["folder"], r["label"], f"{r['change'][0]:+.1f} % / {r['change'][1]:+.1f} %", r["truth"],
                r["decision"]["network"], r["decision"]["sgbm"]] for r in rows)),
        table(["depth", "accepted, helps", "accepted, hurts", "rejected, helps", "rejected, hurts"], counts),
    ])


def main(argv: Sequence[str] | None = None) -> int:
    parser = kit.new_parser(__doc__)
    parser.add_argument("folders", type=path_argument, nargs="+", metavar="DEMO_OUT")
    parser.add_argument("--out", type=path_argument, default=Path("runs/acceptance_depth"), metavar="DIR")
    kit.add_results_page(parser)
    args = parser.parse_args(argv)
    try:
        missing = [folder for folder in args.folders if not (folder / SUMMARY).is_file()]
        if missing:
            raise ValueError(f"{missing[0]}: not a finished `dpc-jax demo --out` folder (no {SUMMARY})")
        kit.claim(args.out, [("DEMO_OUT", folder) for folder in args.folders], option="--out",
                  page=args.results_page, script=__file__)
    except (OSError, ValueError) as error:
        return kit.refuse("acceptance_depth", error)
    from dpc_jax._io import atomic_write

    logging.getLogger("absl").setLevel(logging.ERROR)
    rows = [row for folder in args.folders for row in evaluate_folder(folder)]
    text = report(rows)
    atomic_write(args.out / "acceptance_depth.md", text)
    kit.publish(text, args.results_page, __file__)
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
