"""Localizers: the holders of estimator state. Events in, estimates out.

:mod:`~relloc.localizers.base` validates and batches for every method, from small
collaborators: the team clock (:mod:`~relloc.localizers.clock`), the batching grid that also
gives the live wake rule (:mod:`~relloc.localizers.grid`) and the odometry tracks
(:mod:`~relloc.localizers.tracks`). :mod:`~relloc.localizers.stepped` starts an estimator and
publishes its estimate with what is heard of each robot (:mod:`~relloc.localizers.heard`) and
the consistency watchdog; :mod:`~relloc.localizers.filtered` runs a weighted filter's cycle,
with recovery (:mod:`~relloc.localizers.recovery`, :mod:`~relloc.localizers.divergence`).
The estimator kinds that build on them are :mod:`relloc.estimators`; here are the baselines:
:mod:`~relloc.localizers.multilateration` (least squares) and :mod:`~relloc.localizers.ekf`
(the oracle EKF). :func:`relloc.methods.build_pipeline` chooses the class from the config.
"""
