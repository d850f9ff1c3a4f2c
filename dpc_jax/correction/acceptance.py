"""The ground-truth-free acceptance test: its statistic, and the record of what it decided.

For a correction and a sequence, every frame pair i gives a *paired* difference
``Δ_i = L_i(ξ) − L_i(0)``: the gradient-masked photometric error of the temporal reconstructions
(``dpc_jax.nn.losses.temporal_pair_errors``) with the correction and without it, with the same depth
and validity. Δ < 0 means the corrected relative pose reconstructs the pair better. A part of a
correction passes when its Δ are significantly below zero by the one-sided Wilcoxon signed-rank test
(``scipy.stats.wilcoxon``, ``alternative="less"``) at level ``alpha`` *and* their mean is negative
(:func:`paired_test`). The same test compares two corrections on the same pairs: the differences
``Δ_i(a) − Δ_i(b) = L_i(a) − L_i(b)`` below zero say that ``a`` explains the pairs better than ``b``
(the correction's mean against its remainder, the adapted network against the trained one).
Consecutive pairs share images and motion, so the Δ are not independent and the p-value is
optimistic; the default level 0.01 is chosen strict for that reason.

What to apply, from the tests of the correction's parts, is ``dpc_jax.correction.decision``'s;
:class:`Acceptance` records it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

DEFAULT_ALPHA = 0.01


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


def paired_test(name: str, delta: np.ndarray, alpha: float = DEFAULT_ALPHA) -> PairedTest:
    """One-sided Wilcoxon signed-rank test of ``delta`` (``[M]``) < 0 (see the module docstring)."""
    from scipy import stats

    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    delta = np.asarray(delta, np.float64)
    if delta.ndim != 1 or delta.size == 0 or not np.all(np.isfinite(delta)):
        raise ValueError(f"{name}: Δ must be a non-empty vector of finite numbers, got {delta.shape}")
    mean = float(delta.mean())
    if np.count_nonzero(delta) == 0:
        statistic, p_value = math.nan, 1.0
    else:
        result = stats.wilcoxon(delta, alternative="less", zero_method="wilcox")
        statistic, p_value = float(result.statistic), float(result.pvalue)
    return PairedTest(
        component=name,
        pairs=int(delta.size),
        mean_delta=mean,
        median_delta=float(np.median(delta)),
        improved_share=float(np.mean(delta < 0)),
        statistic=statistic,
        p_value=p_value,
        passed=bool(p_value < alpha and mean < 0),
        std_delta=float(delta.std()),
    )


@dataclass(frozen=True)
class Acceptance:
    """What the acceptance test let through (``dpc_jax.correction.decision.decide``).

    ``decision``: the component applied, ``full | rotation | rotation_<axes> | none``;
    ``remainder``: True when the correction's mean over the sequence was removed (its per-step
    remainder is applied; the mean failed its own test); ``scale``: the factor a judge chose (1
    otherwise); ``mean``: ``[6]`` the mean removed (``[ρ (m), φ (rad)]``), None when none was;
    ``tests``: every test made, by name (e.g. ``rotation``, ``mean of rotation``,
    ``rotation − mean``, ``rotation_x``, ``rotation (judge)``); ``reason``: why, in words;
    ``forced``: applied whatever the tests said; ``delta``: Δ ``[M]`` of the applied correction on
    every pair, measured where it was decided (at the judge's size when there is one), None when
    nothing is applied.
    """

    alpha: float
    tests: dict[str, PairedTest] = field(default_factory=dict)
    decision: str = "none"
    reason: str = ""
    forced: bool = False
    scale: float = 1.0
    remainder: bool = False
    mean: tuple[float, ...] | None = None
    delta: np.ndarray | None = field(default=None, compare=False, repr=False)

    @property
    def part(self) -> str:
        """What is applied, in one name: ``none``, ``rotation``, ``rotation_xz − mean ×0.75``."""
        if self.decision == "none":
            return "none"
        return self.decision + (" − mean" if self.remainder else "") + (
            f" ×{self.scale:g}" if self.scale != 1.0 else "")

    @property
    def mean_delta(self) -> float:
        """Mean Δ of the first part tested (the full correction, or the rotation alone when only that
        was tested): the figure a run's record keeps."""
        return next(iter(self.tests.values())).mean_delta if self.tests else math.nan

    def to_dict(self) -> dict[str, Any]:
        return {
            "alpha": self.alpha,
            "decision": self.decision,
            "remainder": self.remainder,
            "scale": self.scale,
            "part": self.part,
            "mean": None if self.mean is None else list(self.mean),
            "reason": self.reason,
            "forced": self.forced,
            "tests": {name: asdict(test) for name, test in self.tests.items()},
        }
