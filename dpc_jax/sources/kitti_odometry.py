"""The KITTI odometry layout as a source (also the synthetic world's, which ``dpc-jax synth`` writes)."""

from __future__ import annotations

from dpc_jax.data.kitti import open_odometry
from dpc_jax.sources.recording import Recording, Source


def open_source(source: Source) -> Recording:
    """``ROOT/sequences/KEY`` with its ground truth ``ROOT/poses/KEY.txt`` where it exists."""
    return Recording(open_odometry(source.path, str(source.key), grey=source.grey))
