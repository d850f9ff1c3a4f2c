"""Procedural town along a curving road (numpy; geometry only, textures live in ``textures``).

World frame: y points **down** (as in the KITTI camera frame), the ground is the plane y = 0,
so heights above the ground are ``−y``. The road's centreline lies in the x–z plane and is a chain
of *pieces*, each a straight segment or a circular arc, joined with continuous position and
heading. Heading ``ψ`` is measured from +z towards +x, so the forward direction is
``(sin ψ, 0, cos ψ)`` and the right-hand direction ``r(ψ) = (cos ψ, 0, −sin ψ)``.

Every point of the plane has road coordinates ``(s, l)`` relative to a piece: ``s`` the arc length
along the centreline, ``l`` the signed lateral offset (positive to the right). Facades are the
surfaces ``l = const`` of each piece (planes along straights, vertical cylinders along arcs), so
the street follows the curves exactly and adjacent pieces meet without seams.

Street cross-section (``l`` in metres): oncoming lane [−3.5, 0], ego lane [0, 3.5], parking lanes
to ±5.5, curb to ±5.75, sidewalk to the front facades (per side, 9.5–12 m), a second row of taller
buildings behind (10–16 m further out), visible through the gaps between front buildings and over
their roofs. Poles, trees and parked cars stand along both sides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LANE_OFFSET = 1.75
"""Lateral position (m) of a car driving in the ego lane; oncoming traffic uses ``−LANE_OFFSET``."""

CAR_BODY_BOTTOM, CAR_BODY_TOP, CAR_CABIN_TOP = 0.15, 1.0, 1.45
"""Heights (m) of the two boxes a car is made of."""


@dataclass(frozen=True)
class Road:
    """Chain of pieces; arrays ``[P]`` (float64): start point, heading, arc length, curvature.

    ``kappa`` is the signed curvature (1/m, positive turns right, 0 for straights).
    """

    x0: np.ndarray
    z0: np.ndarray
    psi0: np.ndarray
    s0: np.ndarray
    length: np.ndarray
    kappa: np.ndarray

    @property
    def total_length(self) -> float:
        return float(self.s0[-1] + self.length[-1])

    def piece_index(self, s: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.s0, s, side="right") - 1, 0, len(self.s0) - 1)

    def frame(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centreline at arc length ``s``: ``(x, z, ψ, κ)``, arrays shaped like ``s``."""
        s = np.asarray(s, np.float64)
        i = self.piece_index(s)
        ds = s - self.s0[i]
        k = self.kappa[i]
        psi0 = self.psi0[i]
        psi = psi0 + k * ds
        straight = np.abs(k) < 1e-12
        inv_k = np.where(straight, 0.0, 1.0 / np.where(straight, 1.0, k))
        # Arc: centre c = p0 + r(ψ0)/κ and p(s) = c − r(ψ(s))/κ.
        x_arc = self.x0[i] + inv_k * (np.cos(psi0) - np.cos(psi))
        z_arc = self.z0[i] + inv_k * (-np.sin(psi0) + np.sin(psi))
        x = np.where(straight, self.x0[i] + ds * np.sin(psi0), x_arc)
        z = np.where(straight, self.z0[i] + ds * np.cos(psi0), z_arc)
        return x, z, psi, k

    def point(self, s: np.ndarray, lateral: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World ``(x, z)`` of road coordinates ``(s, l = lateral)`` and the road heading there."""
        x, z, psi, _ = self.frame(s)
        return x + lateral * np.cos(psi), z - lateral * np.sin(psi), psi


def make_road(rng: np.random.Generator, length: float) -> Road:
    """Alternating straights (30–110 m) and arcs (radius 55–160 m, 20–55°) of at least ``length`` m.

    The heading stays within ±55° of the initial direction so that the street never folds back onto
    itself (no building of one stretch can stand in another stretch's road).
    """
    x, z, psi, s = 0.0, 0.0, 0.0, 0.0
    rows = []
    straight = True
    first = True
    while s < length:
        if straight:
            seg = rng.uniform(60.0, 110.0) if first else rng.uniform(30.0, 110.0)
            rows.append((x, z, psi, s, seg, 0.0))
            x, z = x + seg * np.sin(psi), z + seg * np.cos(psi)
        else:
            radius = rng.uniform(55.0, 160.0)
            angle = np.deg2rad(rng.uniform(20.0, 55.0))
            sign = rng.choice([-1.0, 1.0])
            if abs(psi + sign * angle) > np.deg2rad(55.0):
                sign = -sign
            k = sign / radius
            seg = angle * radius
            rows.append((x, z, psi, s, seg, k))
            psi_end = psi + k * seg
            x, z = x + (np.cos(psi) - np.cos(psi_end)) / k, z + (np.sin(psi_end) - np.sin(psi)) / k
            psi = psi_end
        s += seg
        straight = not straight
        first = False
    a = np.asarray(rows, np.float64)
    return Road(*(a[:, j].copy() for j in range(6)))


@dataclass(frozen=True)
class Layout:
    """Everything static along one road.

    * ``layers [4, 6]``: facade rows (right front, left front, right back, left back):
      signed offset ``l`` (m), building module length (m), minimum and maximum height (m),
      probability of a gap, hash seed.
    * ``cylinders [N, 6]``: vertical cylinders standing on the ground (poles, tree trunks):
      ``s, x, z, radius, height, kind`` (0 pole, 1 trunk); sorted by ``s``.
    * ``spheres [N, 6]``: tree crowns ``s, x, y, z, radius, seed``; sorted by ``s``.
    * ``cars [N, 7]``: parked cars ``s, x, z, heading, half length, half width, seed``; sorted by ``s``.
    * ``sun [3]``: unit vector towards the sun (world frame, y down).
    """

    road: Road
    layers: np.ndarray
    cylinders: np.ndarray
    spheres: np.ndarray
    cars: np.ndarray
    sun: np.ndarray


def _positions(rng: np.random.Generator, length: float, step: tuple[float, float],
               keep: float) -> np.ndarray:
    s = np.cumsum(rng.uniform(*step, size=int(length / step[0]) + 2))
    s = s[s < length]
    return s[rng.random(len(s)) < keep]


def make_layout(rng: np.random.Generator, length: float) -> Layout:
    """Random town along a new road of at least ``length`` m (see the module docstring)."""
    road = make_road(rng, length)
    total = road.total_length
    front = rng.uniform(9.5, 12.0, size=2)
    back = front + rng.uniform(10.0, 16.0, size=2)
    layers = np.array([
        [front[0], rng.uniform(8.0, 14.0), 5.0, 16.0, 0.18, 101],
        [-front[1], rng.uniform(8.0, 14.0), 5.0, 16.0, 0.18, 102],
        [back[0], rng.uniform(12.0, 20.0), 10.0, 28.0, 0.08, 103],
        [-back[1], rng.uniform(12.0, 20.0), 10.0, 28.0, 0.08, 104],
    ])
    layers[:, 5] += rng.integers(0, 1 << 20, size=4) * 8

    cyl, sph, cars = [], [], []
    for side in (1.0, -1.0):
        s = _positions(rng, total, (18.0, 32.0), 0.9)
        x, z, _ = road.point(s, side * rng.uniform(5.85, 6.05, size=len(s)))
        cyl.append(np.stack([s, x, z, rng.uniform(0.09, 0.14, len(s)), rng.uniform(5.0, 7.5, len(s)),
                             np.zeros(len(s))], 1))
        facade = front[0] if side > 0 else front[1]
        s = _positions(rng, total, (10.0, 26.0), 0.8)
        l_tree = side * (facade - rng.uniform(2.2, 3.0, size=len(s)))
        x, z, _ = road.point(s, l_tree)
        radius = rng.uniform(1.2, 2.0, len(s))
        cyl.append(np.stack([s, x, z, np.full(len(s), 0.18), np.full(len(s), 3.0), np.ones(len(s))], 1))
        sph.append(np.stack([s, x, -(2.6 + radius * rng.uniform(0.8, 1.1, len(s))), z, radius,
                             rng.integers(0, 1 << 20, len(s))], 1))
        half_len = rng.uniform(1.9, 2.4, size=int(total / 5.0) + 2)
        gaps = np.where(rng.random(len(half_len)) < 0.3, rng.uniform(5.0, 15.0, len(half_len)),
                        rng.uniform(0.8, 3.0, len(half_len)))
        s = np.cumsum(2 * half_len + gaps)
        keep = s < total
        s, half_len = s[keep], half_len[keep]
        x, z, psi = road.point(s, side * rng.uniform(4.45, 4.65, len(s)))
        psi = psi + rng.uniform(-0.04, 0.04, len(s)) + (np.pi if rng.random() < 0.5 else 0.0)
        cars.append(np.stack([s, x, z, psi, half_len, rng.uniform(0.85, 0.95, len(s)),
                              rng.integers(0, 1 << 20, len(s))], 1))

    def sort(parts: list[np.ndarray]) -> np.ndarray:
        a = np.concatenate(parts, 0)
        return a[np.argsort(a[:, 0], kind="stable")]

    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.deg2rad(rng.uniform(30.0, 60.0))
    sun = np.array([np.cos(elevation) * np.sin(azimuth), -np.sin(elevation),
                    np.cos(elevation) * np.cos(azimuth)])
    return Layout(road, layers, sort(cyl), sort(sph), sort(cars), sun)
