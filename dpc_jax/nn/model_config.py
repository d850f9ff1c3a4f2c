"""The networks' and losses' configurations, as frozen dataclasses (no JAX).

:class:`ModelConfig` and its :data:`PRESETS` describe both networks (:mod:`dpc_jax.nn.models`);
:class:`SSDPCLossConfig` and :class:`StereoDPCLossConfig` their losses (:mod:`dpc_jax.nn.losses`);
:class:`SupervisedLossConfig` DPC-Net's supervised loss, which either network can be trained with.
They import no JAX, so a training config (:mod:`dpc_jax.training.train_config`) is checked, and a mistake
in it reported, before the command line starts JAX. They are hashable: the losses take them as
static arguments under ``jax.jit``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Literal

Method = Literal["ss_dpc", "stereo_dpc"]


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of both networks (defaults = the reference code, 240×376 input).

    * ``image_size``: ``(H, W)`` of the input images; fixes the pose head's first FC size.
    * ``encoder_planes``, ``encoder_kernels``: output channels and (odd) kernel size per encoder
      block; their length is the encoder depth.
    * ``decoder_planes``: output channels of the transposed conv of each depth-decoder stage,
      deepest first (same length as the encoder). The mask decoder uses the last
      ``mask_source_block`` entries.
    * ``width_multiplier``: scales every encoder/decoder plane count (rounded, at least 1).
    * ``mask_source_block``: 1-based encoder block whose output feeds the mask decoder.
    * ``depth_scales``: number of inverse-depth heads (the last stages of the decoder).
    * ``fc_planes``: ``(hidden, out)`` sizes of the two FC layers of each pose-head reduction.
    * ``fc_activation``: ``"none"`` (reference code) or ``"relu"`` between the FC layers.
    * ``dropout``: dropout rate on the FC reductions of the image features (training mode only).
    * ``prior_dropout``: dropout rate on the prior branch; None = ``dropout`` (the reference).
    * ``pose_init``: ``"pytorch"`` (the reference: PyTorch's default initialisation of every
      layer) or ``"zero"`` (the output FC layer starts at zero weights and bias: ξ_corr = 0).
    * ``pose_features``: what the output layer sees: ``"images_and_prior"`` (the papers: the reduced
      image bottlenecks and the prior branch) or ``"prior"`` (the prior branch only: the
      correction is a learned function of the VO step, fitted to the images by the loss; the
      image branches still give depth and masks).
    * ``pose_scale``: ``(translation m, rotation rad)`` per unit of the output layer, or six
      numbers, one per component ``[ρx, ρy, ρz, φx, φy, φz]`` (0 switches a component off); the
      reference's 0.01 for all. Adam moves every output weight by about the learning rate
      whatever its gradient, so this sets the jitter of each component's correction.
    * ``flow``: append Farnebäck flow (2 channels) to each branch's input; ``None`` = the
      method's default (ss-DPC-Net: True, Stereo DPC: False).
    * ``frames``: frames ``F`` with inverse depth and mask per branch; ``None`` = the method's
      default (ss-DPC-Net: 1, the target t+1; Stereo DPC: 2, frames k and k+1). ss-DPC-Net also
      accepts 2 (frames t and t+1); Stereo DPC needs 2 (its temporal loss goes both ways).
    * ``learn_ssim_weight``: hold a scalar parameter ``s`` and return λ_s = sigmoid(s) in
      ``DPCOutputs.ssim_weight``, initialised to ``ssim_weight_init``; otherwise return None and
      the loss uses its fixed value.
    * ``bn_momentum``: BatchNorm running-average momentum, Flax convention.
    """

    image_size: tuple[int, int] = (240, 376)
    encoder_planes: tuple[int, ...] = (8, 16, 32, 64, 128, 256, 256)
    encoder_kernels: tuple[int, ...] = (7, 5, 3, 3, 3, 3, 3)
    decoder_planes: tuple[int, ...] = (256, 128, 64, 32, 16, 8, 8)
    width_multiplier: float = 1.0
    mask_source_block: int = 5
    depth_scales: int = 4
    fc_planes: tuple[int, int] = (256, 128)
    fc_activation: Literal["none", "relu"] = "none"
    dropout: float = 0.5
    prior_dropout: float | None = None
    pose_init: Literal["pytorch", "zero"] = "pytorch"
    pose_scale: tuple[float, ...] = (0.01, 0.01)
    pose_features: Literal["images_and_prior", "prior"] = "images_and_prior"
    flow: bool | None = None
    frames: int | None = None
    learn_ssim_weight: bool = False
    ssim_weight_init: float = 0.85
    bn_momentum: float = 0.9

    def __post_init__(self) -> None:
        depth = len(self.encoder_planes)
        problems = []
        if len(self.image_size) != 2 or min(self.image_size) < 1:
            problems.append(f"image_size must be (H, W) with H, W >= 1, got {self.image_size}")
        if len(self.encoder_kernels) != depth or len(self.decoder_planes) != depth:
            problems.append(
                f"encoder_planes, encoder_kernels and decoder_planes must have the same length, got "
                f"{depth}, {len(self.encoder_kernels)}, {len(self.decoder_planes)}"
            )
        if any(k < 1 or k % 2 == 0 for k in self.encoder_kernels):
            problems.append(f"encoder_kernels must be odd and positive, got {self.encoder_kernels}")
        if not 1 <= self.depth_scales <= depth:
            problems.append(f"depth_scales must be in [1, {depth}], got {self.depth_scales}")
        if not 1 <= self.mask_source_block <= depth:
            problems.append(f"mask_source_block must be in [1, {depth}], got {self.mask_source_block}")
        if self.width_multiplier <= 0:
            problems.append(f"width_multiplier must be > 0, got {self.width_multiplier}")
        if len(self.fc_planes) != 2 or min(self.fc_planes) < 1:
            problems.append(f"fc_planes must be two positive sizes, got {self.fc_planes}")
        if self.fc_activation not in ("none", "relu"):
            problems.append(f"fc_activation must be 'none' or 'relu', got {self.fc_activation!r}")
        if not 0.0 <= self.dropout < 1.0:
            problems.append(f"dropout must be in [0, 1), got {self.dropout}")
        if self.prior_dropout is not None and not 0.0 <= self.prior_dropout < 1.0:
            problems.append(f"prior_dropout must be None or in [0, 1), got {self.prior_dropout}")
        if len(self.pose_scale) not in (2, 6) or not all(x >= 0 for x in self.pose_scale) or not any(
            self.pose_scale
        ):
            problems.append(f"pose_scale must be 2 or 6 numbers >= 0, not all 0, got {self.pose_scale}")
        if self.pose_features not in ("images_and_prior", "prior"):
            problems.append(f"pose_features must be 'images_and_prior' or 'prior': {self.pose_features!r}")
        if self.pose_init not in ("pytorch", "zero"):
            problems.append(f"pose_init must be 'pytorch' or 'zero', got {self.pose_init!r}")
        if self.frames not in (None, 1, 2):
            problems.append(f"frames must be None, 1 or 2, got {self.frames}")
        if not 0.0 < self.ssim_weight_init < 1.0:
            problems.append(f"ssim_weight_init must be in (0, 1), got {self.ssim_weight_init}")
        if not 0.0 <= self.bn_momentum < 1.0:
            problems.append(f"bn_momentum must be in [0, 1), got {self.bn_momentum}")
        if problems:
            raise ValueError("invalid ModelConfig: " + "; ".join(problems))

    def component_scales(self) -> tuple[float, ...]:
        """The six output scales ``[ρx, ρy, ρz, φx, φy, φz]`` of ``pose_scale``."""
        if len(self.pose_scale) == 2:
            return (self.pose_scale[0],) * 3 + (self.pose_scale[1],) * 3
        return tuple(self.pose_scale)

    def scaled(self, planes: int) -> int:
        """Plane count after the width multiplier."""
        return max(1, round(planes * self.width_multiplier))

    def scale_sizes(self) -> list[tuple[int, int]]:
        """``(h, w)`` of the input followed by the output of every encoder block."""
        h0, w0 = self.image_size
        sizes = [(h0, w0)]
        for _ in self.encoder_planes:
            h, w = sizes[-1]
            sizes.append((-(-h // 2), -(-w // 2)))
        return sizes


PRESETS: dict[str, ModelConfig] = {
    "reference": ModelConfig(),
    # Tests and the CPU demo: 5 encoder blocks at half width, small FC layers, 64×96 images.
    "small": ModelConfig(
        image_size=(64, 96),
        encoder_planes=(8, 16, 32, 64, 128),
        encoder_kernels=(7, 5, 3, 3, 3),
        decoder_planes=(128, 64, 32, 16, 8),
        width_multiplier=0.5,
        mask_source_block=4,
        fc_planes=(64, 32),
    ),
}


def uses_flow(method: str, config: ModelConfig) -> bool:
    """The flow-input rule: ``config.flow`` when set, else the method's default (ss-DPC-Net reads flow)."""
    return config.flow if config.flow is not None else method == "ss_dpc"


@dataclass(frozen=True)
class SSDPCLossConfig:
    """ss-DPC-Net loss (Wagstaff et al. 2020, eq. 7–11).

    * ``exp_weight``: λ_exp of the explainability-mask regulariser (paper 0.23; the reference
      scripts default to 0.18).
    * ``rot_weight``, ``rot_threshold``: a sample whose prior rotation ``‖Log(R_vo)‖ ≥ γ``
      (rad) has its photometric term multiplied by ``1 + λ_rot``.
    * ``rotation_only``: apply only the rotation part of ``ξ_corr`` (ss-DPC-Net on libviso2-s).
    * ``ssim_weight``: λ_s of :func:`photometric_error`; the paper's loss is pure L1 (0). A
      model that learns λ_s (``outputs.ssim_weight`` not None) overrides it.
    * ``grad_threshold``: γ_grad of the gradient mask (epoch selection only).
    * ``mask_floor``: clamp of the mask inside ``−log W``.
    * ``depth_eps``: points closer than this (m) to the source camera plane are invalid.
    """

    method: ClassVar[str] = "ss_dpc"

    exp_weight: float = 0.23
    rot_weight: float = 4.0
    rot_threshold: float = 0.005
    rotation_only: bool = False
    ssim_weight: float = 0.0
    grad_threshold: float = 0.03
    mask_floor: float = 1e-6
    depth_eps: float = 1e-3


@dataclass(frozen=True)
class StereoDPCLossConfig:
    """Stereo DPC loss (Zhang et al. 2021, eq. 14).

    * ``alpha``: (α1 spatial, α2 disparity consistency, α3 temporal, α4 mask regulariser).
    * ``ssim_weight``: fixed λ_s; a model that learns λ_s (``outputs.ssim_weight``) overrides it.
    * ``rotation_only``, ``grad_threshold``, ``mask_floor``, ``depth_eps``: as in
      :class:`SSDPCLossConfig`.
    """

    method: ClassVar[str] = "stereo_dpc"

    alpha: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 0.08)
    ssim_weight: float = 0.85
    rotation_only: bool = False
    grad_threshold: float = 0.03
    mask_floor: float = 1e-6
    depth_eps: float = 1e-3


@dataclass(frozen=True)
class SupervisedLossConfig:
    """DPC-Net's supervised loss (Peretroukhin & Kelly 2018; docs/method.md, "The supervised loss").

    It regresses ``ξ_corr`` on the ground-truth correction of each pair, so it reads ground truth
    (``batch.xi_gt``); either network can be trained with it.

    * ``precision``: the 6 × 6 weight ``Σ⁻¹`` of the SE(3) error, row-major (36 numbers), or its
      diagonal (6 numbers), in the units of ``[ρ (m), φ (rad)]``. DPC-Net uses the inverse
      covariance of the training set's target corrections
      (:func:`dpc_jax.nn.supervised_loss.target_precision`), which the training loop puts here when
      it is None (:func:`dpc_jax.nn.supervised_loss.with_target_precision`); the loss function
      itself weighs every component by 1 when it is None.
    * ``rotation_only``: regress the rotation only, on SO(3), with the rotation block of
      ``precision`` (DPC-Net's rotation-only variant; ss-DPC-Net's setting for stereo priors).
    * ``method``: the network it trains (``"ss_dpc"`` or ``"stereo_dpc"``); the training step
      compiles for that network, as with the self-supervised configs' ``method``.
    """

    precision: tuple[float, ...] | None = None
    rotation_only: bool = False
    method: str = "stereo_dpc"

    def __post_init__(self) -> None:
        if self.method not in ("ss_dpc", "stereo_dpc"):
            raise ValueError(f"method must be 'ss_dpc' or 'stereo_dpc', got {self.method!r}")
        if self.precision is not None:
            values = tuple(float(v) for v in self.precision)
            if len(values) not in (6, 36) or not all(math.isfinite(v) for v in values):
                raise ValueError(
                    "precision must be 6 (diagonal) or 36 (6 × 6, row-major) finite numbers, "
                    f"got {self.precision!r}"
                )
            object.__setattr__(self, "precision", values)

    def precision_matrix(self) -> list[list[float]]:
        """``Σ⁻¹`` as a 6 × 6 nested list (identity when ``precision`` is None)."""
        if self.precision is None:
            return [[1.0 if i == j else 0.0 for j in range(6)] for i in range(6)]
        if len(self.precision) == 6:
            return [[self.precision[i] if i == j else 0.0 for j in range(6)] for i in range(6)]
        return [list(self.precision[6 * i:6 * i + 6]) for i in range(6)]
