"""dpc_jax: self-supervised deep pose correction of classical stereo visual odometry.

The public API is re-exported here lazily (PEP 562), so ``import dpc_jax`` and the command line
start without importing JAX, Flax or OpenCV; ``from dpc_jax import se3_exp`` imports what it needs.
"""

from __future__ import annotations

from dpc_jax.runtime.lazy import lazy_getattr

__version__ = "0.1.0"

# The face: what a user calls to correct, evaluate and read or write trajectories, the networks with their
# configurations, the Lie functions, the data and the synthetic world they run on, training, the live
# corrector and the demo. Everything else (the warps, losses and convolutions the networks are built of,
# the step driver, the caches' format) lives in its package and may move between releases.
_EXPORTS: dict[str, tuple[str, ...]] = {
    # The Lie groups (docs/method.md §1).
    "dpc_jax.geometry.lie": ("so3_exp", "so3_log", "se3_exp", "se3_log", "se3_inverse", "transform_points"),
    # A correction applied to a VO step or a trajectory.
    "dpc_jax.geometry.pose_correction": ("apply_correction", "corrected_trajectory"),
    "dpc_jax.geometry.poses": ("relative_poses", "compose"),
    # Trajectory files.
    "dpc_jax.data.poses_io": ("read_trajectory", "write_kitti_poses", "write_tum", "associate"),
    # Sequences on disk and their preparation.
    "dpc_jax.data": ("StereoSequence", "open_odometry", "open_raw", "prepare_sequence", "Calibration",
                     "load_calibration"),
    "dpc_jax.data.sequence_cache": ("load_cache",),
    # The networks and their configurations.
    "dpc_jax.nn.model_config": ("ModelConfig", "SSDPCLossConfig", "StereoDPCLossConfig"),
    "dpc_jax.nn.models": ("MonoDPC", "StereoDPC", "create_model"),
    "dpc_jax.training.train_config": ("TrainConfig",),
    "dpc_jax.training.loop": ("train",),
    # Correcting: restore a run, correct a prepared sequence (or frame by frame, live), write it.
    "dpc_jax.correction.inference": ("load_run", "TrainedRun"),
    "dpc_jax.correction.corrector": ("correct_cache", "correct_sequence", "write_trajectory"),
    "dpc_jax.results.correction": ("Correction",),
    "dpc_jax.results.acceptance": ("Acceptance",),
    "dpc_jax.correction.live": ("LiveCorrector",),
    # Evaluating against ground truth, and what a prior's error is made of.
    "dpc_jax.eval.evaluation": ("evaluate", "Evaluation"),
    "dpc_jax.eval.metrics": ("m_ate", "segment_errors", "ate", "rpe"),
    "dpc_jax.eval.diagnosis": ("diagnose",),
    # The classical VO, the synthetic world and the demo.
    "dpc_jax.vo": ("StereoVO", "VOConfig", "run_vo"),
    "dpc_jax.synth": ("SynthConfig", "render_sequence", "write_sequences"),
    "dpc_jax.pipelines.synthetic_demo": ("DemoConfig", "run_demo"),
}
__all__ = ["__version__", *(name for names in _EXPORTS.values() for name in names)]
__getattr__ = lazy_getattr("dpc_jax", _EXPORTS, globals())


def __dir__() -> list[str]:
    return sorted(__all__)
