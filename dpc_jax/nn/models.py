"""Flax NNX networks: ss-DPC-Net (``MonoDPC``) and Stereo DPC (``StereoDPC``), docs/method.md §3.

Both are built from one encoder–decoder *branch* (:class:`dpc_jax.nn.branch.Branch`: the encoder,
the depth decoder with its inverse-depth heads and the mask decoder) and a fully connected pose head:

* **Pose head**: flatten the bottleneck → dropout → FC → dropout → FC → dropout; prior branch
  FC 6→· → dropout → FC → dropout on the *normalised* prior ``(ξ_vo − μ) / σ``; concatenate →
  FC 6, times ``pose_scale`` (translation, rotation; the reference multiplies all six by 0.01), =
  ξ_corr ``[ρ, φ]``. ``fc_activation="none"`` (no non-linearity between the
  FC layers) is what the reference code does; ``"relu"`` puts a ReLU after each hidden FC.
  ``μ, σ`` are the model's :class:`PriorStatistics` variable (not trained, saved with the
  checkpoints): 0 and 1 — the reference's unscaled prior — until the training loop sets them from
  its training pairs. ``pose_init="zero"`` zero-initialises the output FC (weights and bias), so
  an untrained network outputs ξ_corr = 0 exactly: the corrected trajectory starts at the prior.

Because the pose head flattens the bottleneck, its first FC layer's input size depends on the
image size; NNX creates every parameter at construction, so the image size is part of
``ModelConfig`` (``image_size``) and the model rejects any other size with a ``ValueError``. To
use another size: ``dataclasses.replace(PRESETS["reference"], image_size=(H, W))``. The
convolutional parts accept any ``H × W``.

Inputs (see ``dpc_jax.nn.batch.Batch``): uint8 images are converted to [0, 1] and whitened with the
ImageNet statistics inside the model; optical flow (pixels) is appended unscaled, as in the
reference. Dense outputs are returned as ``[B, F, H, W]``.

Modes: ``model.train()`` uses batch statistics in BatchNorm (and updates the running averages)
and applies dropout, for which ``model(batch, key=...)`` needs an explicit PRNG key;
``model.eval()`` uses the running averages and no dropout (the key is ignored). The mode is a
static attribute, so ``graphdef, state = nnx.split(model)`` captures it and a pure jitted function
can ``nnx.merge(graphdef, state)``, call the model, and return ``nnx.state(merged)`` with the
updated BatchNorm statistics. When the model runs inside ``jax.grad`` (or another transform)
within that function while the BatchNorm statistics come in as a non-differentiated argument,
merge with ``nnx.merge(graphdef, params, stats, copy=True)``: NNX refuses to write Variables
created at an outer trace level.

The branch's deviations from the reference are listed in :mod:`dpc_jax.nn.branch`; none changes
the parameter count. ``create_model`` initialises the weights as PyTorch does by default.
"""

from __future__ import annotations

import math
from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from dpc_jax.nn.batch import Batch
from dpc_jax.nn.branch import Branch, PhaseKernel, UpConv
from dpc_jax.nn.conv import phase_kernel
from dpc_jax.nn.model_config import Method, ModelConfig, uses_flow
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# The modules that turn features and the prior into ξ_corr (the pose head), by attribute name.
POSE_HEAD = ("reduce", "left_reduce", "right_reduce", "prior", "fc_out")


class FCReduction(nnx.Module):
    """[dropout →] FC → [ReLU] → dropout → FC → [ReLU] → dropout, ``[B, n_in] -> [B, fc_planes[1]]``."""

    def __init__(self, n_in: int, config: ModelConfig, rate: float, dropout_input: bool, rngs: nnx.Rngs):
        hidden, out = config.fc_planes
        self.fc1 = nnx.Linear(n_in, hidden, rngs=rngs)
        self.fc2 = nnx.Linear(hidden, out, rngs=rngs)
        self.dropout = nnx.Dropout(rate)
        self.relu = config.fc_activation == "relu"
        self.dropout_input = dropout_input

    def __call__(self, x: jax.Array, key: jax.Array | None) -> jax.Array:
        keys = [None] * 3 if key is None else list(jax.random.split(key, 3))
        if self.dropout_input:
            x = self.dropout(x, rngs=keys[0])
        for fc, k in ((self.fc1, keys[1]), (self.fc2, keys[2])):
            x = fc(x)
            if self.relu:
                x = jax.nn.relu(x)
            x = self.dropout(x, rngs=k)
        return x


