"""Ablation of the correction remedies on the demo's sequences, one row per remedy added cumulatively.

Every row is the demo (``dpc_jax.pipelines.synthetic_demo``, default data: same rendered sequences,
priors and caches, shared through symbolic links) with the training and correction settings of that
row, from the published choices (``dpc_jax.training.train_config.REFERENCE``, epoch by the gradient
loss, every correction applied) to ours. Per row: the test sequence's segment errors of the prior
and of the final trajectory, Δ of the correction on the test sequence (mean over its pairs, the
network's depth), what the acceptance test decided, and the minutes the row took (training and
correction; the data are made once, by the first row). The table goes to ``WORKDIR/ablation.md``
(and ``.csv``); docs/results/ablation.md shows it (``--results-page`` rewrites it there).

    python experiments/studies/ablation.py --workdir runs/ablation                 # every row, seed 0
    python experiments/studies/ablation.py --workdir runs/ablation --seed 1 --rows 0 5
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax.experiments import script as kit
from dpc_jax.experiments.demos import share
from dpc_jax.experiments.script import interruptible
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.report.tables import number, records_csv, table
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

# The published choices, then each remedy on top of the previous row (TrainConfig / DemoConfig fields).
PUBLISHED = {
    "training": {"pose_init": "pytorch", "pose_warmup_epochs": 0, "prior_normalization": "none",
                 "dropout": 0.5, "prior_dropout": None, "pose_scale": (0.01, 0.01),
                 "pose_features": "images_and_prior"},
    "select": "gradient", "acceptance": False, "adapt_steps": 0,
}
ROWS: list[tuple[str, dict[str, Any]]] = [
    ("reference (published choices)", {}),
    ("+ zero-initialised pose output", {"training": {"pose_init": "zero"}}),
    ("+ pose warm-up (1 epoch)", {"training": {"pose_warmup_epochs": 1}}),
    ("+ scaled prior, no dropout", {"training": {"prior_normalization": "train_statistics", "dropout": 0.0,
                                                 "prior_dropout": 0.0}}),
    ("+ Δ selection and acceptance test", {"select": "delta", "acceptance": True}),
    ("+ rotation output unit 1e-4 rad", {"training": {"pose_scale": (0.01, 1e-4)}}),
    ("+ forward translation only (sideways, vertical off)",
     {"training": {"pose_scale": (0.0, 0.0, 0.01, 1e-4, 1e-4, 1e-4)}}),
    ("+ correction from the prior alone", {"training": {"pose_features": "prior"}}),
    ("+ adaptation to the test sequence (300 steps)", {"adapt_steps": 300}),
]
# The inputs every row shares: the first row makes them.
SHARED = ("data", "vo", "cache")


def row_configs(base: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """The DemoConfig dicts of the rows: ``base`` with the published settings, then the remedies."""
    out = []
    current = {**base, **PUBLISHED, "training": {**base.get("training", {}), **PUBLISHED["training"]}}
    for name, change in ROWS:
        current = {**current, **change,
                   "training": {**current["training"], **change.get("training", {})}}
        out.append((name, current))
    return out


def ablation_markdown(rows: list[dict[str, Any]], seed: int) -> str:
    def pair(t: float | None, r: float | None) -> str:
        return f"{number(t, '.2f')} / {number(r, '.2f')}"

    return "\n".join([
        f"# Ablation of the correction remedies (demo sequences, seed {seed})",
        "",
        "Each row adds one remedy to the row above. Segment errors of the test sequence, translation % / "
        "rotation °/100 m; Δ: mean paired photometric effect of the (final) network's correction on the "
        "test sequence (negative: it explains the images better); acceptance: what the test decided (rows "
        "without it apply every correction); minutes: training and correction of the row.",
        "",
        table(["row", "prior", "final", "change t", "change r", "Δ on the test sequence", "acceptance",
               "minutes"],
              ([r["row"], pair(r["prior_t"], r["prior_r"]), pair(r["final_t"], r["final_r"]),
                f"{r['change_t']:+.1f} %", f"{r['change_r']:+.1f} %", f"{r['delta']:.2e}", r["acceptance"],
                f"{r['minutes']:.1f}"] for r in rows)),
    ])


def main(argv: Sequence[str] | None = None) -> int:
    parser = kit.new_parser(__doc__)
    parser.add_argument("--workdir", type=path_argument, default=Path("runs/ablation"), metavar="DIR")
    parser.add_argument("--seed", type=int, default=0, help="demo seed (its towns and routes)")
    parser.add_argument("--rows", type=int, nargs="+", metavar="K", help="only these rows (0-based)")
    kit.add_no_progress(parser)
    kit.add_results_page(parser)
    args = parser.parse_args(argv)
    try:
        kit.claim(args.workdir, script=__file__, page=args.results_page)
    except (OSError, ValueError) as error:
        return kit.refuse("ablation", error)

    from dpc_jax import config as config_lib
    from dpc_jax._io import atomic_write
    from dpc_jax.pipelines.synthetic_demo import DemoConfig, DemoError, run_demo

    logging.getLogger("absl").setLevel(logging.ERROR)
    configs = row_configs({**config_lib.to_dict(DemoConfig()), "seed": args.seed})
    results = []
    for k in range(len(configs)) if args.rows is None else args.rows:
        name, values = configs[k]
        out = args.workdir / f"row_{k}"
        for folder in SHARED:
            (args.workdir / "shared" / folder).mkdir(parents=True, exist_ok=True)
        share(args.workdir / "shared", out, SHARED)
        began = time.perf_counter()
        try:
            config = config_lib.from_dict(DemoConfig, values, where=f"row {k}")
            summary = run_demo(config, out, progress=kit.progress_flag(args.no_progress),
                               log=lambda line, k=k: print(f"[row {k}] {line}", flush=True))
        except (OSError, ValueError, DemoError) as error:
            return kit.refuse("ablation", f"row {k}: {error}", 1)
        minutes = (time.perf_counter() - began) / 60 - sum(
            summary.seconds.get(s, 0.0) for s in ("render", "vo", "prepare")) / 60
        prior, final = summary.test["prior"], summary.test["corrected"]
        network = summary.final_network
        results.append({
            "row": name,
            "prior_t": prior["seg_trans_pct"],
            "prior_r": prior["seg_rot_deg_per_100m"],
            "final_t": final["seg_trans_pct"],
            "final_r": final["seg_rot_deg_per_100m"],
            "change_t": summary.change_pct["seg_trans_pct"],
            "change_r": summary.change_pct["seg_rot_deg_per_100m"],
            "delta": summary.acceptance[network].mean_delta,
            "acceptance": f"{summary.decisions[network]} → final: {summary.final}",
            "minutes": minutes,
        })
        atomic_write(args.workdir / "ablation.md", ablation_markdown(results, args.seed))
        atomic_write(args.workdir / "ablation.csv", records_csv(results))
    kit.publish(ablation_markdown(results, args.seed), args.results_page, __file__)
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
