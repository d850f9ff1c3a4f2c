"""Convolutions of the networks, written in the forms XLA's CPU backend runs fast.

All functions are pure, NHWC images ``[B, H, W, C]`` and HWIO kernels ``[kh, kw, C_in, C_out]``,
and equal (to float rounding) the ``lax.conv_general_dilated`` / ``lax.conv_transpose`` they
replace, in value and in gradient. Why they exist: XLA's CPU backend hands a convolution to its
fast library (YNNPACK) only when it has more than 16 input or output channels and no input
dilation; the rest run on a generic Eigen path, and that hits exactly the layers of these networks
that carry the most pixels:

* the gradient of a stride-2 convolution with respect to its input is an input-dilated
  convolution: ``conv_s2`` computes both gradients through the equivalent stride-1 convolution of
  the space-to-depth image instead (4·C_in channels, no dilation);
* a transposed convolution is an input-dilated convolution: ``upconv3x3_s2`` evaluates it as one
  stride-1 convolution producing the four output phases, then interleaves them;
* the inverse-depth and mask heads map 8–32 channels to one or two: ``conv3x3_few_outputs``
  evaluates them as a matrix product with the nine taps followed by nine shifted adds, and the
  input gradient as nine shifted multiply-adds;
* in inference, the full-resolution layers (8–10 channels to 8, and the heads to the channel-first
  ``[B, F, H, W]`` maps the networks return) run on channel-first planes: ``conv3x3_planar``
  evaluates each output plane as 9·C shifted multiply-adds, vectorised along the image rows and
  summed in eight interleaved partial sums (a sum written left to right is one chain of
  dependent multiply-adds, which leaves the vector units waiting).

Which library runs the remaining convolutions is a compiler option that the backend module
(``dpc_jax.engine.backend.compiler_options``) chooses per network and per use.

``benchmarks/bench_models.py`` measures the effect on the training step (figures are not kept here:
they depend on the machine and go stale).
"""

from __future__ import annotations

import functools
import operator
from typing import cast

import jax
import jax.numpy as jnp

NHWC = ("NHWC", "HWIO", "NHWC")


def _promote(x: jax.Array, kernel: jax.Array) -> tuple[jax.Array, jax.Array]:
    dtype = jnp.result_type(x, kernel)
    return x.astype(dtype), kernel.astype(dtype)


# --------------------------------------------------------------------------- stride-2 convolution


def _conv_s2_direct(x: jax.Array, kernel: jax.Array) -> jax.Array:
    pad = (kernel.shape[0] - 1) // 2
    return jax.lax.conv_general_dilated(x, kernel, (2, 2), ((pad, pad), (pad, pad)), dimension_numbers=NHWC)


