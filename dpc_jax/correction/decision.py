"""What to apply of a network's correction, decided from measured photometric effects alone.

The decision is a pure function of the proposal ``ξ`` ``[M, 6]`` (one correction per consecutive pair)
and of a *measurement* ``measure({name: ξ' [M, 6]}) → {name: Δ [M]}``: the paired photometric effect
``Δ_i = L_i(ξ'_i) − L_i(0)`` of any correction on the same pairs (``dpc_jax.correction.measure``).
No ground truth, no network: the tests of ``dpc_jax.correction.acceptance`` on what it measures.

**Parts.** A *component* of ξ is which entries are applied: ``full`` (6-DoF), ``rotation`` (φ only)
or ``rotation_<axes>`` (the rotation about some camera axes). Each is taken *whole* (``ξ ⊙ m``) or
as its *remainder* ``ξ ⊙ m − mean_W(ξ ⊙ m)``: the per-step part, with the correction's *mean* removed,
its moving mean over :data:`MEAN_WINDOW` consecutive pairs (:func:`moving_mean`; over the whole
sequence when it is shorter). The two differ in what they do to a trajectory: composed over a stretch
of road, a correction's mean there turns and stretches the path (the drift the segment errors
measure), its remainder only moves single steps. And the per-pair test hardly sees the mean: each
pair's Δ is dominated by how well the correction fits that pair's own error, so a correction that fits
the per-step noise well passes with any small mean it carries, right or wrong, and a wrong mean then
raises the drift (``docs/method.md`` §8). So the mean is tested on its own, on the same pairs:
``Δ_i(whole) − Δ_i(remainder) = L_i(whole) − L_i(remainder)`` below zero says that adding the mean
to the remainder explains the pairs better. The mean is a moving one, not the sequence's: a network
that is wrong about the mean is wrong about it locally as well (its error varies with the scene and
the motion), and a remainder that kept those local means would still drift over 100 m.

**Order.** For each component in ``components`` (``full`` then ``rotation``): the whole part is
applied when its Δ passes *and* its mean passes; else the remainder when its Δ passes; else the next
component; else nothing (the prior). The largest part that passed is applied, each step on
significant evidence (prior ⊂ remainder ⊂ whole). ``mean_test=False`` gives the earlier decision
(whole parts only, the mean never tested apart).

**Axes.** A passed rotation is taken apart by camera axis (x: pitch, y: yaw, z: roll): the same
part about each axis alone is tested, and when some but not all pass, the rotation about those axes
is applied if it passes too (with its own mean test for a whole part). A network can be right about
one axis and wrong about another.

**Judge.** With a second measurement on the same frames prepared at a larger size (``judge``), the
part chosen at the network's size must pass the same tests there too; failing, the next part is
tried. Then of :data:`JUDGE_SCALES` times that part, the one with the lowest mean Δ at the judge is
applied when it passes there.

**Where and how the mean is tested** (:class:`MeanTest`, the options of :data:`MEAN_TESTS`,
``docs/method.md`` §8): at both sizes (today's default), or with a judge at the judge's size only (a
whole part then passes the network's size on its own Δ), at the whole's level or a level of its own,
as help (the differences below zero) or as bounded harm (below a margin of the whole's gain: a
non-inferiority test).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from dpc_jax.correction.acceptance import DEFAULT_ALPHA, paired_test
from dpc_jax.results.acceptance import Acceptance, PairedTest

COMPONENTS = ("full", "rotation")
AXES = "xyz"  # camera axes: x right (pitch), y down (yaw), z forward (roll)
# Pairs the mean of a correction is taken over: well under the shortest segment the segment errors
# measure (100 m, about 100 frames at KITTI's speeds), so that a remainder drifts over none of them.
MEAN_WINDOW = 50
# The scales of a passed correction the judge compares.
JUDGE_SCALES = (0.25, 0.5, 0.75, 1.0)

Measure = Callable[[Mapping[str, np.ndarray]], Mapping[str, np.ndarray]]


@dataclass(frozen=True)
class MeanTest:
    """How a whole part's mean is tested (``docs/method.md`` §8: the options compared, and the rule
    stated before their results that picks the default).

    ``at_judge``: with a judge, test the mean at the judge's size only (at the network's size a whole
    part passes on its own Δ); without one, at the network's size as always. ``alpha``: the mean's own
    level (None: the decision's). ``margin``: 0 tests help (the differences ``D_i = Δ_i(whole) −
    Δ_i(remainder)`` significantly below zero); above 0, bounded harm: ``D_i − margin · G`` significantly
    below zero, ``G = −mean Δ(whole)`` on the tested pairs (the whole's gain, positive once it passed):
    adding the mean costs less than that fraction of what the whole gains.
    """

    at_judge: bool = False
    alpha: float | None = None
    margin: float = 0.0

    def __post_init__(self) -> None:
        if self.alpha is not None and not 0.0 < self.alpha < 1.0:
            raise ValueError(f"the mean's alpha must be in (0, 1), got {self.alpha}")
        if not 0.0 <= self.margin < 1.0:
            raise ValueError(f"the mean's margin must be in [0, 1), got {self.margin}")


# The options compared by the rule of docs/method.md §8 (stated before their results), by the name
# ``dpc-jax correct --decision`` takes. The first is the default until that rule has chosen.
MEAN_TESTS = {
    "mean-at-network": MeanTest(),
    "mean-at-judge": MeanTest(at_judge=True),
    "mean-at-judge-a05": MeanTest(at_judge=True, alpha=0.05),
    "mean-noninferior": MeanTest(at_judge=True, margin=0.05),
}
DEFAULT_MEAN_TEST = "mean-at-network"


def rotation_component(axes: str) -> str:
    """The component of a rotation about ``axes`` (in order, a part of ``"xyz"``): ``rotation_xz``,
    or ``rotation`` for all three."""
    if not axes or "".join(a for a in AXES if a in axes) != axes:
        raise ValueError(f"axes must be a non-empty ordered part of {AXES!r}, got {axes!r}")
    return "rotation" if axes == AXES else f"rotation_{axes}"


def component_mask(component: str) -> np.ndarray:
    """Which entries of ξ = [ρ, φ] a component applies → float64 ``[6]`` of 0/1."""
    if component == "full":
        return np.ones(6)
    if component == "none":
        return np.zeros(6)
    axes = AXES if component == "rotation" else component.removeprefix("rotation_")
    if not component.startswith("rotation") or rotation_component(axes) != component:
        raise ValueError(f"not a component: {component!r}")
    return np.array([0.0, 0.0, 0.0, *(float(a in axes) for a in AXES)])


@dataclass(frozen=True)
class Part:
    """A part of a correction: a component, whole or its remainder (its moving mean over ``window``
    pairs removed), times a scale."""

    component: str
    remainder: bool = False
    scale: float = 1.0
    window: int = MEAN_WINDOW

    @property
    def name(self) -> str:
        return self.component + (" − mean" if self.remainder else "") + (
            f" ×{self.scale:g}" if self.scale != 1.0 else "")

    def of(self, xi: np.ndarray) -> np.ndarray:
        """This part of ``xi`` ``[M, 6]`` → ``[M, 6]`` float64."""
        return part_of(xi, self.component, self.remainder, self.scale, window=self.window)

    def mean(self, xi: np.ndarray) -> np.ndarray:
        """The mean ``[6]`` over all the pairs of the component's entries of ``xi``."""
        return (np.asarray(xi, np.float64) * component_mask(self.component)).mean(axis=0)


def moving_mean(x: np.ndarray, window: int = MEAN_WINDOW) -> np.ndarray:
    """The centred moving mean ``[M, ...]`` of ``x`` ``[M, ...]`` over ``window`` consecutive rows: row k
    the mean of rows ``[k − ⌊window/2⌋, k + ⌈window/2⌉)``, cut to the rows there are (at the ends and
    in a sequence shorter than the window, the mean of fewer rows; the whole mean when ``M ≤
    window/2``)."""
    x = np.asarray(x, np.float64)
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    m = x.shape[0]
    sums = np.concatenate([np.zeros((1, *x.shape[1:])), np.cumsum(x, axis=0)])
    start = np.clip(np.arange(m) - window // 2, 0, m)
    stop = np.clip(np.arange(m) + (window - window // 2), 0, m)
    shape = (m,) + (1,) * (x.ndim - 1)
    return (sums[stop] - sums[start]) / (stop - start).reshape(shape)


def part_of(xi: np.ndarray, component: str, remainder: bool = False, scale: float = 1.0,
            mean: np.ndarray | None = None, window: int = MEAN_WINDOW) -> np.ndarray:
    """``scale · (ξ ⊙ m − [mean])`` → ``[M, 6]`` float64, ``m`` the mask of ``component``.

    ``xi``: ``[M, 6]`` corrections ``[ρ (m), φ (rad)]``; with ``remainder`` the moving mean of
    ``ξ ⊙ m`` over ``window`` pairs (:func:`moving_mean`) is removed, or ``mean`` (``[6]`` or
    ``[M, 6]``) when given: the live corrector's mean of the pairs seen. The one implementation of
    "what is applied" (offline and live).
    """
    xi = np.asarray(xi, np.float64)
    if xi.ndim != 2 or xi.shape[1] != 6:
        raise ValueError(f"xi must be [M, 6], got {xi.shape}")
    masked = xi * component_mask(component)
    if remainder:
        masked = masked - (moving_mean(masked, window) if mean is None else np.asarray(mean, np.float64))
    return scale * masked


def applied_correction(xi: np.ndarray, acceptance: Acceptance) -> np.ndarray:
    """The correction ``[M, 6]`` that ``acceptance`` applies to the proposal ``xi`` (zeros for none)."""
    return part_of(xi, acceptance.decision, acceptance.remainder, acceptance.scale,
                   window=acceptance.window or MEAN_WINDOW)


class _Sized:
    """The measurements at one size, each candidate measured once, and the tests made there; ``mean``:
    how a whole part's mean is tested here (None: not here)."""

    def __init__(self, measure: Measure, xi: np.ndarray, suffix: str, tested: slice | np.ndarray,
                 alpha: float, tests: dict[str, PairedTest], mean: MeanTest | None) -> None:
        self.measure, self.xi, self.suffix, self.tested, self.alpha = measure, xi, suffix, tested, alpha
        self.tests, self.mean = tests, mean
        self.delta: dict[str, np.ndarray] = {}

    def ensure(self, parts: list[Part]) -> None:
        todo = {p.name: p.of(self.xi) for p in parts if p.name not in self.delta}
        if todo:
            measured = self.measure(todo)
            self.delta.update({name: np.asarray(measured[name], np.float64) for name in todo})

    def test(self, name: str, delta: np.ndarray, alpha: float | None = None) -> PairedTest:
        result = paired_test(name + self.suffix, delta[self.tested],
                             self.alpha if alpha is None else alpha)
        self.tests[result.component] = result
        return result

    def passes(self, part: Part, mean_test: bool, said: list[str]) -> bool:
        """Whether ``part`` passes here: its Δ, and for a whole part with ``mean_test`` its mean where
        :attr:`mean` says it is tested here."""
        rest = Part(part.component, True, part.scale, part.window)
        whole = not part.remainder and mean_test and self.mean is not None
        self.ensure([part, rest] if whole else [part])
        test = self.test(part.name, self.delta[part.name])
        said.append(f"{test.component}: p = {test.p_value:.3g}" + ("" if test.passed else " (failed)"))
        if not test.passed or not whole:
            return test.passed
        assert self.mean is not None
        differences = self.delta[part.name] - self.delta[rest.name]
        gain = -float(self.delta[part.name][self.tested].mean())  # > 0: the whole passed
        mean = self.test(f"mean of {part.name}", differences - self.mean.margin * gain, self.mean.alpha)
        margin = f" (margin {self.mean.margin:g} of the gain)" if self.mean.margin else ""
        said.append(f"{mean.component}{margin}: p = {mean.p_value:.3g}"
                    + ("" if mean.passed else " (failed)"))
        return mean.passed


def decide(
    xi: np.ndarray,
    measure: Measure,
    *,
    components: tuple[str, ...] = COMPONENTS,
    alpha: float = DEFAULT_ALPHA,
    tested: np.ndarray | None = None,
    judge: Measure | None = None,
    mean_test: bool = True,
    window: int = MEAN_WINDOW,
    mean: MeanTest = MEAN_TESTS[DEFAULT_MEAN_TEST],
    force: bool = False,
) -> Acceptance:
    """What to apply of ``xi`` ``[M, 6]`` (module docstring) → :class:`Acceptance`.

    ``measure``: Δ ``[M]`` of named corrections ``[M, 6]`` on the M pairs at the network's size;
    ``components``: the components in order of preference (a subset of :data:`COMPONENTS`; a
    rotation-only run: ``("rotation",)``); ``tested``: the pairs the tests use (default all; after
    adaptation, the pairs it never saw; the mean is over all M pairs, as applied); ``judge``: the
    measurement at a larger size; ``mean_test``: test the mean apart (False: the earlier decision);
    ``window``: the pairs the moving mean is taken over; ``mean``: where and how the mean is tested
    (:class:`MeanTest`; with ``mean_test``);
    ``force``: apply the first component whole whatever the tests say (they are still made and
    recorded).
    """
    xi = np.asarray(xi, np.float64)
    unknown = [c for c in components if c not in COMPONENTS]
    if unknown or not components:
        raise ValueError(f"components must be a non-empty subset of {COMPONENTS}, got {components}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    chosen = slice(None) if tested is None else np.asarray(tested)
    tests: dict[str, PairedTest] = {}
    network = _Sized(measure, xi, "", chosen, alpha, tests,
                     None if mean.at_judge and judge is not None else mean)
    judged = None if judge is None else _Sized(judge, xi, " (judge)", chosen, alpha, tests, mean)
    said: list[str] = []
    if force:
        part = Part(components[0], window=window)
        network.passes(part, mean_test, said)
        return _record(alpha, tests, part, xi, network, f"forced ({'; '.join(said)})", forced=True)
    for component in components:
        for remainder in (False, True) if mean_test else (False,):
            part = Part(component, remainder, window=window)
            if not network.passes(part, mean_test, said):
                continue
            candidates = [part]
            if component == "rotation":
                candidates = _axes(network, part, mean_test, said) + candidates
            for candidate in candidates:
                if judged is None:
                    return _record(alpha, tests, candidate, xi, network, "; ".join(said))
                if judged.passes(candidate, mean_test, said):
                    return _scaled(alpha, tests, candidate, xi, judged, said)
    return Acceptance(alpha, tests, "none", "nothing passed (" + "; ".join(said) + "): the prior is kept")


def _axes(network: _Sized, part: Part, mean_test: bool, said: list[str]) -> list[Part]:
    """The rotation about the axes whose part passes alone, when some but not all do and it passes
    itself (``[]`` otherwise)."""
    singles = [Part(rotation_component(a), part.remainder, window=part.window) for a in AXES]
    network.ensure(singles)
    passing = "".join(a for a, p in zip(AXES, singles, strict=True)
                      if network.test(p.name, network.delta[p.name]).passed)
    if passing in ("", AXES):
        return []
    subset = Part(rotation_component(passing), part.remainder, window=part.window)
    said.append(f"alone, only the rotation about {', '.join(passing)} passes")
    return [subset] if network.passes(subset, mean_test, said) else []


def _scaled(alpha: float, tests: dict[str, PairedTest], part: Part, xi: np.ndarray, judged: _Sized,
            said: list[str]) -> Acceptance:
    """``part``, passed at both sizes, at the scale of :data:`JUDGE_SCALES` with the lowest mean Δ at
    the judge when that scale passes there."""
    scaled = [Part(part.component, part.remainder, s, part.window) for s in JUDGE_SCALES]
    judged.ensure(scaled)
    means = {p.scale: float(judged.delta[p.name][judged.tested].mean()) for p in scaled}
    best = min(means, key=lambda s: means[s])
    said.append("mean Δ at the judge by scale: " + ", ".join(f"×{s:g} {m:.3g}" for s, m in means.items()))
    if best != 1.0:
        candidate = Part(part.component, part.remainder, best, part.window)
        test = judged.test(candidate.name, judged.delta[candidate.name])
        if test.passed:
            said.append(f"applied ×{best:g} (p = {test.p_value:.3g})")
            part = candidate
        else:
            said.append(f"×{best:g} did not pass (p = {test.p_value:.3g})")
    return _record(alpha, tests, part, xi, judged, "; ".join(said))


def _record(alpha: float, tests: dict[str, PairedTest], part: Part, xi: np.ndarray, where: _Sized,
            reason: str, forced: bool = False) -> Acceptance:
    where.ensure([part])
    mean = tuple(float(v) for v in part.mean(xi)) if part.remainder else None
    return Acceptance(alpha, tests, part.component, reason, forced=forced, scale=part.scale,
                      remainder=part.remainder, mean=mean, window=part.window if part.remainder else None,
                      delta=where.delta[part.name])


def refused(acceptance: Acceptance, why: str) -> Acceptance:
    """``acceptance`` with nothing applied, for ``why`` (its tests kept)."""
    return Acceptance(acceptance.alpha, acceptance.tests, "none", f"{why}; {acceptance.reason}")
