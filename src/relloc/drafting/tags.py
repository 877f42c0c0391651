"""Second UWB tags found in a bag, and their lever arms estimated from motion capture.

:func:`relloc.sources.inspect_bag.assign_nodes` puts one node on each motion-capture body; a node
left over may be a second tag on one of them. :func:`find_tags` says which body each left-over node
moves with, and where on it it sits, by least squares over the recording's ranges against the
bodies' motion-capture poses (position, and yaw from the orientation):

    range(a, b, t) = |P_A(t) + R(yaw_A(t)) l_a - P_B(t) - R(yaw_B(t)) l_b| + c_a + c_b

with a lever arm ``l`` per extra tag (x forward, y left in the body frame; the node that
:func:`assign_nodes` put on the body is its origin, ``l = 0``: the body's mocap origin is taken to
be at its first tag, as ``uwb_node`` says) and a constant ``c`` per node (its antenna delay: the
pair biases of a UWB team are close to sums of per-node constants). Two tags of one body never
enter: their range is not a distance between two mocap poses.

What the data separate: a lever arm moves a tag's ranges by ``-u_k . R l`` (``u_k`` the
directions to the partners), the node constant moves them all alike; robots standing still with
partners in one half-plane trade the two off along the partners' mean direction (large standard
errors there), partners all round or turning bodies separate them. A free bias per node pair
would absorb a static team's lever arms: not used in 2D. The first tag's lever arm trades off
with the body's mocap origin and is not estimated. Standard errors are cluster-robust by pair
(UWB multipath is a property of the geometry), with the factor ``G / (G - k)``.

A flying team (``dimension`` 3): 3D arms, level bodies, a bias per pair (moving, turning bodies
keep it from the arms), every tag placed from the mocap origin, their mean height held at 0
(ranges see only height differences), a pair's samples clustered per :data:`BLOCK_S`.

Which body: each candidate is fitted with its own lever arm (held to :data:`LEVER_MAX_M`) and
constant, the other nodes' held; the smallest clipped residual wins if below :data:`FIT_MAX_M`. A
wrong body keeps the range to the right body's first tag, so it is seldom close.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from relloc.events import pair_key
from relloc.ros.messages import MessageDecodeError, decode, pose_to_ground_truth, stamp_to_sec
from relloc.sources.inspect_bag import BagInventory
from relloc.sources.rosbag import _open_reader, _with_height
from relloc.sources.tracks import interpolate_track

__all__ = ["LEVER_MAX_M", "TagFit", "find_tags", "mocap_poses", "pose_at"]

LEVER_MAX_M = 1.0
"""A second tag sits at most this far from its body's origin, in x, in y (and in z) (m)."""
FIT_MAX_M = 0.2
"""The most RMS (m, residuals clipped to :data:`CLIP_M`) a body's fit may leave for the node to
be called a tag on it."""
CLIP_M = 1.0
HUBER_M = 0.1
"""Residuals beyond this (m) weigh linearly, not quadratically (multipath pairs)."""
SAMPLES_PER_PAIR = 200
MIN_PARTNERS = 3
"""A tag needs ranges to this many nodes on other bodies (lever arm x, y and its constant);
in 3D, where each pair has its own constant and the bodies turn under the arm, to every other
body's first tag where the team has fewer (three drones: two)."""
BLOCK_S = 5.0
"""In 3D the covariance's clusters are a pair's samples over this many seconds: a pair's own
bias takes up what its samples share, leaving errors that change as the geometry does."""
GAUGE_W = 1.0
"""Weight (per metre) of the pseudo-observation holding the mean height of the tags placed in 3D
at the mocap origins' height: ranges see only differences of the tags' heights."""
MAX_GAP_S = 0.1
SAME_BODY_TOL_M = 0.5
"""Where the node ranges to the body's first tag, that range may differ from the lever arm's
length plus the two node constants by at most this (m): UWB reads short ranges poorly, but not
metres off."""


