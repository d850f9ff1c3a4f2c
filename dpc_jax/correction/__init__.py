"""The correction of a VO trajectory by a trained network, only where the images support it.

* ``inference``: restore a trained run (:class:`~dpc_jax.correction.inference.TrainedRun`) and
  run its network over a prepared sequence (ξ_corr and the paired photometric effect Δ per pair).
* ``acceptance``: the ground-truth-free acceptance test on Δ (full correction, rotation, the
  rotation about some axes, or nothing).
* ``judge``: Δ of a given correction measured on a larger copy of the frames, without the
  network, and the judged decision and scale that follow from it.
* ``corrector``: the whole correction of one sequence (``dpc-jax correct``): predict, test,
  judge, compose the trajectory, choose between the trained and the adapted network, write it.
* ``adapt``: self-supervised adaptation of a trained network to the sequence it corrects.

Above training, the engine, eval and the reports; below the pipelines and the command line. Of
the training package it reads only the run's config and checkpoint format (``pyproject.toml``'s
import contracts).
"""
