"""The step driver (dpc_jax.engine.driver): order, one-step-behind fetches, finiteness, Ctrl-C."""

from __future__ import annotations

from collections.abc import Generator

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dpc_jax.engine.driver import NonFiniteLossError, drive, step_key


def _sum_step(carry: jnp.ndarray, item: float, index: int) -> tuple[jnp.ndarray, dict[str, jnp.ndarray]]:
    carry = carry + item
    return carry, {"loss": carry * 1.0, "index": jnp.asarray(index)}


@pytest.mark.parametrize("in_flight", [1, 2])
def test_drive_is_a_plain_loop_with_the_fetch_behind(in_flight: int) -> None:
    events: list[tuple[str, int]] = []
    items = [1.0, 2.0, 3.0, 4.0]

    def step(carry, item, index):
        events.append(("dispatch", index))
        return _sum_step(carry, item, index)

    seen = []

    def consume(index: int, host: dict, item: float) -> int:
        events.append(("consume", index))
        seen.append((index, float(host["loss"]), int(host["index"]), item))
        return 2

    out = drive(step, jnp.asarray(0.0), items, total=8, desc="t", consume=consume, in_flight=in_flight)
    assert float(out) == 10.0
    # The running sums of a plain loop, in order, each with its own input.
    assert seen == [(0, 1.0, 0, 1.0), (1, 3.0, 1, 2.0), (2, 6.0, 2, 3.0), (3, 10.0, 3, 4.0)]
    # Step i + in_flight is dispatched before step i's outputs are fetched.
    expected = {
        1: [("dispatch", 0), ("dispatch", 1), ("consume", 0), ("dispatch", 2), ("consume", 1),
            ("dispatch", 3), ("consume", 2), ("consume", 3)],
        2: [("dispatch", 0), ("dispatch", 1), ("dispatch", 2), ("consume", 0), ("dispatch", 3),
            ("consume", 1), ("consume", 2), ("consume", 3)],
    }
    assert events == expected[in_flight]


def test_a_non_finite_loss_stops_before_it_is_consumed() -> None:
    consumed: list[int] = []
    with pytest.raises(NonFiniteLossError, match="bad at 2: inf"):
        drive(_sum_step, jnp.asarray(0.0), [1.0, 1.0, np.inf, 1.0, 1.0], total=5, desc="t",
              consume=lambda index, host, item: consumed.append(index), finite="loss",
              on_nonfinite=lambda index, value: f"bad at {index}: {value}")
    assert consumed == [0, 1]


def test_ctrl_c_closes_the_batches_and_says_how_far(capsys: pytest.CaptureFixture[str]) -> None:
    closed = []

    def batches() -> Generator[float, None, None]:
        try:
            yield from [1.0] * 10
        finally:
            closed.append(True)

    def step(carry, item, index):
        if index == 3:  # Ctrl-C while step 3 is being dispatched
            raise KeyboardInterrupt
        return _sum_step(carry, item, index)

    with pytest.raises(KeyboardInterrupt):
        drive(step, jnp.asarray(0.0), batches(), total=10, desc="epoch 1", unit="step")
    assert closed == [True]
    assert "epoch 1: interrupted after 1 of 10 steps" in capsys.readouterr().err


def test_progress_lines_in_a_log(capsys: pytest.CaptureFixture[str]) -> None:
    drive(_sum_step, jnp.asarray(0.0), [1.0, 2.0], total=2, desc="adapt x", progress="lines")
    assert "adapt x: 2/2 steps" in capsys.readouterr().err


def test_step_key_is_fold_in_bit_for_bit() -> None:
    base = jax.random.key(7)
    for index in (0, 1, 123456, 2**31 - 1):
        np.testing.assert_array_equal(jax.random.key_data(step_key(base, index)),
                                      jax.random.key_data(jax.random.fold_in(base, index)))
