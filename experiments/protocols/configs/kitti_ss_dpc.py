"""ss-DPC-Net (Wagstaff, Peretroukhin, Kelly, ICRA 2020) on KITTI odometry with libviso2 priors.

Protocol (three trained networks, "folds"):

* ``stereo_val05``: libviso2-s priors, validation 05 → test 00 and 02 (trained on 06–10);
* ``stereo_val00``: libviso2-s priors, validation 00 → test 05 (trained on 02, 06–10);
* ``mono``: libviso2-m priors rescaled per step to the ground-truth step length (the paper's
  protocol), validation 05 → test 09 and 10 (trained on 00, 02, 06–08).

The mono network (left image pair + Farnebäck flow + prior), 240×376, batch 32, 30 epochs, coupled
L2 4e-6, dropout 0.5, λ_exp = 0.23, λ_rot = 4 for samples with prior rotation ≥ γ = 0.005 rad,
frame-skip augmentation. Stereo priors: Adam 1e-3 halved every 4 epochs and only the rotation of
the correction applied; mono priors: 5e-5 halved every 10 epochs, the full correction (docs/method.md §5).
The epoch is chosen by the validation gradient loss (``--select loop`` for the loop-closure count);
the correction head has the published settings (``dpc_jax.training.train_config.REFERENCE``) and every
correction is applied (no acceptance test).

Command (every fold):

    python experiments/protocols/kitti_ss_dpc.py --kitti-odometry /data/kitti/odometry \\
        --priors ../shared/data/kitti-libviso2 --fold all --workdir runs/kitti_ss_dpc

Produces in WORKDIR: ``results.md`` / ``results.csv`` (per test sequence: segment errors,
m-ATE, ATE of the prior → corrected), ``corrected/FOLD/XX.txt``, ``reports/FOLD/XX/``,
``runs/FOLD/``, ``cache/{stereo,mono}/``. ``--smoke``: 1 epoch of 2 steps on 32×48 images.

This file is also a plain training config for the ``stereo_val05`` fold once its cache exists:

    dpc-jax train --config experiments/protocols/configs/kitti_ss_dpc.py \\
        --workdir runs/kitti_ss_dpc/runs/stereo_val05
"""

from dpc_jax.training.train_config import REFERENCE

PROTOCOL = {
    "sequences": ("00", "02", "05", "06", "07", "08", "09", "10"),
    "folds": {
        "stereo_val05": {"prior": "stereo", "validation": "05", "test": ("00", "02"), "overrides": {}},
        "stereo_val00": {"prior": "stereo", "validation": "00", "test": ("05",), "overrides": {}},
        "mono": {
            "prior": "mono",
            "validation": "05",
            "test": ("09", "10"),
            "overrides": {"learning_rate": 5e-5, "lr_halving_epochs": 10, "rotation_only": False},
        },
    },
    "select": "gradient",
    # The papers apply every correction; the acceptance test (dpc_jax.correction.acceptance) is ours.
    "acceptance": False,
}

CONFIG = {
    "method": "ss_dpc",
    "preset": "reference",
    "image_size": (240, 376),
    "batch_size": 32,
    "epochs": 30,
    "learning_rate": 1e-3,
    "lr_halving_epochs": 4,
    "weight_decay": 4e-6,
    # The published choices of the correction head.
    **REFERENCE,
    "loss": {"exp_weight": 0.23, "rot_weight": 4.0, "rot_threshold": 0.005},
    "rotation_only": True,
    "frame_skip": True,
    "cache_root": "runs/kitti_ss_dpc/cache/stereo",
    "train_sequences": ("06", "07", "08", "09", "10"),
    "validation_sequences": ("05",),
    "test_sequences": ("00", "02"),
}
