"""Procedural, band-limited textures of the synthetic world (pure ``jnp``).

Every albedo here is a function of *surface* coordinates in metres (distance along the road,
height on a facade, position on a car's face, ...), never of the viewing ray, so the same world
point has the same colour in every view: the photometric model of DESIGN §2 holds exactly up to
interpolation. The only view-dependent input is the pixel footprint ``fp`` (metres on the surface
covered by one pixel), used to band-limit: a noise octave or a periodic pattern whose wavelength
falls below ~4 footprints is faded towards its mean (like trilinear mip-mapping), and pattern edges
are smoothed over one footprint. Close to the camera every octave is fully present, so consecutive
frames agree exactly; far away the fading changes by a few percent between frames, on content that
is close to the Nyquist limit anyway.

Noise is hashed value noise (quintic interpolation of per-lattice-point uniforms), summed over
octaves (fBm). All functions broadcast over arbitrary array shapes.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

_M1 = 0x8DA6B343
_M2 = 0xD8163841
_M3 = 0xCB1AB31F
_M4 = 0x85EBCA6B
_M5 = 0xC2B2AE35


def hash3(ix: Array, iy: Array, seed: Array | int) -> Array:
    """Uniform float32 in [0, 1) from three integers (int32 arrays, any sign; broadcast)."""
    h = (
        jnp.asarray(ix).astype(jnp.uint32) * jnp.uint32(_M1)
        + jnp.asarray(iy).astype(jnp.uint32) * jnp.uint32(_M2)
        + jnp.asarray(seed).astype(jnp.uint32) * jnp.uint32(_M3)
    )
    h = (h ^ (h >> 15)) * jnp.uint32(_M4)
    h = (h ^ (h >> 13)) * jnp.uint32(_M5)
    h = h ^ (h >> 16)
    return (h >> 8).astype(jnp.float32) * jnp.float32(1.0 / (1 << 24))


def _quintic(t: Array) -> Array:
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def value_noise(u: Array, v: Array, seed: Array | int) -> Array:
    """Smooth value noise with unit lattice spacing, values in [0, 1)."""
    fu, fv = jnp.floor(u), jnp.floor(v)
    iu, iv = fu.astype(jnp.int32), fv.astype(jnp.int32)
    su, sv = _quintic(u - fu), _quintic(v - fv)
    a = hash3(iu, iv, seed)
    b = hash3(iu + 1, iv, seed)
    c = hash3(iu, iv + 1, seed)
    d = hash3(iu + 1, iv + 1, seed)
    top = a + (b - a) * su
    bottom = c + (d - c) * su
    return top + (bottom - top) * sv


def fade(wavelength: Array | float, fp: Array) -> Array:
    """Weight of a component of ``wavelength`` metres given the pixel footprint ``fp``.

    1 above 4 footprints per wavelength, 0 below 2 (Nyquist), linear in between.
    """
    return jnp.clip(wavelength / jnp.maximum(fp, 1e-6) * 0.5 - 1.0, 0.0, 1.0)


def fbm(u: Array, v: Array, seed: Array | int, scale: float, octaves: int, fp: Array,
        gain: float = 0.55) -> Array:
    """Zero-mean fractal noise: ``octaves`` octaves from wavelength ``scale`` metres, halving.

    The sum of amplitudes is 1 (so the result lies in about [-0.5, 0.5]); octaves finer than the
    footprint are faded out (see :func:`fade`), which lowers the contrast instead of aliasing.
    """
    amps = [gain**i for i in range(octaves)]
    norm = 1.0 / sum(amps)
    total = jnp.zeros(jnp.broadcast_shapes(jnp.shape(u), jnp.shape(v), jnp.shape(fp)), jnp.float32)
    seed = jnp.asarray(seed, jnp.int32)
    for i, amp in enumerate(amps):
        lam = scale / (2.0**i)
        n = value_noise(u / lam, v / lam, seed * 16 + i)
        total = total + (amp * norm) * fade(lam, fp) * (n - 0.5)
    return total


def smoothstep(e0: Array | float, e1: Array | float, x: Array) -> Array:
    t = jnp.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def band(x: Array, lo: Array | float, hi: Array | float, fp: Array) -> Array:
    """Indicator of ``lo <= x <= hi`` with edges smoothed over one footprint (metres)."""
    e = 0.5 * jnp.maximum(fp, 1e-4)
    return jnp.clip(smoothstep(lo - e, lo + e, x) - smoothstep(hi - e, hi + e, x), 0.0, 1.0)


def pulse(x: Array, period: Array | float, lo: Array | float, hi: Array | float, fp: Array) -> Array:
    """Periodic :func:`band`: ``lo <= x mod period <= hi`` (0 < lo < hi < period), band-limited.

    When the period approaches two footprints the pattern fades to its mean duty cycle.
    """
    y = x - jnp.floor(x / period) * period
    duty = (hi - lo) / period
    sharp = band(y, lo, hi, fp)
    f = fade(period, fp)
    return duty + f * (sharp - duty)


def mix(a: Array, b: Array, w: Array) -> Array:
    """``a (1 − w) + b w`` with ``w`` broadcast over a trailing colour axis."""
    return a + (b - a) * w[..., None]


def rgb(r: float, g: float, b: float) -> Array:
    return jnp.array([r, g, b], jnp.float32)


def palette(table: Array, h: Array) -> Array:
    """Pick a row of ``table [P, 3]`` from uniforms ``h`` in [0, 1) (one-hot sum, gather-free)."""
    n = table.shape[0]
    idx = jnp.minimum((h * n).astype(jnp.int32), n - 1)
    onehot = (idx[..., None] == jnp.arange(n)).astype(jnp.float32)
    return onehot @ table


FACADE_COLOURS = jnp.array(
    [[0.78, 0.70, 0.58], [0.70, 0.45, 0.33], [0.62, 0.62, 0.60], [0.85, 0.80, 0.70],
     [0.55, 0.48, 0.40], [0.74, 0.60, 0.42], [0.60, 0.36, 0.28], [0.80, 0.78, 0.74]],
    jnp.float32,
)
CAR_COLOURS = jnp.array(
    [[0.70, 0.10, 0.08], [0.12, 0.20, 0.55], [0.85, 0.85, 0.85], [0.08, 0.08, 0.09],
     [0.50, 0.52, 0.55], [0.15, 0.40, 0.20], [0.85, 0.65, 0.10], [0.35, 0.12, 0.35]],
    jnp.float32,
)


class Noise(NamedTuple):
    """Noise shared by all materials, evaluated once per pixel at the pixel's own surface coordinates.

    ``detail``: 8 octaves from 4 m down to 3 cm; ``coarse``: 3 octaves from 12 m; ``aux``: 5 octaves
    from 1 m (an independent seed). Materials combine these instead of each evaluating its own
    fBm, which keeps the per-pixel cost independent of the number of materials.
    """

    detail: Array
    coarse: Array
    aux: Array


def shared_noise(u: Array, v: Array, seed: Array, fp: Array) -> Noise:
    return Noise(fbm(u, v, seed, 4.0, 8, fp), fbm(u, v, seed + 1, 12.0, 3, fp),
                 fbm(u, v, seed + 2, 1.0, 5, fp))


def ground_albedo(s: Array, lat: Array, fp: Array, n: Noise, facade_right: Array,
                  facade_left: Array) -> Array:
    """Road (asphalt, lane markings), curb, paved sidewalk and grass; ``s`` along, ``lat`` right (m)."""
    al = jnp.abs(lat)
    patches = smoothstep(0.06, 0.12, n.coarse)
    asphalt = rgb(0.31, 0.31, 0.33) * (1.0 + 1.1 * n.detail - 0.3 * patches)[..., None]
    dashes = band(lat, -0.075, 0.075, fp) * pulse(s, 9.0, 1.0, 4.0, fp)
    edges = band(al, 3.425, 3.575, fp)
    parking = band(al, 5.3, 5.4, fp)
    marking = jnp.clip(dashes + edges + parking, 0.0, 1.0) * (0.8 + 0.5 * n.aux)
    road = mix(asphalt, rgb(0.86, 0.86, 0.82), marking)
    tile = 0.6
    ts, tl = jnp.floor(s / tile).astype(jnp.int32), jnp.floor(lat / tile).astype(jnp.int32)
    tile_tone = 0.85 + 0.3 * hash3(ts, tl, 4)
    grout = jnp.maximum(pulse(s, tile, 0.02, 0.06, fp), pulse(lat, tile, 0.02, 0.06, fp))
    paving = rgb(0.58, 0.55, 0.50) * (tile_tone * (1.0 + 0.8 * n.aux + 0.4 * n.detail))[..., None]
    paving = mix(paving, rgb(0.33, 0.31, 0.29), grout * fade(tile, fp))
    curb = rgb(0.66, 0.66, 0.64) * (1.0 + 0.6 * n.aux)[..., None]
    grass = rgb(0.30, 0.36, 0.18) * (1.0 + 1.3 * n.detail + 0.6 * n.coarse)[..., None]
    facade_w = jnp.where(lat > 0, facade_right, facade_left)
    col = mix(road, curb, smoothstep(5.5 - 0.5 * fp, 5.5 + 0.5 * fp, al))
    col = mix(col, paving, smoothstep(5.75 - 0.5 * fp, 5.75 + 0.5 * fp, al))
    return mix(col, grass, smoothstep(facade_w + 0.5, facade_w + 1.0, al))


def facade_albedo(u: Array, v: Array, building: Array, layer_seed: Array, fp: Array, n: Noise) -> Array:
    """Plastered facade with storeys, windows, cornices and shop fronts; ``u`` along, ``v`` up (m)."""
    h1 = hash3(building, layer_seed, 11)
    h2 = hash3(building, layer_seed, 12)
    h3 = hash3(building, layer_seed, 13)
    h4 = hash3(building, layer_seed, 14)
    h5 = hash3(building, layer_seed, 15)
    base = palette(FACADE_COLOURS, h1) * (0.8 + 0.35 * h2)[..., None]
    wall = base * (1.0 + 1.0 * n.detail + 0.3 * n.coarse)[..., None]
    storey = 2.8 + 0.9 * h3
    spacing = 2.0 + 1.8 * h4
    upper = smoothstep(storey - 0.5 * fp, storey + 0.5 * fp, v)
    win_x = pulse(u + h5 * spacing, spacing, 0.25 * spacing, 0.72 * spacing, fp)
    win_y = pulse(v, storey, 0.3 * storey, 0.82 * storey, fp)
    window = win_x * win_y * upper
    sill = win_x * pulse(v, storey, 0.24 * storey, 0.3 * storey, fp) * upper
    cornice = pulse(v, storey, 0.02, 0.14, fp) * upper
    shop = pulse(u, 2.0 * spacing, 0.2 * spacing, 1.8 * spacing, fp) * band(v, 0.3, storey - 0.5, fp)
    glass = rgb(0.10, 0.13, 0.18) * (1.0 + 2.0 * n.aux + 0.4 * h2)[..., None]
    col = mix(wall, wall * 1.3, sill)
    col = mix(col, wall * 0.55, cornice)
    col = mix(col, glass, jnp.maximum(window, (1.0 - upper) * shop))
    return col * (0.65 + 0.35 * smoothstep(0.0, 2.5, v))[..., None]


def pole_albedo(v: Array, kind: Array, fp: Array, n: Noise) -> Array:
    """Metal poles (``kind`` 0, with a reflective band) and tree trunks (``kind`` 1); ``v`` up (m)."""
    metal = rgb(0.46, 0.47, 0.50) * (1.0 + 0.6 * n.aux)[..., None]
    metal = mix(metal, rgb(0.85, 0.85, 0.80), band(v, 2.2, 2.5, fp))
    bark = rgb(0.32, 0.24, 0.17) * (1.0 + 1.5 * n.detail + 0.8 * n.aux)[..., None]
    return mix(metal, bark, kind.astype(jnp.float32))


def foliage_albedo(seed: Array, n: Noise) -> Array:
    """Tree crown."""
    tone = 0.85 + 0.3 * hash3(seed, 0, 31)
    return rgb(0.20, 0.34, 0.11) * (tone * (1.0 + 1.4 * n.detail + 1.0 * n.aux))[..., None]


def car_albedo(a: Array, b: Array, h: Array, face: Array, cabin: Array, half_len: Array,
               seed: Array, fp: Array, n: Noise) -> Array:
    """Car bodies and cabins, in the car's frame: ``a`` forward, ``b`` right, ``h`` up (m).

    ``face``: 0 front/back (normal ±a), 1 side (±b), 2 top/bottom.
    """
    paint = palette(CAR_COLOURS, hash3(seed, 0, 41)) * (1.0 + 0.3 * n.aux)[..., None]
    side = (face == 1).astype(jnp.float32)
    ends = (face == 0).astype(jnp.float32)
    wheel_a = jnp.abs(a) - (half_len - 0.85)
    r = jnp.sqrt(wheel_a * wheel_a + (h - 0.33) ** 2)
    tyre = band(r, -1.0, 0.33, fp) * side
    rim = band(r, -1.0, 0.18, fp) * side
    lights = band(jnp.abs(b), 0.45, 0.75, fp) * band(h, 0.6, 0.75, fp) * ends
    light_col = jnp.where((a > 0)[..., None], rgb(0.95, 0.93, 0.80), rgb(0.75, 0.08, 0.05))
    body = mix(paint, light_col, lights)
    body = mix(body, rgb(0.04, 0.04, 0.04) * (1.0 + n.detail)[..., None], tyre)
    body = mix(body, rgb(0.55, 0.55, 0.57), rim)
    glass_w = (1.0 - (face == 2).astype(jnp.float32)) * band(h, 1.05, 1.42, fp)
    glass = rgb(0.08, 0.10, 0.13) * (1.0 + 1.5 * n.aux)[..., None]
    cab = mix(paint, glass, glass_w)
    return jnp.where(cabin[..., None], cab, body)


def sky_coords(dx: Array, dy: Array, dz: Array) -> tuple[Array, Array, Array]:
    """Direction-only sky coordinates: elevation ``up`` (sine) and a cloud layer ``(cu, cv)``.

    The cloud layer is the plane 300 m above the camera seen from the origin, in units of 40 m so
    that the shared noise's scales give clouds: the sky is at infinity, so only the ray direction
    matters (``dy`` points down).
    """
    n = jnp.sqrt(dx * dx + dy * dy + dz * dz)
    up = -dy / n
    inv = 7.5 / jnp.maximum(up, 0.05)
    return up, dx / n * inv, dz / n * inv


def sky_colour(up: Array, n: Noise) -> Array:
    """Blue gradient with soft clouds (see :func:`sky_coords`)."""
    col = mix(rgb(0.80, 0.84, 0.90), rgb(0.38, 0.56, 0.84), smoothstep(0.0, 0.6, up))
    cloud = smoothstep(-0.05, 0.25, n.coarse + 0.5 * n.detail)
    return mix(col, rgb(0.92, 0.93, 0.95), 0.8 * cloud * smoothstep(0.02, 0.15, up))
