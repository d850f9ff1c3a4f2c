"""Which depth should the acceptance test measure Δ with: the network's own, or OpenCV's StereoSGBM?

The test (``dpc_jax.acceptance``) decides without ground truth; this experiment checks its
decisions against the ground truth on the demo's test sequences. For every demo output folder given
(``dpc-jax demo`` or ``experiments/demo_seeds.py`` layout: ``run/``, ``adapted/``, ``cache/test``)
and every network in it — the epochs kept by each selection criterion and the adapted network — the
test runs twice, with the network's depth and with the SGBM depth, and the full correction is scored
against the ground truth: *helps* (both test segment errors lower), *hurts* (either one more than
2 % higher) or neither. A good test accepts what helps and rejects what hurts. Writes
``OUT/acceptance_depth.md`` (table per network, and the counts).

    python experiments/acceptance_depth.py runs/demo_seeds/seed_* --out runs/acceptance_depth
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax.hugepages import reexec_with_huge_pages

DEPTHS = ("network", "sgbm")


def _outcome(prior: dict[str, Any], corrected: dict[str, Any]) -> str:
    keys = ("seg_trans_pct", "seg_rot_deg_per_100m")
    change = [100 * (corrected[k] - prior[k]) / prior[k] for k in keys]
    if all(c < 0 for c in change):
        return "helps"
    return "hurts" if max(change) > 2 else "neutral"


def evaluate_folder(folder: Path) -> list[dict[str, Any]]:
    """The test's decisions with both depths for every network of one demo folder, and the truth."""
    import numpy as np

    from dpc_jax.correct import correct_cache
    from dpc_jax.data.sequence_cache import load_cache
    from dpc_jax.inference import load_run

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
            estimates = correction.evaluation["estimates"]
            applied = correction.applied
            row["decision"][depth] = applied if applied == "none" else (
                f"{applied}: {_outcome(estimates['prior'], estimates['corrected'])}")
            row["truth"] = _outcome(estimates["prior"], estimates["network"])
            row["change"] = tuple(
                100 * (estimates["network"][k] - estimates["prior"][k]) / estimates["prior"][k]
                for k in ("seg_trans_pct", "seg_rot_deg_per_100m")
            )
        rows.append(row)
    return rows


def report(rows: list[dict[str, Any]]) -> str:
    lines = [
        "# Acceptance test: network depth against SGBM depth",
        "",
        "Each row: one network on its demo's test sequence. truth: what its full correction does to the "
        "test segment errors (helps: both lower; hurts: one more than 2 % higher). The test's decision "
        "with each depth: none (prior kept), or full / rotation (only the rotation applied) with what the "
        "applied correction did. Counts: accepted corrections by what they did, rejected ones by what the "
        "full correction would have done.",
        "",
        "| demo | network | change t / r | truth | network depth | SGBM depth |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        decision = r["decision"]
        lines.append(f"| {r['folder']} | {r['label']} | {r['change'][0]:+.1f} % / {r['change'][1]:+.1f} % | "
                     f"{r['truth']} | {decision['network']} | {decision['sgbm']} |")
    lines += ["", "| depth | accepted, helps | accepted, hurts | rejected, helps | rejected, hurts |",
              "|---|---|---|---|---|"]
    for depth in DEPTHS:
        accepted = [r for r in rows if r["decision"][depth] != "none"]
        rejected = [r for r in rows if r["decision"][depth] == "none"]
        count = {
            (True, "helps"): sum(r["decision"][depth].endswith("helps") for r in accepted),
            (True, "hurts"): sum(r["decision"][depth].endswith("hurts") for r in accepted),
            (False, "helps"): sum(r["truth"] == "helps" for r in rejected),
            (False, "hurts"): sum(r["truth"] == "hurts" for r in rejected),
        }
        lines.append(f"| {depth} | {count[(True, 'helps')]} | {count[(True, 'hurts')]} | "
                     f"{count[(False, 'helps')]} | {count[(False, 'hurts')]} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", type=Path, nargs="+", metavar="DEMO_OUT")
    parser.add_argument("--out", type=Path, default=Path("runs/acceptance_depth"), metavar="DIR")
    args = parser.parse_args(argv)
    from dpc_jax._io import atomic_write

    logging.getLogger("absl").setLevel(logging.ERROR)
    rows = [row for folder in args.folders for row in evaluate_folder(folder)]
    args.out.mkdir(parents=True, exist_ok=True)
    text = report(rows)
    atomic_write(args.out / "acceptance_depth.md", text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(main())
