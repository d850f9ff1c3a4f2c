"""The leave-one-out rule (data/splits.py)."""

from dpc_jax.data.splits import training_names


def test_training_names_keep_the_available_order_without_the_held_out_ones() -> None:
    assert training_names(["07", "00", "05", "02"], ("05", "07")) == ("00", "02")
    assert training_names(["00", "02"], ("00", "02")) == ()


def test_named_training_sequences_are_taken_as_given() -> None:
    assert training_names(["00", "02", "05"], ("05",), ["02", "00"]) == ("02", "00")
    assert training_names(["00", "02"], ("02",), []) == ()
