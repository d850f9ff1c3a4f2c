"""The primitives of the synthetic town as the renderer sees them (jitted JAX): the frame's tables
(:class:`FrameScene`), world rays (:class:`Rays`), the surface kinds, and the analytic ray
intersections with each primitive, with the scan that keeps the nearest over a table.

Primitives: the ground plane, the facade surfaces of the road pieces near the camera (planes along
straights, vertical cylinders along arcs, cut to building outlines), vertical cylinders (poles,
trunks), spheres (tree crowns) and oriented boxes (cars, two per car). The ray parameter ``t`` is
the z-depth in the camera frame (see :mod:`dpc_jax.synth.render`). The road pieces'
parametrisations (arc length along straights and arcs, the facade parameter) are here too: the
renderer's surface coordinates use them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple, cast

import jax
import jax.numpy as jnp
from jax import Array

from dpc_jax.synth import textures as tx
from dpc_jax.synth.world import CAR_BODY_BOTTOM, CAR_BODY_TOP, CAR_CABIN_TOP

NEAR = 0.05
"""Hits closer than this (m, ray parameter = camera depth) are ignored."""
_SEAM = 2e-3
"""Facades extend this far (m) past the ends of their road piece, so that rounding cannot open a
crack where two pieces meet (the surfaces coincide there)."""

# Kinds of surface; their order breaks ties.
SKY, GROUND, FACADE, CYLINDER, SPHERE, CAR = 0, 1, 2, 3, 4, 5
# Cabin box along the car (fractions of the half length) and across (fraction of the half width).
_CABIN_A = (-0.6, 0.4)
_CABIN_B = 0.9
_UNROLL = 4

Row = Array | Sequence[Array]
"""One row of a table: the array itself, or its columns as gathered per pixel by :func:`_rows`."""


class FrameScene(NamedTuple):
    """Primitives visible from one frame (float32 tables of fixed sizes; see :mod:`world`).

    * ``straights [PS, 6]`` and ``arcs [PA, 6]``: road pieces ``x0, z0, ψ0, s0, length, κ``
      (unused slots have length 0).
    * ``layers [4, 6]``: facade rows ``offset, module, h_min, h_max, gap probability, seed``.
    * ``cylinders [NC, 6]``: ``s, x, z, radius, height, kind``.
    * ``spheres [NS, 6]``: ``s, x, y, z, radius, seed``.
    * ``cars [NK, 8]``: ``s, x, z, heading, half length, half width, seed, moving`` (parked cars
      first, then moving ones).
    * ``sun [3]``: unit vector towards the sun.
    """

    straights: Array
    arcs: Array
    layers: Array
    cylinders: Array
    spheres: Array
    cars: Array
    sun: Array


class Rays(NamedTuple):
    ox: Array
    oy: Array
    oz: Array
    dx: Array
    dy: Array
    dz: Array


def safe_inv(d: Array) -> Array:
    return 1.0 / jnp.where(jnp.abs(d) < 1e-12, 1e-12, d)


def _building_height(u: Array, layer: Array) -> Array:
    """Height (m) of the building of facade row ``layer`` at centreline arc length ``u``; 0 in a gap."""
    k = jnp.floor(u * (1.0 / layer[1])).astype(jnp.int32)
    seed = layer[5].astype(jnp.int32)
    h = layer[2] + (layer[3] - layer[2]) * tx.hash3(k, seed, 92)
    return jnp.where(tx.hash3(k, seed, 91) < layer[4], 0.0, h)


def _facade_ok(r: Rays, t: Array, s_loc: Array, piece: Array, layer: Array) -> Array:
    qy = r.oy + t * r.dy
    height = _building_height(piece[3] + s_loc, layer)
    return (t > NEAR) & (s_loc >= -_SEAM) & (s_loc < piece[4] + _SEAM) & (qy <= 0) & (-qy < height)


_ATAN_POLY = (0.9999999582162316, -0.3333230282580835, 0.19973680314608708, -0.14040128648339056,
              0.09967885269468028, -0.060218447732536755, 0.024756206574704478, -0.004830982786439864)


def atan2(y: Array, x: Array) -> Array:
    """``arctan2`` by an odd minimax-style polynomial (error < 2e-7 rad in float32).

    XLA's CPU ``atan2`` is a scalar library call that does not vectorise, unlike this form; the
    small error is irrelevant because angles only parametrise surfaces (a fixed, view-independent
    reparametrisation) and piece ranges overlap by :data:`_SEAM`.
    """
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi, lo = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    a = lo / jnp.where(hi > 0, hi, 1.0)
    s = a * a
    p = jnp.zeros_like(s) + _ATAN_POLY[-1]
    for c in _ATAN_POLY[-2::-1]:
        p = p * s + c
    p = p * a
    p = jnp.where(ay > ax, 0.5 * jnp.pi - p, p)
    p = jnp.where(x < 0, jnp.pi - p, p)
    return jnp.where(y < 0, -p, p)


def _wrap(a: Array) -> Array:
    return a - 2 * jnp.pi * jnp.floor((a + jnp.pi) / (2 * jnp.pi))


def extend_pieces(pieces: Array) -> Array:
    """Append derived columns to piece rows ``[P, 6]`` → ``[P, 13]``: ``sin ψ0, cos ψ0``, arc centre
    ``cx, cz``, turn sign ``σ``, radius and ``tan`` of the arc angle (so that per-pixel code that
    looks a piece up never evaluates trigonometric functions)."""
    psi, k, length = pieces[:, 2], pieces[:, 5], pieces[:, 4]
    sin0, cos0 = jnp.sin(psi), jnp.cos(psi)
    inv_k = 1.0 / jnp.where(k == 0, 1.0, k)
    tan_end = jnp.tan(jnp.abs(k) * length)
    extra = [sin0, cos0, pieces[:, 0] + cos0 * inv_k, pieces[:, 1] - sin0 * inv_k, jnp.sign(k),
             jnp.abs(inv_k), jnp.where(tan_end > 0, tan_end, 1.0)]
    return jnp.concatenate([pieces, jnp.stack(extra, 1)], 1)


def arc_centre(piece: Row) -> tuple[Array, Array, Array, Array]:
    return piece[8], piece[9], piece[10], piece[11]


def arc_s(qx: Array, qz: Array, piece: Array) -> Array:
    """Local arc length of the point ``(qx, qz)`` on arc ``piece`` (by its polar angle)."""
    cx, cz, sigma, radius = arc_centre(piece)
    ang = atan2(sigma * (qz - cz), -sigma * (qx - cx))
    return sigma * _wrap(ang - piece[2]) * radius


def straight_local(qx: Array, qz: Array, piece: Row) -> tuple[Array, Array]:
    fx, fz = piece[6], piece[7]
    ex, ez = qx - piece[0], qz - piece[1]
    return ex * fx + ez * fz, ex * fz - ez * fx


def _closer(best: tuple[Array, Array], t: Array, index: Array | int) -> tuple[Array, Array]:
    closer = t < best[0]
    return jnp.where(closer, t, best[0]), jnp.where(closer, index, best[1])


def straight_facades_t(r: Rays, piece: Array, layers: Array) -> tuple[Array, Array]:
    """Nearest hit on the facade rows of a straight piece (planes ``l = offset``) and its row.

    The rows share the plane normal, so the per-pixel projections are computed once per piece.
    """
    fx, fz = piece[6], piece[7]
    inv_den = safe_inv(r.dx * fz - r.dz * fx)  # direction · r(ψ0), r = (cos ψ0, −sin ψ0)
    ex, ez = r.ox - piece[0], r.oz - piece[1]
    o_lat, o_s = ex * fz - ez * fx, ex * fx + ez * fz
    d_s = r.dx * fx + r.dz * fz
    best = (jnp.full(jnp.shape(inv_den * o_lat), jnp.inf, jnp.float32), jnp.zeros((), jnp.int32))
    for j in range(layers.shape[0]):
        t = (layers[j, 0] - o_lat) * inv_den
        ok = _facade_ok(r, t, o_s + t * d_s, piece, layers[j])
        best = _closer(best, jnp.where(ok, t, jnp.inf), j)
    return best


def arc_param(qx: Array, qz: Array, piece: Row) -> tuple[Array, Array]:
    """Facade parameter along arc ``piece`` and whether the point lies in the arc's sector.

    The parameter is ``length · tan α / tan Θ`` (α the angle from the start radius, Θ the arc's
    angle): monotonic, exact at both ends (so facades continue the neighbouring pieces' arc length
    without a jump) and free of an arctangent, which the intersection loop would pay for per ray and
    surface. Facade textures and building outlines use it, the ground uses the true arc length.
    """
    cx, cz, sigma, _ = arc_centre(piece)
    fx, fz = piece[6], piece[7]
    vx, vz = qx - cx, qz - cz
    x = -sigma * (vx * fz - vz * fx)  # along the start radius (centre → start point)
    y = vx * fx + vz * fz  # along the start tangent
    param = (piece[4] / piece[12]) * y / jnp.where(x > 0, x, 1.0)
    return param, x > 0


def arc_facades_t(r: Rays, a_xz: Array, piece: Array, layers: Array) -> tuple[Array, Array]:
    """Nearest hit on the facade rows of an arc piece (vertical cylinders about the arc's centre).

    Inside a cylinder (the outer facade) only the far root lies ahead; outside it (the inner
    facade) the near root is the visible side (the far one is the inside of the building block).
    The facade parameter (see :func:`arc_param`) is linear in ``t`` in its two components, whose
    per-pixel parts are shared by the rows.
    """
    cx, cz, sigma, radius = arc_centre(piece)
    fx, fz = piece[6], piece[7]
    ex, ez = r.ox - cx, r.oz - cz
    b = ex * r.dx + ez * r.dz
    e2 = ex * ex + ez * ez
    inv_a = safe_inv(a_xz)
    x0, dx0 = -sigma * (ex * fz - ez * fx), -sigma * (r.dx * fz - r.dz * fx)
    y0, dy0 = ex * fx + ez * fz, r.dx * fx + r.dz * fz
    best = (jnp.full(jnp.shape(b * x0), jnp.inf, jnp.float32), jnp.zeros((), jnp.int32))
    for j in range(layers.shape[0]):
        rho = radius - sigma * layers[j, 0]
        c = e2 - rho * rho
        disc = b * b - a_xz * c
        t = (-b + jnp.where(c < 0, 1.0, -1.0) * jnp.sqrt(jnp.maximum(disc, 0.0))) * inv_a
        x = x0 + t * dx0
        param = (piece[4] / piece[12]) * (y0 + t * dy0) / jnp.where(x > 0, x, 1.0)
        ok = (disc >= 0) & (x > 0) & _facade_ok(r, t, param, piece, layers[j])
        best = _closer(best, jnp.where(ok, t, jnp.inf), j)
    return best


def cylinder_t(r: Rays, a_xz: Array, cyl: Array) -> Array:
    ex, ez = r.ox - cyl[1], r.oz - cyl[2]
    b = ex * r.dx + ez * r.dz
    c = ex * ex + ez * ez - cyl[3] * cyl[3]
    disc = b * b - a_xz * c
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) * safe_inv(a_xz)
    qy = r.oy + t * r.dy
    return jnp.where((disc >= 0) & (t > NEAR) & (qy <= 0) & (-qy <= cyl[4]), t, jnp.inf)


def sphere_t(r: Rays, a3: Array, sph: Array) -> Array:
    ex, ey, ez = r.ox - sph[1], r.oy - sph[2], r.oz - sph[3]
    b = ex * r.dx + ey * r.dy + ez * r.dz
    c = ex * ex + ey * ey + ez * ez - sph[4] * sph[4]
    disc = b * b - a3 * c
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / a3
    return jnp.where((disc >= 0) & (t > NEAR), t, jnp.inf)


def car_frame(r: Rays, car: Array) -> tuple[Array, Array, Array, Array]:
    fx, fz = jnp.sin(car[3]), jnp.cos(car[3])
    ex, ez = r.ox - car[1], r.oz - car[2]
    return ex * fx + ez * fz, ex * fz - ez * fx, r.dx * fx + r.dz * fz, r.dx * fz - r.dz * fx


def car_boxes(car: Row) -> tuple[tuple[Array | float, ...], tuple[Array | float, ...]]:
    hl, hw = car[4], car[5]
    body = (-hl, hl, -hw, hw, -CAR_BODY_TOP, -CAR_BODY_BOTTOM)
    cabin = (_CABIN_A[0] * hl, _CABIN_A[1] * hl, -_CABIN_B * hw, _CABIN_B * hw, -CAR_CABIN_TOP, -CAR_BODY_TOP)
    return body, cabin


def slab(
    oa: Array, ob: Array, oy: Array, ia: Array, ib: Array, iy: Array, box: tuple[Array | float, ...]
) -> Array:
    ta0, ta1 = (box[0] - oa) * ia, (box[1] - oa) * ia
    tb0, tb1 = (box[2] - ob) * ib, (box[3] - ob) * ib
    ty0, ty1 = (box[4] - oy) * iy, (box[5] - oy) * iy
    lo = jnp.maximum(jnp.maximum(jnp.minimum(ta0, ta1), jnp.minimum(tb0, tb1)), jnp.minimum(ty0, ty1))
    hi = jnp.minimum(jnp.minimum(jnp.maximum(ta0, ta1), jnp.maximum(tb0, tb1)), jnp.maximum(ty0, ty1))
    return jnp.where((hi >= lo) & (lo > NEAR), lo, jnp.inf)


def nearest(
    table: Array, hit_t: Callable[[Array], Array | tuple[Array, Array]], parts: int = 0
) -> tuple[Array, Array]:
    """Scan ``hit_t(row) -> t [pixels]`` over the rows of ``table``: nearest ``t`` and its row index.

    With ``parts > 0``, ``hit_t`` returns ``(t, part)`` for a row made of that many surfaces, and
    the index is ``row · parts + part``.
    """

    def body(carry: tuple[Array, Array], row: tuple[Array, Array]) -> tuple[tuple[Array, Array], None]:
        if parts:
            t, part = hit_t(row[1])
            return _closer(carry, t, row[0] * parts + part), None
        # Without parts, hit_t returns t alone (the docstring's contract; the type can't say so).
        return _closer(carry, cast(Array, hit_t(row[1])), row[0]), None

    shape = jax.eval_shape(lambda row: hit_t(row)[0] if parts else hit_t(row), table[0]).shape
    init = (jnp.full(shape, jnp.inf, jnp.float32), jnp.zeros(shape, jnp.int32))
    rows = (jnp.arange(table.shape[0], dtype=jnp.int32), table)
    (best, idx), _ = jax.lax.scan(body, init, rows, unroll=1 if parts else _UNROLL)
    return best, idx
