"""The one step driver: feeds batches to a jitted step and keeps the device busy.

Training (``dpc_jax.training.loop``), adaptation (``dpc_jax.correction.adapt``) and inference
(``dpc_jax.engine.predict``) each hand :func:`drive` their step, its carried state and an iterable
of inputs (batches, typically already on the device: ``dpc_jax.data.pipeline`` transfers them in
its worker threads). Per input the driver

1. dispatches ``step(carry, item, index)`` (asynchronous: JAX returns before the device is done)
   and starts copying its outputs to the host;
2. then fetches the outputs of the step ``in_flight`` steps earlier (by default the one before the
   previous: the device always has the steps just dispatched to run while the host waits, and a
   host that takes longer over one step than the device does not leave it idle), checks the named
   output for finiteness, and hands the host values to ``consume``;
3. advances the progress report (``dpc_jax.runtime.progress``: a bar on a terminal, plain lines in a log).

The order of the steps, their inputs and the carried state are exactly those of a plain loop; the
driver adds no computation, and ``consume`` sees the steps in order. A non-finite loss is noticed
``in_flight`` steps late: the state by then is discarded all the same. On Ctrl-C
(``KeyboardInterrupt``) it closes the input iterable (the data workers stop), closes the bar, says
on stderr how far it got, and re-raises.
"""

from __future__ import annotations

import math
import sys
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import jax

from dpc_jax.runtime.progress import Progress, progress_bar

Carry = TypeVar("Carry")
Item = TypeVar("Item")


# The key of step ``index`` from the run's base key: ``jax.random.fold_in`` compiled once, one
# dispatch per step instead of its primitives one by one (the same bits: integer arithmetic).
step_key = jax.jit(jax.random.fold_in)


class NonFiniteLossError(RuntimeError):
    """A step produced a NaN or infinite loss; the run stopped without saving that state."""


def drive(
    step: Callable[[Carry, Item, int], tuple[Carry, Any]],
    carry: Carry,
    items: Iterable[Item],
    *,
    total: int,
    desc: str,
    unit: str = "step",
    progress: Progress = False,
    consume: Callable[[int, Any, Item], int | None] | None = None,
    finite: str | None = None,
    on_nonfinite: Callable[[int, float], str] | None = None,
    postfix: Callable[[Any], dict[str, str]] | None = None,
    in_flight: int = 2,
) -> Carry:
    """Run ``step`` over ``items`` (module docstring); return the last carry.

    ``step(carry, item, index) -> (carry, outputs)``: dispatch one step (index 0, 1, …); ``outputs``
    is a pytree of device arrays. ``consume(index, host_outputs, item)``: called in step order
    with the outputs fetched to numpy; returns the units of progress the step made (None: 1).
    ``finite``: the key of a scalar output that must be finite, else :class:`NonFiniteLossError`
    with the message ``on_nonfinite(index, value)`` (raised before ``consume`` sees that step).
    ``postfix(host_outputs)``: fields shown beside the bar. ``total``: units expected.
    ``in_flight``: steps dispatched ahead of the one whose outputs are fetched (at least 1).
    """
    if in_flight < 1:
        raise ValueError(f"in_flight must be >= 1, got {in_flight}")
    pending: deque[tuple[int, Any, Item]] = deque()
    done = 0

    def fetch(index: int, outputs: Any, item: Item) -> None:
        nonlocal done
        host = jax.device_get(outputs)
        if finite is not None:
            value = float(host[finite])
            if not math.isfinite(value):
                default = f"non-finite {finite} ({value}) at step {index + 1}"
                raise NonFiniteLossError(on_nonfinite(index, value) if on_nonfinite else default)
        units = consume(index, host, item) if consume is not None else None
        units = 1 if units is None else units
        done += units
        bar.update(units)
        if postfix is not None:
            bar.set_postfix(**postfix(host))

    with progress_bar(total, desc, progress, unit) as bar:
        try:
            for index, item in enumerate(items):
                carry, outputs = step(carry, item, index)
                for leaf in jax.tree.leaves(outputs):
                    if isinstance(leaf, jax.Array) and leaf.is_fully_addressable:
                        leaf.copy_to_host_async()
                pending.append((index, outputs, item))
                if len(pending) > in_flight:
                    fetch(*pending.popleft())
            while pending:
                fetch(*pending.popleft())
        except KeyboardInterrupt:
            print(f"{desc}: interrupted after {done} of {total} {unit}s", file=sys.stderr, flush=True)
            raise
        finally:
            # A generator of batches stops its data threads when closed.
            close = getattr(items, "close", None)
            if close is not None:
                close()
    return carry
