"""Reports: Markdown and CSV tables, report files and figures, built from the result types.

``tables`` holds the one implementation of Markdown tables, CSV text, the empty cell and the change
against the prior; ``pages`` the generated blocks of hand-written pages; ``plots`` the figures.
``evaluation_report`` reports an evaluation against ground truth
(:class:`dpc_jax.eval.evaluation.Evaluation`); ``correction_report``, ``demo_report`` and
``protocol_report`` report a correction, the synthetic demo and an experiment's folds. The package
sits below the correction and the pipelines, which call it: correction, acceptance-test, demo and
experiment results are read through the protocols each module declares, so it imports neither.
"""
