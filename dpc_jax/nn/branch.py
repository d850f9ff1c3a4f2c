"""One encoder–decoder branch of both networks (docs/method.md §3) and its layers.

* **Encoder**: ``depth`` blocks conv(k, stride 2, padding (k−1)//2) → ReLU → BatchNorm, no pooling.
  Each block maps a side ``n`` to ``ceil(n / 2)``.
* **Depth decoder**: per stage, transposed conv 3×3 stride 2 (exactly doubles the size) → ReLU,
  crop to the skip tensor of the encoder at that scale (the doubled size is never smaller, since
  the encoder rounds up), concatenate the skip, conv 3×3 → ReLU → BatchNorm. Inverse-depth heads
  (conv 3×3 → ReLU, + 0.001) on the last ``depth_scales`` stages; each head's output is upsampled
  ×2 (bilinear, half-pixel centres as PyTorch's ``interpolate``), cropped, and concatenated into
  the next stage. As in the reference code the finest head is halved: ``0.5 (ReLU(conv) + 0.001)``.
  Only the finest (full-resolution) inverse depth is returned.
* **Mask decoder**: transposed conv 3×3 stride 2 → ReLU from the output of encoder block
  ``mask_source_block`` up to full resolution (cropped to each encoder scale), conv 3×3 → sigmoid.

The branch accepts any ``H × W`` (the crop-to-skip logic handles sizes that are not multiples of
``2**depth``). Everything is NHWC inside, except that in ``model.eval()`` the full-resolution
layers run on channel planes (:class:`Branch`); dense outputs are returned as ``[B, F, H, W]``.

Deviations from the reference (PyTorch, utiasSTARS/ss-dpc-net), none of which changes the
parameter count: BatchNorm running variance uses the biased batch variance (PyTorch's is
unbiased); the transposed-conv kernel is not spatially flipped (a re-parametrisation; see
:class:`UpConv`). BatchNorm momentum 0.9 (Flax convention, weight of the old average) equals
PyTorch's default momentum 0.1.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from dpc_jax.nn.conv import conv3x3_few_outputs, conv3x3_planar, conv_s2, phase_kernel, upconv3x3_s2_phases
from dpc_jax.nn.model_config import ModelConfig

INV_DEPTH_OFFSET = 0.001

def upsample2x_bilinear(x: jax.Array) -> jax.Array:
    """Bilinear ×2 upsampling of ``[B, H, W, C]`` to ``[B, 2H, 2W, C]``.

    Half-pixel centres with edge clamping, i.e. PyTorch ``interpolate(scale_factor=2,
    mode="bilinear", align_corners=False)`` and ``cv2.resize(INTER_LINEAR)``: output pixel 2i
    is 0.75·x[i] + 0.25·x[i−1] and 2i+1 is 0.75·x[i] + 0.25·x[i+1], indices clamped.
    """

    def along(a: jax.Array, axis: int) -> jax.Array:
        n = a.shape[axis]
        # Shifted copies by slicing (a gather would be slower on CPU), edges repeated.
        first = jax.lax.slice_in_dim(a, 0, 1, axis=axis)
        last = jax.lax.slice_in_dim(a, n - 1, n, axis=axis)
        prev = jnp.concatenate([first, jax.lax.slice_in_dim(a, 0, n - 1, axis=axis)], axis=axis)
        nxt = jnp.concatenate([jax.lax.slice_in_dim(a, 1, n, axis=axis), last], axis=axis)
        even = 0.75 * a + 0.25 * prev
        odd = 0.75 * a + 0.25 * nxt
        stacked = jnp.stack([even, odd], axis=axis + 1)
        shape = (*a.shape[:axis], 2 * n, *a.shape[axis + 1 :])
        return stacked.reshape(shape)

    return along(along(x, 1), 2)


def _crop(x: jax.Array, size: tuple[int, ...]) -> jax.Array:
    """Crop ``[B, h, w, C]`` to its top-left ``size`` (the skip tensor's ``(h, w)``)."""
    return x[:, : size[0], : size[1], :]


def _planar_pad(x: jax.Array, pad: int) -> jax.Array:
    """Zero-pad channel-first planes ``[B, C, H, W]`` by ``pad`` on each side of ``H`` and ``W``."""
    return jnp.pad(x, ((0, 0), (0, 0), (pad, pad), (pad, pad)))


def _per_channel(v: jax.Array) -> jax.Array:
    """``[C]`` → ``[C, 1, 1]``, to broadcast over channel-first planes."""
    return v[:, None, None]


# Inference runs the full-resolution layers on channel planes (conv3x3_planar) when the last
# decoder block maps at most this many (input, output) channel pairs: the reference's 10·8 and
# the small preset's 6·4; a wider network keeps XLA's convolutions (one sum of 9·pairs terms).
PLANAR_MAX_CHANNEL_PAIRS = 128


class _ConvBlock(nnx.Module):
    """conv(k, stride s, padding (k−1)//2) → ReLU → BatchNorm (stride 2 via ``conv_s2``)."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int, momentum: float, rngs: nnx.Rngs):
        pad = (kernel - 1) // 2
        self.conv = nnx.Conv(
            cin, cout, (kernel, kernel), strides=stride, padding=((pad, pad), (pad, pad)), rngs=rngs
        )
        self.norm = nnx.BatchNorm(cout, momentum=momentum, rngs=rngs)
        self.stride = stride

    def __call__(self, x: jax.Array) -> jax.Array:
        if self.stride == 2:
            # nnx.Conv only holds the parameters here (names and initialisation as before).
            assert self.conv.bias is not None  # nnx.Conv's default use_bias=True
            y = conv_s2(x, self.conv.kernel[...])
            y = y + self.conv.bias[...].astype(y.dtype)
        else:
            y = self.conv(x)
        return self.norm(jax.nn.relu(y))

    def planar(self, x: jax.Array) -> jax.Array:
        """Inference (running averages) of a 3×3 stride-1 block on channel planes: ``x [B, C_in,
        H + 2, W + 2]`` (zero-padded) → ``[B, C_out, H, W]``; BatchNorm as ``nnx.BatchNorm``
        computes it."""
        norm = self.norm
        assert self.conv.bias is not None and norm.scale is not None and norm.bias is not None
        y = jax.nn.relu(conv3x3_planar(x, self.conv.kernel[...]) + _per_channel(self.conv.bias[...]))
        gain = norm.scale[...] * jax.lax.rsqrt(norm.var[...] + norm.epsilon)
        return (y - _per_channel(norm.mean[...])) * _per_channel(gain) + _per_channel(norm.bias[...])


class PhaseKernel(nnx.Variable):
    """A transposed convolution's kernel in the layout it is evaluated in
    (``dpc_jax.nn.conv.phase_kernel``), derived from its ``kernel`` by
    :func:`dpc_jax.nn.models.prepare_inference`: not a parameter, never trained or saved."""


class UpConv(nnx.Module):
    """Transposed conv 3×3 stride 2 → ReLU, ``[B, h, w, C_in] -> [B, 2h, 2w, C_out]``.

    Mathematically ``lax.conv_transpose(x, kernel, (2, 2), ((1, 2), (1, 2)))`` (Flax's
    ``ConvTranspose`` with that padding, i.e. PyTorch's ``ConvTranspose2d(3, stride=2, padding=1,
    output_padding=1)`` up to a kernel flip), with the same ``[3, 3, C_in, C_out]`` kernel,
    evaluated by ``dpc_jax.nn.conv.upconv3x3_s2``. ``phases`` holds the kernel's phase layout in
    a model made by :func:`dpc_jax.nn.models.prepare_inference` (else None: it is computed on
    every call).
    """

    def __init__(self, cin: int, cout: int, rngs: nnx.Rngs):
        init = nnx.initializers.lecun_normal()
        self.kernel = nnx.Param(init(rngs.params(), (3, 3, cin, cout), jnp.float32))
        self.bias = nnx.Param(jnp.zeros((cout,), jnp.float32))
        self.phases: PhaseKernel | None = nnx.data(None)

    def __call__(self, x: jax.Array, *, channels_first: bool = False) -> jax.Array:
        """``[B, h, w, C_in]`` → ``[B, 2h, 2w, C_out]``, or ``[B, C_out, 2h, 2w]``."""
        phases = phase_kernel(self.kernel[...]) if self.phases is None else self.phases[...]
        y = upconv3x3_s2_phases(x, phases, channels_first=channels_first)
        bias = self.bias[...].astype(y.dtype)
        return jax.nn.relu(y + (_per_channel(bias) if channels_first else bias))


class _Head(nnx.Module):
    """conv 3×3 (stride 1, same size) to ``frames`` channels, without normalisation."""

    def __init__(self, cin: int, cout: int, rngs: nnx.Rngs):
        self.conv = nnx.Conv(cin, cout, (3, 3), padding=((1, 1), (1, 1)), rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        # nnx.Conv only holds the parameters (names and initialisation as before).
        assert self.conv.bias is not None  # nnx.Conv's default use_bias=True
        y = conv3x3_few_outputs(x, self.conv.kernel[...])
        return y + self.conv.bias[...].astype(y.dtype)

    def planar(self, x: jax.Array) -> jax.Array:
        """The head on channel planes: ``x [B, C, H + 2, W + 2]`` (zero-padded) → ``[B, F, H, W]``."""
        assert self.conv.bias is not None
        return conv3x3_planar(x, self.conv.kernel[...]) + _per_channel(self.conv.bias[...])


class Branch(nnx.Module):
    """One encoder with its depth and mask decoders (docs/method.md §3, shared building blocks).

    ``__call__(x [B, H, W, C_in], *, training) -> (bottleneck [B, h, w, C], inv_depth [B, F, H,
    W], mask [B, F, H, W])``; ``H, W`` may be any size.

    A model prepared by :func:`dpc_jax.nn.models.prepare_inference` with ``planar=True`` runs the
    full-resolution layers (the last transposed convolutions, the last block and the two heads) on
    channel planes (``conv3x3_planar``; see :data:`PLANAR_MAX_CHANNEL_PAIRS`) outside ``training``:
    the same function summed in another order, faster on a CPU, and straight to the channel-first maps
    returned. Which path runs is the backend's choice (``dpc_jax.engine.backend``); training keeps
    XLA's convolutions, so its numerics stay what they were.
    """

    def __init__(self, config: ModelConfig, in_channels: int, frames: int, rngs: nnx.Rngs):
        c = config
        enc = [c.scaled(p) for p in c.encoder_planes]
        dec = [c.scaled(p) for p in c.decoder_planes]
        depth = len(enc)
        self.depth = depth
        self.depth_scales = c.depth_scales
        self.mask_source = c.mask_source_block

        cins = [in_channels, *enc[:-1]]
        blocks = zip(cins, enc, c.encoder_kernels, strict=True)
        self.encoder = nnx.List([_ConvBlock(ci, co, k, 2, c.bn_momentum, rngs) for ci, co, k in blocks])
        # Stage s = depth, ..., 1 upsamples to the scale of encoder output s−1 (0 = the input).
        upconvs, iconvs, heads = [], [], []
        for i, s in enumerate(range(depth, 0, -1)):
            cin = enc[-1] if i == 0 else dec[i - 1]
            upconvs.append(UpConv(cin, dec[i], rngs))
            skip = enc[s - 2] if s >= 2 else 0
            previous_head = frames if s < c.depth_scales else 0
            iconvs.append(_ConvBlock(dec[i] + skip + previous_head, dec[i], 3, 1, c.bn_momentum, rngs))
            if s <= c.depth_scales:
                heads.append(_Head(dec[i], frames, rngs))
        self.upconvs = nnx.List(upconvs)
        self.iconvs = nnx.List(iconvs)
        self.heads = nnx.List(heads)

        mask_planes = dec[depth - c.mask_source_block :]
        mask_cins = [enc[c.mask_source_block - 1], *mask_planes[:-1]]
        mask_stages = zip(mask_cins, mask_planes, strict=True)
        self.mask_upconvs = nnx.List([UpConv(ci, co, rngs) for ci, co in mask_stages])
        self.mask_head = _Head(mask_planes[-1], frames, rngs)
        last = self.iconvs[-1].conv.kernel
        # Whether the planar path fits this network's widths, and whether it runs (set by
        # prepare_inference for the backend).
        self.planar_fits = last.shape[2] * last.shape[3] <= PLANAR_MAX_CHANNEL_PAIRS
        self.planar_inference = False

    def __call__(self, x: jax.Array, *, training: bool) -> tuple[jax.Array, jax.Array, jax.Array]:
        planar = self.planar_inference and not training
        features = [x]
        for block in self.encoder:
            features.append(block(features[-1]))
        sizes = [f.shape[1:3] for f in features]

        y = features[-1]
        inv_depth_up: jax.Array | None = None
        inv_depth: jax.Array | None = None
        head_index = 0
        for i, s in enumerate(range(self.depth, 1 if planar else 0, -1)):
            y = _crop(self.upconvs[i](y), sizes[s - 1])
            parts = [y]
            if s >= 2:
                parts.append(features[s - 1])
            if inv_depth_up is not None:
                parts.append(inv_depth_up)
            y = self.iconvs[i](jnp.concatenate(parts, axis=-1))
            if s <= self.depth_scales:
                inv_depth = jax.nn.relu(self.heads[head_index](y)) + INV_DEPTH_OFFSET
                head_index += 1
                if s >= 2:
                    inv_depth_up = _crop(upsample2x_bilinear(inv_depth), sizes[s - 2])
        if planar:
            inv_depth = jax.nn.relu(self._last_stage_planar(y, inv_depth_up, sizes[0])) + INV_DEPTH_OFFSET
        else:
            assert inv_depth is not None  # the last stage s = 1 has a head (ModelConfig: depth_scales >= 1)
            inv_depth = jnp.moveaxis(inv_depth, -1, 1)
        inv_depth = 0.5 * inv_depth

        m = features[self.mask_source]
        last = len(self.mask_upconvs) - 1
        for j, upconv in enumerate(self.mask_upconvs):
            if planar and j == last:
                h, w = sizes[0]
                m = _planar_pad(upconv(m, channels_first=True)[:, :, :h, :w], 2)
            else:
                m = _crop(upconv(m), sizes[self.mask_source - 1 - j])
        if planar:
            # The head over a border of 2, cropped to 1: with a border of 1, XLA reads the centre
            # tap straight from the unpadded planes and fuses their transposition from NHWC into
            # the head, which then runs unvectorised.
            logits = self.mask_head.planar(m)[:, :, 1:-1, 1:-1]
        else:
            logits = jnp.moveaxis(self.mask_head(m), -1, 1)
        mask = jax.nn.sigmoid(logits)
        return features[-1], inv_depth, mask

    def _last_stage_planar(
        self, y: jax.Array, inv_depth_up: jax.Array | None, size: tuple[int, ...]
    ) -> jax.Array:
        """Stage s = 1 of the depth decoder in inference, on channel planes: ``y [B, h, w, C]``
        from stage 2 (and its upsampled inverse depth ``[B, H, W, F]``) → the full-resolution
        head's output before its ReLU, ``[B, F, H, W]``."""
        h, w = size
        u = self.upconvs[-1](y, channels_first=True)[:, :, :h, :w]
        parts = [u] if inv_depth_up is None else [u, jnp.moveaxis(inv_depth_up, -1, 1)]
        x = _planar_pad(jnp.concatenate(parts, axis=1), 2)
        # The block's output over the head's padded domain with its border zeroed, instead of a
        # pad of it: XLA fuses an expensive producer into a pad and runs that fusion unvectorised.
        interior = np.pad(np.ones((h, w), np.float32), 1)
        return self.heads[-1].planar(self.iconvs[-1].planar(x) * interior)