@dataclass(frozen=True)
class TagFit:
    """An extra tag: the body it moves with and its lever arm there."""

    node: str
    body: str
    lever_arm: tuple[float, ...]
    """In the body frame (x forward, y left; z up in 3D, see :func:`find_tags`), m."""
    stderr: tuple[float, ...]
    """Standard errors of ``lever_arm`` (m); ``nan`` without redundancy."""
    rms: float
    """RMS of the tag's residuals in the final fit (m, clipped)."""
    partners: int
    runner_up: str
    """The next best body (empty: none fitted)."""
    runner_up_rms: float
    first: bool = False
    """The body's first tag, placed from the mocap origin too (3D, a body with several tags)."""


Poses = Mapping[str, np.ndarray]
"""Body -> ``(n, 5)`` rows ``t, x, y, z, yaw`` sorted by time."""


def mocap_poses(bag: Path, inv: BagInventory, bodies: Sequence[str]) -> dict[str, np.ndarray]:
    """Each body's mocap poses with height and yaw, timed as :func:`inspect_bag` times its tracks
    (header stamp, else receive time), so they line up with :attr:`BagInventory.ranges`."""
    topics = {inv.mocap_pattern.replace("{body}", b): b for b in bodies}
    rows: dict[str, list[tuple[float, float, float, float, float]]] = {b: [] for b in bodies}
    with _open_reader(Path(bag)) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, recv_ns, raw in reader.messages(conns) if conns else ():
            try:
                msg = decode(raw, conn.msgtype)
            except MessageDecodeError:
                continue
            stamp = stamp_to_sec(msg.header.stamp)
            t = stamp if stamp != 0.0 else recv_ns * 1e-9
            gt = _with_height(pose_to_ground_truth(msg, "", t=t), raw, conn.msgtype, None)
            x, y, *z = gt.position
            rows[topics[conn.topic]].append((t, x, y, z[0] if z else 0.0, gt.yaw))
    out = {}
    for body, v in rows.items():
        arr = np.array(v, dtype=float).reshape(-1, 5)
        out[body] = arr[np.argsort(arr[:, 0], kind="stable")]
    return out


