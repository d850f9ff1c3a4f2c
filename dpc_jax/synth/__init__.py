"""Synthetic stereo driving world, rendered exactly, in the KITTI odometry layout (docs/method.md §6).

* :class:`SynthConfig`, :func:`render_sequence`, :func:`iter_frames` (``sequence``): the Python API.
* :func:`write_sequences`, :func:`write_sequence`, :func:`is_rendered` (``writer``): KITTI-layout output.
* ``world`` (road and town layout), ``trajectory`` (car-like motion), ``render`` (jitted ray
  casting and shading), ``shapes`` (the primitives and their ray intersections), ``textures``
  (band-limited procedural materials).
"""

from dpc_jax.synth.sequence import (
    SynthConfig,
    SynthFrame,
    SynthSequence,
    iter_frames,
    kitti_intrinsics,
    render_sequence,
    sequence_poses,
)
from dpc_jax.synth.writer import calib_text, is_rendered, write_sequence, write_sequences

__all__ = [
    "SynthConfig",
    "SynthFrame",
    "SynthSequence",
    "calib_text",
    "is_rendered",
    "iter_frames",
    "kitti_intrinsics",
    "render_sequence",
    "sequence_poses",
    "write_sequence",
    "write_sequences",
]
