"""Classical feature-based stereo visual odometry (libviso2-s-like), the prior the network corrects.

``run_vo(sequence, config)`` runs it over a :class:`dpc_jax.data.kitti.StereoSequence`;
``run_vo_frames`` over any iterable of grey pairs; :class:`StereoVO` is the per-frame core.
"""

from dpc_jax.vo.odometry import STAGES, StereoVO, VOConfig, VOResult, VOStatus, run_vo, run_vo_frames

__all__ = ["STAGES", "StereoVO", "VOConfig", "VOResult", "VOStatus", "run_vo", "run_vo_frames"]
