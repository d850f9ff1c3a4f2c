"""The correction of a VO trajectory by a trained network, only where the images support it.

* ``inference``: restore a trained run (:class:`~dpc_jax.correction.inference.TrainedRun`) and
  run its network over a prepared sequence (ξ_corr and the paired photometric effect Δ per pair).
* ``measure``: the one measurement, Δ of any correction on the pairs of a prepared sequence, at
  the network's size or on a larger copy of the frames (a judge), without the network.
* ``judge``: the size a judge measures Δ at by default, and the check of a given one (no JAX).
* ``acceptance``: the ground-truth-free test on Δ and the record of what it let through.
* ``decision``: what to apply, from the measured effects alone: the full correction, its rotation,
  the rotation about some axes, each whole or without its mean over the sequence, or nothing.
* ``corrector``: the whole correction of one sequence (``dpc-jax correct``): predict, measure,
  decide, compose the trajectory, choose between the trained and the adapted network, write it.
* ``adapt``: self-supervised adaptation of a trained network to the sequence it corrects.
* ``live``: each pose corrected as its stereo pair arrives, decided by sequential tests.
* ``stream``: the loop of the live commands around it: the frames from their source, replayed at a
  pace, each pose written the moment it is made, and the summary.

Above training, the engine, eval and the reports; below the pipelines and the command line. Of
the training package it reads only the run's config and checkpoint format (``pyproject.toml``'s
import contracts).
"""
