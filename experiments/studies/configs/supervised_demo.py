"""The synthetic demo with Stereo DPC trained by DPC-Net's supervised loss.

Command:

    dpc-jax demo --out runs/supervised_demo --config experiments/studies/configs/supervised_demo.py
    python experiments/studies/linear_baseline.py --demo runs/supervised_demo   # the linear baseline

Produces what ``dpc-jax demo`` produces (``experiments/studies/configs/synthetic_demo.py``), the same data,
prior and seed, but the training step regresses the correction on the training sequences' ground
truth (``supervision: supervised``) instead of the photometric loss; validation, epoch selection,
the acceptance test and the adaptation to the test sequence stay ground-truth free. ``precision``:
the diagonal ``Σ⁻¹`` of 1/σ² per axis with σ = 2 cm per step for translation and 1 mrad for rotation,
about the spread of these priors' step errors (the demo report's table), so that neither part is
ignored; leaving it out uses DPC-Net's, the inverse covariance of the training pairs' targets.
"""

CONFIG = {
    "training": {"supervision": "supervised", "precision": [2500.0, 2500.0, 2500.0, 1e6, 1e6, 1e6]},
}
