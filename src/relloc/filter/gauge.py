"""The formation's gauge: where a shape is put when its orientation is not observed, and the
rotation and handedness that best map one formation onto another.

:func:`gauge` puts formations in the declared gauge (robot 0 on +x, robot 1 on the +y side);
:func:`procrustes_fit` is the 2D Procrustes fit of many formations to one template at once,
what the posterior summary (:mod:`relloc.filter.summary`) finds orientation modes with.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def gauge(rel: FloatArray) -> FloatArray:
    """Formations ``(M, K, 2)`` in the declared gauge: robot 0 on the +x axis, robot 1 (if any)
    on the +y side. Deterministic; a formation with robot 0 at the reference keeps its angle."""
    rel = np.asarray(rel, float)
    return gauge_planes(rel[:, :, 0].T, rel[:, :, 1].T)


def gauge_planes(x: FloatArray, y: FloatArray) -> FloatArray:
    """:func:`gauge` of the formations whose coordinates are the planes ``x`` and ``y``
    ``(K, M)`` (robot ``k``'s of every formation in row ``k``), as ``(M, K, 2)``: turned by
    minus robot 0's angle, then the mirrored ones' y negated (a product by -1 or 1, exact)."""
    k, m = x.shape
    ang = np.arctan2(y[0], x[0])
    theta = -ang
    c, s = np.cos(theta), np.sin(theta)
    gx = c * x
    gx -= s * y
    gy = s * x
    gy += c * y
    if k > 1:
        gy *= np.where(gy[1] < 0.0, -1.0, 1.0)
    out = np.empty((m, k, 2))
    out[:, :, 0], out[:, :, 1] = gx.T, gy.T
    return out


def procrustes_fit(
    planes: FloatArray, template: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rotation and handedness of each formation (coordinate planes ``planes`` ``(2K, M)``: the
    ``x`` rows, then the ``y`` rows) relative to ``template`` ``(K, 2)``: formation ``m`` is best
    explained as ``template`` mirrored (if the handedness is -1: ``y -> -y``) and then turned
    about the reference by the angle whose cosine and sine are returned, with the handedness:
    ``(cos, sin, hand)``."""
    k, m = template.shape[0], planes.shape[1]
    # H = sum_k t_k p_k^T per hypothesis, one einsum: h[a, b] = sum_k t_k[a] p_k[b].
    h = np.einsum("ak,bkm->abm", template.T, planes[: 2 * k].reshape(2, k, m))
    h00, h01, h10, h11 = h[0, 0], h[0, 1], h[1, 0], h[1, 1]
    hand = np.where(h00 * h11 - h01 * h10 < 0.0, -1.0, 1.0) if k > 1 else np.ones(m)
    # proper: p = R(a) t -> (cos, sin) ~ (h00 + h11, h01 - h10); mirrored: p = R(a) F t with
    # F = diag(1, -1) -> (h00 - h11, h01 + h10).
    c = hand * h11
    c += h00
    s = hand * h10
    np.subtract(h01, s, out=s)
    norm = c * c
    norm += s * s
    np.sqrt(norm, out=norm)
    norm[norm == 0.0] = 1.0
    c /= norm
    s /= norm
    return c, s, hand
