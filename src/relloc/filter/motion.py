"""What both filters share about motion and the start: the odometry noise model and the
uniform prior box of relative positions.

The particle filter's predict is one compiled pass (:func:`_propagate`): it draws every normal
it needs from its own stream (SplitMix64 words, each split into two 32-bit halves that a
256-layer ziggurat turns into two normals of 23-bit resolution, ample for noise of centimetres;
seeded per call from the filter's ``numpy.random.Generator``, so a seeded filter stays
reproducible) and adds it to the particle in the same loop. NumPy's generator alone took as long as the rest of the
update at tens of thousands of particles, and drawing into a buffer first is one more pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from relloc.filter import compiled

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
        columns may follow; in place); ``others`` indexes disp/sigma rows.

        Compiled (:func:`relloc.filter.compiled.enabled`): one pass (module docstring), per
        particle the reference's shared draw, then each relative position's own; one word of
        ``rng``'s bit generator seeds it per call. NumPy: the noise drawn from ``rng`` into
        ``work`` (an ``(M, N-1, 2)`` buffer reused from step to step), then added."""
        own = np.sqrt(self.own_variance(sigma, others, dt))
        if not compiled.enabled():
            self._propagate_numpy(particles, others, reference, disp, sigma, own, rng, work)
            return
        if particles.dtype != np.float64 or particles.strides[1] != particles.itemsize:
            raise ValueError("particles must be float64 rows with contiguous columns")
        seed = int(rng.bit_generator.random_raw()) >> 1  # 63 bits: an int64 for the kernel
        _propagate(
            particles,
            np.asarray(disp, dtype=float),
            np.asarray(others, dtype=np.intp),
            int(reference),
            own,
            float(sigma[reference]),
            seed,
        )

    @staticmethod
    def _propagate_numpy(
        particles: FloatArray,
        others: IntArray,
        reference: int,
        disp: FloatArray,
        sigma: FloatArray,
        own: FloatArray,
        rng: np.random.Generator,
        work: FloatArray | None,
    ) -> None:
        """:meth:`propagate` by NumPy calls over the flat ``(M, 2(N-1))`` rows, or over complex
        pairs for the reference's shared draw (the same element-wise arithmetic as
        broadcasting over ``(M, N-1, 2)``, without NumPy's slow loops over an innermost axis of
        1 or 2)."""
        m = particles.shape[0]
        n_others = len(others)
        rel = particles[:, : 2 * n_others]
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


# ----------------------------------------------------------------------------- compiled noise
def _ziggurat_tables(bits: int = 23) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """Marsaglia and Tsang's 256-layer ziggurat for the standard normal (the layout of NumPy's
    ``float32`` generator: 23-bit magnitudes): the acceptance thresholds ``ki``, the layer
    widths ``wi`` (scaled to the magnitude) and the density at each layer's edge ``fi``."""
    dn = tn = 3.6541528853610088
    vn = 0.00492867323399
    q = vn / math.exp(-0.5 * dn * dn)
    ki = np.zeros(256, dtype=np.int64)
    wi, fi = np.zeros(256), np.zeros(256)
    scale = float(2**bits)
    ki[0], ki[1] = int(dn / q * scale), 0
    wi[0], wi[255] = q / scale, dn / scale
    fi[0], fi[255] = 1.0, math.exp(-0.5 * dn * dn)
    for i in range(254, 0, -1):
        dn = math.sqrt(-2.0 * math.log(vn / dn + math.exp(-0.5 * dn * dn)))
        ki[i + 1] = int(dn / tn * scale)
        tn = dn
        fi[i] = math.exp(-0.5 * dn * dn)
        wi[i] = dn / scale
    return ki, wi, fi


_KI, _WI, _FI = _ziggurat_tables()
_ZIG_R = 3.6541528853610088
_U1, _GOLDEN = np.uint64(1), np.uint64(0x9E3779B97F4A7C15)
_MIX1, _MIX2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_S8, _S9, _S11, _S27, _S30, _S31, _S32 = (np.uint64(s) for s in (8, 9, 11, 27, 30, 31, 32))
_MASK8, _MASK23, _MASK32 = np.uint64(0xFF), np.uint64(0x7FFFFF), np.uint64(0xFFFFFFFF)
_TO_UNIT = 1.0 / 9007199254740992.0  # 2^-53


