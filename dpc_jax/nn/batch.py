"""The training/evaluation batch: what the data pipeline yields and the jitted steps consume.

A ``Batch`` is a NamedTuple, hence a pytree: it passes through ``jax.jit`` and device sharding
as is. The pipeline fills it with numpy arrays; every array has the batch axis first, so the
whole batch shards along the mesh's ``data`` axis.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from jax import Array


class Batch(NamedTuple):
    """One batch of consecutive frame pairs ``(k, k+1)``.

    Fields (``B`` samples, images ``H × W``):

    * ``left``, ``right``: uint8 ``[B, 2, H, W, 3]``, frames k and k+1 of the left and right
      camera, RGB in [0, 255] (the losses divide by 255; only the network input is whitened).
    * ``xi_vo``: float32 ``[B, 6]``, prior ``ξ_vo = Log(T_vo_{k+1,k})`` as ``[ρ (m), φ (rad)]``.
    * ``intrinsics``: float32 ``[B, 3, 3]``, K of the (resized) images in pixels.
    * ``baseline``: float32 ``[B]``, stereo baseline in metres (right camera at +B along x).
    * ``weight``: float32 ``[B]``, 1 for real samples and 0 for padding that fills the last
      batch of an in-order evaluation pass to the fixed batch size.
    * ``flow``: float32 ``[B, 2, H, W, 2]`` or None, Farnebäck flow k → k+1 in pixels
      (``[..., 0]`` = Δx column, ``[..., 1]`` = Δy row) of the left (index 0) and right
      (index 1) camera.
    * ``xi_gt``: float32 ``[B, 6]`` or None, ground-truth ``Log(T_gt_{k+1,k})``; for
      evaluation and reporting only, never used by a loss.
    * ``stereo_depth``: ``(inverse depth, valid)`` or None: float32 inverse depth (1/m) and bool
      validity ``[B, camera, frame, H, W]`` of an independent stereo depth (StereoSGBM,
      ``dpc_jax.data.stereo_depth``) of frames k and k+1 of the left (0) and right (1) camera;
      for measuring Δ of a correction (``dpc_jax.nn.losses.with_stereo_depth``), never used by a
      loss.
    """

    left: Array | np.ndarray
    right: Array | np.ndarray
    xi_vo: Array | np.ndarray
    intrinsics: Array | np.ndarray
    baseline: Array | np.ndarray
    weight: Array | np.ndarray
    flow: Array | np.ndarray | None = None
    xi_gt: Array | np.ndarray | None = None
    stereo_depth: tuple[Array | np.ndarray, Array | np.ndarray] | None = None
