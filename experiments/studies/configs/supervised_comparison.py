"""Prior → supervised linear baseline → supervised network → self-supervised network, on what we can run
(``experiments/studies/supervised_comparison.py``).

Command (the whole comparison: the demo at seeds 0–4 twice, the two real drives twice):

    python experiments/studies/supervised_comparison.py --workdir runs/supervised_comparison

    python experiments/studies/supervised_comparison.py --workdir /tmp/smoke --smoke --seeds 0  # wiring

Test data: the synthetic demo's held-out test sequence per seed (``DEMO``), and the two real KITTI
raw drives of ``experiments/protocols/configs/kitti_raw_drives.py`` cross-drive (test 0001 trained
on 0005, test 0005 trained on 0001) with our VO as the prior (``PROTOCOL``: that file's protocol with its
``tests`` narrowed to our VO; ``CONFIG``: its training config). The self-supervised network is
exactly what ``demo_seeds.py`` and ``kitti_raw_drives.py`` train; the supervised one the same
with ``SUPERVISED`` on top (DPC-Net's loss, which reads the training sequences' ground truth, and
the precision of ``configs/supervised_demo.py``: σ = 2 cm and 1 mrad per step; our VO's per-step
error spread on the drives' training frames is 2–51 mm and 0.13–0.74 mrad per axis, the same
order, so the drives keep the demo's weights rather than a second choice). Validation, epoch
selection, adaptation and the acceptance tests stay ground-truth free for both.

``SMOKE_DEMO``: the demo's overrides under ``--smoke`` (tiny images, 12 frames a sequence, one
epoch of two steps, two adaptation steps; the VO falls back on most pairs at 48×80, which the
smoke run accepts); the drives get ``kitti_raw_drives.py``'s own ``--smoke``.

Produces in WORKDIR: ``comparison.md`` (the table and the change against the prior over the seeds)
and ``comparison.csv`` (long form), with the runs it read: ``seed_K/`` (the self-supervised demo,
``demo_seeds.py``'s layout), ``supervised/seed_K/``, ``drives/`` (``kitti_raw_drives.py``'s layout)
and ``supervised/drives/``; the supervised runs read the data, priors and caches of the
self-supervised ones (links), which they share.
"""

import runpy
from pathlib import Path

_HERE = Path(__file__).resolve().parent
_DRIVES = runpy.run_path(str(_HERE.parents[1] / "protocols" / "configs" / "kitti_raw_drives.py"))

# The demo configs of the two networks (their seed is replaced by each --seeds value).
DEMO = {"self": str(_HERE / "synthetic_demo.py"), "supervised": str(_HERE / "supervised_demo.py")}

# The drives: kitti_raw_drives' training config and protocol, our VO as prior and training prior.
CONFIG = _DRIVES["CONFIG"]
PROTOCOL = {**_DRIVES["PROTOCOL"], "tests": (("vo", "vo"),)}

# What makes a training supervised (TrainConfig fields): the supervised demo's.
SUPERVISED = runpy.run_path(DEMO["supervised"])["CONFIG"]["training"]

SMOKE_DEMO = {
    "train_sequences": 1, "train_frames": 12, "validation_frames": 8, "test_frames": 12,
    "render_size": (48, 80), "moving_objects": 1, "max_fallback_share": 1.0, "adapt_steps": 2,
    "holdout_every": 4,
    "training": {"image_size": (32, 48), "batch_size": 2, "epochs": 1, "steps_per_epoch": 2,
                 "pose_warmup_epochs": 0},  # trained past the warm-up: its one epoch trains the pose head
}

# The paragraph above the table: what its rows are.
NOTES = (
    "Rows: the prior; the linear baseline (a correction linear in the prior's step, rotation only, fit by "
    "least squares on the training sequences' ground truth: **supervised**) and its constant term alone "
    "(the mean correction per step: a bias, which does not depend on the speed); Stereo DPC trained with "
    "DPC-Net's loss on the training sequences' ground truth (**supervised**) and the same network trained "
    "self-supervised, each as trained, adapted to the test sequence's images (self-supervised, no ground "
    "truth) and final (what the acceptance tests and the choice keep). Decision: the network's "
    "ground-truth-free acceptance test (demo: `dpc-jax demo`'s words; drives: the axes applied, "
    "`kitti_raw_drives.py`'s). Demo: the held-out test sequence, trained on the training sequences named. "
    "Drives: real KITTI raw, prior our VO, trained on the other drive's frames named, rotation only "
    "applied; segment errors n/a where the test is shorter than 100 m; RPE over one frame."
)
