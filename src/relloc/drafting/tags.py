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

What the data separate. A lever arm moves a tag's ranges by its projection on the directions to
the partners, ``-u_k . R l``; the node constant moves them all alike. With robots standing still
and partners in one half-plane (a corner robot), a lever arm along the partners' mean direction
and the constant trade off, and only the spread of the directions separates them: the standard
errors say how well, and are large along that direction. Partners all round, or the body turning
during the recording, separate them well. A free bias per node *pair* (rather than per node) would
absorb any lever arm of a static team entirely: it is not used here. The first tag's own lever arm
trades off with the body's mocap origin and is not estimated.

Standard errors are cluster-robust by node pair (a pair's samples share its error: UWB multipath
is a property of the geometry, not noise per sample), with the small-sample factor ``G / (G - k)``
for ``G`` pairs and ``k`` unknowns.

Which body: each candidate body is fitted with its own lever arm and node constant (the other
nodes' constants held from their pairs), the lever arm held to :data:`LEVER_MAX_M`; the body whose
fit leaves the smallest clipped residual wins, if that is below :data:`FIT_MAX_M`. A wrong body
keeps the range to the right body's first tag (a few decimetres read against metres of mocap
distance), so it is seldom close.
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
from relloc.sources.rosbag import _open_reader
from relloc.sources.tracks import interpolate_track

__all__ = ["LEVER_MAX_M", "TagFit", "find_tags", "mocap_poses"]

LEVER_MAX_M = 1.0
"""A second tag sits at most this far from its body's origin, in x and in y (m)."""
FIT_MAX_M = 0.2
"""The most RMS (m, residuals clipped to :data:`CLIP_M`) a body's fit may leave for the node to
be called a tag on it."""
CLIP_M = 1.0
HUBER_M = 0.1
"""Residuals beyond this (m) weigh linearly, not quadratically (multipath pairs)."""
SAMPLES_PER_PAIR = 200
MIN_PARTNERS = 3
"""A tag needs ranges to this many nodes on other bodies (lever arm x, y and its constant)."""
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
    lever_arm: tuple[float, float]
    """In the body frame (x forward, y left), m."""
    stderr: tuple[float, float]
    """Standard errors of ``lever_arm`` (m); ``nan`` without redundancy."""
    rms: float
    """RMS of the tag's residuals in the final fit (m, clipped)."""
    partners: int
    runner_up: str
    """The next best body (empty: none fitted)."""
    runner_up_rms: float


Poses = Mapping[str, np.ndarray]
"""Body -> ``(n, 4)`` rows ``t, x, y, yaw`` sorted by time."""


def mocap_poses(bag: Path, inv: BagInventory, bodies: Sequence[str]) -> dict[str, np.ndarray]:
    """Each body's mocap poses with yaw, timed as :func:`inspect_bag` times its tracks (header
    stamp, else receive time), so they line up with :attr:`BagInventory.ranges`."""
    topics = {inv.mocap_pattern.replace("{body}", b): b for b in bodies}
    rows: dict[str, list[tuple[float, float, float, float]]] = {b: [] for b in bodies}
    with _open_reader(Path(bag)) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, recv_ns, raw in reader.messages(conns) if conns else ():
            try:
                msg = decode(raw, conn.msgtype)
            except MessageDecodeError:
                continue
            stamp = stamp_to_sec(msg.header.stamp)
            t = stamp if stamp != 0.0 else recv_ns * 1e-9
            gt = pose_to_ground_truth(msg, "", t=t)
            rows[topics[conn.topic]].append((t, gt.position[0], gt.position[1], gt.yaw))
    out = {}
    for body, v in rows.items():
        arr = np.array(v, dtype=float).reshape(-1, 4)
        out[body] = arr[np.argsort(arr[:, 0], kind="stable")]
    return out


