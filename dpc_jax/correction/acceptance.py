"""The ground-truth-free acceptance test: does the correction explain the images better than the prior?

For a network and a sequence, every frame pair i gives a *paired* difference
``Δ_i = L_i(ξ_corr) − L_i(0)``: the gradient-masked photometric error of the temporal
reconstructions (``dpc_jax.nn.losses.correction_deltas``) with the correction and without it, with
the same depth and validity. Δ < 0 means the corrected relative pose reconstructs the pair better.
The test is one-sided: the correction is accepted when the Δ are significantly below zero by the
Wilcoxon signed-rank test (``scipy.stats.wilcoxon``, ``alternative="less"``) at level ``alpha``
*and* their mean is negative. Consecutive pairs share images and motion, so the Δ are not
independent and the p-value is optimistic; the default level 0.01 is chosen strict for that
reason.

The test runs per component: ``full`` (the correction as trained: 6-DoF, or only its rotation
for a rotation-only run) and ``rotation`` (only its rotation part). The decision is the first
that passes in that order, else ``none`` (the prior is kept).

A passed ``rotation`` is then taken apart by axis (:func:`supported_axes`): the rotation about
each camera axis alone (x: pitch, y: yaw, z: roll) is tested the same way, and when some but not
all pass, only those axes are applied (``rotation_xz``: about x and z), provided that rotation
passes the test too. A network can be right about one axis and wrong about another; on a real
drive a rotation that helped as a whole carried a yaw that hurt on its own and, summed over
100 m, turned the travel (``docs/method.md`` §8). When no single axis passes (the effect is
spread over them), the whole rotation stays.

Measured on a larger copy of the frames (a judge, ``dpc_jax.correction.judge``), a passed correction must
pass there too and is also scaled: of ×0.25, ×0.5, ×0.75 and ×1 the one with the lowest mean Δ is
applied, provided it passes the test itself.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

DEFAULT_ALPHA = 0.01
COMPONENTS = ("full", "rotation")
AXES = "xyz"  # camera axes: x right (pitch), y down (yaw), z forward (roll)
AXIS_COMPONENTS = tuple(f"rotation_{a}" for a in AXES)


def rotation_component(axes: str) -> str:
    """The component of a rotation about ``axes`` (in order, a part of ``"xyz"``): ``rotation_xz``,
    or ``rotation`` for all three."""
    if not axes or "".join(a for a in AXES if a in axes) != axes:
        raise ValueError(f"axes must be a non-empty ordered part of {AXES!r}, got {axes!r}")
    return "rotation" if axes == AXES else f"rotation_{axes}"


def component_mask(component: str) -> np.ndarray:
    """Which entries of ξ = [ρ, φ] a decision applies → float64 ``[6]`` of 0/1."""
    if component == "full":
        return np.ones(6)
    if component == "none":
        return np.zeros(6)
    axes = AXES if component == "rotation" else component.removeprefix("rotation_")
    if not component.startswith("rotation") or rotation_component(axes) != component:
        raise ValueError(f"not a decision: {component!r}")
    return np.array([0.0, 0.0, 0.0, *(float(a in axes) for a in AXES)])


@dataclass(frozen=True)
class ComponentTest:
    """The test of one component over ``pairs`` frame pairs.

    ``mean_delta``/``median_delta``: of Δ; ``improved_share``: fraction of pairs with Δ < 0;
    ``statistic``, ``p_value``: Wilcoxon signed-rank (``nan``/1 when every Δ is 0);
    ``passed``: ``p_value < alpha`` and ``mean_delta < 0``.
    """

    component: str
    pairs: int
    mean_delta: float
    median_delta: float
    improved_share: float
    statistic: float
    p_value: float
    passed: bool


@dataclass(frozen=True)
class Acceptance:
    """Outcome of the acceptance test: ``decision`` ∈ ``full | rotation | rotation_<axes> | none``,
    the ``scale`` of the applied correction (1 unless a judge chose less, ``dpc_jax.correction.judge``)
    and why."""

    alpha: float
    tests: dict[str, ComponentTest] = field(default_factory=dict)
    decision: str = "none"
    reason: str = ""
    forced: bool = False
    scale: float = 1.0

    @property
    def mean_delta(self) -> float:
        """Mean Δ of the first component tested (the full correction, or the rotation alone when
        only that was tested): the figure a run's record keeps."""
        return next(iter(self.tests.values())).mean_delta

    def to_dict(self) -> dict[str, Any]:
        return {
            "alpha": self.alpha,
            "decision": self.decision,
            "reason": self.reason,
            "forced": self.forced,
            "scale": self.scale,
            "tests": {name: asdict(test) for name, test in self.tests.items()},
        }