def _space_to_depth_conv(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """The stride-2 convolution as a stride-1 one on the space-to-depth image.

    With ``t = (k+1)/2`` and the kernel zero-padded to ``2t × 2t``, output ``m`` of a stride-2
    convolution reads padded input rows ``2m … 2m+2t−1``, i.e. row-pairs ``m … m+t−1``: a
    stride-1 ``t × t`` convolution over ``[B, H'/2, W'/2, 4·C_in]`` (H', W' padded to
    ``2(out + t − 1)``) with the kernel regrouped the same way.
    """
    b, h, w, c = x.shape
    k = kernel.shape[0]
    t, pad = (k + 1) // 2, (k - 1) // 2
    out_h, out_w = -(-h // 2), -(-w // 2)
    hp, wp = 2 * (out_h + t - 1), 2 * (out_w + t - 1)
    xp = jnp.pad(x, ((0, 0), (pad, hp - h - pad), (pad, wp - w - pad), (0, 0)))
    xs = xp.reshape(b, hp // 2, 2, wp // 2, 2, c).transpose(0, 1, 3, 2, 4, 5)
    xs = xs.reshape(b, hp // 2, wp // 2, 4 * c)
    kp = jnp.pad(kernel, ((0, 2 * t - k), (0, 2 * t - k), (0, 0), (0, 0)))
    ks = kp.reshape(t, 2, t, 2, c, -1).transpose(0, 2, 1, 3, 4, 5).reshape(t, t, 4 * c, -1)
    return jax.lax.conv_general_dilated(xs, ks, (1, 1), "VALID", dimension_numbers=NHWC)


@jax.custom_vjp
def _conv_s2(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return _conv_s2_direct(x, kernel)


def _conv_s2_fwd(x: jax.Array, kernel: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    return _conv_s2_direct(x, kernel), (x, kernel)


def _conv_s2_bwd(residuals: tuple[jax.Array, jax.Array], g: jax.Array) -> tuple[jax.Array, jax.Array]:
    _, vjp = jax.vjp(_space_to_depth_conv, *residuals)
    return vjp(g)


_conv_s2.defvjp(_conv_s2_fwd, _conv_s2_bwd)


def conv_s2(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """Stride-2 convolution with padding ``(k−1)//2``: ``[B, H, W, C_in] -> [B, ⌈H/2⌉, ⌈W/2⌉, C_out]``.

    ``kernel``: ``[k, k, C_in, C_out]``, ``k`` odd. The forward pass is XLA's strided convolution;
    both gradients are those of the space-to-depth form (same values, no input dilation).
    """
    if kernel.shape[0] != kernel.shape[1] or kernel.shape[0] % 2 == 0:
        raise ValueError(f"conv_s2 needs a square kernel of odd size, got {kernel.shape[:2]}")
    return _conv_s2(*_promote(x, kernel))


# ------------------------------------------------------------------ transposed convolution, ×2


# Along each axis, output phase q (position 2m + q) at input offset a (input m + a) takes tap
# _PHASE_TAP[q][a] of the 3×3 kernel, or nothing.
_PHASE_TAP = ((1, None), (0, 2))


def phase_kernel(kernel: jax.Array) -> jax.Array:
    """``[3, 3, C_in, C_out]`` → ``[2, 2, C_in, 4·C_out]`` = [row offset, col offset, C_in,
    (row phase, col phase, C_out)]: the 2×2 stride-1 kernel of every output phase of
    :func:`upconv3x3_s2`.

    Pure data movement, written as one concatenation in the final layout (a stack and a transpose
    cost a second pass over the largest kernels on every call). Inference computes it once per
    sequence (``dpc_jax.nn.models.prepare_inference``) and calls :func:`upconv3x3_s2_phases`.
    """
    zero = jnp.zeros(kernel.shape[2:], kernel.dtype)

    def taps(a: int, b: int) -> list[jax.Array]:
        blocks = []
        for q in (0, 1):
            for r in (0, 1):
                ty, tx = _PHASE_TAP[q][a], _PHASE_TAP[r][b]
                blocks.append(zero if ty is None or tx is None else kernel[ty, tx])
        return blocks

    return jnp.stack([jnp.stack([jnp.concatenate(taps(a, b), axis=-1) for b in (0, 1)]) for a in (0, 1)])


def upconv3x3_s2_phases(x: jax.Array, phases: jax.Array, *, channels_first: bool = False) -> jax.Array:
    """:func:`upconv3x3_s2` with the kernel given as its :func:`phase_kernel` ``[2, 2, C_in,
    4·C_out]``: ``[B, h, w, C_in] -> [B, 2h, 2w, C_out]`` (or ``[B, C_out, 2h, 2w]``)."""
    if phases.shape[:2] != (2, 2) or phases.shape[3] % 4:
        raise ValueError(f"upconv3x3_s2_phases needs a [2, 2, C_in, 4*C_out] kernel, got {phases.shape}")
    x, phases = _promote(x, phases)
    cout = phases.shape[3] // 4
    y = jax.lax.conv_general_dilated(x, phases, (1, 1), ((0, 1), (0, 1)), dimension_numbers=NHWC)
    b, h, w, _ = y.shape
    planes = y.reshape(b, h, w, 2, 2, cout)
    if channels_first:
        return planes.transpose(0, 5, 1, 3, 2, 4).reshape(b, cout, 2 * h, 2 * w)
    return planes.transpose(0, 1, 3, 2, 4, 5).reshape(b, 2 * h, 2 * w, cout)


def upconv3x3_s2(x: jax.Array, kernel: jax.Array, *, channels_first: bool = False) -> jax.Array:
    """Transposed convolution 3×3, stride 2: ``[B, h, w, C_in] -> [B, 2h, 2w, C_out]``, or
    ``[B, C_out, 2h, 2w]`` with ``channels_first`` (the same interleaving pass, another order).

    Equals ``lax.conv_transpose(x, kernel, (2, 2), ((1, 2), (1, 2)))`` (Flax's ``ConvTranspose``
    with that padding; PyTorch's ``ConvTranspose2d(3, stride=2, padding=1, output_padding=1)`` up
    to a kernel flip), evaluated as one stride-1 2×2 convolution producing the four output phases
    (:func:`phase_kernel`), then interleaved (depth-to-space).
    """
    return upconv3x3_s2_phases(x, phase_kernel(kernel), channels_first=channels_first)


# ------------------------------------------------------ 3×3 convolution to a few output channels


def _conv3x3_same(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return jax.lax.conv_general_dilated(x, kernel, (1, 1), ((1, 1), (1, 1)), dimension_numbers=NHWC)


@jax.custom_vjp
def _conv3x3_few(x: jax.Array, kernel: jax.Array) -> jax.Array:
    h, w = x.shape[1:3]
    cin = kernel.shape[2]
    xp = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    outputs = []
    for j in range(kernel.shape[3]):
        # Column t of z is tap t = 3a + b of output channel j at every padded pixel. The nine
        # columns are padded to 16 and there is one product per output channel: both measured
        # faster in the full training step than 9 columns or one product with 9F columns.
        taps = jnp.pad(kernel[..., j].transpose(2, 0, 1).reshape(cin, 9), ((0, 0), (0, 7)))
        z = jnp.einsum("bhwc,cn->bhwn", xp, taps)
        outputs.append(sum(z[:, a : a + h, b : b + w, 3 * a + b, None] for a in range(3) for b in range(3)))
    return jnp.concatenate(outputs, axis=-1)


def _conv3x3_few_fwd(x: jax.Array, kernel: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    return _conv3x3_few(x, kernel), (x, kernel)


def _conv3x3_few_bwd(residuals: tuple[jax.Array, jax.Array], g: jax.Array) -> tuple[jax.Array, jax.Array]:
    x, kernel = residuals
    h, w = x.shape[1:3]
    # dx[p] = Σ_{a,b,j} g[p − (a−1, b−1), j] · kernel[a, b, :, j]: nine shifted copies of each
    # one-channel cotangent times a channel vector, one elementwise pass.
    gp = jnp.pad(g, ((0, 0), (1, 1), (1, 1), (0, 0)))
    # sum() starts from the int 0, which the type checker keeps in the result's type; the generator
    # is never empty (nine taps, at least one output channel), so the sum is an Array.
    dx = cast(jax.Array, sum(
        gp[:, 2 - a : 2 - a + h, 2 - b : 2 - b + w, j : j + 1] * kernel[a, b, :, j]
        for a in range(3)
        for b in range(3)
        for j in range(kernel.shape[3])
    ))
    _, kernel_vjp = jax.vjp(lambda k: _conv3x3_same(x, k), kernel)
    return dx, kernel_vjp(g)[0]


_conv3x3_few.defvjp(_conv3x3_few_fwd, _conv3x3_few_bwd)


def conv3x3_few_outputs(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """3×3 convolution, stride 1, zero padding 1, to a few output channels.

    ``x [B, H, W, C_in]``, ``kernel [3, 3, C_in, F]`` → ``[B, H, W, F]``. Meant for ``F`` of 1 or 2
    (the heads); the forward pass costs F ``C_in × 16`` matrix products per pixel.
    """
    if kernel.shape[:2] != (3, 3):
        raise ValueError(f"conv3x3_few_outputs needs a 3x3 kernel, got {kernel.shape[:2]}")
    return _conv3x3_few(*_promote(x, kernel))


# ------------------------------------------------------------- 3×3 convolution on channel planes


def conv3x3_planar(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """3×3 convolution, stride 1, *no* padding, on channel-first planes: ``x [B, C, H, W]``,
    ``kernel [3, 3, C, F]`` → ``[B, F, H − 2, W − 2]``; the caller pads (or produces ``x``
    padded).

    Each output plane is the sum of the 9·C shifted input planes times their kernel taps: one
    elementwise pass per output plane, vectorised along W, with no matrix product and no
    intermediate. Meant for a few channels (the networks' full-resolution layers in inference:
    ``C·F`` ≤ 80), where it beats XLA's convolutions.
    """
    if kernel.shape[:2] != (3, 3) or kernel.shape[2] != x.shape[1]:
        raise ValueError(f"conv3x3_planar needs a [3, 3, {x.shape[1]}, F] kernel, got {kernel.shape}")
    x, kernel = _promote(x, kernel)
    h, w = x.shape[2] - 2, x.shape[3] - 2
    planes = [
        _interleaved_sum([
            x[:, c, a : a + h, b : b + w] * kernel[a, b, c, j]
            for a in range(3)
            for b in range(3)
            for c in range(kernel.shape[2])
        ])
        for j in range(kernel.shape[3])
    ]
    return jnp.stack(planes, axis=1)


# Partial sums of _interleaved_sum: independent multiply-add chains enough to cover one
# multiply-add's latency on the two vector units of an x86 core (4 cycles each).
_ACCUMULATORS = 8


def _interleaved_sum(terms: list[jax.Array]) -> jax.Array:
    """``Σ terms`` as :data:`_ACCUMULATORS` interleaved partial sums, then added pairwise.

    Floating-point addition is not associative, so XLA compiles a sum written left to right (90
    terms for 10 input channels) as one chain of dependent multiply-adds, each waiting for the
    one before; partial sums give the core independent chains to overlap.
    """
    n = min(_ACCUMULATORS, len(terms))
    sums = [functools.reduce(operator.add, terms[i::n]) for i in range(n)]
    while len(sums) > 1:
        sums = [sums[i] + sums[i + 1] if i + 1 < len(sums) else sums[i] for i in range(0, len(sums), 2)]
    return sums[0]