def pose_at(
    track: np.ndarray, t: np.ndarray, dim: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(position (n, dim), yaw (n,), valid)`` of a pose track at times ``t``: ``x, y`` and,
    for ``dim`` 3, ``z``."""
    x, y, ok = interpolate_track(track[:, 0], track[:, 1], track[:, 2], t, max_gap=MAX_GAP_S)
    cols = [x, y]
    if dim == 3:
        z, _, _ = interpolate_track(track[:, 0], track[:, 3], track[:, 3], t, max_gap=MAX_GAP_S)
        cols.append(z)
    c, s, _ = interpolate_track(
        track[:, 0], np.cos(track[:, 4]), np.sin(track[:, 4]), t, max_gap=MAX_GAP_S
    )
    return np.stack(cols, axis=-1), np.arctan2(s, c), ok


@dataclass
class _Pairs:
    """Range samples of the node pairs on two different bodies, with both bodies' poses."""

    a: list[str]
    b: list[str]
    key: np.ndarray
    """Pair index of each sample."""
    t: np.ndarray
    rng: np.ndarray
    pa: np.ndarray
    pb: np.ndarray
    ya: np.ndarray
    yb: np.ndarray


def _samples(
    inv: BagInventory,
    poses: Poses,
    body_of: Mapping[str, str],
    pairs: Sequence[tuple[str, str]],
    dim: int,
) -> _Pairs:
    a_: list[str] = []
    b_: list[str] = []
    keys: list[np.ndarray] = []
    times: list[np.ndarray] = []
    rng: list[np.ndarray] = []
    pa: list[np.ndarray] = []
    pb: list[np.ndarray] = []
    ya: list[np.ndarray] = []
    yb: list[np.ndarray] = []
    for a, b in pairs:
        r = inv.ranges.get(pair_key(a, b))
        if r is None or r.shape[0] == 0:
            continue
        if r.shape[0] > SAMPLES_PER_PAIR:
            r = r[np.linspace(0, r.shape[0] - 1, SAMPLES_PER_PAIR).astype(int)]
        xa, yawa, oka = pose_at(poses[body_of[a]], r[:, 0], dim)
        xb, yawb, okb = pose_at(poses[body_of[b]], r[:, 0], dim)
        ok = oka & okb & np.isfinite(r[:, 1])
        if not ok.any():
            continue
        keys.append(np.full(int(ok.sum()), len(a_)))
        times.append(r[ok, 0])
        a_.append(a)
        b_.append(b)
        rng.append(r[ok, 1])
        pa.append(xa[ok])
        pb.append(xb[ok])
        ya.append(yawa[ok])
        yb.append(yawb[ok])
    if not a_:
        empty = np.zeros(0)
        flat = empty.reshape(0, dim)
        return _Pairs([], [], empty.astype(int), empty, empty, flat, flat, empty, empty)
    return _Pairs(
        a_,
        b_,
        np.concatenate(keys),
        np.concatenate(times),
        np.concatenate(rng),
        np.concatenate(pa),
        np.concatenate(pb),
        np.concatenate(ya),
        np.concatenate(yb),
    )


def _rot(yaw: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Body-frame vectors ``v`` (n, 2 or 3) in the world frame: turned by ``yaw`` (level bodies)."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = v.copy()
    out[:, 0] = c * v[:, 0] - s * v[:, 1]
    out[:, 1] = s * v[:, 0] + c * v[:, 1]
    return out


class _Model:
    """Residuals and Jacobian of the range model over some pairs: unknowns a constant per node in
    ``const`` (a node's for every pair it is in, or a pair key's, ``"n_1-n_2"``, for that pair
    alone) and a lever arm per node in ``arms``, of the samples' dimension (any other node's
    lever arm is 0 and its constant held at ``fixed_const``). ``gauge``: the arms' mean z is
    held at 0 by a pseudo-observation (3D, where nothing else fixes the tags' common height).
    ``block_s``: the covariance's clusters are a pair's samples in blocks of this many seconds
    (else the pair's samples)."""

    def __init__(
        self,
        s: _Pairs,
        const: Sequence[str],
        arms: Sequence[str],
        fixed_const: Mapping[str, float],
        gauge: bool = False,
        block_s: float | None = None,
    ) -> None:
        self.s = s
        self.const = list(const)
        self.arms = list(arms)
        self.dim = int(s.pa.shape[1])
        n = len(s.rng)
        self.k = len(self.const) + self.dim * len(self.arms)
        self.gauge = np.zeros(self.k)
        if gauge and self.dim == 3 and self.arms:
            self.gauge[len(self.const) + 2 :: 3] = GAUGE_W / len(self.arms)
        index = {name: i for i, name in enumerate(self.const)}
        ca, cb, held = [-1], [-1], [0.0]  # padding: a model without samples
        for a, b in zip(s.a, s.b, strict=True):
            own = index.get(pair_key(a, b), -1)
            ca.append(own if own >= 0 else index.get(a, -1))
            cb.append(-1 if own >= 0 else index.get(b, -1))
            held.append(
                0.0
                if own >= 0
                else (fixed_const.get(a, 0.0) if a not in index else 0.0)
                + (fixed_const.get(b, 0.0) if b not in index else 0.0)
            )
        self.ci_a, self.ci_b = np.array(ca)[s.key + 1], np.array(cb)[s.key + 1]
        self.held = np.array(held)[s.key + 1]
        self.cluster = s.key
        if block_s is not None and n:
            blocks = np.floor((s.t - s.t.min()) / block_s).astype(int)
            self.cluster = np.unique(s.key * (blocks.max() + 1) + blocks, return_inverse=True)[1]
        la = np.array([self.arms.index(x) if x in self.arms else -1 for x in s.a], dtype=int)
        lb = np.array([self.arms.index(x) if x in self.arms else -1 for x in s.b], dtype=int)
        self.li_a, self.li_b = la[s.key], lb[s.key]
        self.rows = np.arange(n)

    def _arms(self, x: np.ndarray, idx: np.ndarray) -> np.ndarray:
        arms = x[len(self.const) :].reshape(-1, self.dim)
        out = np.zeros((len(idx), self.dim))
        ok = idx >= 0
        out[ok] = arms[idx[ok]]
        return out

    def _geometry(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self.s
        ta = s.pa + _rot(s.ya, self._arms(x, self.li_a))
        tb = s.pb + _rot(s.yb, self._arms(x, self.li_b))
        d = ta - tb
        dist = np.hypot.reduce(d, axis=1)
        return dist, d / np.maximum(dist, 1e-9)[:, None]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        dist, _ = self._geometry(x)
        c = np.append(x[: len(self.const)], 0.0)  # index -1 reads the 0 appended
        return dist + c[self.ci_a] + c[self.ci_b] + self.held - self.s.rng

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        _, u = self._geometry(x)
        s = self.s
        jac = np.zeros((len(s.rng), self.k))
        for idx, sign in ((self.ci_a, 1.0), (self.ci_b, 1.0)):
            ok = idx >= 0
            jac[self.rows[ok], idx[ok]] += sign
        n0 = len(self.const)
        for idx, yaw, sign in ((self.li_a, s.ya, 1.0), (self.li_b, s.yb, -1.0)):
            ok = idx >= 0
            # d|v|/dl = R(yaw)^T u
            c, sn = np.cos(yaw[ok]), np.sin(yaw[ok])
            ux, uy = u[ok, 0], u[ok, 1]
            rows, col = self.rows[ok], n0 + self.dim * idx[ok]
            jac[rows, col] += sign * (c * ux + sn * uy)
            jac[rows, col + 1] += sign * (-sn * ux + c * uy)
            if self.dim == 3:
                jac[rows, col + 2] += sign * u[ok, 2]
        return jac

    def solve(self, x0: np.ndarray, bounds: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        if not self.gauge.any():
            fun, jac = self.residuals, self.jacobian
        else:

            def fun(x: np.ndarray) -> np.ndarray:
                return np.append(self.residuals(x), self.gauge @ x)

            def jac(x: np.ndarray) -> np.ndarray:
                return np.vstack([self.jacobian(x), self.gauge])

        sol = least_squares(
            fun,
            x0,
            jac=jac,
            bounds=bounds,
            loss="huber",
            f_scale=HUBER_M,
            method="trf",
        )
        return np.asarray(sol.x)

    def covariance(self, x: np.ndarray) -> np.ndarray:
        """Cluster-robust (by pair, or pair and time block) covariance of the Huber-weighted fit
        at ``x``."""
        r = self.residuals(x)
        jac = self.jacobian(x)
        w = np.minimum(1.0, HUBER_M / np.maximum(np.abs(r), 1e-12))
        jw = jac * w[:, None]
        bread = np.linalg.pinv(jac.T @ jw + np.outer(self.gauge, self.gauge))
        groups = int(self.cluster.max()) + 1 if r.size else 0
        meat = np.zeros((self.k, self.k))
        for g in range(groups):
            sel = self.cluster == g
            score = jw[sel].T @ r[sel]
            meat += np.outer(score, score)
        factor = groups / (groups - self.k) if groups > self.k else math.nan
        return factor * bread @ meat @ bread

    def rms(self, x: np.ndarray, pairs: np.ndarray | None = None) -> float:
        """RMS over pairs of each pair's mean clipped squared residual (pairs weigh alike)."""
        r2 = np.minimum(self.residuals(x) ** 2, CLIP_M**2)
        groups = np.unique(self.s.key) if pairs is None else pairs
        per = [float(r2[self.s.key == g].mean()) for g in groups if np.any(self.s.key == g)]
        return math.sqrt(sum(per) / len(per)) if per else math.inf


def _node_constants(pair_bias: Mapping[str, float], nodes: Sequence[str]) -> dict[str, float]:
    """Per-node constants ``c`` with ``bias(a, b) ~ c_a + c_b`` (least squares; a weak pull to
    half the median bias keeps a team of too few pairs determined)."""
    nodes = list(nodes)
    rows, ys = [], []
    for key, bias in pair_bias.items():
        a, _, b = key.partition("-")
        if a in nodes and b in nodes:
            row = np.zeros(len(nodes))
            row[nodes.index(a)] = row[nodes.index(b)] = 1.0
            rows.append(row)
            ys.append(bias)
    half = float(np.median(ys)) / 2 if ys else 0.0
    prior = 0.01
    mat = np.vstack([*rows, prior * np.eye(len(nodes))]) if rows else prior * np.eye(len(nodes))
    rhs = np.concatenate([np.array(ys), np.full(len(nodes), prior * half)])
    sol, *_ = np.linalg.lstsq(mat, rhs, rcond=None)
    return dict(zip(nodes, (float(v) for v in sol), strict=True))


def _pair_biases(s: _Pairs) -> tuple[list[str], list[float]]:
    """A constant per pair of ``s`` (3D: a flying team moves and turns, so a pair's own bias
    does not take up a lever arm) and each one's first guess: its median of range - distance."""
    left = s.rng - np.hypot.reduce(s.pa - s.pb, axis=1)
    keys = [pair_key(a, b) for a, b in zip(s.a, s.b, strict=True)]
    return keys, [float(np.median(left[s.key == g])) for g in range(len(keys))]


def find_tags(
    inv: BagInventory,
    poses: Poses,
    mapping: Mapping[str, str],
    pair_bias: Mapping[str, float],
    names: Mapping[str, str] | None = None,
    dimension: int = 2,
) -> tuple[list[TagFit], list[str]]:
    """The extra tags among the nodes ``mapping`` (body -> first node) leaves out, with their
    lever arms, and notes on the nodes that fit no body (``names``: body -> robot, for them).

    ``dimension`` 3 (a flying team): positions and lever arms are 3D, the bodies level (turned by
    their yaw only, as the team's estimators take them), and every tag of a body with several is
    placed from the body's mocap origin, its first tag included (marked :attr:`TagFit.first`): a
    quadrotor's origin is its centre, not a tag. Ranges see only differences of the tags'
    heights, so the mean z of the tags placed is held at 0 (the mocap origins' height)."""
    names = dict(names or {})
    body_of = {node: body for body, node in mapping.items()}
    first = list(body_of)
    consts = _node_constants(pair_bias, first)
    found: dict[str, tuple[str, float, str, float, int]] = {}
    notes: list[str] = []
    needed = MIN_PARTNERS if dimension == 2 else min(MIN_PARTNERS, len(mapping) - 1)
    for node in sorted(set(inv.nodes) - set(first)):
        scored: list[tuple[float, str, int]] = []
        for body in sorted(mapping):
            partners = [n for n in first if body_of[n] != body]
            pairs = [(node, n) for n in partners]
            s = _samples(inv, poses, {**body_of, node: body}, pairs, dimension)
            if len(s.a) < needed:
                continue
            if dimension == 2:
                const = [node]
                left = s.rng - np.hypot.reduce(s.pa - s.pb, axis=1)
                guess = [float(np.median(left)) - float(np.median([consts[b] for b in s.b]))]
            else:
                const, guess = _pair_biases(s)
            model = _Model(s, const, [node], consts)
            m = len(const)
            lo = np.array([*([-5.0] * m), *([-LEVER_MAX_M] * dimension)])
            x0 = np.concatenate([np.clip(guess, -4.9, 4.9), np.zeros(dimension)])
            x = model.solve(x0, (lo, -lo))
            if np.any(np.abs(x[m:]) > LEVER_MAX_M - 0.01):
                continue  # held at the bound: not a tag of this body
            own = inv.ranges.get(pair_key(node, mapping[body]))
            if own is not None and own.shape[0]:
                bias = x[0] + consts[mapping[body]] if dimension == 2 else float(np.median(x[:m]))
                expected = float(np.hypot.reduce(x[m:])) + bias
                if abs(float(np.median(own[:, 1])) - expected) > SAME_BODY_TOL_M:
                    continue  # its range to the body's first tag says it is elsewhere
            scored.append((model.rms(x), body, len(s.a)))
        if not scored:
            notes.append(
                f"{node}: fits no motion-capture body (ranges to fewer than {needed} "
                f"other nodes, a lever arm beyond {LEVER_MAX_M:g} m, or a range to the body's "
                "first tag that says it is elsewhere): left out"
            )
            continue
        scored.sort()
        best_rms, best, partners_n = scored[0]
        runner = scored[1] if len(scored) > 1 else (math.inf, "", 0)
        if best_rms > FIT_MAX_M:
            notes.append(
                f"{node}: moves with no motion-capture body (best {names.get(best, best)} leaves {best_rms:.3f} m): left out"
            )
            continue
        found[node] = (best, best_rms, runner[1], runner[0], partners_n)
    if not found:
        return [], notes
    return _joint_fit(inv, poses, mapping, body_of, consts, found, dimension), notes


def _joint_fit(
    inv: BagInventory,
    poses: Poses,
    mapping: Mapping[str, str],
    body_of: Mapping[str, str],
    consts: Mapping[str, float],
    found: Mapping[str, tuple[str, float, str, float, int]],
    dimension: int,
) -> list[TagFit]:
    """Every node's constant and every extra tag's lever arm at once (in 3D the first tags' of
    their bodies too), over every pair of nodes on two different bodies."""
    where = {**body_of, **{n: f[0] for n, f in found.items()}}
    nodes = sorted(where)
    pairs = [(a, b) for i, a in enumerate(nodes) for b in nodes[i + 1 :] if where[a] != where[b]]
    s = _samples(inv, poses, where, pairs, dimension)
    extra = sorted(found)
    firsts = sorted({mapping[f[0]] for f in found.values()}) if dimension == 3 else []
    placed = sorted([*extra, *firsts])
    if dimension == 2:
        const = nodes
        guess = [consts.get(n, float(np.median(list(consts.values())))) for n in nodes]
    else:
        const, guess = _pair_biases(s)
    block = BLOCK_S if dimension == 3 else None
    model = _Model(s, const, placed, {}, gauge=True, block_s=block)
    x0 = np.concatenate([guess, np.zeros(dimension * len(placed))])
    big = np.full(len(const), 5.0)
    arm = np.full(dimension * len(placed), LEVER_MAX_M)
    x = model.solve(x0, (np.concatenate([-big, -arm]), np.concatenate([big, arm])))
    cov = model.covariance(x)
    out = []
    n0 = len(const)
    for i, node in enumerate(placed):
        j = n0 + dimension * i
        own = np.array([g for g in range(len(s.a)) if node in (s.a[g], s.b[g])])
        se = np.sqrt(np.clip(np.diag(cov)[j : j + dimension], 0.0, None))
        if node in found:
            body, _rms, runner, runner_rms, partners = found[node]
        else:
            body, runner, runner_rms, partners = where[node], "", math.inf, len(own)
        out.append(
            TagFit(
                node,
                body,
                tuple(float(v) for v in x[j : j + dimension]),
                tuple(float(v) for v in se),
                model.rms(x, own),
                partners,
                runner,
                runner_rms,
                first=node not in found,
            )
        )
    return out
