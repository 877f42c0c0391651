"""What both filters share about motion and the start: the odometry noise model and the
uniform prior box of relative positions."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

PROCESS_NOISE = 0.03
"""Random-walk noise of every relative position (m per sqrt(s)): keeps static robots' particles
diverse."""
NOISE_PER_M = 0.05
"""Odometry displacement noise: standard deviation per metre travelled (fraction)."""
NOISE_PER_RAD = 0.02
"""Lateral odometry noise per radian turned (m/rad), for heading errors during turns."""


@dataclass(frozen=True)
class OdometryMotion:
    """Relative-position process model driven by every robot's odometry.

    Robot ``i`` moved by ``disp[i]`` over ``dt`` seconds with per-axis standard deviation
    ``sigma[i]`` (:meth:`step_sigma`: ``noise_per_m`` per metre travelled plus ``noise_per_rad``
    per radian turned). The relative position of ``i`` with respect to the reference ``r``
    moves by ``disp[i] - disp[r]``; the reference's noise is drawn once per particle and shared
    by every relative position, as it is in reality. ``process_noise`` (m/sqrt(s)) adds a
    random walk so that particles of static robots stay diverse.
    """

    process_noise: float = PROCESS_NOISE
    noise_per_m: float = NOISE_PER_M
    noise_per_rad: float = NOISE_PER_RAD

    def step_sigma(self, distance: float, turn: float) -> float:
        """Per-axis standard deviation of one robot's displacement over one step."""
        return self.noise_per_m * distance + self.noise_per_rad * turn

    def own_variance(
        self, sigma: FloatArray, others: IntArray | list[int], dt: float
    ) -> FloatArray:
        """Per non-reference robot, the variance of its own motion noise over ``dt``: its
        odometry's and the random walk's (the reference's adds to every one, in common)."""
        return sigma[others] ** 2 + self.process_noise**2 * max(dt, 0.0)

    def propagate(
        self,
        particles: FloatArray,
        others: IntArray,
        reference: int,
        disp: FloatArray,
        sigma: FloatArray,
        dt: float,
        rng: np.random.Generator,
        work: FloatArray | None = None,
    ) -> None:
        """Move the position columns of ``particles`` (``(M, D)``, ``D >= 2(N-1)``: online-bias
        columns may follow; in place); ``others`` indexes disp/sigma rows. ``work``: an
        ``(M, N-1, 2)`` buffer the noise is drawn into (reused from step to step, it saves
        faulting in a fresh array per call); the numbers are the same either way.

        Every operation runs over the flat ``(M, 2(N-1))`` rows, or over complex pairs for the
        reference's shared draw: the same element-wise arithmetic as broadcasting over
        ``(M, N-1, 2)``, without NumPy's slow loops over an innermost axis of 1 or 2."""
        m = particles.shape[0]
        n_others = len(others)
        rel = particles[:, : 2 * n_others]
        own = np.sqrt(self.own_variance(sigma, others, dt))
        shape = (m, n_others, 2)
        if work is None or work.shape != shape:
            work = np.empty(shape)
        noise = rng.standard_normal(shape, out=work).reshape(m, 2 * n_others)
        noise *= np.repeat(own, 2)
        noise += (disp[others] - disp[reference]).reshape(-1)
        if sigma[reference] > 0.0:
            common = rng.standard_normal((m, 1, 2))
            common *= sigma[reference]
            # complex128 views: one complex subtraction is the two real ones, exactly
            pairs = noise.view(np.complex128)
            pairs -= common.reshape(m, 2).view(np.complex128)
        rel += noise


@dataclass(frozen=True)
class PriorBox:
    """Uniform prior over relative positions: each robot is anywhere in the arena
    ``(xmin, xmax, ymin, ymax)``, so a relative position spans twice its extent."""

    area: tuple[float, float, float, float]

    @cached_property
    def half_extent(self) -> FloatArray:
        xmin, xmax, ymin, ymax = self.area
        return np.array([xmax - xmin, ymax - ymin], dtype=float)

    def sample(self, rng: np.random.Generator, m: int, n_others: int) -> FloatArray:
        """``m`` formations uniform over the box, shape ``(m, 2 n_others)``."""
        u = rng.uniform(-1.0, 1.0, size=(m, n_others, 2)) * self.half_extent
        return u.reshape(m, 2 * n_others)

    def contains(self, positions: FloatArray) -> NDArray[np.bool_]:
        """Which rows of ``positions`` (``(m, 2 n_others)``) lie inside the box."""
        m = positions.shape[0]
        return np.all(np.abs(positions.reshape(m, -1, 2)) <= self.half_extent, axis=(1, 2))