def _pose_at(track: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(xy (n, 2), yaw (n,), valid)`` of a pose track at times ``t``."""
    x, y, ok = interpolate_track(track[:, 0], track[:, 1], track[:, 2], t, max_gap=MAX_GAP_S)
    c, s, _ = interpolate_track(
        track[:, 0], np.cos(track[:, 3]), np.sin(track[:, 3]), t, max_gap=MAX_GAP_S
    )
    return np.stack([x, y], axis=-1), np.arctan2(s, c), ok


@dataclass
class _Pairs:
    """Range samples of the node pairs on two different bodies, with both bodies' poses."""

    a: list[str]
    b: list[str]
    key: np.ndarray
    """Pair index of each sample."""
    rng: np.ndarray
    pa: np.ndarray
    pb: np.ndarray
    ya: np.ndarray
    yb: np.ndarray


def _samples(
    inv: BagInventory, poses: Poses, body_of: Mapping[str, str], pairs: Sequence[tuple[str, str]]
) -> _Pairs:
    a_: list[str] = []
    b_: list[str] = []
    keys: list[np.ndarray] = []
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
        xa, yawa, oka = _pose_at(poses[body_of[a]], r[:, 0])
        xb, yawb, okb = _pose_at(poses[body_of[b]], r[:, 0])
        ok = oka & okb & np.isfinite(r[:, 1])
        if not ok.any():
            continue
        keys.append(np.full(int(ok.sum()), len(a_)))
        a_.append(a)
        b_.append(b)
        rng.append(r[ok, 1])
        pa.append(xa[ok])
        pb.append(xb[ok])
        ya.append(yawa[ok])
        yb.append(yawb[ok])
    if not a_:
        empty = np.zeros(0)
        return _Pairs(
            [], [], empty.astype(int), empty, empty.reshape(0, 2), empty.reshape(0, 2), empty, empty
        )
    return _Pairs(
        a_,
        b_,
        np.concatenate(keys),
        np.concatenate(rng),
        np.concatenate(pa),
        np.concatenate(pb),
        np.concatenate(ya),
        np.concatenate(yb),
    )


def _rot(yaw: np.ndarray, v: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]], axis=-1)


