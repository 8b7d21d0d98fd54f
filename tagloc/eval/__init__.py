"""Evaluation: metrics against ground truth, the NEES test, eval, bench, the paper's baselines, the demo."""
