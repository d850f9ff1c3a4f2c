"""Procedural, band-limited textures of the synthetic world (pure ``jnp``).

Every albedo here is a function of *surface* coordinates in metres (distance along the road,
height on a facade, position on a car's face, ...), never of the viewing ray, so the same world
point has the same colour in every view: the photometric model of docs/method.md §2 holds exactly up to
interpolation. The only view-dependent input is the pixel footprint (metres on the surface covered
by one pixel), passed as its reciprocal ``ppm`` (pixels per metre; multiplications are cheaper than
divisions here) and used to band-limit: a noise octave or a periodic pattern whose wavelength falls
below ~4 footprints is faded towards its mean (like trilinear mip-mapping), and pattern edges are
smoothed over one footprint. Close to the camera every octave is fully present, so consecutive
frames agree exactly; far away the fading changes by a few percent between frames, on content that
is close to the Nyquist limit anyway.

Noise is hashed value noise (quintic interpolation of per-lattice-point uniforms), summed over
octaves (fBm). All functions broadcast over arbitrary array shapes.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

_M1 = 0x8DA6B343
_M2 = 0xD8163841
_M3 = 0xCB1AB31F
_M4 = 0x85EBCA6B
_M5 = 0xC2B2AE35


def hash3(ix: Array | int, iy: Array | int, seed: Array | int) -> Array:
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


def fade(wavelength: Array | float, ppm: Array) -> Array:
    """Weight of a component of ``wavelength`` metres at ``ppm`` pixels per metre.

    1 above 4 pixels per wavelength, 0 below 2 (Nyquist), linear in between.
    """
    return jnp.clip(wavelength * ppm * 0.5 - 1.0, 0.0, 1.0)


def fbm(u: Array, v: Array, seed: Array | int, scale: float, octaves: int, ppm: Array,
        gain: float = 0.55) -> Array:
    """Zero-mean fractal noise: ``octaves`` octaves from wavelength ``scale`` metres, halving.

    The sum of amplitudes is 1 (so the result lies in about [-0.5, 0.5]); octaves finer than the
    footprint are faded out (see :func:`fade`), which lowers the contrast instead of aliasing.
    """
    amps = [gain**i for i in range(octaves)]
    norm = 1.0 / sum(amps)
    total = jnp.zeros(jnp.broadcast_shapes(jnp.shape(u), jnp.shape(v), jnp.shape(ppm)), jnp.float32)
    seed = jnp.asarray(seed, jnp.int32)
    for i, amp in enumerate(amps):
        lam = scale / (2.0**i)
        n = value_noise(u * (1.0 / lam), v * (1.0 / lam), seed * 16 + i)
        total = total + (amp * norm) * fade(lam, ppm) * (n - 0.5)
    return total


def smooth01(t: Array) -> Array:
    t = jnp.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def smoothstep(e0: float, e1: float, x: Array) -> Array:
    """Smooth 0 → 1 as ``x`` goes from ``e0`` to ``e1`` (constants)."""
    return smooth01((x - e0) * (1.0 / (e1 - e0)))


def edge(d: Array, ppm: Array) -> Array:
    """Smooth 0 → 1 as the signed distance ``d`` (m) crosses 0, over one pixel footprint."""
    return smooth01(d * ppm + 0.5)


def band(x: Array, lo: Array | float, hi: Array | float, ppm: Array) -> Array:
    """Indicator of ``lo <= x <= hi`` with edges smoothed over one footprint."""
    return jnp.maximum(edge(x - lo, ppm) - edge(x - hi, ppm), 0.0)


def pulse(x: Array, period: Array | float, lo: Array | float, hi: Array | float, ppm: Array) -> Array:
    """Periodic :func:`band`: ``lo <= x mod period <= hi`` (0 < lo < hi < period), band-limited.

    When the period approaches two footprints the pattern fades to its mean duty cycle.
    """
    inv = 1.0 / period
    y = x - jnp.floor(x * inv) * period
    duty = (hi - lo) * inv
    return duty + fade(period, ppm) * (band(y, lo, hi, ppm) - duty)


Colour = tuple[Array | float, Array | float, Array | float]
"""Colours are planar (three arrays or floats): applying a scalar field to an interleaved
``[..., 3]`` array would make XLA evaluate the field's whole expression once per channel."""


def rgb(r: float, g: float, b: float) -> Colour:
    return (r, g, b)


def scale(c: Colour, f: Array | float) -> Colour:
    return (c[0] * f, c[1] * f, c[2] * f)


def mix(a: Colour, b: Colour, w: Array) -> Colour:
    """``a (1 − w) + b w``."""
    return (a[0] + (b[0] - a[0]) * w, a[1] + (b[1] - a[1]) * w, a[2] + (b[2] - a[2]) * w)


