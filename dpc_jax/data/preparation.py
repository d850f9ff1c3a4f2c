"""One stereo frame prepared as the network and the acceptance test see it: the one preparation under
``dpc-jax prepare`` (``dpc_jax.data.cache``) and the live correction (``dpc_jax.correction.live``).

A frame is resized to the network's input size with area interpolation, the right image first
resampled by the rig's disparity calibration residual, and matched with StereoSGBM at that size
(``dpc_jax.data.stereo_depth``); the intrinsics are scaled with the images
(``dpc_jax.geometry.camera.scale_intrinsics``).
"""

from __future__ import annotations

from concurrent.futures import Executor
from pathlib import Path

import cv2
import jax
import numpy as np

from dpc_jax.data.sequence_cache import (
    Frames,
    SequenceCache,
    decode_flow,
    encode_flow,
    flow_step,
    stereo_depth_views,
)
from dpc_jax.data.stereo_depth import sgbm_disparity, sgbm_fits
from dpc_jax.geometry.camera import scale_intrinsics


def as_rgb(image: np.ndarray, name: str = "image") -> np.ndarray:
    """A decoded camera image as the cache stores it: uint8 ``[H, W, 3]`` (RGB), a grey ``[H, W]`` one
    replicated to three channels (what decoding a grey PNG in colour gives)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"{name}: expected an 8-bit image, got {image.dtype}")
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"{name}: expected [H, W] grey or [H, W, 3] colour, got shape {image.shape}")
    return image


def resized_image(image: np.ndarray, size: tuple[int, int], shift: float = 0.0) -> np.ndarray:
    """``image`` (uint8 ``[H, W, 3]``) resized to ``size = (H, W)`` (INTER_AREA); first, with ``shift``
    (px at the source resolution), resampled at ``u + shift`` (bilinear) so that its content moves
    ``shift`` px to the left."""
    if shift:
        move = np.array([[1.0, 0.0, shift], [0.0, 1.0, 0.0]])
        image = cv2.warpAffine(image, move, (image.shape[1], image.shape[0]),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
    if image.shape[:2] == tuple(size):
        return image
    return cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_AREA)


def resized_intrinsics(K: np.ndarray, source: tuple[int, int], size: tuple[int, int],
                       half_pixel: bool = True) -> np.ndarray:
    """float64 ``[3, 3]`` intrinsics of images of ``source = (H, W)`` px resized to ``size``."""
    (h0, w0), (h1, w1) = source, size
    # scale_intrinsics is JAX code, which computes in float32 unless x64 is on.
    with jax.enable_x64(True):
        scaled = scale_intrinsics(np.asarray(K, np.float64), w1 / w0, h1 / h0, half_pixel=half_pixel)
        return np.asarray(scaled, np.float64)


def prepared_pair(
    left: np.ndarray, right: np.ndarray, size: tuple[int, int], K: np.ndarray, baseline: float,
    disparity_offset: float = 0.0, match: bool = True, pool: Executor | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One frame as the cache stores it → ``(left, right, disparity)``: the images uint8 ``[H, W, 3]``
    at ``size``, the right one resampled by ``disparity_offset`` (px at the source resolution) first,
    and StereoSGBM's fixed-point disparity of both cameras (int16 ``[2, H, W]``), None when the images
    are too narrow to match or ``match`` is False. ``K``: the intrinsics at ``size``; ``baseline``:
    metres; ``pool``: the right camera's matched on one of its threads
    (``dpc_jax.data.stereo_depth.sgbm_disparity``)."""
    small_left = resized_image(left, size)
    small_right = resized_image(right, size, float(disparity_offset))
    disparity = matched_pair(small_left, small_right, K, baseline, pool) if match else None
    return small_left, small_right, disparity


def matched_pair(left: np.ndarray, right: np.ndarray, K: np.ndarray, baseline: float,
                 pool: Executor | None = None) -> np.ndarray | None:
    """StereoSGBM's disparity of both cameras of a pair prepared at the size of ``K`` (int16 ``[2, H, W]``,
    ``dpc_jax.data.stereo_depth.sgbm_disparity``), None when the images are too narrow to match."""
    fu = float(K[0, 0])
    if not sgbm_fits(left.shape[1], fu, baseline):
        return None
    return sgbm_disparity(left, right, fu, baseline, pool=pool)


def pair_cache(frames: tuple[tuple[np.ndarray, np.ndarray, np.ndarray | None], ...], K: np.ndarray,
               baseline: float, prior: np.ndarray, *, flow: bool = False) -> SequenceCache:
    """Two prepared frames ``(left [H, W, 3] uint8, right, disparity [H, W] px or None)`` at the size of
    ``K`` ``[3, 3]``, with the prior's poses ``[2, 4, 4]``, as a cache in memory (what prediction and
    measurement read: the live correction's pair); ``flow``: with the optical flow between them, quantised
    as ``prepare`` stores it (``dpc_jax.data.sequence_cache.encode_flow``)."""
    from dpc_jax.data.cache_products import farneback_flow, grey

    (left0, right0, disparity0), (left1, right1, disparity1) = frames
    flows: dict[str, Frames] = {}
    if flow:
        step = flow_step((left0.shape[0], left0.shape[1]))
        pair = np.stack([farneback_flow(grey(a), grey(b)) for a, b in ((left0, left1), (right0, right1))])
        flows["forward"] = decode_flow(encode_flow(pair, step)[None], step)
    depth = None
    if disparity0 is not None and disparity1 is not None:
        depth = stereo_depth_views(np.stack([disparity0, disparity1]), float(K[0, 0]) * baseline)
    return SequenceCache(
        path=Path("<live>"), name="live", left=np.stack([left0, left1]), right=np.stack([right0, right1]),
        prior=prior, gt=None, K=K, baseline=baseline, indices=np.arange(2), times=np.zeros(2), flows=flows,
        manifest={}, stereo_depth=depth)
