"""What the networks return and the loss assemblies take (so losses never import the models)."""

from __future__ import annotations

from typing import NamedTuple

from jax import Array


class BranchOutputs(NamedTuple):
    """Dense outputs of one encoder–decoder branch at full input resolution ``H × W``.

    * ``inv_depth``: ``[B, F, H, W]`` inverse depth (1/m) of ``F`` frames, ``> 0``.
    * ``mask``: ``[B, F, H, W]`` explainability mask in (0, 1) (sigmoid output).

    For ss-DPC-Net ``F = 1``: the target frame t+1. For Stereo DPC ``F = 2``: frames k and k+1
    of the branch's camera.
    """

    inv_depth: Array
    mask: Array


class DPCOutputs(NamedTuple):
    """Outputs of ``MonoDPC`` / ``StereoDPC``.

    * ``xi_corr``: ``[B, 6]`` pose correction ``[ρ, φ]``; ``T* = Exp(ξ_corr) · T_vo``.
    * ``left``: the left (or only, for mono) branch.
    * ``right``: the right branch, None for mono.
    * ``ssim_weight``: scalar λ_s in (0, 1) when the model learns it (sigmoid of a parameter),
      None when the loss uses its fixed configured value.
    """

    xi_corr: Array
    left: BranchOutputs
    right: BranchOutputs | None = None
    ssim_weight: Array | None = None