def palette(table: Array, h: Array) -> Colour:
    """Row of ``table [P, 3]`` picked by uniforms ``h`` in [0, 1)."""
    idx = jnp.minimum((h * table.shape[0]).astype(jnp.int32), table.shape[0] - 1)
    return (jnp.take(table[:, 0], idx), jnp.take(table[:, 1], idx), jnp.take(table[:, 2], idx))


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


def shared_noise(u: Array, v: Array, seed: Array, ppm: Array) -> Noise:
    return Noise(fbm(u, v, seed, 4.0, 8, ppm), fbm(u, v, seed + 1, 12.0, 3, ppm),
                 fbm(u, v, seed + 2, 1.0, 5, ppm))


def ground_albedo(s: Array, lat: Array, ppm: Array, n: Noise, facade_right: Array,
                  facade_left: Array) -> Colour:
    """Road (asphalt, lane markings), curb, paved sidewalk and grass; ``s`` along, ``lat`` right (m)."""
    al = jnp.abs(lat)
    patches = smoothstep(0.05, 0.11, n.coarse)
    asphalt = scale(rgb(0.31, 0.31, 0.33), 1.0 + 1.3 * n.detail + 0.4 * n.aux - 0.35 * patches)
    dashes = band(lat, -0.075, 0.075, ppm) * pulse(s, 9.0, 1.0, 4.0, ppm)
    edges = band(al, 3.425, 3.575, ppm)
    parking = band(al, 5.3, 5.4, ppm) + band(al, 3.6, 5.4, ppm) * pulse(s, 6.0, 0.0 + 0.05, 0.15, ppm)
    marking = jnp.clip(dashes + edges + parking, 0.0, 1.0) * (0.8 + 0.6 * n.aux)
    road = mix(asphalt, rgb(0.86, 0.86, 0.82), marking)
    tile = 0.6
    ts, tl = jnp.floor(s * (1 / tile)).astype(jnp.int32), jnp.floor(lat * (1 / tile)).astype(jnp.int32)
    tile_tone = 0.8 + 0.4 * hash3(ts, tl, 4)
    grout = jnp.maximum(pulse(s, tile, 0.02, 0.06, ppm), pulse(lat, tile, 0.02, 0.06, ppm))
    paving = scale(rgb(0.58, 0.55, 0.50), tile_tone * (1.0 + 0.8 * n.aux + 0.5 * n.detail))
    paving = mix(paving, rgb(0.30, 0.28, 0.26), grout)
    curb = scale(rgb(0.66, 0.66, 0.64), 1.0 + 0.6 * n.aux)
    grass = scale(rgb(0.30, 0.36, 0.18), 1.0 + 1.3 * n.detail + 0.6 * n.coarse)
    facade_w = jnp.where(lat > 0, facade_right, facade_left)
    col = mix(road, curb, edge(al - 5.5, ppm))
    col = mix(col, paving, edge(al - 5.75, ppm))
    return mix(col, grass, smoothstep(0.5, 1.0, al - facade_w))


def facade_albedo(u: Array, v: Array, building: Array, layer_seed: Array, ppm: Array, n: Noise) -> Colour:
    """Facade with storeys, framed windows with mullions, cornices, panel joints and shop fronts;
    ``u`` along, ``v`` up (m)."""
    h1 = hash3(building, layer_seed, 11)
    h2 = hash3(building, layer_seed, 12)
    h3 = hash3(building, layer_seed, 13)
    h4 = hash3(building, layer_seed, 14)
    h5 = hash3(building, layer_seed, 15)
    base = scale(palette(FACADE_COLOURS, h1), 0.8 + 0.35 * h2)
    storey = 2.8 + 0.9 * h3
    spacing = 2.0 + 1.8 * h4
    upper = edge(v - storey, ppm)
    x = u + h5 * spacing
    win_x = pulse(x, spacing, 0.25 * spacing, 0.72 * spacing, ppm)
    win_y = pulse(v, storey, 0.3 * storey, 0.82 * storey, ppm)
    frame_x = pulse(x, spacing, 0.2 * spacing, 0.77 * spacing, ppm)
    frame_y = pulse(v, storey, 0.25 * storey, 0.87 * storey, ppm)
    window = win_x * win_y * upper
    frame = jnp.maximum(frame_x * frame_y * upper - window, 0.0)
    mullion = jnp.maximum(pulse(x, spacing, 0.475 * spacing, 0.495 * spacing, ppm),
                          pulse(v, storey, 0.6 * storey, 0.62 * storey, ppm)) * window
    cornice = pulse(v, storey, 0.02, 0.16, ppm) * upper
    joints = jnp.where(h2 > 0.5, pulse(v, 0.45, 0.0 + 0.01, 0.04, ppm), pulse(u, 1.2, 0.01, 0.04, ppm))
    shop = pulse(u, 2.0 * spacing, 0.2 * spacing, 1.8 * spacing, ppm) * band(v, 0.3, storey - 0.5, ppm)
    lum = (1.0 + 1.1 * n.detail + 0.3 * n.coarse) * (1.0 + 0.35 * frame - 0.45 * cornice - 0.25 * joints)
    wall = scale(base, lum)
    glass = scale(rgb(0.10, 0.13, 0.18), 1.0 + 2.0 * n.aux + 0.4 * h2 + 3.0 * mullion)
    col = mix(wall, glass, jnp.maximum(window, (1.0 - upper) * shop))
    return scale(col, 0.65 + 0.35 * smoothstep(0.0, 2.5, v))


