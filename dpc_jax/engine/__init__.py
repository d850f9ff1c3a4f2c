"""The machinery below training, adaptation and inference: the one step driver
(:mod:`~dpc_jax.engine.driver`), the device mesh (:mod:`~dpc_jax.engine.parallel`), the choices that
depend on the backend JAX runs on (:mod:`~dpc_jax.engine.backend`) and the network over a cached
sequence (:mod:`~dpc_jax.engine.predict`). It imports neither the training loop nor inference.
"""
