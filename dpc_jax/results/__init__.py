"""The typed results of a run, each with one way to write and read it.

``acceptance``: what an acceptance test measured and let through
(:class:`~dpc_jax.results.acceptance.PairedTest`, :class:`~dpc_jax.results.acceptance.Acceptance`);
``correction``: a corrected sequence
(:class:`~dpc_jax.results.correction.Correction`, written as its summary); ``demo``: the synthetic demo's
summary (:class:`~dpc_jax.results.demo.DemoSummary`, ``summary.json``); ``fold``: one test sequence of an
experiment's fold (:class:`~dpc_jax.results.fold.FoldResult`, ``results.json``). The evaluation against
ground truth is :class:`dpc_jax.eval.evaluation.Evaluation`, below this package.

The package sits below the reports, the correction and the pipelines: they build these results and
the reports read them, so no layer mirrors another's types. A result is a frozen dataclass; ``to_dict``
gives its JSON-ready form and ``from_dict`` reads that form back, except where a result holds arrays that
JSON does not (a correction's trajectories): it is written, and read in memory.
"""
