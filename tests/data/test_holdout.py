"""The hold-out split's feasibility (``dpc_jax.data.holdout.holdout_problem``), on sequences whose
kept-out and adaptable pairs are counted by hand."""

from __future__ import annotations

from dpc_jax.data.holdout import holdout_problem


def test_a_split_with_a_pair_kept_out_and_one_to_adapt_on_holds() -> None:
    # 4 frames, 3 pairs, every 5th: pair 2 kept out (frames 2, 3), pair 0 (frames 0, 1) touches neither.
    assert holdout_problem(4, 5, "seq") is None


def test_a_split_that_keeps_nothing_out_names_the_largest_that_fits() -> None:
    # 3 pairs, every 8th: the first kept-out pair would be 4, past the last. Every 4th and 5th keep pair 2
    # out and leave pair 0; every 6th starts at 3: none.
    assert holdout_problem(4, 8, "cache/05") == (
        "--holdout-every 8: keeps 0 of the 3 frame pairs of cache/05 out of adaptation and leaves 3 that "
        "touch none of their frames, but its test needs at least one kept out and one to adapt on; use "
        "--holdout-every 5 or less")


def test_a_sequence_too_short_for_any_split_is_named() -> None:
    # 2 pairs: every K >= 4 starts at pair K // 2 >= 2, past the last.
    problem = holdout_problem(3, 4, "seq")
    assert problem is not None and problem.endswith("; seq is too short to adapt on")
    assert problem.startswith("--holdout-every 4: keeps 0 of the 2 frame pairs of seq")
