"""KITTI data layer: readers, VO priors, the preprocessing cache and the numpy input pipeline.

* :mod:`dpc_jax.data.kitti`: ``open_odometry``, ``open_raw``, ``load_image``, ``StereoSequence``.
* :mod:`dpc_jax.data.priors`: ``load_prior``, ``relative_xi``, ``rescale_monocular``.
* :mod:`dpc_jax.data.cache`: ``prepare_sequence`` (the ``dpc-jax prepare`` command).
* :mod:`dpc_jax.data.pipeline`: ``load_cache``, ``TrainLoader``, ``iterate_sequence``, ``leave_one_out``.
"""

from dpc_jax.data.cache import prepare_sequence
from dpc_jax.data.kitti import StereoSequence, load_image, open_odometry, open_raw
from dpc_jax.data.pipeline import (
    SequenceCache,
    Split,
    TrainLoader,
    iterate_sequence,
    leave_one_out,
    load_cache,
)
from dpc_jax.data.priors import load_prior, relative_xi, rescale_monocular

__all__ = [
    "SequenceCache",
    "Split",
    "StereoSequence",
    "TrainLoader",
    "iterate_sequence",
    "leave_one_out",
    "load_cache",
    "load_image",
    "load_prior",
    "open_odometry",
    "open_raw",
    "prepare_sequence",
    "relative_xi",
    "rescale_monocular",
]
