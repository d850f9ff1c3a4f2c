"""Exact ray casting of the synthetic town (jitted JAX).

Every pixel's ray (through the pixel centre; pixel centres at integer coordinates) is intersected
analytically with all primitives of the frame's :class:`FrameScene`: the ground plane, the facade
surfaces of the road pieces near the camera (planes along straights, vertical cylinders along arcs,
cut to building outlines), vertical cylinders (poles, trunks), spheres (tree crowns) and oriented
boxes (cars, two per car). The nearest hit wins; rays that hit nothing see the sky (at infinity).

Rays are parametrised so that the ray parameter is the z-depth in the camera frame: the direction
is ``R_wc K⁻¹ [u, v, 1]ᵀ``, hence ``t`` of the hit *is* the depth map. Colour = albedo from
:mod:`textures` (a function of surface coordinates) × Lambertian shading with a fixed sun (a function
of the surface normal), both view-independent, so a static world point looks the same from every
camera. Only the band-limiting footprint depends on the view (see :mod:`textures`).

The primitive loops are ``lax.scan`` over parameter tables (fixed sizes, so one compilation per
image size) that carry only the nearest distance and primitive index; surface attributes are then
recomputed once per pixel for the winning primitive of each kind.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
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


def _safe_inv(d: Array) -> Array:
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


def _atan2(y: Array, x: Array) -> Array:
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


def _extend_pieces(pieces: Array) -> Array:
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


def _arc_centre(piece: Row) -> tuple[Array, Array, Array, Array]:
    return piece[8], piece[9], piece[10], piece[11]


def _arc_s(qx: Array, qz: Array, piece: Array) -> Array:
    """Local arc length of the point ``(qx, qz)`` on arc ``piece`` (by its polar angle)."""
    cx, cz, sigma, radius = _arc_centre(piece)
    ang = _atan2(sigma * (qz - cz), -sigma * (qx - cx))
    return sigma * _wrap(ang - piece[2]) * radius


def _straight_local(qx: Array, qz: Array, piece: Row) -> tuple[Array, Array]:
    fx, fz = piece[6], piece[7]
    ex, ez = qx - piece[0], qz - piece[1]
    return ex * fx + ez * fz, ex * fz - ez * fx


def _closer(best: tuple[Array, Array], t: Array, index: Array | int) -> tuple[Array, Array]:
    closer = t < best[0]
    return jnp.where(closer, t, best[0]), jnp.where(closer, index, best[1])


def _straight_facades_t(r: Rays, piece: Array, layers: Array) -> tuple[Array, Array]:
    """Nearest hit on the facade rows of a straight piece (planes ``l = offset``) and its row.

    The rows share the plane normal, so the per-pixel projections are computed once per piece.
    """
    fx, fz = piece[6], piece[7]
    inv_den = _safe_inv(r.dx * fz - r.dz * fx)  # direction · r(ψ0), r = (cos ψ0, −sin ψ0)
    ex, ez = r.ox - piece[0], r.oz - piece[1]
    o_lat, o_s = ex * fz - ez * fx, ex * fx + ez * fz
    d_s = r.dx * fx + r.dz * fz
    best = (jnp.full(jnp.shape(inv_den * o_lat), jnp.inf, jnp.float32), jnp.zeros((), jnp.int32))
    for j in range(layers.shape[0]):
        t = (layers[j, 0] - o_lat) * inv_den
        ok = _facade_ok(r, t, o_s + t * d_s, piece, layers[j])
        best = _closer(best, jnp.where(ok, t, jnp.inf), j)
    return best


def _arc_param(qx: Array, qz: Array, piece: Row) -> tuple[Array, Array]:
    """Facade parameter along arc ``piece`` and whether the point lies in the arc's sector.

    The parameter is ``length · tan α / tan Θ`` (α the angle from the start radius, Θ the arc's
    angle): monotonic, exact at both ends (so facades continue the neighbouring pieces' arc length
    without a jump) and free of an arctangent, which the intersection loop would pay for per ray and
    surface. Facade textures and building outlines use it, the ground uses the true arc length.
    """
    cx, cz, sigma, _ = _arc_centre(piece)
    fx, fz = piece[6], piece[7]
    vx, vz = qx - cx, qz - cz
    x = -sigma * (vx * fz - vz * fx)  # along the start radius (centre → start point)
    y = vx * fx + vz * fz  # along the start tangent
    param = (piece[4] / piece[12]) * y / jnp.where(x > 0, x, 1.0)
    return param, x > 0


def _arc_facades_t(r: Rays, a_xz: Array, piece: Array, layers: Array) -> tuple[Array, Array]:
    """Nearest hit on the facade rows of an arc piece (vertical cylinders about the arc's centre).

    Inside a cylinder (the outer facade) only the far root lies ahead; outside it (the inner
    facade) the near root is the visible side (the far one is the inside of the building block).
    The facade parameter (see :func:`_arc_param`) is linear in ``t`` in its two components, whose
    per-pixel parts are shared by the rows.
    """
    cx, cz, sigma, radius = _arc_centre(piece)
    fx, fz = piece[6], piece[7]
    ex, ez = r.ox - cx, r.oz - cz
    b = ex * r.dx + ez * r.dz
    e2 = ex * ex + ez * ez
    inv_a = _safe_inv(a_xz)
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


def _cylinder_t(r: Rays, a_xz: Array, cyl: Array) -> Array:
    ex, ez = r.ox - cyl[1], r.oz - cyl[2]
    b = ex * r.dx + ez * r.dz
    c = ex * ex + ez * ez - cyl[3] * cyl[3]
    disc = b * b - a_xz * c
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) * _safe_inv(a_xz)
    qy = r.oy + t * r.dy
    return jnp.where((disc >= 0) & (t > NEAR) & (qy <= 0) & (-qy <= cyl[4]), t, jnp.inf)


def _sphere_t(r: Rays, a3: Array, sph: Array) -> Array:
    ex, ey, ez = r.ox - sph[1], r.oy - sph[2], r.oz - sph[3]
    b = ex * r.dx + ey * r.dy + ez * r.dz
    c = ex * ex + ey * ey + ez * ez - sph[4] * sph[4]
    disc = b * b - a3 * c
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / a3
    return jnp.where((disc >= 0) & (t > NEAR), t, jnp.inf)


def _car_frame(r: Rays, car: Array) -> tuple[Array, Array, Array, Array]:
    fx, fz = jnp.sin(car[3]), jnp.cos(car[3])
    ex, ez = r.ox - car[1], r.oz - car[2]
    return ex * fx + ez * fz, ex * fz - ez * fx, r.dx * fx + r.dz * fz, r.dx * fz - r.dz * fx


def _car_boxes(car: Row) -> tuple[tuple[Array | float, ...], tuple[Array | float, ...]]:
    hl, hw = car[4], car[5]
    body = (-hl, hl, -hw, hw, -CAR_BODY_TOP, -CAR_BODY_BOTTOM)
    cabin = (_CABIN_A[0] * hl, _CABIN_A[1] * hl, -_CABIN_B * hw, _CABIN_B * hw, -CAR_CABIN_TOP, -CAR_BODY_TOP)
    return body, cabin


def _slab(
    oa: Array, ob: Array, oy: Array, ia: Array, ib: Array, iy: Array, box: tuple[Array | float, ...]
) -> Array:
    ta0, ta1 = (box[0] - oa) * ia, (box[1] - oa) * ia
    tb0, tb1 = (box[2] - ob) * ib, (box[3] - ob) * ib
    ty0, ty1 = (box[4] - oy) * iy, (box[5] - oy) * iy
    lo = jnp.maximum(jnp.maximum(jnp.minimum(ta0, ta1), jnp.minimum(tb0, tb1)), jnp.minimum(ty0, ty1))
    hi = jnp.minimum(jnp.minimum(jnp.maximum(ta0, ta1), jnp.maximum(tb0, tb1)), jnp.maximum(ty0, ty1))
    return jnp.where((hi >= lo) & (lo > NEAR), lo, jnp.inf)


def _nearest(
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


def _rows(table: Array, index: Array) -> list[Array]:
    """Columns of ``table[index]``: one 1-D gather per column (each a contiguous output)."""
    return [jnp.take(table[:, j], index, mode="clip") for j in range(table.shape[1])]


def _footprint(u: Array, v: Array) -> Array:
    """Texture footprint (m per pixel) from finite differences of the surface coordinates.

    Of the backward and forward difference along each image axis the smaller is used, so that
    a depth edge (where one neighbour lies on another surface) does not blur the texture.
    """

    def axis_fp(a: Array, axis: int) -> Array:
        d = jnp.abs(jnp.diff(a, axis=axis))
        pad_lo = [(0, 0)] * a.ndim
        pad_hi = [(0, 0)] * a.ndim
        pad_lo[axis] = (1, 0)
        pad_hi[axis] = (0, 1)
        back = jnp.pad(d, pad_lo, mode="edge")
        fwd = jnp.pad(d, pad_hi, mode="edge")
        return jnp.minimum(back, fwd)

    fp = jnp.maximum(jnp.maximum(axis_fp(u, -1), axis_fp(u, -2)), jnp.maximum(axis_fp(v, -1), axis_fp(v, -2)))
    return jnp.clip(jnp.where(jnp.isfinite(fp), fp, 1e3), 1e-5, 1e3)


def camera_rays(K: Array, height: int, width: int) -> Array:
    """Camera-frame ray directions ``[H, W, 3]`` with unit z (pixel centres at integers)."""
    v, u = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32), jnp.arange(width, dtype=jnp.float32),
                        indexing="ij")
    return jnp.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], jnp.ones_like(u)], -1)


class Surface(NamedTuple):
    """Per-pixel result of the geometry stage, ``[2, H, W]`` each (left, right camera).

    ``kind`` (see the constants), ``depth`` (m, ``inf`` = sky), texture coordinates ``u, v`` (m) and
    noise ``seed`` of the visible surface (for the ground ``u, v`` are the road coordinates
    ``s, l``), the unit ``normal`` (3 arrays), and the further inputs of each material's albedo
    (only meaningful where that material is visible).
    """

    kind: Array
    depth: Array
    u: Array
    v: Array
    seed: Array
    normal: tuple[Array, Array, Array]
    moving: Array
    up: Array
    height: Array
    building: Array
    layer_seed: Array
    cylinder_kind: Array
    sphere_seed: Array
    car_a: Array
    car_b: Array
    car_face: Array
    car_cabin: Array
    car_half_len: Array
    car_seed: Array


def _rays(pose: Array, K: Array, baseline: Array, height: int, width: int, right_shift: Array) -> Rays:
    """World rays of both cameras; the right camera's principal point is ``right_shift`` px left of
    ``K``'s (a calibration residual: measured disparities are ``right_shift`` px larger)."""
    f32 = jnp.float32
    pose = pose.astype(f32)
    rot = pose[:3, :3]
    K = K.astype(f32)
    cam = camera_rays(K, height, width)
    cam = jnp.stack([cam, cam.at[..., 0].add(right_shift.astype(f32) / K[0, 0])])
    # Written out: as a matrix product XLA hands this to a library call that is slower here.
    dirs = cam[..., 0:1] * rot[:, 0] + cam[..., 1:2] * rot[:, 1] + cam[..., 2:3] * rot[:, 2]
    origins = jnp.stack([pose[:3, 3], pose[:3, 3] + baseline.astype(f32) * rot[:, 0]])
    o = origins[:, None, None, :]
    return Rays(o[..., 0], o[..., 1], o[..., 2], dirs[..., 0], dirs[..., 1], dirs[..., 2])


class Hits(NamedTuple):
    """Nearest hit per pixel ``[2, H, W]``: surface kind, depth, and the winning primitive's row in
    the facade (straights then arcs, × rows), cylinder, sphere and car tables."""

    kind: Array
    depth: Array
    facade: Array
    cylinder: Array
    sphere: Array
    car: Array


@partial(jax.jit, static_argnames=("height", "width"))
def nearest_hits(scene: FrameScene, pose: Array, K: Array, baseline: Array, right_shift: Array, *,
                 height: int, width: int) -> Hits:
    """Visibility: the nearest surface along every ray of both cameras."""
    r = _rays(pose, K, baseline, height, width, right_shift)
    a_xz = r.dx * r.dx + r.dz * r.dz
    a3 = a_xz + r.dy * r.dy
    n_straight = scene.straights.shape[0] * scene.layers.shape[0]

    t_ground = jnp.where(r.dy > 0, -r.oy * _safe_inv(r.dy), jnp.inf) + jnp.zeros_like(a_xz)
    t_ground = jnp.where(t_ground > NEAR, t_ground, jnp.inf)
    rows = scene.layers.shape[0]
    t_fs, i_fs = _nearest(_extend_pieces(scene.straights), lambda p: _straight_facades_t(r, p, scene.layers),
                          rows)
    t_fa, i_fa = _nearest(_extend_pieces(scene.arcs), lambda p: _arc_facades_t(r, a_xz, p, scene.layers),
                          rows)
    t_cyl, i_cyl = _nearest(scene.cylinders, lambda c: _cylinder_t(r, a_xz, c))
    t_sph, i_sph = _nearest(scene.spheres, lambda s: _sphere_t(r, a3, s))
    iy = _safe_inv(r.dy)

    def car_t(car: Array) -> Array:
        oa, ob, da, db = _car_frame(r, car)
        ia, ib = _safe_inv(da), _safe_inv(db)
        body, cabin = _car_boxes(car)
        return jnp.minimum(_slab(oa, ob, r.oy, ia, ib, iy, body), _slab(oa, ob, r.oy, ia, ib, iy, cabin))

    t_car, i_car = _nearest(scene.cars, car_t)

    t_fac = jnp.minimum(t_fs, t_fa)
    i_fac = jnp.where(t_fs <= t_fa, i_fs, i_fa + n_straight)
    ts = jnp.stack([jnp.full_like(t_ground, 1e30), t_ground, t_fac, t_cyl, t_sph, t_car])
    ts = jnp.where(jnp.isfinite(ts), ts, 2e30)
    kind = jnp.argmin(ts, axis=0).astype(jnp.int32)
    depth = jnp.min(ts, axis=0)
    return Hits(kind, jnp.where(kind == SKY, jnp.inf, depth), i_fac, i_cyl, i_sph, i_car)


@partial(jax.jit, static_argnames=("height", "width"))
def surface_attributes(scene: FrameScene, hits: Hits, pose: Array, K: Array, baseline: Array,
                       right_shift: Array, *, height: int, width: int) -> Surface:
    """Surface coordinates, normals and material inputs at every pixel's nearest hit."""
    r = _rays(pose, K, baseline, height, width, right_shift)
    kind = hits.kind
    i_fac, i_cyl, i_sph, i_car = hits.facade, hits.cylinder, hits.sphere, hits.car
    t = jnp.where(kind == SKY, 0.0, hits.depth)
    qx, qy, qz = r.ox + t * r.dx, r.oy + t * r.dy, r.oz + t * r.dz
    zero = jnp.zeros_like(qx)

    # Ground: road coordinates relative to the piece that contains the point and is nearest laterally.
    pieces = _extend_pieces(jnp.concatenate([scene.straights, scene.arcs], 0))
    g_s, g_l, g_score = zero, zero, jnp.full_like(qx, jnp.inf)
    for i in range(pieces.shape[0]):
        p = pieces[i]
        if i >= scene.straights.shape[0]:
            cx, cz, sigma, radius = _arc_centre(p)
            s_loc = _arc_s(qx, qz, p)
            lat = sigma * (radius - jnp.sqrt((qx - cx) ** 2 + (qz - cz) ** 2))
        else:
            s_loc, lat = _straight_local(qx, qz, p)
        outside = jnp.maximum(-s_loc, s_loc - p[4])
        score = jnp.abs(lat) + jnp.where(outside > 0, 1e4 + outside, 0.0) + jnp.where(p[4] > 0, 0.0, 1e8)
        better = score < g_score
        g_s, g_l = jnp.where(better, p[3] + s_loc, g_s), jnp.where(better, lat, g_l)
        g_score = jnp.minimum(score, g_score)

    # Facades: recompute the local arc length at the hit for the winning (piece, row).
    fpiece = _rows(pieces, i_fac // scene.layers.shape[0])
    flayer = _rows(scene.layers, i_fac % scene.layers.shape[0])
    fp6 = fpiece
    s_str, _ = _straight_local(qx, qz, fp6)
    f_u = fp6[3] + jnp.where(fp6[5] != 0, _arc_param(qx, qz, fp6)[0], s_str)
    f_building = jnp.floor(f_u * jnp.take(1.0 / scene.layers[:, 1], i_fac % scene.layers.shape[0]))
    f_building = f_building.astype(jnp.int32)
    f_seed = flayer[5].astype(jnp.int32)
    # Normal towards the road: −side · r(ψ), r(ψ) = (cos ψ, −sin ψ) constant along a straight,
    # radial along an arc (r(ψ(s)) = −σ (q − c) / |q − c|).
    vx, vz = qx - fp6[8], qz - fp6[9]
    inv_len = jax.lax.rsqrt(jnp.maximum(vx * vx + vz * vz, 1e-12))
    arc = fp6[5] != 0
    rx = jnp.where(arc, -fp6[10] * vx * inv_len, fp6[7])
    rz = jnp.where(arc, -fp6[10] * vz * inv_len, -fp6[6])
    f_side = -jnp.sign(flayer[0])
    f_n = (f_side * rx, zero, f_side * rz)

    cyl = _rows(scene.cylinders, i_cyl)
    c_nx, c_nz = (qx - cyl[1]) / cyl[3], (qz - cyl[2]) / cyl[3]
    c_u = _atan2(c_nz, c_nx) * cyl[3]
    sph = _rows(scene.spheres, i_sph)
    s_n = tuple((q - sph[j]) / sph[4] for q, j in ((qx, 1), (qy, 2), (qz, 3)))
    s_u = _atan2(s_n[2], s_n[0]) * sph[4]

    k8 = _rows(scene.cars, i_car)
    cf_x, cf_z = jnp.take(jnp.sin(scene.cars[:, 3]), i_car), jnp.take(jnp.cos(scene.cars[:, 3]), i_car)
    ka = (qx - k8[1]) * cf_x + (qz - k8[2]) * cf_z
    kb = (qx - k8[1]) * cf_z - (qz - k8[2]) * cf_x
    kh = -qy
    body, cabin = _car_boxes(k8)
    in_cabin = kh > CAR_BODY_TOP + 1e-4
    box = [jnp.where(in_cabin, c, b) for b, c in zip(body, cabin, strict=True)]
    da = jnp.minimum(jnp.abs(ka - box[0]), jnp.abs(ka - box[1]))
    db = jnp.minimum(jnp.abs(kb - box[2]), jnp.abs(kb - box[3]))
    dh = jnp.minimum(jnp.abs(-kh - box[4]), jnp.abs(-kh - box[5]))
    face = jnp.where((da <= db) & (da <= dh), 0, jnp.where(db <= dh, 1, 2))
    sa = jnp.sign(ka - 0.5 * (box[0] + box[1]))
    sb = jnp.sign(kb - 0.5 * (box[2] + box[3]))
    k_n = (
        jnp.where(face == 0, sa * cf_x, jnp.where(face == 1, sb * cf_z, 0.0)),
        jnp.where(face == 2, -1.0, 0.0),
        jnp.where(face == 0, sa * cf_z, jnp.where(face == 1, -sb * cf_x, 0.0)),
    )
    k_u = jnp.where(face == 1, ka, kb)
    k_v = jnp.where(face == 2, ka, kh)

    up, sky_u, sky_v = tx.sky_coords(r.dx + zero, r.dy + zero, r.dz + zero)

    def select(values: tuple[Array, ...]) -> Array:
        return jnp.select([kind == k for k in range(6)], [jnp.broadcast_to(v, kind.shape) for v in values])

    ones = jnp.ones(kind.shape, jnp.int32)
    normal = tuple(select((zero, zero, f_n[j], (c_nx, zero, c_nz)[j], s_n[j], k_n[j])) for j in range(3))
    return Surface(
        kind=kind, depth=hits.depth,
        u=select((sky_u, g_s, f_u, c_u, s_u, k_u)), v=select((sky_v, g_l, -qy, -qy, -qy, k_v)),
        seed=select((ones, ones * 2, f_building * 7 + f_seed, cyl[5].astype(jnp.int32) + 3,
                     sph[5].astype(jnp.int32), k8[6].astype(jnp.int32))),
        normal=(normal[0], jnp.where(kind == GROUND, -1.0, normal[1]), normal[2]),
        moving=(kind == CAR) & (k8[7] > 0.5), up=up, height=-qy,
        building=f_building, layer_seed=f_seed, cylinder_kind=cyl[5],
        sphere_seed=sph[5].astype(jnp.int32),
        car_a=ka, car_b=kb, car_face=face.astype(jnp.int32), car_cabin=in_cabin, car_half_len=k8[4],
        car_seed=k8[6].astype(jnp.int32),
    )


@jax.jit
def _noise(u: Array, v: Array, seed: Array) -> tuple[Array, tx.Noise]:
    """Pixels per metre of texture (the reciprocal footprint) and the shared noise."""
    ppm = 1.0 / _footprint(u, v)
    return ppm, tx.shared_noise(u, v, seed, ppm)


def _facade_edges(layers: Array) -> tuple[Array, Array]:
    facade_r = jnp.max(jnp.where(layers[:2, 0] > 0, layers[:2, 0], 0.0))
    facade_l = -jnp.min(jnp.where(layers[:2, 0] < 0, layers[:2, 0], 0.0))
    return facade_r, facade_l


# One compilation per material: XLA fuses a single program's materials into one expression per
# channel and recomputes their shared fields many times over (several times slower than this).
_MATERIALS = (
    jax.jit(lambda s, ppm, n, layers: tx.sky_colour(s.up, n)),
    jax.jit(lambda s, ppm, n, layers: tx.ground_albedo(s.u, s.v, ppm, n, *_facade_edges(layers))),
    jax.jit(lambda s, ppm, n, layers: tx.facade_albedo(s.u, s.height, s.building, s.layer_seed, ppm, n)),
    jax.jit(lambda s, ppm, n, layers: tx.pole_albedo(s.height, s.cylinder_kind, ppm, n)),
    jax.jit(lambda s, ppm, n, layers: tx.foliage_albedo(s.sphere_seed, n)),
    jax.jit(lambda s, ppm, n, layers: tx.car_albedo(s.car_a, s.car_b, s.height, s.car_face, s.car_cabin,
                                                    s.car_half_len, s.car_seed, ppm, n)),
)


@partial(jax.jit, static_argnames=("apply_gamma", "quantise"))
def _compose(surf: Surface, albedos: tuple[tx.Colour, ...], sun: Array, gain: Array, gamma: Array,
             apply_gamma: bool, quantise: bool) -> Array:
    """Pick each pixel's material, shade (Lambert + ambient), apply the illumination, → [0, 255]
    (rounded to uint8 when ``quantise``)."""
    n = surf.normal
    lambert = jnp.maximum(n[0] * sun[0] + n[1] * sun[1] + n[2] * sun[2], 0.0)
    shade = jnp.where(surf.kind == SKY, 1.0, 0.55 + 0.6 * lambert)
    channels = []
    for c in range(3):
        value = jnp.broadcast_to(albedos[0][c], shade.shape)
        for k in range(1, len(albedos)):
            value = jnp.where(surf.kind == k, albedos[k][c], value)
        colour = jnp.clip(value * shade, 0.0, 1.0)
        if apply_gamma:  # a power is costly on CPU; skipped when the illumination does not drift
            colour = colour**gamma
        value = 255.0 * jnp.clip(gain * colour, 0.0, 1.0)
        channels.append(jnp.round(value).astype(jnp.uint8) if quantise else value)
    return jnp.stack(channels, -1)


def _shade(surf: Surface, ppm: Array, noise: tx.Noise, layers: Array, sun: Array, gain: Array,
           gamma: Array, apply_gamma: bool, quantise: bool = False) -> Array:
    albedos = tuple(material(surf, ppm, noise, layers) for material in _MATERIALS)
    return _compose(surf, albedos, sun, gain, gamma, apply_gamma=apply_gamma, quantise=quantise)


def render_stereo(scene: FrameScene, pose: Array, K: Array, baseline: Array, gain: float, gamma: float,
                  *, height: int, width: int, quantise: bool = False,
                  disparity_offset: float = 0.0) -> tuple[Array, Array, Array]:
    """Render the left and right views of one frame.

    Three jitted stages (geometry, noise, shading): separate compilations keep XLA from fusing a
    stage's whole expression graph into each of its many consumers, which would recompute it.

    Args:
      scene: primitives (float32).
      pose: ``[4, 4]`` camera-to-world pose of the left camera (world frame of :mod:`world`).
      K: ``[3, 3]`` intrinsics of both (rectified) cameras; baseline: metres, right camera at
        ``+baseline`` along the left camera's x axis.
      gain, gamma: global illumination: ``I = gain · albedo_shaded ** gamma`` (before quantisation).
      disparity_offset: px; the right camera's principal point lies this far left of ``K``'s, so a
        disparity measured with ``K`` is this much larger than ``fu·B/Z`` (a calibration residual).
    Returns:
      ``image [2, H, W, 3]`` float32 in [0, 255] (uint8 if ``quantise``), ``depth [2, H, W]`` float32 z-depth
      in metres (``inf`` for sky), ``moving [2, H, W]`` bool (pixel shows a moving car). Index 0 is
      the left camera, 1 the right.
    """
    shift = jnp.float32(disparity_offset)
    hits = nearest_hits(scene, pose, K, baseline, shift, height=height, width=width)
    surf = surface_attributes(scene, hits, pose, K, baseline, shift, height=height, width=width)
    ppm, noise = _noise(surf.u, surf.v, surf.seed)
    image = _shade(surf, ppm, noise, scene.layers, scene.sun, jnp.float32(gain), jnp.float32(gamma),
                   apply_gamma=float(gamma) != 1.0, quantise=quantise)
    return image, surf.depth, surf.moving
