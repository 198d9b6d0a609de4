"""Evaluation helpers: scores of results against ground truth."""

from torchfit.eval.metrics import cdnet_counts, precision_recall_f

__all__ = ["cdnet_counts", "precision_recall_f"]
