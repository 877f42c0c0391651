"""The estimate every localizer emits: positions relative to the reference robot, with their
covariances and, where a method estimates them, headings, biases and odometry scales.

It is vocabulary, like the events: stages (association gates on it), sinks, evaluation and
navigation read it without depending on the localizers that produce it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

RESOLVE_HINT = (
    "formation orientation unobservable: drive any robot but the reference about 0.5 m, "
    "or give detections"
)
"""What the status says while the orientation is not observable."""
DOMINANT_MODE_WEIGHT = 0.9
"""A published mode lighter than this competes with others: not converged (navigation holds)."""


OWN_FRAME = "own frame"
"""``shape_gauge`` of a shape in the localizer's own, continuous frame (no robot on +x)."""
HEADING_FRAME = "heading"
"""Axes of the team's shared heading frame (the compass's), origin at the reference robot."""
BODY_FRAME = "body"
"""The reference robot's body frame (x forward, y left) at the estimate's time."""
FORMATION_FRAME = "formation"
"""The formation in a gauge (:attr:`Estimate.shape_gauge`): the reference at the origin and a
rotation/reflection that nothing measured fixes, where the orientation is not observable
(:meth:`Estimate.published`)."""


Position = tuple[float, ...]
"""A position (m): ``(x, y)`` in 2D, ``(x, y, z)`` in 3D; an estimate's positions share one
dimension (:attr:`Estimate.dimension`)."""
Covariance = tuple[tuple[float, ...], ...]
"""A position's covariance (m^2), ``D x D`` rows for a position of dimension ``D``."""


def position_of(values: Iterable[float]) -> Position:
    """A position from any sequence of coordinates (a NumPy row, a message's fields)."""
    return tuple(float(v) for v in values)


def covariance_of(matrix: Iterable[Iterable[float]]) -> Covariance:
    """A covariance from any ``D x D`` nested sequence (a NumPy matrix)."""
    return tuple(tuple(float(v) for v in row) for row in matrix)


