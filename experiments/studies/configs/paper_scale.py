"""The papers' scale on a synthetic stand-in: KITTI odometry's sequence lengths, 240×376, both methods.

Both papers train on about 46,000 pairs at 240×376 (Stereo DPC: KITTI odometry 00, 02, 05–10 and 24
raw drives; ss-DPC-Net: the odometry sequences and about 10,000 raw images) for 30 epochs at batch
32. This stand-in renders synthetic sequences with the lengths of KITTI 00–10 (23,201 frames; the
``--frames N`` option scales every length by N / 23,201), runs our VO on them, prepares both
methods' caches, trains each method, corrects the longest sequence (00) and measures every stage:
wall and CPU time, frames or samples per second, peak resident memory, bytes on disk.

Command (the CPU rows of docs/performance.md's "Scale" table; ``--frames 1000`` for the smaller run):

    python experiments/studies/paper_scale.py --workdir runs/paper_scale_4000 --frames 4000 --docs

and on a GPU machine (the papers' batch, two full epochs of each method):

    python experiments/studies/paper_scale.py --workdir runs/paper_scale_gpu --frames 12000 --profile gpu \\
        --docs

Writes ``WORKDIR/scale.md`` and ``WORKDIR/scale.csv``; ``data/`` (rendered), ``vo/`` (priors),
``cache/stereo_dpc``, ``cache/ss_dpc`` (with flow augmentation), ``runs/``, ``corrected/``,
``reports/``, ``stages/`` (one JSON per finished stage: a rerun reuses it).
"""

import runpy
from pathlib import Path

_CONFIGS = Path(__file__).resolve().parents[2] / "protocols" / "configs"

# KITTI odometry's sequences and their frame counts.
KITTI_LENGTHS = {
    "00": 4541, "01": 1101, "02": 4661, "03": 801, "04": 271, "05": 2761,
    "06": 1101, "07": 1101, "08": 4071, "09": 1591, "10": 1201,
}
# The papers' training set, for the extrapolated 30-epoch time.
PAPER_PAIRS = 46_000
PAPER_EPOCHS = 30

SCALE = {
    "size": (240, 376),
    "seed": 0,
    # Corrected (and held out of training); epoch selection reads the validation sequence.
    "test": "00",
    "validation": "04",
    # The stand-in's rendering, as the demo's harder world.
    "moving_objects": 6,
    "illumination_drift": 0.3,
    "noise": 1.0,
}

# Training length per profile: "cpu" measures a few steps of each method (a 2-core machine trains
# at a few samples per second), "gpu" two full epochs at the papers' batch.
PROFILES = {
    "cpu": {"batch_size": 8, "epochs": 1, "steps_per_epoch": 24},
    "gpu": {"batch_size": 32, "epochs": 2, "steps_per_epoch": None},
}

# Each method's published configuration (the KITTI protocols' configs), its data replaced.
METHODS = {
    "stereo_dpc": runpy.run_path(str(_CONFIGS / "kitti_stereo_dpc.py"))["CONFIG"],
    "ss_dpc": runpy.run_path(str(_CONFIGS / "kitti_ss_dpc.py"))["CONFIG"],
}
