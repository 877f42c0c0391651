"""Evaluation against ground truth: APE/ATE metrics, reports and tables, plots, calibration.

It sits above the engine: the engine hands ground-truth events to a truth sink
(:class:`relloc.evaluation.metrics.GroundTruth`) and never imports evaluation.
"""
