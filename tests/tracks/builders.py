"""Track shapes with known geometry, built in code for the tests (no library files needed)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from tracks import Track
from tracks.geometry import FloatArray


def turtle(
    pieces: Sequence[tuple[float, float]],
    *,
    start: tuple[float, float] = (0.0, 0.0),
    heading: float = 0.0,
    spacing: float = 0.05,
) -> FloatArray:
    """Points (N, 2) m of a path of straights and arcs, the end point left out.

    Args:
        pieces: (length m, curvature 1/m) for each piece; curvature > 0 turns left.
        start: first point, m.
        heading: initial heading, rad.
        spacing: distance between points along the path, m (each piece is split evenly).
    """
    pts = []
    x, y, h = float(start[0]), float(start[1]), float(heading)
    for length, kappa in pieces:
        n = max(1, round(length / spacing))
        u = np.arange(n) * (length / n)
        if kappa == 0.0:
            px, py = x + u * np.cos(h), y + u * np.sin(h)
        else:
            r = 1.0 / kappa
            px = x + r * (np.sin(h + kappa * u) - np.sin(h))
            py = y - r * (np.cos(h + kappa * u) - np.cos(h))
        pts.append(np.column_stack([px, py]))
        if kappa == 0.0:
            x, y = x + length * np.cos(h), y + length * np.sin(h)
        else:
            x += (np.sin(h + kappa * length) - np.sin(h)) / kappa
            y -= (np.cos(h + kappa * length) - np.cos(h)) / kappa
            h += kappa * length
    return np.vstack(pts)


def stadium_points(straight: float, radius: float, spacing: float = 0.05) -> FloatArray:
    """Anticlockwise stadium centre line starting at (-straight/2, -radius) heading +x."""
    pieces = [(straight, 0.0), (np.pi * radius, 1 / radius)] * 2
    return turtle(pieces, start=(-straight / 2, -radius), spacing=spacing)


def stadium(
    straight: float = 30.0,
    radius: float = 10.0,
    width_left: float = 2.0,
    width_right: float = 1.5,
    *,
    name: str = "stadium",
) -> Track:
    """A smoothed anticlockwise stadium track with asymmetric constant half-widths."""
    return Track(stadium_points(straight, radius, 0.5), width_left, width_right, name=name)


def wavy_stadium(name: str = "wavy") -> Track:
    """A stadium whose half-widths vary along the lap (left and right differently)."""
    pts = stadium_points(30.0, 10.0, 0.5)
    phase = np.linspace(0.0, 2 * np.pi, len(pts), endpoint=False)
    return Track(pts, 1.6 + 0.4 * np.sin(phase), 1.2 + 0.3 * np.cos(2 * phase), name=name)


def circle_points(radius: float, n: int = 64) -> FloatArray:
    """Anticlockwise circle of ``n`` points about the origin."""
    th = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return radius * np.column_stack([np.cos(th), np.sin(th)])


def bone_points(gap: float, spacing: float = 0.2) -> FloatArray:
    """A dog-bone circuit: two parallel straights ``gap`` m apart joined by round lobes.

    The straights (x from -10 to 10 m, at y = ∓gap/2) are far apart along the lap but only
    ``gap`` m apart in the plane; each lobe flares out with 4 m radius bends.
    """
    flare, lobe = 4.0, gap + 4.0  # lobe radius that closes the shape symmetrically
    end = [(flare * np.pi / 3, -1 / flare), (lobe * 5 * np.pi / 3, 1 / lobe)]
    end.append((flare * np.pi / 3, -1 / flare))
    pieces = [(20.0, 0.0), *end, (20.0, 0.0), *end]
    return turtle(pieces, start=(-10.0, -gap / 2), spacing=spacing)


def hairpin_points(radius: float = 0.6, spacing: float = 0.2) -> FloatArray:
    """Anticlockwise circuit (about 40 m) with one ``radius`` m hairpin at s ≈ 12 m.

    A 12 m straight, the 180° hairpin, an S-bend (two 60° arcs of 2 m radius) that opens
    the return straight 3.2 m away, the straight back and a 1.6 m-radius 180° turn home.
    """
    s_bend = [(2 * np.pi / 3, -0.5), (2 * np.pi / 3, 0.5)]
    back = 12.0 - 2 * 2.0 * np.sin(np.pi / 3)  # the S-bend moves 2 · 2 sin 60° m back in x
    pieces = [(12.0, 0.0), (np.pi * radius, 1 / radius), *s_bend, (back, 0.0)]
    pieces.append((np.pi * 1.6, 1 / 1.6))
    return turtle(pieces, spacing=spacing)


def chicane_points(
    radius: float = 0.62, angle: float = np.pi / 3, spacing: float = 0.15
) -> FloatArray:
    """Anticlockwise DeepRacer-sized circuit (about 27 m) with a chicane on both straights.

    Shaped like the AWS DeepRacer "Carrera" track's S-bend (0.62-0.70 m radii between 2.5-3 m
    straights): each straight is 3 m, a chicane (right ``angle``, left ``2 angle``, right
    ``angle``, all at ``radius`` m) and 3 m more; 1.6 m-radius 180° turns join them. The two
    chicanes shift their straights by the same amount in opposite directions, so it closes.
    """
    chicane = [(radius * angle, -1 / radius), (2 * radius * angle, 1 / radius)]
    chicane.append((radius * angle, -1 / radius))
    turn = (np.pi * 1.6, 1 / 1.6)
    pieces = [(3.0, 0.0), *chicane, (3.0, 0.0), turn, (3.0, 0.0), *chicane, (3.0, 0.0), turn]
    return turtle(pieces, spacing=spacing)
