"""The demo over several seeds (other towns and routes): does the correction help on every one?

For each seed the demo (``dpc_jax.pipelines.synthetic_demo``, default config unless ``--config``) runs into
``WORKDIR/seed_K``; the table ``WORKDIR/seeds.md`` (and ``seeds.csv``) has per seed the test
sequence's segment errors of the prior, of the network as trained and of the network adapted to
the test sequence (each with its acceptance decision), of the final trajectory, its change against
the prior, and the minutes the demo took. Re-running reuses each seed's finished stages.

    python experiments/studies/demo_seeds.py --seeds 0 1 2 3 4 --workdir runs/demo_seeds
    python experiments/studies/demo_seeds.py --seeds 0 1 --workdir runs/x --config my.py --set adapt_steps=0
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dpc_jax.experiments import script as kit
from dpc_jax.experiments.demos import demo_config
from dpc_jax.experiments.script import interruptible
from dpc_jax.pipelines.protocol import parse_overrides, path_argument
from dpc_jax.report.tables import EMPTY, change_pct, records_csv, table
from dpc_jax.results.demo import DemoSummary
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

DEFAULT_CONFIG = Path(__file__).resolve().parent / "configs" / "synthetic_demo.py"
SEG = ("seg_trans_pct", "seg_rot_deg_per_100m")


def _pair(values: dict[str, Any] | None) -> str:
    if values is None:
        return EMPTY
    t, r = (values[k] for k in SEG)
    return EMPTY if t is None or r is None else f"{t:.2f} / {r:.2f}"


def _row(seed: int, summary: DemoSummary, minutes: float, earlier: dict[str, Any]) -> dict[str, Any]:
    test, change = summary.test, summary.change_pct
    return {
        "seed": seed,
        "prior": _pair(test["prior"]),
        "trained": _pair(test.get("trained")),
        "trained_test": summary.decisions.get("trained", EMPTY),
        "adapted": _pair(test.get("adapted")),
        "adapted_test": summary.decisions.get("adapted", EMPTY),
        "final": f"{summary.final}: {_pair(test['corrected'])}",
        "change_t_pct": change["seg_trans_pct"],
        "change_r_pct": change["seg_rot_deg_per_100m"],
        "earlier": f"{earlier['final']}: {_pair(earlier['metrics'])}",
        "earlier_change_t_pct": change_pct(test["prior"][SEG[0]], earlier["metrics"][SEG[0]]),
        "earlier_change_r_pct": change_pct(test["prior"][SEG[1]], earlier["metrics"][SEG[1]]),
        "minutes": minutes,
    }


def earlier_decision(workdir: Path, config: Any) -> dict[str, Any]:
    """The final of a finished demo decided the earlier way (its mean not tested apart) from its own
    networks: ``{"final": "adapted (rotation)", "metrics": summary}``."""
    from dpc_jax.eval.evaluation import evaluate
    from dpc_jax.pipelines.synthetic_demo import decided_again_in

    final, correction = decided_again_in(workdir, config, mean_test=False)
    assert correction.ground_truth is not None  # the demo's test sequence has its ground truth
    metrics = evaluate(correction.ground_truth, {"final": correction.corrected}).estimates["final"]
    label = final if final == "prior" else f"{final} ({correction.acceptance.part})"
    return {"final": label, "metrics": metrics}


def decided_again(workdir: Path, config: Any) -> DemoSummary:
    """A finished demo's summary with its final decided again by this dpc_jax from its networks."""
    import dataclasses

    from dpc_jax.eval.evaluation import evaluate
    from dpc_jax.pipelines.synthetic_demo import decided_again_in

    summary = DemoSummary.read(workdir)
    final, correction = decided_again_in(workdir, config)
    assert correction.ground_truth is not None
    metrics = evaluate(correction.ground_truth, {"final": correction.corrected}).estimates["final"]
    test = {**summary.test, "corrected": metrics}
    change = {k: change_pct(test["prior"][k], metrics[k]) for k in SEG}
    return dataclasses.replace(summary, test=test, final=final, change_pct=change)


