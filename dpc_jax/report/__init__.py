"""Reports: Markdown and CSV tables, report files and figures, built from the result types.

``tables`` holds the one implementation of Markdown tables, CSV text, the empty cell and the change
against the prior; ``pages`` the generated blocks of hand-written pages; ``plots`` the figures.
``evaluation_report`` reports an evaluation against ground truth
(:class:`dpc_jax.eval.evaluation.Evaluation`); ``correction_report``, ``demo_report`` and
``protocol_report`` report a correction, the synthetic demo and an experiment's folds from their result
types (``dpc_jax.results``, the floor below). The package sits below the correction and the pipelines,
which call it, and imports neither.
"""
