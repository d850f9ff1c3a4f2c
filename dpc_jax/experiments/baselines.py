"""The supervised linear baseline (``dpc_jax.eval.linear_baseline``) as the studies set it beside the
networks: fit on training sequences' ground truth and prior, applied to a test sequence's prior,
evaluated as every correction is (``dpc_jax.eval.evaluation.evaluate``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from dpc_jax.eval.evaluation import Metrics


def linear_baselines(train: Sequence[tuple[np.ndarray, np.ndarray]], gt: np.ndarray, prior: np.ndarray,
                     fits: Mapping[str, Mapping[str, bool]]) -> dict[str, Metrics]:
    """``prior`` and each baseline of ``fits`` (label → options of
    ``dpc_jax.eval.linear_baseline.fit_linear_correction``: ``rotation_only``, ``constant_only``), fit on
    the ``(ground truth, prior)`` trajectories ``[N, 4, 4]`` of ``train``, applied to ``prior``: label →
    metrics against ``gt``."""
    from dpc_jax.eval.evaluation import evaluate
    from dpc_jax.eval.linear_baseline import apply_linear_correction, fit_linear_correction

    estimates = {label: apply_linear_correction(fit_linear_correction(train, **options), prior)
                 for label, options in fits.items()}
    return evaluate(gt, {"prior": prior, **estimates}).estimates
