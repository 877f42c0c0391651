"""Localizers: the holders of filter state. Events in, estimates out.

:mod:`~relloc.localizers.base` validates, batches on the update grid, keeps the odometry
tracks and emits estimates for every method; :mod:`~relloc.localizers.sampled` runs the
particle filter, :mod:`~relloc.localizers.self_calibrating` the Gaussian-sum filter that
estimates headings, odometry scales and range biases, :mod:`~relloc.localizers.multilateration`
the least-squares baseline; :mod:`~relloc.localizers.start` is the annealed start both particle
localizers begin with. :func:`relloc.methods.build_pipeline` chooses the class from the config.
"""