def pole_albedo(v: Array, kind: Array, ppm: Array, n: Noise) -> Colour:
    """Metal poles (``kind`` 0, with a reflective band) and tree trunks (``kind`` 1); ``v`` up (m)."""
    metal = scale(rgb(0.46, 0.47, 0.50), 1.0 + 0.6 * n.aux + 0.9 * band(v, 2.2, 2.5, ppm))
    bark = scale(rgb(0.32, 0.24, 0.17), 1.0 + 1.5 * n.detail + 0.8 * n.aux)
    return mix(metal, bark, kind.astype(jnp.float32))


def foliage_albedo(seed: Array, n: Noise) -> Colour:
    """Tree crown."""
    tone = 0.85 + 0.3 * hash3(seed, 0, 31)
    return scale(rgb(0.20, 0.34, 0.11), tone * (1.0 + 1.4 * n.detail + 1.0 * n.aux))


def car_albedo(a: Array, b: Array, h: Array, face: Array, cabin: Array, half_len: Array,
               seed: Array, ppm: Array, n: Noise) -> Colour:
    """Car bodies and cabins, in the car's frame: ``a`` forward, ``b`` right, ``h`` up (m).

    ``face``: 0 front/back (normal ±a), 1 side (±b), 2 top/bottom.
    """
    paint = palette(CAR_COLOURS, hash3(seed, 0, 41))
    side = (face == 1).astype(jnp.float32)
    ends = (face == 0).astype(jnp.float32)
    wheel_a = jnp.abs(a) - (half_len - 0.85)
    r = jnp.sqrt(wheel_a * wheel_a + (h - 0.33) ** 2)
    tyre = band(r, -1.0, 0.33, ppm) * side
    rim = band(r, -1.0, 0.18, ppm) * side
    lights = band(jnp.abs(b), 0.45, 0.75, ppm) * band(h, 0.6, 0.75, ppm) * ends
    trim = band(h, 0.45, 0.5, ppm) + band(jnp.abs(a), -1.0, 0.02, ppm) * side
    front = (a > 0).astype(jnp.float32)
    light_col = mix(rgb(0.75, 0.08, 0.05), rgb(0.95, 0.93, 0.80), front)
    body = scale(paint, 1.0 + 0.4 * n.aux - 0.5 * trim)
    body = mix(body, light_col, lights)
    body = mix(body, scale(rgb(0.04, 0.04, 0.04), 1.0 + n.detail), tyre)
    body = mix(body, rgb(0.55, 0.55, 0.57), rim)
    glass_w = (1.0 - (face == 2).astype(jnp.float32)) * band(h, 1.05, 1.42, ppm)
    glass = scale(rgb(0.08, 0.10, 0.13), 1.0 + 1.5 * n.aux)
    cab = mix(scale(paint, 1.0 + 0.4 * n.aux), glass, glass_w)
    return mix(body, cab, cabin.astype(jnp.float32))


def sky_coords(dx: Array, dy: Array, dz: Array) -> tuple[Array, Array, Array]:
    """Direction-only sky coordinates: elevation ``up`` (sine) and a cloud layer ``(cu, cv)``.

    The cloud layer is the plane 300 m above the camera seen from the origin, in units of 40 m so
    that the shared noise's scales give clouds: the sky is at infinity, so only the ray direction
    matters (``dy`` points down).
    """
    inv_n = jax.lax.rsqrt(dx * dx + dy * dy + dz * dz)
    up = -dy * inv_n
    inv = 7.5 / jnp.maximum(up, 0.05)
    return up, dx * inv_n * inv, dz * inv_n * inv


def sky_colour(up: Array, n: Noise) -> Colour:
    """Blue gradient with soft clouds (see :func:`sky_coords`)."""
    col = mix(rgb(0.80, 0.84, 0.90), rgb(0.38, 0.56, 0.84), smoothstep(0.0, 0.6, up))
    cloud = smoothstep(-0.05, 0.25, n.coarse + 0.5 * n.detail)
    return mix(col, rgb(0.92, 0.93, 0.95), 0.8 * cloud * smoothstep(0.02, 0.15, up))
