"""The minimal training config for sequences of your own: Stereo DPC, the small network, a CPU budget.

Your data in the KITTI odometry layout (``ROOT/sequences/XX/{image_2,image_3}``, ``calib.txt``,
``times.txt``; ``ROOT/poses/XX.txt`` if you have ground truth, used only for reports) and one VO
estimate per sequence. ``calib.txt`` must describe the stored images: ``vo`` and ``prepare`` refuse one
written for another image size (principal point outside the middle half of the image, or a focal length
that gives an implausible field of view). Commands, from the repository root (edit ``cache_root`` and
the sequence names below to match):

    dpc-jax vo --kitti-odometry ROOT --sequence 00 --out priors/00.txt     # or your own VO's poses
    dpc-jax prepare --kitti-odometry ROOT --sequence 00 01 02 --prior 'priors/{seq}.txt' \\
        --out cache/own_data --size 64x96
    dpc-jax train --config experiments/protocols/configs/own_data.py --workdir runs/own_data
    dpc-jax correct --checkpoint runs/own_data --data cache/own_data/02 --out corrected_02.txt \\
        --report report_02

Produces in ``runs/own_data``: ``checkpoints/`` (every epoch and the best ones by the validation
criteria), ``metrics.csv`` and ``tensorboard/``. Every cached sequence except the validation one
(and any ``test_sequences``) is trained on; the validation sequence chooses the epoch and needs no
ground truth. The cache's ``--size`` must equal ``image_size``. For the papers' settings (the
reference network at 240×376, batch 32, 30 epochs; hours on a GPU) start from
``experiments/protocols/configs/kitti_stereo_dpc.py`` instead.
"""

CONFIG = {
    "method": "stereo_dpc",
    "preset": "small",
    "image_size": (64, 96),
    "batch_size": 8,
    "epochs": 10,
    "learning_rate": 2e-3,
    "lr_halving_epochs": 4,
    "cache_root": "cache/own_data",
    "validation_sequences": ("02",),
}
