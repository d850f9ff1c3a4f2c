"""``TrainConfig``: one training run as data, and the published settings (``REFERENCE``).

Importing this module does not import JAX or the training loop: inference (``dpc_jax.correction.inference``)
reads a run's stored config with it.

Defaults and the reference
--------------------------
The defaults of the correction head are the *improved* ones (``IMPROVED``); ``REFERENCE`` holds
the published choices (ss-DPC-Net's released code: PyTorch initialisation of the pose layer, no
warm-up, the prior fed unscaled, dropout 0.5 on the whole pose head). Each improvement is a
separate field, so a config can take any subset (``experiments/studies/ablation.py`` adds them one by
one; its table in docs/results/ablation.md is the measurement behind them):

* ``pose_init="zero"``: the output FC layer starts at zero, so an untrained network's corrected
  trajectory *is* the prior (with the reference initialisation it outputs an almost constant
  correction of a few mrad and mm per frame, several times a good VO's whole error).
* ``pose_warmup_epochs``/``pose_warmup_steps``: the first updates see ξ_corr = 0 in the loss, so
  depth, masks and λ_s learn before the pose head does (early depth is poor and explains
  parallax with rotation).
* ``prior_normalization="train_statistics"``: the prior branch sees ``(ξ_vo − μ) / σ`` with the
  per-component mean and standard deviation of the training pairs' priors (stored in the
  model's state, so inference uses the same), instead of metres and radians side by side.
* ``dropout`` on the image-feature reductions and ``prior_dropout`` on the prior branch set
  apart; both off by default (training-mode dropout 0.5 moves the correction by mrad between
  keys, far more than the precision a correction needs).
* ``pose_lr_multiplier``: the pose head's learning rate relative to the rest.
* ``pose_scale``: the correction per unit of the output layer, per component ``[ρx, ρy, ρz, φx,
  φy, φz]``: 1 cm along the direction of travel (z), 0.1 mrad for rotations, and no sideways or
  vertical translation. The reference's 0.01 for all makes a rotation unit a hundred times larger
  than a good VO's rotation error per frame (Adam moves every output weight by about the learning
  rate, so the rotation then jitters by more than the drift it should learn). And a small yaw
  and a sideways step move distant image content alike: free to correct both, the networks traded
  one for the other along that valley of the photometric loss (a spurious sideways correction of
  5–8 mm per frame against the wrong yaw); a VO's systematic translation error lies along its
  direction of travel (a scale error: docs/results/demo.md), so the other two are off.
* ``pose_features="prior"``: the correction is a learned function of the VO step alone (the image
  branches still give the depth and masks the loss needs). What a correction can learn is the
  VO's systematic error, a function of its motion; from 64×96 images the per-pair correction is
  noisy, and that noise adds to the trajectory's error.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from dpc_jax.config import ConfigError, unknown_key_error
from dpc_jax.nn.model_config import (
    PRESETS,
    ModelConfig,
    SSDPCLossConfig,
    StereoDPCLossConfig,
    SupervisedLossConfig,
    uses_flow,
)

METHODS = ("ss_dpc", "stereo_dpc")
PRIOR_NORMALIZATIONS = ("none", "train_statistics")
ACCEPTANCE_DEPTHS = ("network", "sgbm")
# "self": the method's self-supervised loss (no ground truth is read for training); "supervised":
# DPC-Net's supervised loss (nn.config.SupervisedLossConfig), which reads ground truth.
SUPERVISIONS = ("self", "supervised")
# Epoch selection criterion (``dpc-jax correct --select``) → the run's checkpoint folder holding
# that epoch (see dpc_jax.training.checkpoints).
SELECTIONS = {
    "delta": "best_delta", "gradient": "best_gradient_loss", "loop": "best_loop_closures", "last": "epochs",
}
DEFAULT_SELECTION = "delta"  # the epoch that lowered the validation Δ most (none if none lowered it)

# The published choices of the correction head (see the module docstring).
REFERENCE: dict[str, Any] = {
    "pose_init": "pytorch",
    "pose_warmup_epochs": 0,
    "pose_warmup_steps": 0,
    "prior_normalization": "none",
    "dropout": 0.5,
    "prior_dropout": None,
    "pose_lr_multiplier": 1.0,
    "pose_scale": (0.01, 0.01),
    "pose_features": "images_and_prior",
}


@dataclass(frozen=True)
class TrainConfig:
    """One training run, as data (docs/method.md §5; the optimisation defaults are the Stereo DPC paper's).

    Model
        * ``method``: ``"ss_dpc"`` (ss-DPC-Net, mono + flow) or ``"stereo_dpc"`` (Zhang et al.).
        * ``preset``: a key of ``dpc_jax.nn.model_config.PRESETS`` (``"reference"``, ``"small"``).
        * ``model``: overrides of ``ModelConfig`` fields on top of the preset.
        * ``image_size``: ``(H, W)`` of the cached images and the network input; None = the
          preset's.
        * ``learn_ssim_weight``: λ_s mode: True learns λ_s = sigmoid(s) (a model parameter),
          False uses the loss config's fixed value.
    Correction head (defaults: the improved settings; ``REFERENCE``: the published ones)
        * ``pose_init``: ``"zero"`` or ``"pytorch"`` (see ``ModelConfig.pose_init``).
        * ``pose_warmup_epochs``, ``pose_warmup_steps``: the loss sees ξ_corr = 0 for the first
          ``pose_warmup_epochs · steps_per_epoch + pose_warmup_steps`` optimizer steps.
        * ``prior_normalization``: ``"train_statistics"`` or ``"none"``.
        * ``dropout``: dropout rate on the FC reductions of the image features.
        * ``prior_dropout``: dropout rate on the prior branch; None = ``dropout``.
        * ``pose_lr_multiplier``: learning-rate factor of the pose head (FC reductions, prior
          branch, output layer).
        * ``pose_scale``: ``(translation m, rotation rad)`` per unit of the output layer, or six
          numbers, one per component (0 switches it off).
        * ``pose_features``: ``"images_and_prior"`` or ``"prior"`` (see ``ModelConfig``).
    Loss
        * ``loss``: overrides of the method's loss config (``SSDPCLossConfig`` or
          ``StereoDPCLossConfig``): term weights, fixed λ_s, rotation weighting γ and λ_rot, ...
        * ``rotation_only``: apply only the rotation part of ξ_corr when composing corrected
          trajectories (ss-DPC-Net with a stereo prior); passed to the loss config too when it
          has such a field.
        * ``supervision``: ``"self"`` (the method's self-supervised loss; training batches carry no
          ground truth) or ``"supervised"`` (DPC-Net's supervised loss, ``SupervisedLossConfig``:
          the training batches carry the ground truth, which every training sequence must have).
          Validation, epoch selection and the acceptance test use the method's loss either way.
        * ``precision``: with ``supervision: supervised``, the loss's ``Σ⁻¹`` (6 diagonal or 36
          numbers); None: DPC-Net's, the inverse covariance of the training pairs' target corrections.
    Optimisation
        * ``batch_size`` (global, over all devices and hosts), ``epochs``.
        * ``learning_rate``, ``lr_halving_epochs``: initial rate, halved every that many epochs.
        * ``weight_decay``: coupled L2 (PyTorch ``Adam(weight_decay=...)``).
        * ``steps_per_epoch``: cap on the optimizer steps per epoch; None = one full pass.
        * ``seed``: parameter initialisation and dropout; ``data_seed``: shuffling.
    Data (a preprocessing cache written by ``dpc-jax prepare``)
        * ``cache_root``: directory of the cache.
        * ``train_sequences``: empty = every cached sequence except validation and test ones.
        * ``validation_sequences``: used for epoch selection (no ground truth needed).
        * ``test_sequences``: held out, never loaded by training (recorded in the split).
        * ``frame_skip``: add a copy of each training sequence with every second frame.
        * ``reverse``: add reversed copies of the training sequences.
    Selection
        * ``acceptance_depth``: the depth with which the correction's photometric effect Δ is
          measured on the validation sequence (selection ``delta``) and, by default, by
          ``dpc-jax correct``: ``"network"`` (the network's own) or ``"sgbm"`` (OpenCV
          StereoSGBM on the pair, Stereo DPC only).
    Run
        * ``keep_checkpoints``: how many every-epoch checkpoints to keep (best ones are extra).
        * ``log_every``: steps between TensorBoard training scalars.
        * ``distributed``: call ``jax.distributed.initialize`` (several hosts; see
          ``dpc_jax.engine.parallel``).
    """

    method: str = "stereo_dpc"
    preset: str = "reference"
    model: dict[str, Any] = field(default_factory=dict)
    image_size: tuple[int, int] | None = None
    learn_ssim_weight: bool = False
    pose_init: str = "zero"
    pose_warmup_epochs: int = 1
    pose_warmup_steps: int = 0
    prior_normalization: str = "train_statistics"
    dropout: float = 0.0
    prior_dropout: float | None = 0.0
    pose_lr_multiplier: float = 1.0
    pose_scale: tuple[float, ...] = (0.0, 0.0, 0.01, 1e-4, 1e-4, 1e-4)
    pose_features: str = "prior"
    loss: dict[str, Any] = field(default_factory=dict)
    rotation_only: bool = False
    supervision: str = "self"
    precision: tuple[float, ...] | None = None
    batch_size: int = 32
    epochs: int = 30
    learning_rate: float = 6e-3
    lr_halving_epochs: int = 5
    weight_decay: float = 4e-6
    steps_per_epoch: int | None = None
    seed: int = 0
    data_seed: int = 0
    cache_root: str = ""
    train_sequences: tuple[str, ...] = ()
    validation_sequences: tuple[str, ...] = ()
    test_sequences: tuple[str, ...] = ()
    frame_skip: bool = True
    reverse: bool = False
    acceptance_depth: str = "network"
    keep_checkpoints: int = 3
    log_every: int = 10
    distributed: bool = False

    def __post_init__(self) -> None:
        problems = []
        if self.method not in METHODS:
            problems.append(f"method must be one of {METHODS}, got {self.method!r}")
        for name in ("batch_size", "epochs", "lr_halving_epochs", "keep_checkpoints", "log_every"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("pose_warmup_epochs", "pose_warmup_steps"):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.steps_per_epoch is not None and self.steps_per_epoch < 1:
            problems.append(f"steps_per_epoch must be >= 1 or None, got {self.steps_per_epoch}")
        if not self.learning_rate > 0 or not math.isfinite(self.learning_rate):
            problems.append(f"learning_rate must be > 0, got {self.learning_rate}")
        if not self.pose_lr_multiplier > 0 or not math.isfinite(self.pose_lr_multiplier):
            problems.append(f"pose_lr_multiplier must be > 0, got {self.pose_lr_multiplier}")
        if not self.weight_decay >= 0:
            problems.append(f"weight_decay must be >= 0, got {self.weight_decay}")
        if self.prior_normalization not in PRIOR_NORMALIZATIONS:
            problems.append(
                f"prior_normalization must be one of {PRIOR_NORMALIZATIONS}, got {self.prior_normalization!r}"
            )
        if self.acceptance_depth not in ACCEPTANCE_DEPTHS:
            problems.append(
                f"acceptance_depth must be one of {ACCEPTANCE_DEPTHS}, got {self.acceptance_depth!r}"
            )
        elif self.acceptance_depth == "sgbm" and self.method != "stereo_dpc":
            problems.append("acceptance_depth 'sgbm' needs the stereo method (stereo_dpc)")
        if self.supervision not in SUPERVISIONS:
            problems.append(f"supervision must be one of {SUPERVISIONS}, got {self.supervision!r}")
        elif self.precision is not None and self.supervision != "supervised":
            problems.append("precision is used only with supervision 'supervised'")
        if self.image_size is not None and min(self.image_size) < 1:
            problems.append(f"image_size must be positive, got {self.image_size}")
        top_level = ("image_size", "dropout", "prior_dropout", "pose_init", "pose_scale", "pose_features",
                     "learn_ssim_weight")
        for key in top_level:
            if key in self.model:
                problems.append(f"model.{key} duplicates the top-level key {key!r}; set it there")
        if not self.validation_sequences:
            problems.append("validation_sequences is empty; epoch selection needs at least one")
        for name in ("train_sequences", "validation_sequences", "test_sequences"):
            seqs = getattr(self, name)
            if len(set(seqs)) != len(seqs):
                problems.append(f"{name} lists a sequence twice: {list(seqs)}")
        for a, b in (("train", "validation"), ("train", "test"), ("validation", "test")):
            common = sorted(set(getattr(self, f"{a}_sequences")) & set(getattr(self, f"{b}_sequences")))
            if common:
                problems.append(f"sequence(s) {common} are both in {a}_sequences and {b}_sequences")
        if problems:
            raise ConfigError("invalid TrainConfig: " + "; ".join(problems))
        # Fail now, not after data loading, on bad model or loss overrides.
        self.model_config()
        self.loss_config()
        self.train_loss_config()

    def model_config(self) -> ModelConfig:
        """The ``ModelConfig``: the preset, the ``model`` overrides and the top-level model keys."""
        if self.preset not in PRESETS:
            raise ConfigError(f"preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        base = PRESETS[self.preset]
        overrides = dict(
            self.model, dropout=self.dropout, prior_dropout=self.prior_dropout, pose_init=self.pose_init,
            pose_scale=tuple(self.pose_scale), pose_features=self.pose_features,
            learn_ssim_weight=self.learn_ssim_weight,
        )
        if self.image_size is not None:
            overrides["image_size"] = tuple(self.image_size)
        return _replace(base, overrides, "model")

    def loss_config(self) -> SSDPCLossConfig | StereoDPCLossConfig:
        """The method's loss config dataclass with the ``loss`` overrides (and ``rotation_only``)."""
        base = SSDPCLossConfig() if self.method == "ss_dpc" else StereoDPCLossConfig()
        overrides = dict(self.loss)
        if "rotation_only" in overrides:
            raise ConfigError("loss.rotation_only duplicates the top-level key 'rotation_only'; set it there")
        if any(f.name == "rotation_only" for f in dataclasses.fields(base)):
            overrides["rotation_only"] = self.rotation_only
        return _replace(base, overrides, "loss")

    def train_loss_config(self) -> SSDPCLossConfig | StereoDPCLossConfig | SupervisedLossConfig:
        """The loss the training step minimises: :meth:`loss_config`, or with ``supervision:
        supervised`` DPC-Net's supervised loss for this method's network."""
        if self.supervision != "supervised":
            return self.loss_config()
        try:
            return SupervisedLossConfig(
                precision=None if self.precision is None else tuple(self.precision),
                rotation_only=self.rotation_only, method=self.method,
            )
        except ValueError as error:
            raise ConfigError(f"invalid TrainConfig: {error}") from None

    @property
    def resolved_image_size(self) -> tuple[int, int]:
        h, w = self.model_config().image_size
        return h, w

    @property
    def use_flow(self) -> bool:
        """Whether the network reads optical flow (the method's default unless ``model`` says)."""
        return uses_flow(self.method, self.model_config())

    def pose_training_problem(self) -> str | None:
        """Why this config's training can never move the pose head, or None: the pose warm-up
        (``pose_warmup_epochs``) lasting every epoch, so the loss sees ξ_corr = 0 throughout and the
        trained network corrects nothing (with ``pose_init="zero"`` its correction is exactly 0).
        ``dpc-jax train`` refuses such a config; ``dpc_jax.training.loop.train`` warns."""
        if self.supervision == "supervised" or self.epochs > self.pose_warmup_epochs:
            return None
        return (f"epochs {self.epochs} <= pose_warmup_epochs {self.pose_warmup_epochs}: the loss sees "
                "ξ_corr = 0 in every epoch, so the pose layer is never trained and the network corrects "
                f"nothing; give epochs >= {self.pose_warmup_epochs + 1} (or a shorter pose_warmup_epochs)")

    def warmup_steps(self, steps_per_epoch: int) -> int:
        """Optimizer steps during which the loss sees ξ_corr = 0: none with the supervised loss,
        which sees nothing but ξ_corr (held at 0 it would give every weight a zero gradient)."""
        if self.supervision == "supervised":
            return 0
        return self.pose_warmup_epochs * steps_per_epoch + self.pose_warmup_steps


def _replace(base: Any, overrides: dict[str, Any], where: str) -> Any:
    """``dataclasses.replace`` with unknown keys and the dataclass's own checks as ``ConfigError``."""
    names = [f.name for f in dataclasses.fields(base)]
    for key in overrides:
        if key not in names:
            raise unknown_key_error(key, names, where)
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    try:
        return dataclasses.replace(base, **values)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{where}: {error}") from None
