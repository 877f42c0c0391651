"""Evaluation against ground truth: APE/ATE metrics, reports and tables, plots, calibration, and
the ranging CSV of a recording (its UWB errors against motion capture, for training and scoring).

It sits above the engine: the engine hands ground-truth events to a truth sink
(:class:`relloc.evaluation.metrics.GroundTruth`) and never imports evaluation.
"""
