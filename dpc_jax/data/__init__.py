"""KITTI data layer: readers, VO priors, the preprocessing cache and the numpy input pipeline.

* :mod:`dpc_jax.data.kitti`: ``open_odometry``, ``open_raw``, ``load_image``, ``StereoSequence``.
* :mod:`dpc_jax.data.calibration`: ``Calibration``, ``load_calibration`` (a KITTI calibration file's
  stereo pair).
* :mod:`dpc_jax.data.priors`: ``load_prior``, ``relative_xi``, ``rescale_monocular``.
* :mod:`dpc_jax.data.cache`: ``prepare_sequence`` (the ``dpc-jax prepare`` command).
* :mod:`dpc_jax.data.sequence_cache`: ``load_cache``, ``SequenceCache`` (the cache's on-disk format
  and its reader, without JAX).
* :mod:`dpc_jax.data.pipeline`: ``TrainLoader``, ``iterate_sequence``, ``leave_one_out``.

The names above are re-exported lazily (PEP 562), as in :mod:`dpc_jax`: importing one module of the
package (the trajectory files of :mod:`dpc_jax.data.poses_io` or the caches of
:mod:`dpc_jax.data.sequence_cache`, which the command line reads before it starts JAX) does not import
JAX and OpenCV through the others.
"""

from __future__ import annotations

from dpc_jax.runtime.lazy import lazy_getattr

_EXPORTS: dict[str, tuple[str, ...]] = {
    "dpc_jax.data.cache": ("prepare_sequence",),
    "dpc_jax.data.calibration": ("Calibration", "load_calibration"),
    "dpc_jax.data.kitti": ("StereoSequence", "load_image", "open_odometry", "open_raw"),
    "dpc_jax.data.pipeline": ("Split", "TrainLoader", "iterate_sequence", "leave_one_out"),
    "dpc_jax.data.priors": ("load_prior", "relative_xi", "rescale_monocular"),
    "dpc_jax.data.sequence_cache": ("SequenceCache", "load_cache"),
}
__all__ = sorted(name for names in _EXPORTS.values() for name in names)
__getattr__ = lazy_getattr("dpc_jax.data", _EXPORTS, globals())


def __dir__() -> list[str]:
    return sorted(__all__)
