"""Δ of a given correction on a prepared sequence, with its stereo depth and no network.

The acceptance test (``dpc_jax.acceptance``) judges a correction by its paired photometric effect
``Δ_k = L_k(ξ) − L_k(0)`` on the pairs ``(k, k+1)``. With the StereoSGBM depth the cache holds
(``dpc_jax.data.cache``), ``L`` (:func:`dpc_jax.nn.losses.temporal_pair_errors`: the temporal
reconstructions of both cameras, gradient-masked, no explainability mask) needs only the images,
the calibration, the prior's step and ξ: not the network that proposed ξ. So a correction
predicted at the network's input size can be judged on a copy of the sequence prepared at a
larger size (a *judge*): ξ is a pose, the same at every image size, and the photometric loss
resolves rotations better with more pixels (``docs/method.md`` §8). λ_s is the loss config's
fixed value (a network's learned one is the network's).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dpc_jax.data.pipeline import iterate_sequence
from dpc_jax.data.sequence_cache import SequenceCache
from dpc_jax.engine.driver import drive
from dpc_jax.engine.predict import stereo_depth_of
from dpc_jax.nn.batch import Batch
from dpc_jax.nn.config import SSDPCLossConfig, StereoDPCLossConfig
from dpc_jax.nn.losses import temporal_pair_errors, with_stereo_depth
from dpc_jax.nn.outputs import BranchOutputs, DPCOutputs


@functools.partial(jax.jit, static_argnames="config")
def _effects(batch: Batch, xi: jax.Array, masks: jax.Array, config: StereoDPCLossConfig,
             none: jax.Array | None = None) -> jax.Array:
    """Δ ``[C, B]`` of ``xi [B, 6] ⊙ masks[c] [6]`` for each of the ``C`` masks (module docstring),
    with ``batch.stereo_depth``; ``none``: ``L(0)`` ``[B]`` if already measured, else measured here."""
    assert batch.stereo_depth is not None
    ones = jnp.ones(batch.stereo_depth[0].shape[:1] + batch.stereo_depth[0].shape[2:], jnp.float32)
    branch = BranchOutputs(ones, ones)
    outputs, valid = with_stereo_depth(DPCOutputs(jnp.zeros_like(xi), branch, branch), batch.stereo_depth)
    if none is None:
        none = temporal_pair_errors(outputs, batch, config, valid)
    return jnp.stack([temporal_pair_errors(outputs._replace(xi_corr=xi * masks[c]), batch, config, valid)
                      - none for c in range(masks.shape[0])])


def correction_effects(
    cache: SequenceCache,
    xi_corr: np.ndarray,
    masks: Mapping[str, np.ndarray],
    config: SSDPCLossConfig | StereoDPCLossConfig,
    batch_size: int = 8,
    none: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Δ of ``xi_corr ⊙ mask`` on every pair of ``cache`` for each named mask → ``{name: [N-1]}``.

    ``xi_corr``: ``[N-1, 6]`` corrections ``[ρ (m), φ (rad)]`` of the cache's consecutive pairs
    (e.g. predicted on another cache of the same frames); ``masks``: ``{name: [6]}`` weights of
    the entries of ξ (0/1 to select, or a scale); ``config``: the loss whose temporal error is
    measured. Depth: the cache's StereoSGBM depth (computed now if it holds none). ``none``:
    ``L(0)`` ``[N-1]`` of every pair when already measured on this cache with this depth (a
    prediction's ``photometric``), which spares its evaluation; else measured here.
    """
    if not isinstance(config, StereoDPCLossConfig):
        raise ValueError(f"{cache.path}: judging needs both cameras (Stereo DPC's loss), got "
                         f"{type(config).__name__}")
    xi_corr = np.asarray(xi_corr, np.float32)
    pairs = len(cache) - 1
    if xi_corr.shape != (pairs, 6):
        raise ValueError(f"{cache.path}: xi_corr must be [{pairs}, 6] for its {pairs + 1} frames, "
                         f"got {xi_corr.shape}")
    if not masks:
        raise ValueError("no mask to judge")
    if none is not None and np.shape(none) != (pairs,):
        raise ValueError(f"{cache.path}: L(0) must be [{pairs}], got {np.shape(none)}")
    names = list(masks)
    stacked = jnp.asarray(np.stack([np.asarray(masks[n], np.float32) for n in names]))
    stereo = stereo_depth_of(cache, "sgbm")
    assert stereo is not None  # "sgbm" always gives a depth
    size = max(1, min(batch_size, pairs))
    out: list[np.ndarray] = []
    known_none = None if none is None else np.asarray(none, np.float32)

    def put(batch: Batch) -> tuple[Batch, np.ndarray]:
        return jax.device_put(batch), np.asarray(batch.weight)

    def run(carry: None, item: tuple[Batch, np.ndarray], index: int) -> tuple[None, Any]:
        rows = np.minimum(np.arange(index * size, (index + 1) * size), pairs - 1)
        known = None if known_none is None else jnp.asarray(known_none[rows])
        return carry, _effects(item[0], jnp.asarray(xi_corr[rows]), stacked, config=config, none=known)

    def consume(index: int, effects: np.ndarray, item: tuple[Batch, np.ndarray]) -> int:
        real = item[1] > 0
        out.append(np.asarray(effects, np.float64)[:, real])
        return int(real.sum())

    # The step driver: batch k+1 is dispatched before the effects of batch k are fetched.
    batches = iterate_sequence(cache, size, flow=False, put=put, stereo_depth=stereo)
    drive(run, None, batches, total=pairs, desc=f"judge {cache.name}", unit="pair", consume=consume)
    merged = np.concatenate(out, axis=1)
    return {name: merged[i] for i, name in enumerate(names)}
