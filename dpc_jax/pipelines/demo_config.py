"""What the synthetic demo (:mod:`dpc_jax.pipelines.synthetic_demo`) renders, how it trains and how it
corrects."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

from dpc_jax import config as config_lib
from dpc_jax.data.holdout import MIN_EVERY
from dpc_jax.training.train_config import SELECTIONS
from dpc_jax.vo.odometry import FALLBACK_WARNING_SHARE

# Training defaults of the demo (``TrainConfig`` fields); ``DemoConfig.training`` overrides them.
TRAINING: dict[str, Any] = {
    "method": "stereo_dpc",
    "preset": "small",
    "image_size": (64, 96),
    "batch_size": 8,
    "epochs": 8,
    "learning_rate": 2e-3,
    "lr_halving_epochs": 2,
    "keep_checkpoints": 1,
}
# The demo sets these itself (paths and split).
_MANAGED = ("cache_root", "train_sequences", "validation_sequences", "test_sequences")


@dataclass(frozen=True)
class DemoConfig:
    """What the demo renders, how it trains and how it corrects.

    Data
        * ``train_sequences``, ``train_frames``: number and length (frames, 10 Hz) of the training
          sequences; ``validation_frames``, ``test_frames``: the one validation (epoch selection)
          and one test (held out) sequence.
        * ``render_size``: ``(H, W)`` of the rendered images (the VO runs on them; the network
          sees them resized to the training ``image_size``).
        * ``moving_objects``, ``illumination_drift``, ``noise``, ``disparity_offset``: see
          ``dpc_jax.synth.SynthConfig``.
        * ``vo_estimate_offset``: the prior's VO self-calibrates the disparity offset (False: it
          ignores the residual, as libviso2).
        * ``rectify_offset``: measure the residual with our VO's online estimate and rectify the
          network's images by it.
        * ``seed``: training sequence i has seed ``seed + i``, validation ``seed + 100``, test
          ``seed + 200``.
    Training and correction
        * ``training``: ``TrainConfig`` fields overriding :data:`TRAINING` (not the cache root
          or the split, which the demo sets).
        * ``select``: the epoch used for the test: ``delta`` (most negative validation Δ; no ground
          truth), ``gradient``, ``loop`` or ``last``.
        * ``acceptance``: apply a correction only where the acceptance test passes (False: apply
          every correction, as the papers do).
        * ``mean_test``: test the correction's mean over the sequence on its own
          (``dpc_jax.correction.decision``; False: the earlier decision, a whole part or nothing).
        * ``adapt_steps`` (0: no adaptation), ``holdout_every``: see ``dpc_jax.correction.adapt``.
        * ``max_fallback_share``: the demo refuses a prior whose VO fell back to constant velocity on
          more of the pairs than this (default ``dpc_jax.vo.odometry.FALLBACK_WARNING_SHARE``).
    """

    train_sequences: int = 2
    train_frames: int = 300
    validation_frames: int = 150
    test_frames: int = 300
    render_size: tuple[int, int] = (240, 376)
    moving_objects: int = 6
    illumination_drift: float = 0.3
    noise: float = 1.0
    disparity_offset: float = -0.8
    vo_estimate_offset: bool = False
    rectify_offset: bool = True
    seed: int = 0
    training: dict[str, Any] = field(default_factory=dict)
    select: str = "delta"
    acceptance: bool = True
    mean_test: bool = True
    adapt_steps: int = 300
    holdout_every: int = 5
    max_fallback_share: float = FALLBACK_WARNING_SHARE

    def __post_init__(self) -> None:
        problems = []
        if self.train_sequences < 1:
            problems.append(f"train_sequences must be >= 1, got {self.train_sequences}")
        for name in ("train_frames", "validation_frames", "test_frames"):
            if getattr(self, name) < 3:
                problems.append(f"{name} must be >= 3, got {getattr(self, name)}")
        if self.select not in SELECTIONS:
            problems.append(f"select must be one of {tuple(SELECTIONS)}, got {self.select!r}")
        if self.adapt_steps < 0 or self.holdout_every < MIN_EVERY:
            problems.append(f"adapt_steps must be >= 0 and holdout_every >= {MIN_EVERY}, got "
                            f"{self.adapt_steps}, {self.holdout_every}")
        managed = sorted(set(self.training) & set(_MANAGED))
        if managed:
            problems.append(f"training sets {managed}, which the demo chooses itself")
        if problems:
            raise config_lib.ConfigError("invalid DemoConfig: " + "; ".join(problems))
        self.synth_config("test")  # SynthConfig's own checks
        self.train_config("cache")  # TrainConfig's own checks

    @property
    def sequences(self) -> dict[str, str]:
        """Sequence name → role (``train``, ``validation``, ``test``), in rendering order."""
        names = {f"train{i}": "train" for i in range(self.train_sequences)}
        return {**names, "val": "validation", "test": "test"}

    def synth_config(self, name: str) -> Any:
        """The ``SynthConfig`` of sequence ``name`` (see :attr:`sequences`)."""
        from dpc_jax.synth import SynthConfig

        if name.startswith("train"):
            frames, seed = self.train_frames, self.seed + int(name[5:])
        elif name == "val":
            frames, seed = self.validation_frames, self.seed + 100
        elif name == "test":
            frames, seed = self.test_frames, self.seed + 200
        else:
            raise KeyError(f"no demo sequence {name!r}; expected one of {list(self.sequences)}")
        return SynthConfig(
            frames=frames, height=self.render_size[0], width=self.render_size[1], seed=seed,
            moving_objects=self.moving_objects, illumination_drift=self.illumination_drift, noise=self.noise,
            disparity_offset=self.disparity_offset,
        )

    def train_config(self, cache_root: str | os.PathLike) -> Any:
        """The ``TrainConfig`` of the demo's run on the caches under ``cache_root``."""
        from dpc_jax.training.train_config import TrainConfig

        roles = self.sequences
        values = {
            **TRAINING,
            **self.training,
            "cache_root": str(cache_root),
            "train_sequences": tuple(n for n, r in roles.items() if r == "train"),
            "validation_sequences": ("val",),
            "test_sequences": ("test",),
        }
        return config_lib.from_dict(TrainConfig, values, where="DemoConfig.training")