class PriorStatistics(nnx.Variable):
    """``[2, 6]`` float32: per-component mean (row 0) and scale (row 1) of ξ_vo ``[ρ (m), φ (rad)]``.

    The prior branch sees ``(ξ_vo − mean) / scale``. Not a parameter (the optimizer never touches
    it); saved and restored with the model's state. See :func:`set_prior_statistics`.
    """


def set_prior_statistics(model: _DPCBase, mean: np.ndarray, scale: np.ndarray) -> None:
    """Normalise the prior input of ``model`` by ``mean`` and ``scale`` (``[6]`` each, scale > 0)."""
    mean, scale = np.asarray(mean, np.float64), np.asarray(scale, np.float64)
    ok = mean.shape == scale.shape == (6,) and np.all(np.isfinite(mean)) and np.all(scale > 0)
    if not ok:
        raise ValueError(f"prior statistics must be 6 finite means and 6 positive scales: {mean}, {scale}")
    model.prior_statistics.set_value(jnp.asarray(np.stack([mean, scale]), jnp.float32))


def _whiten(images: jax.Array | np.ndarray) -> jax.Array:
    """uint8 ``[..., 3]`` → float32 in [0, 1] → ImageNet-whitened."""
    x = images.astype(jnp.float32) / 255.0
    # A jax.Array also for numpy images (numpy minus a jax.Array is one); numpy's stubs say ndarray.
    whitened = (x - jnp.asarray(IMAGENET_MEAN, jnp.float32)) / jnp.asarray(IMAGENET_STD, jnp.float32)
    return cast(jax.Array, whitened)


def _branch_input(images: jax.Array | np.ndarray, flow: jax.Array | np.ndarray | None) -> jax.Array:
    """``images`` uint8 ``[B, 2, H, W, 3]`` (+ flow ``[B, H, W, 2]``) → ``[B, H, W, 6 (+2)]``."""
    parts: list[jax.Array | np.ndarray] = [_whiten(images[:, 0]), _whiten(images[:, 1])]
    if flow is not None:
        parts.append(flow.astype(jnp.float32))
    return jnp.concatenate(parts, axis=-1)


def _ssim_logit(config: ModelConfig) -> jax.Array:
    """Initial λ_s parameter: sigmoid⁻¹(ssim_weight_init)."""
    p = config.ssim_weight_init
    return jnp.asarray(math.log(p / (1.0 - p)), jnp.float32)