@compiled.njit(cache=True)
def _next(state: NDArray[np.uint64]) -> np.uint64:
    """SplitMix64: the next 64 random bits of ``state[0]`` (which it advances)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@compiled.njit(cache=True)
def _unit(state: NDArray[np.uint64]) -> float:
    """A uniform double in ``[0, 1)``."""
    return float(np.int64(_next(state) >> _S11)) * _TO_UNIT


@compiled.njit(cache=True)
def _normal_slow(state: NDArray[np.uint64], idx: int, x: float, negative: bool) -> float:
    """The ziggurat's rare branches: the base layer's tail, and the wedges (about 1 % of the
    draws); loops until one is accepted, on fresh 32-bit halves."""
    while True:
        if idx == 0:
            while True:
                xx = -math.log1p(-_unit(state)) / _ZIG_R
                yy = -math.log1p(-_unit(state))
                if yy + yy > xx * xx:
                    return -(_ZIG_R + xx) if negative else _ZIG_R + xx
        if (_FI[idx - 1] - _FI[idx]) * _unit(state) + _FI[idx] < math.exp(-0.5 * x * x):
            return x
        r = _next(state) & _MASK32
        idx = int(r & _MASK8)
        negative = bool((r >> _S8) & _U1)
        rabs = np.int64((r >> _S9) & _MASK23)
        x = float(rabs) * _WI[idx]
        if negative:
            x = -x
        if rabs < _KI[idx]:
            return x


@compiled.njit(cache=True)
def _normal(state: NDArray[np.uint64], r: np.uint64) -> float:
    """A standard normal from the 32 random bits ``r``: 8 pick the layer, 1 the sign, 23 the
    magnitude; about 1 % of the draws take more bits from ``state`` (:func:`_normal_slow`)."""
    idx = int(r & _MASK8)
    sign = 1.0 - 2.0 * float(np.int64((r >> _S8) & _U1))
    rabs = np.int64((r >> _S9) & _MASK23)  # signed: one instruction to convert, not a branch
    x = float(rabs) * _WI[idx] * sign
    if rabs < _KI[idx]:
        return x
    return _normal_slow(state, idx, x, sign < 0.0)


@compiled.njit(cache=True)
def standard_normal(seed: int, n: int) -> FloatArray:
    """``n`` draws of the compiled stream seeded with ``seed`` (what :func:`_propagate` adds;
    for tests of the distribution)."""
    state = np.full(1, np.uint64(seed), dtype=np.uint64)
    out = np.empty(n + 1)
    for i in range(0, n, 2):
        r = _next(state)  # two normals per word (not through a function returning a pair:
        out[i] = _normal(state, r & _MASK32)  # that compiles to twice the time)
        out[i + 1] = _normal(state, r >> _S32)
    return out[:n]


@compiled.njit(cache=True)
def _propagate(
    particles: FloatArray,
    disp: FloatArray,
    others: IntArray,
    reference: int,
    own: FloatArray,
    sigma_ref: float,
    seed: int,
) -> None:
    """Per particle: ``x_j += step_j + own_{j//2} n_j - sigma_ref c_{j%2}``, with ``step`` the
    displacements ``disp`` of the ``others`` less the ``reference``'s (flattened), ``c`` the
    reference's draw shared by the particle's relative positions (none when ``sigma_ref`` is
    0), every ``n`` and ``c`` a standard normal of the stream seeded by ``seed``."""
    state = np.full(1, np.uint64(seed), dtype=np.uint64)
    cols = 2 * others.shape[0]
    step = np.empty(cols)
    for j in range(others.shape[0]):
        step[2 * j] = disp[others[j], 0] - disp[reference, 0]
        step[2 * j + 1] = disp[others[j], 1] - disp[reference, 1]
    for i in range(particles.shape[0]):
        cx = cy = 0.0
        if sigma_ref > 0.0:
            r = _next(state)
            cx = sigma_ref * _normal(state, r & _MASK32)
            cy = sigma_ref * _normal(state, r >> _S32)
        row = particles[i]
        for j in range(0, cols, 2):
            s = own[j // 2]
            r = _next(state)
            row[j] += step[j] + s * _normal(state, r & _MASK32) - cx
            row[j + 1] += step[j + 1] + s * _normal(state, r >> _S32) - cy