def component_test(component: str, delta: np.ndarray, alpha: float = DEFAULT_ALPHA) -> ComponentTest:
    """One-sided Wilcoxon signed-rank test of ``delta`` (``[M]``) < 0 (see the module docstring)."""
    from scipy import stats

    delta = np.asarray(delta, np.float64)
    if delta.ndim != 1 or delta.size == 0 or not np.all(np.isfinite(delta)):
        raise ValueError(f"{component}: Δ must be a non-empty vector of finite numbers, got {delta.shape}")
    mean = float(delta.mean())
    if np.count_nonzero(delta) == 0:
        statistic, p_value = math.nan, 1.0
    else:
        result = stats.wilcoxon(delta, alternative="less", zero_method="wilcox")
        statistic, p_value = float(result.statistic), float(result.pvalue)
    return ComponentTest(
        component=component,
        pairs=int(delta.size),
        mean_delta=mean,
        median_delta=float(np.median(delta)),
        improved_share=float(np.mean(delta < 0)),
        statistic=statistic,
        p_value=p_value,
        passed=bool(p_value < alpha and mean < 0),
    )


def acceptance_test(
    deltas: dict[str, np.ndarray], alpha: float = DEFAULT_ALPHA, components: tuple[str, ...] = COMPONENTS
) -> Acceptance:
    """Test each of ``components`` (in order of preference) on its Δ; decide (module docstring).

    ``deltas``: ``{component: Δ [M]}`` as from ``dpc_jax.nn.losses.correction_deltas`` (pairs
    already selected, padding dropped).
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    unknown = [c for c in components if c not in COMPONENTS]
    if unknown or not components:
        raise ValueError(f"components must be a non-empty subset of {COMPONENTS}, got {components}")
    tests = {c: component_test(c, deltas[c], alpha) for c in components}
    for c in components:
        t = tests[c]
        if t.passed:
            return Acceptance(alpha, tests, c, f"{c}: mean Δ {t.mean_delta:.3g} < 0, p = {t.p_value:.3g}")
    parts = [f"{c}: mean Δ {t.mean_delta:.3g}, p = {t.p_value:.3g}" for c, t in tests.items()]
    return Acceptance(alpha, tests, "none", "no component significantly below 0 (" + "; ".join(parts) + ")")


def supported_axes(
    deltas: dict[str, np.ndarray], alpha: float = DEFAULT_ALPHA
) -> tuple[str, dict[str, ComponentTest]]:
    """The camera axes whose rotation alone passes the test → ``(axes, tests)``, ``axes`` in order
    (``"xz"``, ``""`` when none does); ``deltas``: Δ ``[M]`` of each of :data:`AXIS_COMPONENTS`."""
    tests = {c: component_test(c, deltas[c], alpha) for c in AXIS_COMPONENTS}
    return "".join(a for a, c in zip(AXES, AXIS_COMPONENTS, strict=True) if tests[c].passed), tests


def forced(acceptance: Acceptance, component: str) -> Acceptance:
    """``acceptance`` with the decision overridden to ``component`` (``--force``), statistics kept."""
    if component not in COMPONENTS:
        raise ValueError(f"component must be one of {COMPONENTS}, got {component!r}")
    return Acceptance(acceptance.alpha, acceptance.tests, component,
                      f"forced ({acceptance.decision} by the test: {acceptance.reason})", forced=True)


def refine_rotation(
    acceptance: Acceptance,
    delta: dict[str, np.ndarray],
    subset_delta: Callable[[str], np.ndarray],
    pairs: np.ndarray | None = None,
) -> tuple[Acceptance, dict[str, np.ndarray]]:
    """A passed ``rotation`` decision narrowed to the axes whose rotation alone passes the test
    (``dpc_jax.correction.acceptance``) → ``(acceptance, delta)``.

    ``delta``: Δ ``[N-1]`` per component, with the single axes; ``subset_delta(axes)``: Δ of the
    rotation about ``axes`` (two of them: it needs another pass of the network); ``pairs``: the
    pairs the test uses (default all). The narrowed rotation must pass the test itself; its Δ is
    added to ``delta`` (what :func:`dpc_jax.correction.corrector.choose` compares). With no axis or every axis
    passing alone, the rotation is kept whole; the per-axis tests are recorded either way.
    """
    chosen = slice(None) if pairs is None else np.asarray(pairs)
    axes, tests = supported_axes({c: delta[c][chosen] for c in AXIS_COMPONENTS}, acceptance.alpha)
    recorded = dataclasses.replace(acceptance, tests={**acceptance.tests, **tests})
    if axes in ("", AXES):
        return recorded, delta
    component = rotation_component(axes)
    delta = {**delta, component: delta[component] if component in delta else subset_delta(axes)}
    test = component_test(component, delta[component][chosen], acceptance.alpha)
    tests[component] = test
    recorded = dataclasses.replace(acceptance, tests={**acceptance.tests, **tests})
    if not test.passed:
        return dataclasses.replace(recorded, reason=f"{acceptance.reason}; the axes passing alone ({axes}) "
                                                     f"did not pass together (p = {test.p_value:.3g})"), delta
    dropped = ", ".join(a for a in AXES if a not in axes)
    return dataclasses.replace(
        recorded, decision=component,
        reason=f"{acceptance.reason}; only the rotation about {', '.join(axes)} passes alone "
               f"({component}: mean Δ {test.mean_delta:.3g}, p = {test.p_value:.3g}); {dropped} dropped",
    ), delta