class _DPCBase(nnx.Module):
    """Shared checks, the prior branch, the output layer and the optional λ_s parameter."""

    def __init__(self, config: ModelConfig, method: Method, n_branches: int, rngs: nnx.Rngs):
        self.config = config
        self.uses_images = config.pose_features == "images_and_prior"
        n_pose_inputs = (n_branches if self.uses_images else 0) + 1
        self.method = method
        self.use_flow = uses_flow(method, config)
        self.frames = config.frames if config.frames is not None else (1 if method == "ss_dpc" else 2)
        self.in_channels = 6 + (2 if self.use_flow else 0)
        h, w = config.scale_sizes()[-1]
        self.bottleneck_features = h * w * config.scaled(config.encoder_planes[-1])
        prior_rate = config.dropout if config.prior_dropout is None else config.prior_dropout
        self.prior = FCReduction(6, config, prior_rate, False, rngs)
        self.prior_statistics = PriorStatistics(jnp.stack([jnp.zeros(6), jnp.ones(6)]).astype(jnp.float32))
        self.fc_out = nnx.Linear(n_pose_inputs * config.fc_planes[1], 6, rngs=rngs)
        self.ssim_logit: nnx.Param[jax.Array] | None
        if config.learn_ssim_weight:
            self.ssim_logit = nnx.Param(_ssim_logit(config))
        else:
            self.ssim_logit = nnx.data(None)

    def _check(self, batch: Batch, key: jax.Array | None) -> None:
        name = type(self).__name__
        expected = (2, *self.config.image_size, 3)
        for field in ("left", "right") if self.method == "stereo_dpc" else ("left",):
            images = getattr(batch, field)
            if images.ndim != 5 or tuple(images.shape[1:]) != expected:
                raise ValueError(
                    f"{name}: batch.{field} must have shape [B, {', '.join(map(str, expected))}] "
                    f"(ModelConfig.image_size={self.config.image_size}), got {tuple(images.shape)}"
                )
        if self.use_flow:
            if batch.flow is None:
                raise ValueError(f"{name}: the model was configured with flow input but batch.flow is None")
            expected_flow = (batch.left.shape[0], 2, *self.config.image_size, 2)
            if tuple(batch.flow.shape) != expected_flow:
                raise ValueError(
                    f"{name}: batch.flow must have shape {list(expected_flow)}, got {tuple(batch.flow.shape)}"
                )
        if tuple(batch.xi_vo.shape) != (batch.left.shape[0], 6):
            raise ValueError(f"{name}: batch.xi_vo must have shape [B, 6], got {tuple(batch.xi_vo.shape)}")
        if self._training and any(
            isinstance(m, UpConv) and m.phases is not None for _, m in nnx.iter_modules(self)
        ):
            raise ValueError(f"{name}: a model prepared for inference (prepare_inference) cannot train")
        rates = (self.config.dropout, self.prior.dropout.rate)
        training_dropout = self._training and max(rates) > 0
        if training_dropout and key is None:
            raise ValueError(f"{name}: training mode applies dropout and needs key=jax.random.key(...)")

    @property
    def _training(self) -> bool:
        """Training mode (``model.train()``), as opposed to ``model.eval()``."""
        return not self.prior.dropout.deterministic

    def _keys(self, key: jax.Array | None, n: int) -> list[jax.Array | None]:
        if key is None or not self._training:
            return [None] * n
        return list(jax.random.split(key, n))

    def _reduction(self, rngs: nnx.Rngs) -> FCReduction | None:
        """The FC reduction of one branch's bottleneck, or None when the pose head ignores images."""
        if not self.uses_images:
            return nnx.data(None)
        return FCReduction(self.bottleneck_features, self.config, self.config.dropout, True, rngs)

    def _pose(
        self, reduced: list[jax.Array], xi_vo: jax.Array | np.ndarray, key: jax.Array | None
    ) -> jax.Array:
        mean, std = self.prior_statistics[...]
        prior = (xi_vo.astype(jnp.float32) - mean) / std
        features = jnp.concatenate([*reduced, self.prior(prior, key)], axis=-1)
        return jnp.asarray(self.config.component_scales(), jnp.float32) * self.fc_out(features)

    def _ssim_weight(self) -> jax.Array | None:
        return None if self.ssim_logit is None else jax.nn.sigmoid(self.ssim_logit[...])


class MonoDPC(_DPCBase):
    """ss-DPC-Net: input ``[I_t, I_{t+1}(, flow t→t+1)]`` of the left camera and the prior.

    ``model(batch, key=None) -> DPCOutputs`` with ``xi_corr [B, 6]``, ``left`` = inverse depth and
    mask ``[B, F, H, W]`` (``F = 1``: the target t+1), ``right = None``.
    """

    def __init__(self, config: ModelConfig, rngs: nnx.Rngs):
        super().__init__(config, "ss_dpc", 1, rngs)
        self.branch = Branch(config, self.in_channels, self.frames, rngs)
        self.reduce = self._reduction(rngs)

    def __call__(self, batch: Batch, *, key: jax.Array | None = None) -> DPCOutputs:
        self._check(batch, key)
        # _check raised if the model reads flow and the batch has none.
        flow = batch.flow[:, 0] if self.use_flow and batch.flow is not None else None
        bottleneck, inv_depth, mask = self.branch(_branch_input(batch.left, flow), training=self._training)
        k_reduce, k_prior = self._keys(key, 2)
        flat = bottleneck.reshape(bottleneck.shape[0], -1)
        reduced = [] if self.reduce is None else [self.reduce(flat, k_reduce)]
        xi_corr = self._pose(reduced, batch.xi_vo, k_prior)
        return DPCOutputs(xi_corr, BranchOutputs(inv_depth, mask), None, self._ssim_weight())


