"""Reports: Markdown and CSV tables, report files and figures, built from the result types.

``tables`` holds the Markdown/CSV helpers the reports share; ``evaluation`` and ``plots`` report an
evaluation against ground truth (:class:`dpc_jax.eval.evaluation.Evaluation`); ``correction``,
``demo`` and ``protocol`` report a correction, the synthetic demo and an experiment's folds. The
computation lives below this package (``dpc_jax.eval``, ``dpc_jax.correction.acceptance``); the pipelines and
the command line call it. Correction, demo and experiment results are read through the protocols
each module declares, so this package imports neither the correction nor the pipelines.
"""
