"""Exact ray casting of the synthetic town (jitted JAX).

Every pixel's ray (through the pixel centre; pixel centres at integer coordinates) is intersected
analytically with all primitives of the frame's :class:`FrameScene` (their intersections are in
:mod:`dpc_jax.synth.shapes`): the ground plane, the facade surfaces of the road pieces near the
camera (planes along straights, vertical cylinders along arcs, cut to building outlines), vertical
cylinders (poles, trunks), spheres (tree crowns) and oriented boxes (cars, two per car). The nearest
hit wins; rays that hit nothing see the sky (at infinity).

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

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from dpc_jax.synth import textures as tx
from dpc_jax.synth.shapes import (
    CAR,
    GROUND,
    NEAR,
    SKY,
    FrameScene,
    Rays,
    arc_centre,
    arc_facades_t,
    arc_param,
    arc_s,
    atan2,
    car_boxes,
    car_frame,
    cylinder_t,
    extend_pieces,
    nearest,
    safe_inv,
    slab,
    sphere_t,
    straight_facades_t,
    straight_local,
)
from dpc_jax.synth.world import CAR_BODY_TOP


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

    t_ground = jnp.where(r.dy > 0, -r.oy * safe_inv(r.dy), jnp.inf) + jnp.zeros_like(a_xz)
    t_ground = jnp.where(t_ground > NEAR, t_ground, jnp.inf)
    rows = scene.layers.shape[0]
    t_fs, i_fs = nearest(extend_pieces(scene.straights), lambda p: straight_facades_t(r, p, scene.layers),
                          rows)
    t_fa, i_fa = nearest(extend_pieces(scene.arcs), lambda p: arc_facades_t(r, a_xz, p, scene.layers),
                          rows)
    t_cyl, i_cyl = nearest(scene.cylinders, lambda c: cylinder_t(r, a_xz, c))
    t_sph, i_sph = nearest(scene.spheres, lambda s: sphere_t(r, a3, s))
    iy = safe_inv(r.dy)

    def car_t(car: Array) -> Array:
        oa, ob, da, db = car_frame(r, car)
        ia, ib = safe_inv(da), safe_inv(db)
        body, cabin = car_boxes(car)
        return jnp.minimum(slab(oa, ob, r.oy, ia, ib, iy, body), slab(oa, ob, r.oy, ia, ib, iy, cabin))

    t_car, i_car = nearest(scene.cars, car_t)

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
    pieces = extend_pieces(jnp.concatenate([scene.straights, scene.arcs], 0))
    g_s, g_l, g_score = zero, zero, jnp.full_like(qx, jnp.inf)
    for i in range(pieces.shape[0]):
        p = pieces[i]
        if i >= scene.straights.shape[0]:
            cx, cz, sigma, radius = arc_centre(p)
            s_loc = arc_s(qx, qz, p)
            lat = sigma * (radius - jnp.sqrt((qx - cx) ** 2 + (qz - cz) ** 2))
        else:
            s_loc, lat = straight_local(qx, qz, p)
        outside = jnp.maximum(-s_loc, s_loc - p[4])
        score = jnp.abs(lat) + jnp.where(outside > 0, 1e4 + outside, 0.0) + jnp.where(p[4] > 0, 0.0, 1e8)
        better = score < g_score
        g_s, g_l = jnp.where(better, p[3] + s_loc, g_s), jnp.where(better, lat, g_l)
        g_score = jnp.minimum(score, g_score)

    # Facades: recompute the local arc length at the hit for the winning (piece, row).
    fpiece = _rows(pieces, i_fac // scene.layers.shape[0])
    flayer = _rows(scene.layers, i_fac % scene.layers.shape[0])
    fp6 = fpiece
    s_str, _ = straight_local(qx, qz, fp6)
    f_u = fp6[3] + jnp.where(fp6[5] != 0, arc_param(qx, qz, fp6)[0], s_str)
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
    c_u = atan2(c_nz, c_nx) * cyl[3]
    sph = _rows(scene.spheres, i_sph)
    s_n = tuple((q - sph[j]) / sph[4] for q, j in ((qx, 1), (qy, 2), (qz, 3)))
    s_u = atan2(s_n[2], s_n[0]) * sph[4]

    k8 = _rows(scene.cars, i_car)
    cf_x, cf_z = jnp.take(jnp.sin(scene.cars[:, 3]), i_car), jnp.take(jnp.cos(scene.cars[:, 3]), i_car)
    ka = (qx - k8[1]) * cf_x + (qz - k8[2]) * cf_z
    kb = (qx - k8[1]) * cf_z - (qz - k8[2]) * cf_x
    kh = -qy
    body, cabin = car_boxes(k8)
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
