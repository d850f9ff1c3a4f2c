"""The parts of a network's correction ξ: which entries are applied, whole or without their moving mean,
at a scale (``dpc_jax.correction.decision`` decides which part to apply; this says what each is).

A *component* of ξ = ``[ρ, φ]`` is which entries are applied: ``full`` (6-DoF), ``rotation`` (φ only)
or ``rotation_<axes>`` (the rotation about some camera axes). A :class:`Part` takes a component whole
(``ξ ⊙ m``) or as its *remainder* ``ξ ⊙ m − mean_W(ξ ⊙ m)`` (its moving mean over ``window`` pairs
removed, centred or trailing: :func:`moving_mean`), times a scale. :func:`part_of` is the one
implementation of what is applied, offline and live.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dpc_jax.results.acceptance import Acceptance, part_name

AXES = "xyz"  # camera axes: x right (pitch), y down (yaw), z forward (roll)
# Pairs the mean of a correction is taken over: well under the shortest segment the segment errors
# measure (100 m, about 100 frames at KITTI's speeds), so that a remainder drifts over none of them.
MEAN_WINDOW = 50


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
    pairs removed: centred, or with ``trailing`` over the pairs up to each one), times a scale."""

    component: str
    remainder: bool = False
    scale: float = 1.0
    window: int = MEAN_WINDOW
    trailing: bool = False

    @property
    def name(self) -> str:
        """Its one name (:func:`~dpc_jax.results.acceptance.part_name`): ``rotation_xz − mean ×0.5``."""
        return part_name(self.component, self.remainder, self.scale)

    def of(self, xi: np.ndarray) -> np.ndarray:
        """This part of ``xi`` ``[M, 6]`` → ``[M, 6]`` float64."""
        return part_of(xi, self.component, self.remainder, self.scale, self.window, self.trailing)

    def mean(self, xi: np.ndarray) -> np.ndarray:
        """The mean ``[6]`` over all the pairs of the component's entries of ``xi``."""
        return (np.asarray(xi, np.float64) * component_mask(self.component)).mean(axis=0)


def moving_mean(x: np.ndarray, window: int = MEAN_WINDOW, trailing: bool = False) -> np.ndarray:
    """The centred moving mean ``[M, ...]`` of ``x`` ``[M, ...]`` over ``window`` consecutive rows: row k
    the mean of rows ``[k − ⌊window/2⌋, k + ⌈window/2⌉)``, cut to the rows there are (at the ends and
    in a sequence shorter than the window, the mean of fewer rows; the whole mean when ``M ≤
    window/2``). ``trailing``: the mean of rows ``[k − window + 1, k]`` instead, what is known at row
    k while the rows arrive (the live corrector's)."""
    x = np.asarray(x, np.float64)
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    m = x.shape[0]
    sums = np.concatenate([np.zeros((1, *x.shape[1:])), np.cumsum(x, axis=0)])
    before = window - 1 if trailing else window // 2
    start = np.clip(np.arange(m) - before, 0, m)
    stop = np.clip(np.arange(m) + window - before, 0, m)
    shape = (m,) + (1,) * (x.ndim - 1)
    return (sums[stop] - sums[start]) / (stop - start).reshape(shape)


def part_of(xi: np.ndarray, component: str, remainder: bool = False, scale: float = 1.0,
            window: int = MEAN_WINDOW, trailing: bool = False) -> np.ndarray:
    """``scale · (ξ ⊙ m − [mean])`` → ``[M, 6]`` float64, ``m`` the mask of ``component``.

    ``xi``: ``[M, 6]`` corrections ``[ρ (m), φ (rad)]``; with ``remainder`` the moving mean of
    ``ξ ⊙ m`` over ``window`` pairs (:func:`moving_mean`, centred or ``trailing``) is removed. The one
    implementation of "what is applied" (offline and live: the live corrector's pair is the last row
    of its last ``window`` corrections, with the trailing mean).
    """
    xi = np.asarray(xi, np.float64)
    if xi.ndim != 2 or xi.shape[1] != 6:
        raise ValueError(f"xi must be [M, 6], got {xi.shape}")
    masked = xi * component_mask(component)
    if remainder:
        masked = masked - moving_mean(masked, window, trailing)
    return scale * masked


def applied_correction(xi: np.ndarray, acceptance: Acceptance) -> np.ndarray:
    """The correction ``[M, 6]`` that ``acceptance`` applies to the proposal ``xi`` (zeros for none)."""
    return part_of(xi, acceptance.component, acceptance.remainder, acceptance.scale,
                   acceptance.window or MEAN_WINDOW, acceptance.trailing)
