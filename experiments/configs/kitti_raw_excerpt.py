"""The complete pipeline on the real 108-frame KITTI raw excerpt (2011_09_26_drive_0001): a smoke test.

What runs: our classical stereo VO over the drive (started at the first ground-truth pose) and the
libviso2-s estimate from ``libviso2/stereo_2011_09_26_drive_0001.mat`` are the two priors; the
drive is prepared at 64×96 (the ``small`` preset); Stereo DPC is trained briefly with our VO
prior on frames 0–79 and validated (epoch selection by the gradient loss, no ground truth) on
frames 80–107 — the validation frames are never trained on; then both priors of the *whole*
drive are corrected (full 6-DoF) and evaluated against the ground truth of the ``.mat``.

This is **not a reproduction** of either paper: 108 frames (~107 m, below the 100–800 m segment
lengths' useful range), tiny images, a small network and a few epochs; the test drive contains
the training frames 0–79. It shows that every stage works on real images; its numbers say
nothing about the method's accuracy. It runs in a few minutes on a 2-core CPU.

Command:

    python experiments/kitti_raw_excerpt.py --workdir runs/kitti_raw_excerpt

(``--kitti-raw`` defaults to ``../shared/data/kitti-raw`` beside the repository.) Produces in
WORKDIR: ``results.md`` / ``results.csv`` (per prior: m-ATE, ATE, segment errors of prior →
corrected), ``corrected/excerpt/{vo,libviso2}.txt``, ``reports/excerpt/{vo,libviso2}/``
(report.md and plots), ``priors/vo.txt``, ``runs/excerpt/``, ``cache/``.
"""

PROTOCOL = {
    "date": "2011_09_26",
    "drive": "0001",
    "libviso2": "libviso2/stereo_2011_09_26_drive_0001.mat",
    "train_frames": (0, 80),
    "validation_frames": (80, 108),
    # Our settings (not a paper reproduction): the epoch with the most negative validation Δ, and
    # each prior corrected only where the acceptance test on its own images allows it.
    "select": "delta",
    "acceptance": True,
}

CONFIG = {
    "method": "stereo_dpc",
    "preset": "small",
    "image_size": (64, 96),
    "batch_size": 8,
    "epochs": 4,
    "learning_rate": 1e-3,
    "lr_halving_epochs": 2,
    "weight_decay": 4e-6,
    "loss": {"alpha": (1.0, 1.0, 1.0, 0.08), "ssim_weight": 0.85},
    "rotation_only": False,
    "frame_skip": True,
    "cache_root": "runs/kitti_raw_excerpt/cache",
    "train_sequences": ("train",),
    "validation_sequences": ("validation",),
    "test_sequences": ("vo", "libviso2"),
}
