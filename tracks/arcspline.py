"""A shape-preserving closed curve through points: a G1 spline of circular arcs (biarcs).

A C2 curve (the periodic cubic spline :class:`tracks.geometry.Track` normally fits) cannot
follow data whose curvature jumps, as a straight running into a bend does: it overshoots there
and bends tighter than the points themselves (a 0.6 m hairpin sampled every 0.2-0.3 m comes
out at 0.47-0.51 m). Circular arcs can: between each two points this fits a biarc (two arcs
meeting with a common tangent), and chooses the tangent at every point to make the tightest
arc on either side as wide as it can be. Curvature is then piecewise constant (it jumps where
the data's does) and stays close to the points' own three-point radius.

>>> import numpy as np
>>> th = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
>>> ring = 5.0 * np.column_stack([np.cos(th), np.sin(th)])
>>> centre, _, _, kappa = arc_spline_curve(ring, np.ones((24, 2)), 0.1)
>>> bool(np.allclose(np.linalg.norm(centre, axis=1), 5.0)), bool(np.allclose(kappa, 0.2))
(True, True)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

SWEEPS = 16  # tangent-optimisation sweeps (the search step shrinks by 0.7 each)
GRID = 25  # tangent angles tried per point and sweep
POWER = 16  # exponent of the curvature cost: high enough to act as the maximum


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.asarray(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], dtype=np.float64)


def _unit(angle: FloatArray) -> FloatArray:
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def biarcs(
    p0: FloatArray, th0: FloatArray, p1: FloatArray, th1: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The equal-leg biarc from ``p0`` (heading ``th0``) to ``p1`` (heading ``th1``).

    Arrays broadcast over leading axes; points are (..., 2) m, headings (...) rad.

    Returns:
        joint (..., 2) m where the arcs meet; signed curvatures ``k1``, ``k2`` (...) 1/m of the
        first and second arc; ``ok`` (...) 1.0 where the biarc exists (else 0.0).
    """
    t1, t2 = _unit(th0), _unit(th1)
    v = p1 - p0
    vt = np.sum(v * (t1 + t2), axis=-1)
    vv = np.sum(v * v, axis=-1)
    c = 1.0 - np.sum(t1 * t2, axis=-1)
    parallel = c < 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(
            parallel,
            vv / (4.0 * np.sum(v * t2, axis=-1)),
            (-vt + np.sqrt(np.maximum(vt**2 + 2.0 * c * vv, 0.0)))
            / (2.0 * np.where(parallel, 1, c)),
        )
        joint = 0.5 * ((p0 + d[..., None] * t1) + (p1 - d[..., None] * t2))
        a = joint - p0
        b = p1 - joint
        k1 = 2.0 * _cross(t1, a) / np.sum(a * a, axis=-1)
        k2 = 2.0 * _cross(b, t2) / np.sum(b * b, axis=-1)
    ok = np.isfinite(d) & (d > 0) & np.isfinite(k1) & np.isfinite(k2)
    return joint, np.where(ok, k1, 0.0), np.where(ok, k2, 0.0), ok.astype(np.float64)


def _segment_cost(
    p0: FloatArray, th0: FloatArray, p1: FloatArray, th1: FloatArray, scale: float
) -> FloatArray:
    """``∫ (κ · scale)^POWER ds`` over each biarc (m), inf where none exists: a smooth
    stand-in for its tightest curvature that still ranks every other arc."""
    joint, k1, k2, ok = biarcs(p0, th0, p1, th1)
    len1 = np.linalg.norm(joint - p0, axis=-1)
    len2 = np.linalg.norm(p1 - joint, axis=-1)
    with np.errstate(over="ignore"):
        cost = np.abs(k1 * scale) ** POWER * len1 + np.abs(k2 * scale) ** POWER * len2
    return np.where(ok > 0, cost, np.inf)