def seeds_markdown(rows: list[dict[str, Any]], config_name: str) -> str:
    """The table: one row per seed (segment errors t % / r °/100 m)."""
    lines = [
        f"# The demo over {len(rows)} seeds ({config_name})",
        "",
        "Test sequence segment errors, translation % / rotation °/100 m. *trained*: the network as trained; "
        "*adapted*: adapted to the test sequence's own images (no ground truth); each with its acceptance "
        "test; *final*: what `corrected.txt` holds; change: final against the prior; *earlier decision*: "
        "the final of the same networks decided without testing the correction's mean apart.",
        "",
        *table(["seed", "prior", "trained", "test", "adapted", "test", "final", "change t", "change r",
                "earlier decision", "change t", "change r", "minutes"],
               ([str(r["seed"]), r["prior"], r["trained"], r["trained_test"], r["adapted"], r["adapted_test"],
                 r["final"], f"{r['change_t_pct']:+.1f} %", f"{r['change_r_pct']:+.1f} %", r["earlier"],
                 f"{r['earlier_change_t_pct']:+.1f} %", f"{r['earlier_change_r_pct']:+.1f} %",
                 f"{r['minutes']:.1f}"] for r in rows)).splitlines(),
    ]
    good = [r for r in rows if r["change_t_pct"] <= -20 and r["change_r_pct"] <= -20]
    worse = [r for r in rows
             if max(r["change_t_pct"], r["change_r_pct"]) > 2 or math.isnan(r["change_t_pct"])]
    lines += ["", f"Both segment errors at least 20 % lower: {len(good)} of {len(rows)} seeds; "
              f"worse than the prior by more than 2 % in either: {len(worse)}."]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = kit.new_parser(__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], metavar="K")
    parser.add_argument("--workdir", type=path_argument, default=Path("runs/demo_seeds"), metavar="DIR")
    parser.add_argument("--config", type=path_argument, default=DEFAULT_CONFIG, metavar="FILE",
                        help="demo config (CONFIG = DemoConfig(...) or a dict); its seed is replaced")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a DemoConfig field (JSON value), e.g. --set adapt_steps=0")
    parser.add_argument("--decide-again", action="store_true",
                        help="the seeds' folders hold finished demos (of an earlier dpc_jax, say): decide "
                        "their networks' corrections again with this one, nothing trained or adapted")
    kit.add_no_progress(parser)
    kit.add_results_page(parser)
    args = parser.parse_args(argv)
    try:
        overrides = parse_overrides(args.set)
        configs = {seed: demo_config(args.config, seed, overrides) for seed in args.seeds}
        kit.claim(args.workdir, [("--config", args.config)], script=__file__, page=args.results_page)
    except (OSError, ValueError) as error:  # a ConfigError is a ValueError
        return kit.refuse("demo_seeds", error)

    from dpc_jax._io import atomic_write
    from dpc_jax.pipelines.synthetic_demo import DemoError, run_demo

    logging.getLogger("absl").setLevel(logging.ERROR)
    progress, rows = kit.progress_flag(args.no_progress), []
    for seed, config in configs.items():
        began = time.perf_counter()
        try:
            if args.decide_again:
                summary = decided_again(args.workdir / f"seed_{seed}", config)
            else:
                summary = run_demo(config, args.workdir / f"seed_{seed}", progress=progress,
                                   log=lambda line, seed=seed: print(f"[seed {seed}] {line}", flush=True))
        except (OSError, ValueError, DemoError) as error:
            return kit.refuse("demo_seeds", f"seed {seed}: {error}", 1)
        minutes = (time.perf_counter() - began) / 60
        rows.append(_row(seed, summary, minutes, earlier_decision(args.workdir / f"seed_{seed}", config)))
        text = seeds_markdown(rows, args.config.name + (" " + " ".join(args.set) if args.set else ""))
        atomic_write(args.workdir / "seeds.md", text)
        atomic_write(args.workdir / "seeds.csv", records_csv(rows))
    kit.publish(text, args.results_page, __file__)
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
