"""The synthetic demo: what ``dpc-jax demo`` runs; this file spells out its defaults.

Command:

    dpc-jax demo --out runs/synthetic_demo

What it produces in OUT (see ``dpc_jax.pipelines.synthetic_demo``): ``data/`` (rendered synthetic
sequences in the KITTI odometry layout: train0, train1 for training, val for epoch selection, test held out),
``vo/`` (priors from our classical stereo VO with its offset estimate off, and the calibration
runs with it on), ``cache/`` (prepared at the network's size, rectified by the measured offset),
``run/`` (the Stereo DPC training run), ``adapted/`` (the network adapted to the test sequence),
``report.md`` (the prior's error composition; prior, network as trained, network adapted and the
final trajectory on the test sequence; plots), ``corrected.txt``, ``summary.json``. Over several
seeds: ``python experiments/studies/demo_seeds.py``.
"""

CONFIG = {
    "train_sequences": 2,
    "train_frames": 300,
    "validation_frames": 150,
    "test_frames": 300,
    "render_size": (240, 376),
    "moving_objects": 6,
    "illumination_drift": 0.3,
    "noise": 1.0,
    "disparity_offset": -0.8,
    "vo_estimate_offset": False,
    "rectify_offset": True,
    "seed": 0,
    "training": {},
    "select": "delta",
    "acceptance": True,
    "adapt_steps": 300,
    "holdout_every": 5,
    "max_fallback_share": 0.05,
}