class StereoDPC(_DPCBase):
    """Stereo DPC (Zhang et al.): left branch on ``[I_k^l, I_{k+1}^l]``, right branch (separate
    weights) on ``[I_k^r, I_{k+1}^r]`` (each optionally + its flow), one ξ_corr from both reduced
    bottlenecks and the prior.

    ``model(batch, key=None) -> DPCOutputs`` with ``left`` and ``right`` inverse depth and masks
    ``[B, 2, H, W]`` of frames k and k+1.
    """

    def __init__(self, config: ModelConfig, rngs: nnx.Rngs):
        super().__init__(config, "stereo_dpc", 2, rngs)
        if self.frames != 2:
            raise ValueError(f"StereoDPC predicts frames k and k+1 (frames=2), got frames={config.frames}")
        self.left_branch = Branch(config, self.in_channels, self.frames, rngs)
        self.right_branch = Branch(config, self.in_channels, self.frames, rngs)
        self.left_reduce = self._reduction(rngs)
        self.right_reduce = self._reduction(rngs)

    def __call__(self, batch: Batch, *, key: jax.Array | None = None) -> DPCOutputs:
        self._check(batch, key)
        # _check raised if the model reads flow and the batch has none.
        left_flow = batch.flow[:, 0] if self.use_flow and batch.flow is not None else None
        right_flow = batch.flow[:, 1] if self.use_flow and batch.flow is not None else None
        bl, dl, ml = self.left_branch(_branch_input(batch.left, left_flow), training=self._training)
        br, dr, mr = self.right_branch(_branch_input(batch.right, right_flow), training=self._training)
        k_left, k_right, k_prior = self._keys(key, 3)
        # Both reductions exist, or neither (_reduction).
        reduced = [] if self.left_reduce is None or self.right_reduce is None else [
            self.left_reduce(bl.reshape(bl.shape[0], -1), k_left),
            self.right_reduce(br.reshape(br.shape[0], -1), k_right),
        ]
        xi_corr = self._pose(reduced, batch.xi_vo, k_prior)
        return DPCOutputs(xi_corr, BranchOutputs(dl, ml), BranchOutputs(dr, mr), self._ssim_weight())


def _init_like_pytorch(model: nnx.Module, seed: int) -> None:
    """Fill the weights of an (abstract) model in place with PyTorch's default initialisation.

    Conv, transposed conv and linear kernels and biases ~ U(−1/√fan_in, 1/√fan_in) (PyTorch's
    ``kaiming_uniform_(a=√5)`` and bias rule; for a transposed conv PyTorch takes the fan-in from
    its output channels), BatchNorm scale 1, bias 0, running mean 0, variance 1. The reference
    trained from this initialisation. Drawing with numpy also avoids compiling one XLA random
    kernel per parameter shape, which costs tens of seconds on a CPU.
    """
    rng = np.random.default_rng(seed)
    for _, module in nnx.iter_modules(model):
        if isinstance(module, UpConv):
            *window, _, cout = module.kernel.shape
            fan_in = cout * math.prod(window)
        elif isinstance(module, nnx.Conv | nnx.Linear):
            fan_in = math.prod(module.kernel.shape[:-1])
        elif isinstance(module, nnx.BatchNorm):
            n = module.num_features
            for var, value in (
                (module.scale, 1.0),
                (module.bias, 0.0),
                (module.mean, 0.0),
                (module.var, 1.0),
            ):
                assert var is not None  # nnx.BatchNorm's defaults use_scale=use_bias=True
                var.set_value(jnp.full((n,), value, jnp.float32))
            continue
        else:
            continue
        bound = 1.0 / math.sqrt(fan_in)
        for var in (module.kernel, module.bias):
            assert var is not None  # every conv and linear layer here has a bias
            var.set_value(jnp.asarray(rng.uniform(-bound, bound, var.shape).astype(np.float32)))


