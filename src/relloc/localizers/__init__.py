"""Localizers: the holders of filter state. Events in, estimates out.

:mod:`~relloc.localizers.base` validates and batches for every method, from small
collaborators: the team clock (:mod:`~relloc.localizers.clock`), the batching grid that also
gives the live wake rule (:mod:`~relloc.localizers.grid`) and the odometry tracks
(:mod:`~relloc.localizers.tracks`). :mod:`~relloc.localizers.filtered` runs a filter's step,
with recovery (:mod:`~relloc.localizers.recovery`, :mod:`~relloc.localizers.divergence`) and
what is heard of each robot (:mod:`~relloc.localizers.heard`). The methods:
:mod:`~relloc.estimators.particle.localizer` runs the particle filter, :mod:`~relloc.estimators.gaussian_sum.localizer`
the Gaussian-sum filter that estimates headings, odometry scales and range biases,
:mod:`~relloc.estimators.range_graph.localizer` the large-team Gaussian sum,
:mod:`~relloc.localizers.multilateration` the least-squares baseline and
:mod:`~relloc.localizers.ekf` the oracle EKF. :func:`relloc.methods.build_pipeline` chooses the
class from the config.
"""
