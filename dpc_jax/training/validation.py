"""Validation of one training epoch (docs/method.md §5): the figures the checkpoint selection
criteria (``dpc_jax.training.checkpoints``) and the metrics log read, from
``dpc_jax.engine.predict.predict_sequence`` on each validation sequence (:func:`validate`)."""

from __future__ import annotations

import numpy as np
from flax import nnx
from jax.sharding import Mesh

from dpc_jax.engine.predict import predict_sequence
from dpc_jax.eval import metrics as metrics_lib
from dpc_jax.eval.evaluation import segment_summary
from dpc_jax.geometry.pose_correction import corrected_trajectory
from dpc_jax.training.train_config import TrainConfig
from dpc_jax.training.train_data import TrainData


def validate(
    model_graphdef: nnx.GraphDef, model_state: nnx.State, data: TrainData, config: TrainConfig, mesh: Mesh
) -> dict[str, float]:
    """Validation figures of one epoch (docs/method.md §5), means over the validation pairs.

    * ``val_loss``: the training loss in evaluation mode;
    * ``val_gradient_loss``: the photometric loss on high-gradient pixels (selection a);
    * ``val_loop_closures``: loop closures of the corrected validation trajectories, summed
      (selection b);
    * ``val_delta``, ``val_delta_rotation``: mean Δ of the full / rotation-only correction
      (selection ``delta``; ``dpc_jax.correction.acceptance``);
    * ``val_{prior,corrected}_{t,r}_err``: segment errors against ground truth, averaged over the
      sequences that have it (reporting only; NaN without ground truth).
    """
    loss_config = config.loss_config()
    weighted = {"loss": 0.0, "gradient_loss": 0.0, "delta": 0.0, "delta_rotation": 0.0}
    pairs = 0
    closures = 0
    errors: list[tuple[float, float, float, float]] = []
    for seq in data.validation:
        prediction = predict_sequence(
            (model_graphdef, model_state), seq.cache, loss_config, batch_size=config.batch_size,
            use_flow=data.use_flow, stereo_depth=seq.stereo_depth, mesh=mesh,
        )
        n = prediction.xi_corr.shape[0]
        weighted["loss"] += prediction.loss * n
        weighted["gradient_loss"] += prediction.gradient_loss * n
        weighted["delta"] += float(prediction.delta["full"].sum())
        weighted["delta_rotation"] += float(prediction.delta["rotation"].sum())
        pairs += n
        first = seq.ground_truth[0] if seq.ground_truth is not None else seq.prior[0]
        corrected = corrected_trajectory(prediction.xi_corr, seq.prior, first, config.rotation_only)
        closures += int(metrics_lib.count_loop_closures(corrected))
        if seq.ground_truth is not None:
            errors.append(
                (*segment_summary(seq.ground_truth, seq.prior), *segment_summary(seq.ground_truth, corrected))
            )
    mean_errors = np.mean(errors, axis=0) if errors else np.full(4, np.nan)
    return {
        **{f"val_{k}": v / pairs for k, v in weighted.items()},
        "val_loop_closures": closures,
        "val_prior_t_err": float(mean_errors[0]),
        "val_prior_r_err": float(mean_errors[1]),
        "val_corrected_t_err": float(mean_errors[2]),
        "val_corrected_r_err": float(mean_errors[3]),
    }