def create_model(method: str, config: ModelConfig, seed: int) -> MonoDPC | StereoDPC:
    """Build ``MonoDPC`` (``"ss_dpc"``) or ``StereoDPC`` (``"stereo_dpc"``) in training mode.

    Weights are drawn from ``seed`` with PyTorch's default initialisation (see
    ``_init_like_pytorch``), the output FC layer zeroed with ``config.pose_init == "zero"``, the
    prior statistics set to the identity normalisation; call ``model.eval()`` for inference.
    """
    classes: dict[str, type[MonoDPC] | type[StereoDPC]] = {"ss_dpc": MonoDPC, "stereo_dpc": StereoDPC}
    if method not in classes:
        raise ValueError(f"unknown method {method!r}; expected 'ss_dpc' or 'stereo_dpc'")
    model = nnx.eval_shape(lambda: classes[method](config, nnx.Rngs(params=seed)))
    _init_like_pytorch(model, seed)
    model.prior_statistics.set_value(jnp.stack([jnp.zeros(6), jnp.ones(6)]).astype(jnp.float32))
    if config.pose_init == "zero":
        for var in (model.fc_out.kernel, model.fc_out.bias):
            assert var is not None  # nnx.Linear's default use_bias=True
            var.set_value(jnp.zeros(var.shape, jnp.float32))
    if config.learn_ssim_weight:
        assert model.ssim_logit is not None  # a Param with learn_ssim_weight (_DPCBase)
        model.ssim_logit.set_value(_ssim_logit(config))
    leftover = [x for x in jax.tree.leaves(nnx.state(model)) if isinstance(x, jax.ShapeDtypeStruct)]
    if leftover:
        raise RuntimeError(f"create_model left {len(leftover)} variables uninitialised")
    return model


# One compiled function for all the kernels of a model (op by op, every shape compiles its own ops).
_phase_kernels = jax.jit(lambda kernels: [phase_kernel(k) for k in kernels])


def prepare_inference(
    graphdef: nnx.GraphDef, state: nnx.State, *, planar: bool = False
) -> tuple[nnx.GraphDef, nnx.State]:
    """The model ``(graphdef, state)`` (from ``nnx.split``) in evaluation mode with every transposed
    convolution's phase kernel computed once, as ``nnx.split`` returns it: for a sequence of
    batches. Without ``planar``, the same outputs bit for bit as the model itself in evaluation
    mode, without rearranging the largest kernels (up to 2.4 MB) on every call; with ``planar``,
    the full-resolution layers run on channel planes where the widths allow it (:class:`Branch`;
    the same outputs to float rounding). The prepared model refuses to train (its phase kernels
    would go stale); ``graphdef, state`` are not modified. ``dpc_jax.engine.backend`` chooses
    ``planar`` for the backend.
    """
    model = nnx.merge(graphdef, state)
    model.eval()
    for _, branch in nnx.iter_modules(model):
        if isinstance(branch, Branch):
            branch.planar_inference = planar and branch.planar_fits
    upconvs = [m for _, m in nnx.iter_modules(model) if isinstance(m, UpConv)]
    phases = _phase_kernels([m.kernel[...] for m in upconvs])
    for module, value in zip(upconvs, phases, strict=True):
        module.phases = PhaseKernel(value)
    return nnx.split(model)


def count_parameters(model: nnx.Module) -> int:
    """Number of trainable scalars (``nnx.Param``; BatchNorm running statistics excluded)."""
    return sum(x.size for x in jax.tree.leaves(nnx.state(model, nnx.Param)))
