"""relloc: relative multi-robot localization from odometry, UWB ranges and cooperative detections."""

__version__ = "0.1.0"
