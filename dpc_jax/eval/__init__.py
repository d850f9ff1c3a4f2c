"""Evaluation: trajectory metrics, the evaluation of estimates against ground truth, its report and plots."""
