"""Training: the run configuration, the optimizer, the jitted step, the loop, checkpoints and devices."""
