"""A trajectory's steps taken apart and checked against the images, with no network: the travel of each
step (length, elevation, lateral angle) and steps that exchange rotation and travel between two
trajectories (``experiments/studies/excerpt_ground_truth.py``), and the photometric error of candidate
steps at full resolution with OpenCV StereoSGBM depth."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from dpc_jax.runtime.progress import Progress

MAX_DEPTH_M = 40.0  # farther pixels move by well under a pixel per step: they cannot tell poses apart
MIN_GRADIENT = 0.05  # grey levels per pixel (Sobel / 8): textureless pixels cannot either


def step_geometry(relative: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Travel of each step ``T_{t+1,t}`` ``[N, 4, 4]`` in frame t: ``(length m, elevation rad, lateral rad)``.

    The camera looks along +z with y down; elevation is the upward angle of the travel direction,
    lateral its angle towards +x.
    """
    travel = -np.einsum("nji,nj->ni", relative[:, :3, :3], relative[:, :3, 3])
    length = np.linalg.norm(travel, axis=1)
    elevation = np.arctan2(-travel[:, 1], np.hypot(travel[:, 0], travel[:, 2]))
    lateral = np.arctan2(travel[:, 0], travel[:, 2])
    return length, elevation, lateral


def with_travel(rotation_from: np.ndarray, length: np.ndarray, elevation: np.ndarray,
                lateral: np.ndarray) -> np.ndarray:
    """Steps ``[N, 4, 4]`` with the rotations of ``rotation_from`` and the given travel in frame t."""
    direction = np.stack([np.cos(elevation) * np.sin(lateral), -np.sin(elevation),
                          np.cos(elevation) * np.cos(lateral)], axis=1)
    out = rotation_from.copy()
    out[:, :3, 3] = -np.einsum("nij,nj->ni", rotation_from[:, :3, :3], length[:, None] * direction)
    return out


def exchange(rotation_from: np.ndarray, translation_from: np.ndarray) -> np.ndarray:
    """Steps with the rotations of one set and the travel (in frame t) of the other."""
    return with_travel(rotation_from, *step_geometry(translation_from))


def photometric_errors(sequence: Any, candidates: np.ndarray, offsets_px: Sequence[float],
                       progress: Progress) -> np.ndarray:
    """Mean L1 grey error ``[pairs, offsets, C]`` of each candidate step ``T_{t+1,t}`` ``[C, pairs, 4, 4]``
    of ``sequence`` (its grey left images, 0–1): frame t rebuilt from frame t+1 with frame t's SGBM depth
    for each disparity offset (px, added to SGBM's disparities), over the pixels every candidate keeps in
    view that are textured (gradient ≥ :data:`MIN_GRADIENT`) and near (≤ :data:`MAX_DEPTH_M`)."""
    import cv2
    import jax
    import jax.numpy as jnp
    from tqdm.auto import tqdm

    from dpc_jax.data.stereo_depth import sgbm_inverse_depth
    from dpc_jax.geometry.warp import inverse_warp

    K = jnp.asarray(sequence.K, jnp.float32)
    fb = float(sequence.K[0, 0] * sequence.baseline)

    @jax.jit
    def errors(source: jax.Array, target: jax.Array, depth: jax.Array, keep: jax.Array,
               steps: jax.Array) -> jax.Array:
        # Rebuild frame t from frame t+1 with frame t's depth: T_source_target = T_{t+1,t}.
        rebuilt, valid = inverse_warp(source[..., None], depth, steps, K)
        common = keep & jnp.all(valid, axis=0)
        residual = jnp.abs(rebuilt[..., 0] - target)
        return jnp.sum(residual * common, axis=(1, 2)) / jnp.maximum(jnp.sum(common), 1)

    frames = list(sequence.images.stream(sequence.image_size))

    def grey(k: int) -> np.ndarray:
        return frames[k].decode(grey=True)[0].astype(np.float32) / 255

    pairs = candidates.shape[1]
    out = np.zeros((pairs, len(offsets_px), candidates.shape[0]))
    source = grey(0)
    for i in tqdm(range(pairs), desc="pairs", disable=not progress):
        left, right = frames[i].decode()
        inv_depth, valid, _, _ = sgbm_inverse_depth(left, right, sequence.K[0, 0], sequence.baseline)
        target, source = source, grey(i + 1)  # each frame is decoded once as grey
        gradient = np.hypot(cv2.Sobel(target, cv2.CV_32F, 1, 0), cv2.Sobel(target, cv2.CV_32F, 0, 1)) / 8
        steps = jnp.asarray(candidates[:, i], jnp.float32)
        for k, offset in enumerate(offsets_px):
            shifted = np.where(valid, inv_depth + offset / fb, 0.0)
            keep = valid & (shifted >= 1 / MAX_DEPTH_M) & (gradient >= MIN_GRADIENT)
            depth = np.where(keep, 1 / np.maximum(shifted, 1e-6), 1.0).astype(np.float32)
            out[i, k] = np.asarray(errors(source, target, depth, keep, steps))
    return out
