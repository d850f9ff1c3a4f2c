"""Training: the run configuration, the optimizer, the jitted step, the loop and checkpoints (the device
mesh is the engine's, ``dpc_jax.engine.parallel``)."""