class _Model:
    """Residuals and Jacobian of the range model over some pairs: unknowns a constant per node in
    ``const`` and a lever arm per node in ``arms`` (any other node's lever arm is 0 and its
    constant held at ``fixed_const``)."""

    def __init__(
        self,
        s: _Pairs,
        const: Sequence[str],
        arms: Sequence[str],
        fixed_const: Mapping[str, float],
    ) -> None:
        self.s = s
        self.const = list(const)
        self.arms = list(arms)
        n = len(s.rng)
        self.k = len(self.const) + 2 * len(self.arms)
        ca = np.array([self.const.index(x) if x in self.const else -1 for x in s.a], dtype=int)
        cb = np.array([self.const.index(x) if x in self.const else -1 for x in s.b], dtype=int)
        self.ci_a, self.ci_b = ca[s.key], cb[s.key]
        held_a = np.array([fixed_const.get(x, 0.0) for x in s.a] or [0.0])[s.key]
        held_b = np.array([fixed_const.get(x, 0.0) for x in s.b] or [0.0])[s.key]
        self.held = np.where(self.ci_a < 0, held_a, 0.0) + np.where(self.ci_b < 0, held_b, 0.0)
        la = np.array([self.arms.index(x) if x in self.arms else -1 for x in s.a], dtype=int)
        lb = np.array([self.arms.index(x) if x in self.arms else -1 for x in s.b], dtype=int)
        self.li_a, self.li_b = la[s.key], lb[s.key]
        self.rows = np.arange(n)

    def _arms(self, x: np.ndarray, idx: np.ndarray) -> np.ndarray:
        arms = x[len(self.const) :].reshape(-1, 2)
        out = np.zeros((len(idx), 2))
        ok = idx >= 0
        out[ok] = arms[idx[ok]]
        return out

    def _geometry(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self.s
        ta = s.pa + _rot(s.ya, self._arms(x, self.li_a))
        tb = s.pb + _rot(s.yb, self._arms(x, self.li_b))
        d = ta - tb
        dist = np.hypot(d[:, 0], d[:, 1])
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
            rows = self.rows[ok]
            jac[rows, n0 + 2 * idx[ok]] += sign * (c * ux + sn * uy)
            jac[rows, n0 + 2 * idx[ok] + 1] += sign * (-sn * ux + c * uy)
        return jac

    def solve(self, x0: np.ndarray, bounds: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        sol = least_squares(
            self.residuals,
            x0,
            jac=self.jacobian,
            bounds=bounds,
            loss="huber",
            f_scale=HUBER_M,
            method="trf",
        )
        return np.asarray(sol.x)

    def covariance(self, x: np.ndarray) -> np.ndarray:
        """Cluster-robust (by pair) covariance of the Huber-weighted fit at ``x``."""
        r = self.residuals(x)
        jac = self.jacobian(x)
        w = np.minimum(1.0, HUBER_M / np.maximum(np.abs(r), 1e-12))
        jw = jac * w[:, None]
        bread = np.linalg.pinv(jac.T @ jw)
        groups = int(self.s.key.max()) + 1 if r.size else 0
        meat = np.zeros((self.k, self.k))
        for g in range(groups):
            sel = self.s.key == g
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


def find_tags(
    inv: BagInventory,
    poses: Poses,
    mapping: Mapping[str, str],
    pair_bias: Mapping[str, float],
    names: Mapping[str, str] | None = None,
) -> tuple[list[TagFit], list[str]]:
    """The extra tags among the nodes ``mapping`` (body -> first node) leaves out, with their
    lever arms, and notes on the nodes that fit no body (``names``: body -> robot, for them)."""
    names = dict(names or {})
    body_of = {node: body for body, node in mapping.items()}
    first = list(body_of)
    consts = _node_constants(pair_bias, first)
    found: dict[str, tuple[str, float, str, float, int]] = {}
    notes: list[str] = []
    lo = np.array([-5.0, -LEVER_MAX_M, -LEVER_MAX_M])
    hi = np.array([5.0, LEVER_MAX_M, LEVER_MAX_M])
    for node in sorted(set(inv.nodes) - set(first)):
        scored: list[tuple[float, str, int]] = []
        for body in sorted(mapping):
            partners = [n for n in first if body_of[n] != body]
            s = _samples(inv, poses, {**body_of, node: body}, [(node, n) for n in partners])
            if len(s.a) < MIN_PARTNERS:
                continue
            model = _Model(s, [node], [node], consts)
            guess = float(np.median(s.rng - np.hypot(*(s.pa - s.pb).T))) - float(
                np.median([consts[b] for b in s.b])
            )
            x = model.solve(np.array([min(max(guess, -4.9), 4.9), 0.0, 0.0]), (lo, hi))
            if np.any(np.abs(x[1:]) > LEVER_MAX_M - 0.01):
                continue  # held at the bound: not a tag of this body
            own = inv.ranges.get(pair_key(node, mapping[body]))
            if own is not None and own.shape[0]:
                expected = math.hypot(x[1], x[2]) + x[0] + consts[mapping[body]]
                if abs(float(np.median(own[:, 1])) - expected) > SAME_BODY_TOL_M:
                    continue  # its range to the body's first tag says it is elsewhere
            scored.append((model.rms(x), body, len(s.a)))
        if not scored:
            notes.append(
                f"{node}: fits no motion-capture body (ranges to fewer than {MIN_PARTNERS} "
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
    return _joint_fit(inv, poses, mapping, body_of, consts, found), notes


def _joint_fit(
    inv: BagInventory,
    poses: Poses,
    mapping: Mapping[str, str],
    body_of: Mapping[str, str],
    consts: Mapping[str, float],
    found: Mapping[str, tuple[str, float, str, float, int]],
) -> list[TagFit]:
    """Every node's constant and every extra tag's lever arm at once, over every pair of nodes
    on two different bodies."""
    where = {**body_of, **{n: f[0] for n, f in found.items()}}
    nodes = sorted(where)
    pairs = [(a, b) for i, a in enumerate(nodes) for b in nodes[i + 1 :] if where[a] != where[b]]
    s = _samples(inv, poses, where, pairs)
    extra = sorted(found)
    model = _Model(s, nodes, extra, {})
    x0 = np.concatenate(
        [
            [consts.get(n, float(np.median(list(consts.values())))) for n in nodes],
            np.zeros(2 * len(extra)),
        ]
    )
    big = np.full(len(nodes), 5.0)
    arm = np.full(2 * len(extra), LEVER_MAX_M)
    x = model.solve(x0, (np.concatenate([-big, -arm]), np.concatenate([big, arm])))
    cov = model.covariance(x)
    out = []
    n0 = len(nodes)
    for i, node in enumerate(extra):
        j = n0 + 2 * i
        own = np.array([g for g in range(len(s.a)) if node in (s.a[g], s.b[g])])
        se = np.sqrt(np.clip(np.diag(cov)[j : j + 2], 0.0, None))
        body, _rms, runner, runner_rms, partners = found[node]
        out.append(
            TagFit(
                node,
                body,
                (float(x[j]), float(x[j + 1])),
                (float(se[0]), float(se[1])),
                model.rms(x, own),
                partners,
                runner,
                runner_rms,
            )
        )
    return out
