"""dpc_jax: self-supervised deep pose correction of classical stereo visual odometry.

The public API is re-exported here lazily (PEP 562), so ``import dpc_jax`` and the command line
start without importing JAX, Flax or OpenCV; ``from dpc_jax import se3_exp`` imports what it needs.
"""

from __future__ import annotations

from dpc_jax.runtime.lazy import lazy_getattr

__version__ = "0.1.0"

_EXPORTS: dict[str, tuple[str, ...]] = {
    "dpc_jax.geometry.lie": (
        "so3_hat", "so3_vee", "so3_exp", "so3_log", "so3_left_jacobian", "so3_left_jacobian_inv",
        "se3_exp", "se3_log", "se3_inverse", "transform_points", "project_to_so3",
    ),
    "dpc_jax.geometry.camera": ("scale_intrinsics", "pixel_grid", "backproject", "project"),
    "dpc_jax.geometry.warp": ("bilinear_sample", "inverse_warp", "stereo_warp", "disparity_consistency"),
    "dpc_jax.geometry.ssim": ("ssim_loss",),
    "dpc_jax.geometry.pose_correction": ("apply_correction", "corrected_trajectory"),
    "dpc_jax.nn.model_config": (
        "ModelConfig", "PRESETS", "SSDPCLossConfig", "StereoDPCLossConfig", "SupervisedLossConfig",
    ),
    "dpc_jax.nn.losses": (
        "ss_dpc_loss", "stereo_dpc_loss", "dpc_loss", "supervised_dpc_loss",
        "gradient_loss", "temporal_pair_errors", "correction_deltas",
    ),
    "dpc_jax.nn.batch": ("Batch",),
    "dpc_jax.nn.outputs": ("BranchOutputs", "DPCOutputs"),
    "dpc_jax.geometry.poses": ("relative_poses", "compose", "remove_static_frames"),
    "dpc_jax.data.poses_io": (
        "read_trajectory", "read_kitti_poses", "read_tum", "read_mat", "write_kitti_poses", "write_tum",
        "validate_poses",
    ),
    "dpc_jax.eval.metrics": (
        "m_ate", "c_ate", "segment_errors", "kitti_devkit_errors", "ate", "rpe", "count_loop_closures",
        "trajectory_metrics",
    ),
    "dpc_jax.eval.evaluation": ("evaluate", "Evaluation"),
    "dpc_jax.report.evaluation_report": ("write_report", "export_trajectories"),
    "dpc_jax.eval.diagnosis": ("diagnose", "Diagnosis"),
    "dpc_jax.eval.linear_baseline": ("LinearCorrection", "fit_linear_correction", "apply_linear_correction"),
    "dpc_jax.data": (
        "StereoSequence", "open_odometry", "open_raw", "load_image", "prepare_sequence",
        "TrainLoader", "iterate_sequence", "leave_one_out",
    ),
    "dpc_jax.data.sequence_cache": ("load_cache",),
    "dpc_jax.synth": ("SynthConfig", "render_sequence", "write_sequences"),
    "dpc_jax.vo": ("StereoVO", "VOConfig", "VOResult", "VOStatus", "run_vo", "run_vo_frames"),
    "dpc_jax.nn.conv": ("conv_s2", "upconv3x3_s2", "conv3x3_few_outputs"),
    "dpc_jax.nn.models": (
        "MonoDPC", "StereoDPC", "create_model", "count_parameters", "prepare_inference",
    ),
    "dpc_jax.training.train_config": ("TrainConfig", "REFERENCE"),
    "dpc_jax.training.optim": ("make_optimizer", "create_train_state", "learning_rate_schedule"),
    "dpc_jax.training.steps": ("make_train_step", "NonFiniteLossError"),
    "dpc_jax.training.checkpoints": ("Checkpoints",),
    "dpc_jax.engine.parallel": ("make_mesh", "shard_batch", "replicate"),
    "dpc_jax.runtime.hugepages": ("reexec_with_huge_pages", "huge_pages_requested"),
    "dpc_jax.config": ("ConfigError", "load_file"),
    "dpc_jax.correction.inference": ("load_run", "predict_sequence", "predict_corrections", "TrainedRun"),
    "dpc_jax.correction.acceptance": ("Acceptance", "paired_test"),
    "dpc_jax.correction.decision": ("decide",),
    "dpc_jax.correction.corrector": ("correct_cache", "correct_sequence", "write_trajectory"),
    "dpc_jax.pipelines.synthetic_demo": ("DemoConfig", "run_demo"),
}
__all__ = ["__version__", *(name for names in _EXPORTS.values() for name in names)]
__getattr__ = lazy_getattr("dpc_jax", _EXPORTS, globals())


def __dir__() -> list[str]:
    return sorted(__all__)
