"""What an acceptance test measured and let through (the tests themselves: ``dpc_jax.correction.acceptance``
and ``dpc_jax.correction.decision``)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class PairedTest:
    """The test of one paired difference over ``pairs`` frame pairs.

    ``mean_delta``/``median_delta``: of the differences; ``improved_share``: fraction below 0;
    ``statistic``, ``p_value``: Wilcoxon signed-rank (``nan``/1 when every difference is 0);
    ``passed``: ``p_value < alpha`` and ``mean_delta < 0``; ``std_delta``: the standard deviation of
    the differences (what the power of the test on more pairs follows from).
    """

    component: str
    pairs: int
    mean_delta: float
    median_delta: float
    improved_share: float
    statistic: float
    p_value: float
    passed: bool
    std_delta: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PairedTest:
        return cls(**data)


def part_name(component: str, remainder: bool = False, scale: float = 1.0) -> str:
    """The one name of a part of a correction: ``rotation``, ``rotation_xz − mean ×0.75``; ``none`` for
    nothing applied (the names the tests, the records and the live corrector's frames use)."""
    if component == "none":
        return "none"
    return component + (" − mean" if remainder else "") + (f" ×{scale:g}" if scale != 1.0 else "")


def mean_test_name(name: str) -> str:
    """The name of the test of the mean of the part ``name``: ``mean of rotation``."""
    return f"mean of {name}"


def judge_test_name(name: str) -> str:
    """The name of the test ``name`` made at the judge's size: ``rotation (judge)``."""
    return f"{name} (judge)"


@dataclass(frozen=True)
class Acceptance:
    """What the acceptance test let through (``dpc_jax.correction.decision.decide``).

    :attr:`part` names what is applied (the one name of it, :func:`part_name`); its pieces:
    ``component``: ``full | rotation | rotation_<axes> | none``;
    ``remainder``: True when the correction's mean was removed (its per-step remainder is applied;
    the mean failed its own test), the mean a moving one over ``window`` pairs
    (``dpc_jax.correction.parts.moving_mean``), centred or, with ``trailing``, of the pairs up to
    each one; ``scale``: the factor a judge chose (1 otherwise);
    ``mean``: ``[6]`` the overall mean of what was removed (``[ρ (m), φ (rad)]``), None when nothing
    was;
    ``tests``: every test made, by name (e.g. ``rotation``, ``mean of rotation``,
    ``rotation − mean``, ``rotation_x``, ``rotation (judge)``); ``reason``: why, in words;
    ``forced``: applied whatever the tests said; ``delta``: Δ ``[M]`` of the applied correction on
    every pair, measured where it was decided (at the judge's size when there is one), None when
    nothing is applied (and in a record read back: :meth:`to_dict` does not hold it).
    """

    alpha: float
    tests: dict[str, PairedTest] = field(default_factory=dict)
    component: str = "none"
    reason: str = ""
    forced: bool = False
    scale: float = 1.0
    remainder: bool = False
    mean: tuple[float, ...] | None = None
    window: int | None = None
    trailing: bool = False
    delta: np.ndarray | None = field(default=None, compare=False, repr=False)

    @property
    def part(self) -> str:
        """What is applied, in one name: ``none``, ``rotation``, ``rotation_xz − mean ×0.75``."""
        return part_name(self.component, self.remainder, self.scale)

    @property
    def mean_delta(self) -> float:
        """Mean Δ of the first part tested (the full correction, or the rotation alone when only that
        was tested): the figure a run's record keeps."""
        return next(iter(self.tests.values())).mean_delta if self.tests else math.nan

    def to_dict(self) -> dict[str, Any]:
        return {
            "alpha": self.alpha,
            "component": self.component,
            "remainder": self.remainder,
            "scale": self.scale,
            "part": self.part,
            "mean": None if self.mean is None else list(self.mean),
            "window": self.window,
            "trailing": self.trailing,
            "reason": self.reason,
            "forced": self.forced,
            "tests": {name: test.to_dict() for name, test in self.tests.items()},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Acceptance:
        """The record of :meth:`to_dict` (its ``part`` is derived, so not read)."""
        mean = data["mean"]
        # Records written before the component had its name held it as "decision".
        component = data["component"] if "component" in data else data["decision"]
        return cls(data["alpha"], {name: PairedTest.from_dict(t) for name, t in data["tests"].items()},
                   component, data["reason"], data["forced"], data["scale"], data["remainder"],
                   None if mean is None else tuple(mean), data.get("window"), bool(data.get("trailing")))
