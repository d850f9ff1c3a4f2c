"""Evaluation: trajectory metrics, the evaluation of estimates against ground truth, the error diagnosis
and the linear baseline. Their tables, reports and figures are ``dpc_jax.report``'s."""
