"""Calibrations the data contradict: counted, logged and published, never silently trusted.

A calibrated pair bias is a prior (:class:`relloc.localizers.priors.BiasPrior`), still
estimated. Under the model the posterior mean of a Gaussian variable moves from its prior mean
by a shift of variance ``prior_var - posterior_var``; a shift beyond ``SIGMAS`` of that is a
contradiction. Judged per calibrated pair (its bias) and, where the estimator publishes them,
per node offset (a transceiver's delay shared by its pairs: a node that moved since its
calibration shifts all its pairs a little, which its offset collects). A calibrated pair is
contradicted when its own shift or one of its nodes' is.

Published in the localizer's stats like the range-correction self-check's switches:
``calibration_contradicted.<pair>`` (1 while contradicted, 0 once it is not any more) and
``calibration_contradicted`` (onsets, each logged). The estimate itself needs no switch: the
prior already lets the data move the bias, and the node offsets take a node's shift
(docs/explanation/bias-offsets.md).
"""

from __future__ import annotations

import logging
import math
from collections import Counter

from relloc.config import TeamConfig
from relloc.localizers.priors import BiasPrior

log = logging.getLogger(__name__)

SIGMAS = 3.0
"""Shift (in its own standard deviations) beyond which the data contradict a prior."""


def shift_score(prior_mean: float, prior_var: float, mean: float, std: float) -> float:
    """How far a posterior ``mean`` (``std``) moved from its prior, in standard deviations of
    the shift the model expects (``prior_var - std^2``, floored at 1 % of ``prior_var``)."""
    expected = max(prior_var - std * std, 0.01 * prior_var)
    return abs(mean - prior_mean) / math.sqrt(expected)


class CalibrationCheck:
    """Judges each published estimate's biases against a :class:`BiasPrior`."""

    def __init__(self, prior: BiasPrior, calibrated: frozenset[str]) -> None:
        self.prior = prior
        self.calibrated = calibrated
        """The node pairs whose prior is a calibration."""
        self._variance = dict(zip(prior.pairs, prior.variance.tolist(), strict=True))
        self._mean = dict(zip(prior.pairs, prior.mean.tolist(), strict=True))
        self._latent = dict(zip(prior.latents, prior.latent_sigma.tolist(), strict=True))
        self.flagged: set[str] = set()

    def judge(
        self,
        biases: dict[str, tuple[float, float]],
        offsets: dict[str, tuple[float, float]],
        stats: Counter[str],
    ) -> set[str]:
        """The calibrated pairs ``biases`` and ``offsets`` (name -> mean, std) contradict;
        their changes are counted and logged in ``stats``."""
        moved_nodes = {
            name
            for name, (m, sd) in offsets.items()
            if name in self._latent and shift_score(0.0, self._latent[name] ** 2, m, sd) > SIGMAS
        }
        now = set()
        for pair in self.calibrated:
            if pair not in biases:
                continue
            m, sd = biases[pair]
            own = shift_score(self._mean[pair], self._variance[pair], m, sd) > SIGMAS
            if own or moved_nodes.intersection(pair.split("-")):
                now.add(pair)
        for pair in sorted(now - self.flagged):
            stats["calibration_contradicted"] += 1
            log.warning("the data contradict the calibration of UWB pair %s", pair)
        for pair in now ^ self.flagged:
            stats[f"calibration_contradicted.{pair}"] = int(pair in now)
        self.flagged = now
        return now


def calibration_check(config: TeamConfig, prior: BiasPrior) -> CalibrationCheck | None:
    """The check of a team's online biases, ``None`` where no online pair is calibrated."""
    calibrated = frozenset(p for p in prior.pairs if p in config.uwb.pairs)
    return CalibrationCheck(prior, calibrated) if calibrated else None
