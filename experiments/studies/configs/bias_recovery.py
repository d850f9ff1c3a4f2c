"""Bias recovery (the scientific check of self-supervision): Stereo DPC, small preset, synthetic sequences.

The data are made by ``experiments/studies/bias_recovery.py`` under ``OUT/cache`` (``--out OUT``, default
``runs/bias_recovery``; the script sets ``cache_root`` to it):
sequences s00–s03 for training, s04 for validation (epoch selection), s05 held out for the test.
Their priors are the true relative poses with a yaw bias of 0.15°/frame plus noise.
"""

from dpc_jax.training.train_config import TrainConfig

CONFIG = TrainConfig(
    method="stereo_dpc",
    preset="small",
    image_size=(64, 96),
    batch_size=8,
    epochs=6,
    learning_rate=2e-3,
    lr_halving_epochs=2,
    steps_per_epoch=100,
    cache_root="runs/bias_recovery/cache",
    train_sequences=("s00", "s01", "s02", "s03"),
    validation_sequences=("s04",),
    test_sequences=("s05",),
    log_every=10,
)
