"""How small an error self-supervision can find: the detection limit by bias, pairs, steps and resolution.

What runs and why: ``configs/detection_limit.py``; the grid and the cells: ``dpc_jax.experiments.detection``;
what they answer, the rule among the options and the tables: ``detection_answer``, ``detection_rule`` and
``detection_page`` beside it. Per cell (bias scale s, training pairs N, the steps it trained for, input
resolution, world) the table gives the fraction of the planted bias removed on the held-out test sequences,
prior → final, from the mean per-axis rotation error per step and from the rotational segment error; the
same for the network's proposal applied whatever its tests said and for the earlier decision (the mean not
tested apart); what the tests applied with the p of the whole rotation, of its mean and of its remainder;
the final's change of the rotational segment error and m-ATE against the prior; the training time.

    python experiments/studies/detection_limit.py --workdir runs/detection_limit
    python experiments/studies/detection_limit.py --quick --workdir /tmp/dl_quick

``--include OTHER`` adds the cells of another work folder (another world's, or the ``--profile gpu``
run's) to the tables and the figure; ``--results-page FILE`` writes the tables into that page's results
block.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from dpc_jax._io import atomic_write
from dpc_jax.experiments import detection as D
from dpc_jax.experiments.detection_answer import cell_mean
from dpc_jax.experiments.detection_page import CSV_COLUMNS, figure, long_rows, markdown
from dpc_jax.experiments.detection_rule import CHECKING_WORLD, CHOOSING_WORLDS, OPTION_COLUMNS
from dpc_jax.experiments.records import Records
from dpc_jax.experiments.script import (
    Clock,
    add_data_option,
    add_results_page,
    claim,
    data_given,
    interruptible,
    new_parser,
    publish,
    refuse,
)
from dpc_jax.experiments.stamp import stamp
from dpc_jax.pipelines.protocol import path_argument
from dpc_jax.report.tables import csv_text
from dpc_jax.runtime.hugepages import reexec_with_huge_pages

CONFIG = Path(__file__).resolve().parent / "configs" / "detection_limit.py"


def image_size(text: str) -> tuple[int, int]:
    height, _, width = text.partition("x")
    try:
        return int(height), int(width)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW, e.g. 64x96, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    parser = new_parser(__doc__)
    parser.add_argument("--workdir", type=path_argument, required=True,
                        help="where everything is made (reused on a rerun)")
    parser.add_argument("--profile", choices=("cpu", "worlds", "gpu"), default="cpu",
                        help="the grid (configs/detection_limit.py)")
    parser.add_argument("--world-seed", type=int, default=0, metavar="K",
                        help="render another world (K >= 1; each world in a work folder of its own, "
                        "tabulated together with --include)")
    parser.add_argument("--quick", action="store_true", help="the tiny grid that checks the wiring")
    add_data_option(parser, "--libviso2", "kitti-libviso2", metavar="DIR",
                    help="folder of libviso2-s's stereo_*.mat with ground truth (the reference ×1); not read "
                    "when WORKDIR/reference.json exists")
    parser.add_argument("--pairs", type=int, nargs="+", metavar="N",
                        help="run only the cells of these N of the grid (e.g. in two work folders side by "
                        "side, tabulated together with --include)")
    parser.add_argument("--sizes", type=image_size, nargs="+", metavar="HxW",
                        help="run only the cells of these input sizes of the grid")
    parser.add_argument("--scales", type=float, nargs="+", metavar="S",
                        help="run only the cells of these bias scales of the grid")
    parser.add_argument("--fixed-epochs", action="store_true",
                        help="run only the fixed-epoch cells (not those trained with N = 1,000's steps)")
    parser.add_argument("--include", type=path_argument, action="append", default=[], metavar="WORKDIR",
                        help="also tabulate the finished cells of this work folder (repeatable)")
    add_results_page(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    clock = Clock()
    try:
        if args.world_seed < 0:
            raise ValueError(f"--world-seed {args.world_seed}: expected 0 (the study's world) or more")
        study, paper_pairs = D.load_study(CONFIG, args.profile, args.quick, args.world_seed)
        study = study.restricted(args.pairs, args.sizes, args.scales)
        if args.fixed_epochs:
            study = dataclasses.replace(study, matched=())
        for other in args.include:
            if not (other / "cells").is_dir():
                raise ValueError(f"--include {other}: no cells/ folder (not a work folder of this study)")
        recorded = sorted({cell.get("world_seed", 0) for cell in Records(args.workdir / "cells").all()})
        if recorded and recorded != [args.world_seed]:
            raise ValueError(f"--workdir {args.workdir}: holds the cells of world {recorded[0]}, not of "
                             f"--world-seed {args.world_seed}; each world needs a work folder of its own")
        inputs = [("--libviso2", args.libviso2), *(("--include", other) for other in args.include)]
        workdir = claim(args.workdir, inputs, script=__file__, page=args.results_page)
        assert workdir is not None
        reference_path = workdir / "reference.json"
        if not reference_path.is_file():
            measured = D.libviso2_reference(data_given(args.libviso2, "--libviso2"))
            atomic_write(reference_path, json.dumps(measured, indent=1))
        reference = json.loads(reference_path.read_text())
    except (OSError, ValueError) as error:
        return refuse("detection_limit", error)
    made = stamp()
    D.render(study, workdir / "data")
    cells = Records(workdir / "cells")
    roots: dict[tuple[tuple[int, int], float], Path] = {}
    for cell in study.cells():
        size, scale = cell[:2]
        done = cells.read(D.cell_key(*cell))
        if done is not None and done.get("correction") == study.correction:
            continue  # measured with the study's correction; else measured again, its training kept
        if (size, scale) not in roots:
            roots[size, scale] = D.prepare(study, workdir, reference, scale, size)
        measured = D.run_cell(study, workdir, roots[size, scale], cell, made, done)
        record = cells.write(D.cell_key(*cell), measured)
        finals = ", ".join(f"{x['decision']} {x['final_r_change_pct']:+.1f} %" for x in record["tests"])
        clock.say(f"{record['key']}: removed (axis) network {cell_mean(record, 'found_axis_network'):.2f}, "
                  f"final {cell_mean(record, 'found_axis_final'):.2f}, earlier "
                  f"{cell_mean(record, 'found_axis_earlier'):.2f}; {finals}")
    found = [c for d in (workdir, *args.include) for c in Records(d / "cells").all()]
    # A cell measured with another correction (outside --pairs/--sizes/--scales here) is not comparable.
    tabulated = [c for c in found if c.get("correction") == study.correction]
    stale = [c["key"] for c in found if c.get("correction") != study.correction]
    if stale:
        clock.say(f"{len(stale)} cells measured with another correction are not tabulated "
                  f"({', '.join(stale)}); a run that includes them measures them again")
    # The cells the rule of docs/method.md §8 needs decided: world 0's cpu grid, the other worlds' grid.
    expected = {} if args.quick else {
        world: {D.cell_key(*cell) for cell in D.load_study(CONFIG, "cpu" if world == 0 else "worlds", False,
                                                           world)[0].cells()}
        for world in (*CHOOSING_WORLDS, CHECKING_WORLD)}
    text = markdown(tabulated, reference, paper_pairs, clock.minutes, args.quick, expected)
    atomic_write(workdir / "detection_limit.md", text)
    atomic_write(workdir / "detection_limit.csv",
                 csv_text((*CSV_COLUMNS, *OPTION_COLUMNS), long_rows(tabulated)))
    figure(tabulated, reference, workdir / "detection_limit.png")
    publish(text, args.results_page, __file__)
    if args.results_page is not None:
        # The page links the figure by the same name, beside it; written after the page, whose stamp
        # would otherwise call a clean checkout dirty.
        figure(tabulated, reference, args.results_page.with_name("detection_limit.png"))
    return 0


if __name__ == "__main__":
    reexec_with_huge_pages()
    sys.exit(interruptible(main, __file__))
