"""Layout of the particle state.

A particle is one row of an ``(M, D)`` array. The first ``2(N-1)`` columns hold the positions
of the non-reference robots relative to the reference robot, in the team's shared heading
frame (``x, y`` of each robot in config order). The reference robot is the origin and is not
stored. Further blocks are appended by self-calibrating models; ``StateLayout`` names every
column block so that models index the state by meaning, never by magic number:

* ``bias_pairs``: for each UWB node pair whose range bias is estimated online, two columns,
  the mean and the variance of that particle's Gaussian belief about the bias. The bias is
  *Rao-Blackwellised*: given a particle's positions a range is linear in the bias, so each
  particle carries a one-dimensional Kalman filter per pair instead of sampling the bias
  (which would multiply the particles needed).

Only the position block is *sampled* (moved by Metropolis steps, rotated by symmetries);
the other blocks are sufficient statistics that resampling copies along.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TeamLayout:
    """Robots of the team and the reference robot: what every filter's state layout shares."""

    robots: tuple[str, ...]
    reference: str
    bias_pairs: tuple[str, ...] = ()
    """UWB node pairs (``"n_3-n_7"``) whose range bias the filter estimates online, in
    column order; how the state holds them is the subclass's (:meth:`bias_belief_column`,
    :meth:`bias_state_columns`)."""

    def __post_init__(self) -> None:
        if self.reference not in self.robots:
            raise ValueError(f"reference {self.reference!r} is not one of {self.robots}")
        if len(self.robots) < 2:
            raise ValueError("a team needs at least two robots")

    @property
    def others(self) -> tuple[str, ...]:
        """The non-reference robots, whose positions are in the state, in state order."""
        return tuple(r for r in self.robots if r != self.reference)

    @property
    def n_others(self) -> int:
        return len(self.robots) - 1

    def index(self, robot: str) -> int:
        """Index of ``robot`` in :attr:`robots` (the reference included)."""
        try:
            return self.robots.index(robot)
        except ValueError:
            raise KeyError(f"unknown robot {robot!r}") from None

    def slot(self, robot: str) -> int:
        """Position of ``robot`` among the non-reference robots (-1 for the reference): its
        position columns are ``2 slot, 2 slot + 1``."""
        return -1 if robot == self.reference else self.others.index(robot)

    def slot_of(self, index: int) -> int:
        """:meth:`slot` of the robot with team index ``index``."""
        return self.slot(self.robots[index])

    def positions(self, particles: FloatArray) -> FloatArray:
        """All robots' relative positions as coordinate planes of shape ``(2, N, M)``.

        ``positions[0, i]`` holds robot ``i``'s x over all particles (the reference's row is
        zero). Robot-major rows make the gathers of the measurement models
        (``positions[:, index_a]``) contiguous, which is several times faster than gathering
        along the middle axis of an ``(M, N, 2)`` array.
        """
        m = particles.shape[0]
        out = np.zeros((2, len(self.robots), m))
        rel = particles[:, : 2 * self.n_others].T.reshape(-1, 2, m)  # (N-1, 2, M)
        out[:, self._other_rows, :] = rel.transpose(1, 0, 2)
        return out

    @cached_property
    def columns_of_robots(self) -> NDArray[np.intp]:
        """Per team index, the first of the robot's two position columns in a particle row
        (``2 slot``), -1 for the reference (read-only)."""
        out = np.array(
            [-1 if r == self.reference else 2 * self.others.index(r) for r in self.robots],
            dtype=np.intp,
        )
        out.flags.writeable = False
        return out

    @cached_property
    def _other_rows(self) -> NDArray[np.intp]:
        return np.array(
            [i for i, r in enumerate(self.robots) if r != self.reference], dtype=np.intp
        )

    def bias_belief_column(self, pair: str) -> int:
        """Column of the mean of a per-particle Gaussian belief about ``pair``'s bias (its
        variance is the next column), -1 if the state holds none."""
        return -1

    def bias_state_columns(self, pair: str) -> tuple[int, ...]:
        """State columns whose sum a range of ``pair`` sees on top of its fixed bias (an
        estimated bias as a state variable), ``()`` if none."""
        return ()


@dataclass(frozen=True)
class StateLayout(TeamLayout):
    """The column blocks of the sampled filter's particle state."""

    @property
    def dim(self) -> int:
        return 2 * (len(self.robots) - 1)

    @property
    def width(self) -> int:
        """All columns: positions, then a (mean, variance) pair per online bias."""
        return self.dim + 2 * len(self.bias_pairs)

    def bias_columns(self, pair: str) -> tuple[int, int]:
        """Columns (mean, variance) of ``pair``'s online bias belief."""
        k = self.bias_pairs.index(pair)
        return self.dim + 2 * k, self.dim + 2 * k + 1

    def bias_belief_column(self, pair: str) -> int:
        return self.bias_columns(pair)[0] if pair in self.bias_pairs else -1

    def columns(self, robot: str) -> slice:
        """Columns of ``robot``'s relative position (the reference has none)."""
        k = self.others.index(robot)
        return slice(2 * k, 2 * k + 2)
