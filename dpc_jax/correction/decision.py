"""What to apply of a network's correction, decided from measured photometric effects alone.

The decision is a pure function of the proposal ``ξ`` ``[M, 6]`` (one correction per consecutive pair)
and of a *measurement* ``measure({name: ξ' [M, 6]}) → {name: Δ [M]}``: the paired photometric effect
``Δ_i = L_i(ξ'_i) − L_i(0)`` of any correction on the same pairs (``dpc_jax.correction.measure``).
No ground truth, no network: the tests of ``dpc_jax.correction.acceptance`` on what it measures.

**Parts** (``dpc_jax.correction.parts``). A *component* of ξ is which entries are applied: ``full``
(6-DoF), ``rotation`` (φ only) or ``rotation_<axes>`` (the rotation about some camera axes). Each is
taken *whole* (``ξ ⊙ m``) or as its *remainder* ``ξ ⊙ m − mean_W(ξ ⊙ m)``: the per-step part, with the
correction's *mean* removed, its moving mean over ``MEAN_WINDOW`` consecutive pairs (centred offline,
trailing live; over the whole sequence when it is shorter). The two differ in what they do to a
trajectory: composed over a stretch of road, a correction's mean there turns and stretches the path (the
drift the segment errors measure), its remainder only moves single steps. And the per-pair test hardly
sees the mean: each pair's Δ is dominated by how well the correction fits that pair's own error, so a
correction that fits the per-step noise well passes with any small mean it carries, right or wrong, and
a wrong mean then raises the drift (``docs/method.md`` §8). So the mean is tested on its own, on the
same pairs: ``Δ_i(whole) − Δ_i(remainder) = L_i(whole) − L_i(remainder)`` below zero says that adding
the mean to the remainder explains the pairs better. The mean is a moving one, not the sequence's: a
network that is wrong about the mean is wrong about it locally as well (its error varies with the scene
and the motion), and a remainder that kept those local means would still drift over 100 m.

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

**One decision, offline and live.** :class:`Decision` is that walk over the tests of the parts, fed
the pairs' Δ: with fixed-sample tests (offline, :func:`decide`: every pair, measured only when the
walk reaches a part) or sequential ones (the live corrector, ``dpc_jax.correction.live``).

**Where and how the mean is tested** (:class:`MeanTest`, the options of :data:`MEAN_TESTS`,
``docs/method.md`` §8): at both sizes (today's default), or with a judge at the judge's size only (a
whole part then passes the network's size on its own Δ), at the whole's level or a level of its own,
as help (the differences below zero) or as bounded harm (below a margin of the whole's gain: a
non-inferiority test).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial

import numpy as np

from dpc_jax.correction.acceptance import DEFAULT_ALPHA, SequentialTest, paired_test
from dpc_jax.correction.parts import AXES, MEAN_WINDOW, Part, rotation_component
from dpc_jax.results.acceptance import Acceptance, PairedTest, judge_test_name, mean_test_name

COMPONENTS = ("full", "rotation")
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
# ``dpc-jax correct --decision`` takes; the default is the one the rule chose
# (docs/results/detection_limit.md).
MEAN_TESTS = {
    "mean-at-network": MeanTest(),
    "mean-at-judge": MeanTest(at_judge=True),
    "mean-at-judge-a05": MeanTest(at_judge=True, alpha=0.05),
    "mean-noninferior": MeanTest(at_judge=True, margin=0.05),
}
DEFAULT_MEAN_TEST = "mean-at-judge-a05"


NETWORK, JUDGE = "network", "judge"  # the sizes a part is measured at


class _Missing(Exception):
    """A fixed-sample decision reached a part whose Δ it has not been given."""


@dataclass
class _Walk:
    """One pass of the decision over its tests: what it consulted, made and said, and its outcome."""

    consulted: list[tuple[str, Part]]
    made: dict[str, PairedTest]
    said: list[str]
    part: Part | None = None
    missing: tuple[tuple[str, Part], ...] = ()


@dataclass(frozen=True)
class Outcome:
    """What a :class:`Decision` applies now (``part``; None: nothing), the tests it made (fixed-sample:
    by name; sequential: empty, its tests are :attr:`Decision.tests`) and why, in words."""

    part: Part | None
    tests: dict[str, PairedTest]
    reason: str


class Decision:
    """The one decision of what to apply (module docstring), fed the Δ of the parts pair by pair.

    ``update`` takes each pair's Δ of the parts it :meth:`needs` (at the network's size and at the
    judge's); :attr:`outcome` is what to apply after the pairs fed. The parts, their order and names,
    the tests of a whole part's mean, the axes and the judge's scale are one walk over the tests
    (:meth:`_choose`): a part is applied only once its own tests accept it. The test of one part is
    ``sequential`` (live: :class:`~dpc_jax.correction.acceptance.SequentialTest`, valid however long
    it is watched, the walk asks for every part it passes by) or fixed-sample (offline: the
    one-sided Wilcoxon test of every Δ fed, :func:`paired_test`; the walk stops at the first part it
    has no Δ of, so that only the parts that can still change what is applied are measured).
    ``trailing``: a remainder removes the mean of the pairs up to each one (what live can know) rather
    than the centred one; it changes what the driver measures (:attr:`Part.of`), not the tests.
    Fed every pair of a sequence, the fixed-sample decision is :func:`decide`'s.
    """

    def __init__(
        self,
        *,
        components: tuple[str, ...] = COMPONENTS,
        alpha: float = DEFAULT_ALPHA,
        judge: bool = False,
        mean_test: bool = True,
        window: int = MEAN_WINDOW,
        trailing: bool = False,
        mean: MeanTest = MEAN_TESTS[DEFAULT_MEAN_TEST],
        force: bool = False,
        sequential: bool = False,
    ) -> None:
        unknown = [c for c in components if c not in COMPONENTS]
        if unknown or not components:
            raise ValueError(f"components must be a non-empty subset of {COMPONENTS}, got {components}")
        if not 0.0 < alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1), got {alpha}")
        self.components, self.alpha, self.judge = tuple(components), float(alpha), bool(judge)
        self.mean_test, self.window, self.trailing = bool(mean_test), int(window), bool(trailing)
        self.force, self.sequential = bool(force), bool(sequential)
        # Where a whole part's mean is tested (None: not at that size).
        self._mean = {NETWORK: None if mean.at_judge and judge else mean, JUDGE: mean if judge else None}
        self._fed: dict[tuple[str, Part], list[np.ndarray]] = {}  # fixed-sample: the Δ fed
        self.tests: dict[str, SequentialTest] = {}  # sequential: by test name

    def part(self, component: str, remainder: bool = False, scale: float = 1.0) -> Part:
        """A part of this decision (its window and mean)."""
        return Part(component, remainder, scale, self.window, self.trailing)

    def needs(self) -> list[tuple[str, Part]]:
        """``(size, part)`` whose Δ the next :meth:`update` must carry: sequential, every part the walk
        consults; fixed-sample, those it stopped at (none: the decision is made)."""
        walk = self._walk()
        return list(walk.missing) if not self.sequential else list(dict.fromkeys(walk.consulted))

    def update(self, network: Mapping[Part, float | np.ndarray],
               judge: Mapping[Part, float | np.ndarray] | None = None) -> tuple[str, ...]:
        """Take Δ of parts on the next pair (sequential: one number each) or pairs (fixed-sample: a
        number or ``[K]`` each, the same pairs for all) → the tests accepted or withdrawn there."""
        events: list[str] = []
        for size, given in ((NETWORK, network), (JUDGE, judge or {})):
            if not self.sequential:
                for part, value in given.items():
                    values = np.atleast_1d(np.asarray(value, np.float64))
                    self._fed.setdefault((size, part), []).append(values)
                continue
            name = judge_test_name if size == JUDGE else str
            for part, value in given.items():
                events += self._feed(name(part.name), float(value), self.alpha)
            mean = self._mean[size]
            for part in given:
                rest = Part(part.component, True, part.scale, part.window, part.trailing)
                if mean is None or not self.mean_test or part.remainder or rest not in given:
                    continue
                # Bounded harm against the whole's gain so far (the fixed-sample test's, over all pairs).
                gain = -self.tests[name(part.name)].mean
                difference = float(given[part]) - float(given[rest]) - mean.margin * gain
                events += self._feed(name(mean_test_name(part.name)), difference, mean.alpha or self.alpha)
        return tuple(events)

    def _feed(self, name: str, value: float, alpha: float) -> list[str]:
        change = self.tests.setdefault(name, SequentialTest(name, alpha)).update(value)
        return [] if change is None else [f"{name} {change}"]

    @property
    def outcome(self) -> Outcome:
        """What to apply after the pairs fed (fixed-sample: ``ValueError`` while it :meth:`needs` Δ)."""
        walk = self._walk()
        if walk.missing:
            needed = ", ".join(f"{p.name} ({s})" for s, p in walk.missing)
            raise ValueError(f"the decision needs Δ of {needed}")
        said = "; ".join(walk.said)
        if self.force:
            return Outcome(walk.part, walk.made, f"forced ({said})")
        if walk.part is None:
            return Outcome(None, walk.made, f"nothing passed ({said}): the prior is kept")
        return Outcome(walk.part, walk.made, said)

    def _walk(self) -> _Walk:
        walk = _Walk([], {}, [])
        try:
            walk.part = self._choose(walk)
        except _Missing:
            walk.part = None
        return walk

    def _choose(self, walk: _Walk) -> Part | None:
        """The walk: for each component in order, the whole part (its Δ and its mean), else its remainder;
        a rotation narrowed to the axes that pass alone; at the judge too, then at the judge's scale."""
        if self.force:
            part = self.part(self.components[0])
            self._passes(walk, NETWORK, part)
            return part
        for component in self.components:
            for remainder in (False, True) if self.mean_test else (False,):
                part = self.part(component, remainder)
                if not self._passes(walk, NETWORK, part):
                    continue
                candidates = [part]
                if component == "rotation":
                    candidates = self._axes(walk, part) + candidates
                for candidate in candidates:
                    if not self.judge:
                        return candidate
                    if self._passes(walk, JUDGE, candidate):
                        return self._scaled(walk, candidate)
        return None

    def _consult(self, walk: _Walk, size: str, parts: list[Part]) -> None:
        walk.consulted += [(size, p) for p in parts]
        missing = tuple((size, p) for p in parts if (size, p) not in self._fed)
        if missing and not self.sequential:
            walk.missing = missing
            raise _Missing

    def _delta(self, size: str, part: Part) -> np.ndarray:
        return np.concatenate(self._fed[size, part])

    def _test(self, walk: _Walk, size: str, name: str, values: Callable[[], np.ndarray],
              alpha: float | None = None, note: str | None = "") -> tuple[bool, str]:
        """The test ``name`` at ``size`` → (accepted, its figure in words), said as the walk goes (with
        ``note`` after the name; None: not said)."""
        name = judge_test_name(name) if size == JUDGE else name
        if self.sequential:
            test = self.tests.get(name)
            passed, words = test is not None and test.accepted, f"{0 if test is None else test.pairs} pairs"
        else:
            result = paired_test(name, values(), self.alpha if alpha is None else alpha)
            walk.made[result.component] = result
            passed, words = result.passed, f"p = {result.p_value:.3g}"
        if note is not None:
            walk.said.append(f"{name}{note}: {words}" + ("" if passed else " (failed)"))
        return passed, words

    def _passes(self, walk: _Walk, size: str, part: Part) -> bool:
        """Whether ``part`` passes at ``size``: its Δ, and for a whole part (with ``mean_test``) its mean
        where :attr:`_mean` says it is tested."""
        mean = self._mean[size] if self.mean_test and not part.remainder else None
        rest = Part(part.component, True, part.scale, part.window, part.trailing)
        self._consult(walk, size, [part] if mean is None else [part, rest])
        passed, _ = self._test(walk, size, part.name, lambda: self._delta(size, part))
        if not passed or mean is None:
            return passed

        def differences() -> np.ndarray:
            whole = self._delta(size, part)
            return whole - self._delta(size, rest) + mean.margin * float(whole.mean())  # margin · gain

        note = f" (margin {mean.margin:g} of the gain)" if mean.margin else ""
        return self._test(walk, size, mean_test_name(part.name), differences, mean.alpha, note)[0]

    def _axes(self, walk: _Walk, part: Part) -> list[Part]:
        """The rotation about the axes whose part passes alone, when some but not all do and it passes
        its own tests (``[]`` otherwise)."""
        singles = [self.part(rotation_component(a), part.remainder) for a in AXES]
        self._consult(walk, NETWORK, singles)
        passing = "".join(a for a, single in zip(AXES, singles, strict=True)
                          if self._test(walk, NETWORK, single.name, partial(self._delta, NETWORK, single))[0])
        if passing in ("", AXES):
            return []
        subset = self.part(rotation_component(passing), part.remainder)
        walk.said.append(f"alone, only the rotation about {', '.join(passing)} passes")
        return [subset] if self._passes(walk, NETWORK, subset) else []

    def _scaled(self, walk: _Walk, part: Part) -> Part:
        """``part``, passed at both sizes, at the scale of :data:`JUDGE_SCALES` with the lowest mean Δ at
        the judge when that scale passes there."""
        scaled = [self.part(part.component, part.remainder, s) for s in JUDGE_SCALES]
        self._consult(walk, JUDGE, scaled)
        means = {p.scale: self._mean_delta(p) for p in scaled}
        best = min(means, key=lambda s: means[s])
        walk.said.append("mean Δ at the judge by scale: "
                         + ", ".join(f"×{s:g} {m:.3g}" for s, m in means.items()))
        if best == 1.0:
            return part
        candidate = self.part(part.component, part.remainder, best)
        passed, words = self._test(walk, JUDGE, candidate.name, lambda: self._delta(JUDGE, candidate),
                                   note=None)
        walk.said.append(f"applied ×{best:g} ({words})" if passed else f"×{best:g} did not pass ({words})")
        return candidate if passed else part

    def _mean_delta(self, part: Part) -> float:
        """Mean Δ of ``part`` at the judge over the pairs fed."""
        if self.sequential:
            test = self.tests.get(judge_test_name(part.name))
            return math.inf if test is None or not test.pairs else test.mean
        return float(self._delta(JUDGE, part).mean())


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
    trailing: bool = False,
    mean: MeanTest = MEAN_TESTS[DEFAULT_MEAN_TEST],
    force: bool = False,
) -> Acceptance:
    """What to apply of ``xi`` ``[M, 6]`` (module docstring): the fixed-sample :class:`Decision` fed
    every pair → :class:`Acceptance`. It measures only what the decision still needs: each time it
    stops at parts it has no Δ of, those are measured on all M pairs at once and fed.

    ``measure``: Δ ``[M]`` of named corrections ``[M, 6]`` on the M pairs at the network's size;
    ``components``: the components in order of preference (a subset of :data:`COMPONENTS`; a
    rotation-only run: ``("rotation",)``); ``tested``: the pairs the tests use (default all; after
    adaptation, the pairs it never saw; the mean is over all M pairs, as applied); ``judge``: the
    measurement at a larger size; ``mean_test``: test the mean apart (False: the earlier decision);
    ``window``: the pairs the moving mean is taken over, centred or ``trailing``; ``mean``: where and
    how the mean is tested (:class:`MeanTest`; with ``mean_test``); ``force``: apply the first
    component whole whatever the tests say (they are still made and recorded).
    """
    xi = np.asarray(xi, np.float64)
    decision = Decision(components=components, alpha=alpha, judge=judge is not None, mean_test=mean_test,
                        window=window, trailing=trailing, mean=mean, force=force)
    chosen = slice(None) if tested is None else np.asarray(tested)
    measures = {NETWORK: measure, JUDGE: judge}
    measured: dict[tuple[str, Part], np.ndarray] = {}
    while needs := decision.needs():
        fed: dict[str, dict[Part, np.ndarray]] = {NETWORK: {}, JUDGE: {}}
        for size, at in measures.items():
            parts = [p for s, p in needs if s == size]
            if parts and at is not None:
                got = at({p.name: p.of(xi) for p in parts})
                for p in parts:
                    measured[size, p] = np.asarray(got[p.name], np.float64)
                    fed[size][p] = measured[size, p][chosen]
        decision.update(fed[NETWORK], fed[JUDGE])
    outcome = decision.outcome
    part = outcome.part
    if part is None:
        return Acceptance(alpha, outcome.tests, "none", outcome.reason)
    where = JUDGE if judge is not None and not force else NETWORK
    return Acceptance(alpha, outcome.tests, part.component, outcome.reason, forced=force, scale=part.scale,
                      remainder=part.remainder, mean=tuple(float(v) for v in part.mean(xi)) if part.remainder
                      else None, window=part.window if part.remainder else None,
                      trailing=part.trailing and part.remainder, delta=measured[where, part])


def refused(acceptance: Acceptance, why: str) -> Acceptance:
    """``acceptance`` with nothing applied, for ``why`` (its tests kept)."""
    return Acceptance(acceptance.alpha, acceptance.tests, "none", f"{why}; {acceptance.reason}")
