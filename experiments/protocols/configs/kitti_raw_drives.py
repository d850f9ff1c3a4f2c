"""Two real KITTI raw drives, learn on one and correct the other (``kitti_raw_drives.py``).

Drives (``../shared/data/kitti-raw``): ``2011_09_26_drive_0001`` (108 frames, about 107 m, the colour
pair) and ``2011_09_26_drive_0005`` (frames 0–90 of the drive, about 34 m, the grey pair, read as three
equal channels so one network takes both drives). Priors: our classical stereo VO (run on each drive,
started at its first ground-truth pose, its disparity offset estimated online) and libviso2-s
(``libviso2/stereo_*.mat``; of drive 0005's 154 poses the first 91 belong to the images).

For every training drive and training prior a Stereo DPC network is trained on that drive (its
``train_frames``; epoch by validation Δ on its ``validation_frames``, no ground truth) and then
corrects the *other* drive: our VO's prior with the network trained on our VO, libviso2-s's prior with
the network trained on our VO *and* with the one trained on libviso2-s (the papers' setting: the prior
they correct is the prior they learn from). Each correction runs with the network as trained and as
adapted to the test drive (``adapt_steps``; its ground truth never read), behind the acceptance test,
measured on the test drive prepared at ``judge_size`` (240×376, the excerpt's);
``dpc_jax.correction.corrector.choose`` keeps the final.
Every network's images are rectified by the disparity offset our VO measured on that drive (no
ground truth). Only the rotation of the correction is applied (see
``rotation_only`` in ``configs/kitti_raw_excerpt.py``).

The training config and the settings the two protocols share are ``configs/kitti_raw_excerpt.py``'s
(derived from it, not copied), with the drives' cache and test sequence.

Command:

    python experiments/protocols/kitti_raw_drives.py --workdir runs/kitti_raw_drives

Produces in WORKDIR: ``results.md`` (the table: per test drive, prior and training prior, the rows
prior, trained, adapted, final) and ``results.csv`` (long form, one row per test drive, prior, training
prior and estimate), plus ``priors/``, ``cache/``, ``runs/``, ``reports/``, ``corrected/``, ``adapted/``.
"""

import runpy
from pathlib import Path

_EXCERPT = runpy.run_path(str(Path(__file__).with_name("kitti_raw_excerpt.py")))

PROTOCOL = {
    # The excerpt's date, epoch selection, rectification, adaptation, rotation-only correction, judge
    # size and decisions (every acceptance test on a test drive measured on its frames prepared at
    # ``judge_size``, 240×376, the correction's mean tested apart, and every correction decided again by
    # the earlier decision and each option of where the mean is tested; see configs/kitti_raw_excerpt.py).
    **{key: _EXCERPT["PROTOCOL"][key]
       for key in ("date", "select", "rectify_offset", "adapt_steps", "holdout_every", "rotation_only",
                   "judge_size", "mean_test", "decisions")},
    "drives": {
        "0001": {"libviso2": "libviso2/stereo_2011_09_26_drive_0001.mat",
                 "train_frames": (0, 80), "validation_frames": (80, 108)},
        "0005": {"libviso2": "libviso2/stereo_2011_09_26_drive_0005.mat",
                 "train_frames": (0, 68), "validation_frames": (68, 91)},
    },
    # (test prior, training prior) pairs: every test drive is corrected by networks of the other drive.
    "tests": (("vo", "vo"), ("libviso2", "vo"), ("libviso2", "libviso2")),
}

CONFIG = {**_EXCERPT["CONFIG"], "cache_root": "runs/kitti_raw_drives/cache", "test_sequences": ("test",)}