@dataclass(frozen=True)
class Estimate:
    """Positions of every non-reference robot relative to the reference, with covariances, in
    the frame :attr:`frame` names: one the measurements observe."""

    t: float
    method: str
    reference: str
    positions: dict[str, Position]
    covariances: dict[str, Covariance] = field(default_factory=dict)
    ess: float | None = None
    headings: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Heading-estimate mode: per robot, the rotation that takes its odometry displacements
    into the reference robot's odometry frame, as (circular mean, circular std) in rad. A
    spread near pi says the heading is unobservable so far (the robot has not moved). The
    reference's own entry starts at 0 (by definition) and follows its odometry's drift."""
    biases: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Online-bias mode: per UWB node pair, the range bias (mean, std) in m. A std still at its
    prior says the bias is unobservable so far (the pair's distance has not changed)."""
    scales: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Online-scale mode: per robot, the odometry scale (mean, std)."""
    orientation_observable: bool = True
    """Whether the formation's rotation and reflection about the reference are resolved
    (:mod:`relloc.filter.summary`). While False, ``positions`` and ``covariances`` are the
    moments of the posterior over the whole ring of orientations (the covariance covers the
    truth, the positions alone mean little): use ``shape`` and ``distances``."""
    mode_weight: float = 1.0
    """Posterior weight of the mode that ``positions`` summarise (1 for a unimodal posterior)."""
    n_modes: int = 1
    """How many orientation/handedness modes the posterior has."""
    weighted_mean: dict[str, Position] = field(default_factory=dict)
    """Diagnostic: the weighted mean over every hypothesis, modes mixed (not an estimate)."""
    shape: dict[str, Position] = field(default_factory=dict)
    """The formation's shape relative to the reference in the declared gauge: turned so that
    ``shape_gauge`` lies on the reference's +x axis, mirrored so that the next robot (in the
    config's order) lies on the +y side. Known even when the orientation is not."""
    shape_gauge: str = ""
    """The robot put on the reference's +x axis in ``shape``; :data:`OWN_FRAME` where the
    shape is in the localizer's own frame instead: an arbitrary rotation/reflection that it
    keeps continuous over time (the smoother's), so that one alignment holds for a run."""
    shape_covariances: dict[str, Covariance] = field(default_factory=dict)
    """Each robot's covariance in ``shape``'s gauge."""
    distances: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Every pair's distance (mean, std) in m, keyed by :func:`relloc.events.pair_key`; the
    reference's pairs included."""
    recovering: bool = False
    """The localizer found itself lost (most of a robot's ranges disagree with the estimate)
    and is re-injecting hypotheses: the positions are not to be trusted until it clears."""
    inconsistent: bool = False
    """The published covariance stopped covering the filter's own innovations
    (:mod:`relloc.localizers.watchdog`): the covariances are widened by what the innovations
    say and the localizer restarts; the positions are not to be trusted until it clears."""
    particles: int | None = None
    """Particles (hypotheses) the filter held for this estimate: the adaptive count of the
    sampled filter (:mod:`relloc.filter.adaptive`); ``None`` for methods without."""
    unseen: dict[str, float] = field(default_factory=dict)
    """Robots nothing has been heard of for a while (odometry past its extrapolation, no range
    for 2 s), with the seconds since: where they are now is unknown. Their positions are where
    they were last seen; their covariances (all of them, when the reference is unseen) have
    grown at ``[filter.odometry] unseen_speed``, so that they still cover a robot that drove
    on meanwhile."""
    frame: str = HEADING_FRAME
    """Where ``positions`` and ``covariances`` are: :data:`HEADING_FRAME` (with a compass, or
    methods aligned to the truth) or :data:`BODY_FRAME` (headings estimated: the reference's
    odometry frame turns against the world as its heading drifts, unobserved, so relloc
    publishes in the reference's body frame, which sightings and ranges do observe)."""
    yaws: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Robots with several UWB tags (their ranges show their heading): each one's heading in
    the frame of :attr:`frame` (the reference's body frame where the reference has several tags
    too), (mean, std) in rad."""

    @property
    def dimension(self) -> int:
        """The positions' dimension: 2 (``x, y``) or 3 (``x, y, z``); 2 when there are none."""
        return len(next(iter(self.positions.values()), (0.0, 0.0)))

    def position(self, robot: str) -> NDArray[np.float64]:
        """``robot``'s position as an array of :attr:`dimension`."""
        return np.asarray(self.positions[robot], dtype=float)

    def covariance(self, robot: str) -> NDArray[np.float64] | None:
        """``robot``'s covariance as a ``D x D`` array (``None``: the estimate gives none)."""
        cov = self.covariances.get(robot)
        return None if cov is None else np.asarray(cov, dtype=float)

    @property
    def frame_id(self) -> str:
        """The frame's ROS name: the reference's name for the heading frame (a frame with the
        compass's axes at the reference), ``<reference>/base_link`` for its body frame,
        ``<reference>/formation`` for the formation in its gauge."""
        if self.frame == BODY_FRAME:
            return f"{self.reference}/base_link"
        if self.frame == FORMATION_FRAME:
            return f"{self.reference}/formation"
        return self.reference

    def published(self) -> Estimate:
        """What relloc publishes of this estimate (TUM files, MCAP, Zenoh poses): itself where
        the orientation is observable; where it is not, the formation in its gauge
        (positions ``shape``, covariances ``shape_covariances``, frame
        :data:`FORMATION_FRAME`), since the moments over the ring of orientations sit at the
        reference for every robot and show nobody where anyone is. The ring moments stay in
        ``positions`` of the estimate itself (what evaluation and the association read)."""
        if self.orientation_observable or not self.shape or self.frame == FORMATION_FRAME:
            return self
        return replace(
            self,
            positions=dict(self.shape),
            covariances=dict(self.shape_covariances),
            frame=FORMATION_FRAME,
        )

    def in_body_frame(self, yaw: float) -> Estimate:
        """This estimate in the reference's body frame, the reference's heading in the
        heading frame being ``yaw`` (rad): positions, covariances and yaws turned by ``-yaw``
        about z (the heading frame's estimate of a compass team seen from the reference, as
        an onboard view publishes it); itself where it is not in the heading frame or ``yaw``
        is not finite. The shape stays in its own gauge; the headings stay odometry-frame
        rotations (:attr:`headings`)."""
        if self.frame != HEADING_FRAME or not math.isfinite(yaw):
            return self
        c, s = math.cos(yaw), math.sin(yaw)
        turn = np.eye(self.dimension)
        turn[:2, :2] = ((c, s), (-s, c))

        def position(p: Position) -> Position:
            return position_of(turn @ np.asarray(p, float))

        def covariance(cov: Covariance) -> Covariance:
            return covariance_of(turn @ np.asarray(cov, float) @ turn.T)

        return replace(
            self,
            positions={r: position(p) for r, p in self.positions.items()},
            covariances={r: covariance(c) for r, c in self.covariances.items()},
            weighted_mean={r: position(p) for r, p in self.weighted_mean.items()},
            yaws={r: (math.remainder(m - yaw, math.tau), sd) for r, (m, sd) in self.yaws.items()},
            frame=BODY_FRAME,
        )

    @property
    def status(self) -> str:
        """One line on what the estimate means: what would resolve the orientation, or that
        the posterior has competing modes, that the localizer is recovering or inconsistent, or ``ok``."""
        if self.recovering:
            return "recovering: the measurements stopped fitting the estimate; hypotheses are being re-injected"
        if self.inconsistent:
            return (
                "inconsistent: the innovations exceed the published covariance; widened, restarting"
            )
        if self.unseen:
            who = ", ".join(f"{r} for {s:.1f} s" for r, s in sorted(self.unseen.items()))
            return f"unseen: {who} (no odometry, no range): positions are where last seen, covariances widened"
        if not self.orientation_observable:
            return RESOLVE_HINT
        if self.mode_weight < DOMINANT_MODE_WEIGHT:
            return f"{self.n_modes} modes: the published one holds {self.mode_weight:.0%} of the posterior"
        return "ok"

    def std(self, robot: str) -> float:
        """Position standard deviation of ``robot``: sqrt of the covariance's largest eigenvalue."""
        cov = self.covariance(robot)
        if cov is None:
            return math.nan
        return float(np.sqrt(np.max(np.linalg.eigvalsh(cov))))