def fit_tangents(points: FloatArray) -> FloatArray:
    """Headings (K,) rad at closed points (K, 2) that keep the biarcs between them wide.

    Starts from the tangents of the three-point circles and improves each point's heading
    in turn (even points, then odd ones, so neighbours stay fixed while a point moves),
    minimising ``∫ κ^16 ds`` of its two biarcs: nearly their tightest curvature, but smooth
    enough that coordinate descent does not stall on a maximum set elsewhere.
    """
    k = len(points)
    nxt = np.roll(points, -1, axis=0)
    chord = nxt - points
    length = np.linalg.norm(chord, axis=1)
    a, b, c = np.roll(points, 1, axis=0), points, nxt
    sides = np.linalg.norm(b - a, axis=1) * length * np.linalg.norm(a - c, axis=1)
    kappa = 2.0 * _cross(b - a, c - a) / np.maximum(sides, 1e-300)
    theta = np.arctan2(chord[:, 1], chord[:, 0]) - np.arcsin(np.clip(kappa * length / 2, -1, 1))
    scale = 1.0 / max(float(np.abs(kappa).max()), 1e-9)  # the data's tightest bend costs 1
    offsets = np.linspace(-1.0, 1.0, GRID)
    groups = [np.arange(0, k - (k % 2), 2), np.arange(1, k, 2)]
    if k % 2:
        groups.append(np.array([k - 1]))
    for sweep in range(SWEEPS):
        step = 0.3 * 0.7**sweep
        for idx in groups:
            cand = theta[idx, None] + step * offsets[None, :]  # (M, G)
            prev, after = (idx - 1) % k, (idx + 1) % k
            here = points[idx][:, None, :]
            before = _segment_cost(
                points[prev][:, None, :], theta[prev][:, None], here, cand, scale
            )
            beyond = _segment_cost(
                here, cand, points[after][:, None, :], theta[after][:, None], scale
            )
            cost = before + beyond
            theta[idx] = cand[np.arange(len(idx)), np.argmin(cost, axis=1)]
    return theta


def _arc_offset(kappa: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Local (x along the start heading, y to its left) m after ``u`` m on an arc of
    curvature ``kappa`` (stable as ``kappa`` -> 0)."""
    a = kappa * u
    x = u * np.sinc(a / np.pi)
    y = u * a * 0.5 * np.sinc(a / (2 * np.pi)) ** 2
    return x, y


def arc_spline_curve(
    points: FloatArray, widths: FloatArray, spacing: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Biarc spline through closed points, resampled at even arc length.

    Args:
        points: (K, 2) control points in order, m; the curve closes from the last to the first.
        widths: (K, 2) left/right half-widths at the control points, m (linear along each
            span).
        spacing: target distance between resampled points, m.

    Returns:
        centre (N, 2) m, widths (N, 2) m, unit tangents (N, 2), curvature (N,) 1/m, as
        :func:`tracks.geometry.smooth_closed_curve` returns them.
    """
    k = len(points)
    theta = fit_tangents(points)
    nxt = np.roll(points, -1, axis=0)
    joint, k1, k2, _ = biarcs(points, theta, nxt, np.roll(theta, -1))
    # Two arcs per span: start point, start heading, curvature, length.
    chord1 = np.linalg.norm(joint - points, axis=1)
    chord2 = np.linalg.norm(nxt - joint, axis=1)

    def arc_len(kappa: FloatArray, chord: FloatArray) -> FloatArray:
        half = np.clip(np.abs(kappa) * chord / 2, 0.0, 1.0)
        return np.where(
            half > 1e-12, 2 * np.arcsin(half) / np.maximum(np.abs(kappa), 1e-300), chord
        )

    len1, len2 = arc_len(k1, chord1), arc_len(k2, chord2)
    start = np.empty((2 * k, 2))
    start[0::2], start[1::2] = points, joint
    head = np.empty(2 * k)
    head[0::2], head[1::2] = theta, theta + k1 * len1
    curv = np.empty(2 * k)
    curv[0::2], curv[1::2] = k1, k2
    lens = np.empty(2 * k)
    lens[0::2], lens[1::2] = len1, len2
    ends = np.cumsum(lens)
    total = float(ends[-1])
    n = max(8, round(total / spacing))
    s = np.arange(n) * (total / n)
    j = np.minimum(np.searchsorted(ends, s, side="right"), 2 * k - 1)
    u = s - (ends[j] - lens[j])
    x, y = _arc_offset(curv[j], u)
    c, sn = np.cos(head[j]), np.sin(head[j])
    centre = start[j] + np.stack([c * x - sn * y, sn * x + c * y], axis=1)
    heading = head[j] + curv[j] * u
    span = j // 2
    frac = (s - np.where(j % 2, ends[j] - lens[j] - len1[span], ends[j] - lens[j])) / (
        len1[span] + len2[span]
    )
    nxt_w = np.roll(widths, -1, axis=0)
    w = widths[span] + frac[:, None] * (nxt_w[span] - widths[span])
    return centre, w, _unit(heading), curv[j]
