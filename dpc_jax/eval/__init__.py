"""Evaluation: trajectory metrics, the evaluation of estimates against ground truth, the error diagnosis
and the linear baseline, and the metrics' plain float64 loops they are checked against
(``reference_metrics``). Their tables, reports and figures are ``dpc_jax.report``'s."""
