"""Server-rendered charts: small inline SVG documents, no JavaScript, no plotting library.

Two charts: a submission's rating history (μ with its ±3σ band and the ordinal μ − 3σ the
leaderboard sorts by) and a race's lap times (one line per car). Each returns an ``<svg>``
string that the templates insert as it is; every piece of text in it is escaped here.

>>> svg = rating_history_svg([(25.0, 8.33), (27.1, 7.2), (28.0, 6.1)])
>>> svg.startswith("<svg") and svg.count("<polyline") == 2
True
>>> "Ada &amp; co" in lap_time_svg([("Ada & co", [12.5, 11.9])])
True
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from html import escape

from arena.colours import car_colour

WIDTH = 640  # px, the SVG viewBox; the CSS scales it to the column
HEIGHT = 240  # px
MARGIN_LEFT = 48  # px: room for the y tick labels
MARGIN_RIGHT = 12
MARGIN_TOP = 22  # px: room for the y axis label above the top tick
MARGIN_BOTTOM = 30  # px: room for the x tick labels
N_TICKS = 5  # about this many ticks per axis
MU_COLOUR = "#1d78d6"
ORDINAL_COLOUR = "#2b2b2b"
BAND_COLOUR = "#1d78d6"


def car_hex(i: int) -> str:
    """CSS colour ``#rrggbb`` of car ``i`` (as in the 3D replay).

    >>> car_hex(0)
    '#e63946'
    """
    r, g, b = car_colour(i)
    return f"#{r:02x}{g:02x}{b:02x}"


def nice_ticks(lo: float, hi: float, n: int = N_TICKS) -> list[float]:
    """About ``n`` round tick values (steps of 1, 2 or 5 × 10^k) covering ``[lo, hi]``.

    >>> nice_ticks(0.0, 10.0)
    [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
    >>> nice_ticks(3.0, 3.0)
    [2.0, 2.5, 3.0, 3.5, 4.0]
    """
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi - lo < 1e-9:
        lo, hi = lo - 1.0, hi + 1.0
    raw = (hi - lo) / max(n, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 5.0, 10.0) if m * mag >= raw)
    first = math.floor(lo / step) * step
    ticks = []
    k = 0
    while first + k * step <= hi + step * 1e-6:
        ticks.append(round(first + k * step, 10))
        k += 1
    if ticks[-1] < hi - 1e-9:
        ticks.append(round(first + k * step, 10))
    return ticks


class _Frame:
    """Maps data coordinates to SVG pixels inside the plot area."""

    def __init__(self, x_lo: float, x_hi: float, y_lo: float, y_hi: float) -> None:
        self.x_lo, self.x_hi = x_lo, (x_hi if x_hi > x_lo else x_lo + 1.0)
        self.y_lo, self.y_hi = y_lo, (y_hi if y_hi > y_lo else y_lo + 1.0)

    def x(self, value: float) -> float:
        """Pixel column of data ``value``."""
        span = WIDTH - MARGIN_LEFT - MARGIN_RIGHT
        return MARGIN_LEFT + (value - self.x_lo) / (self.x_hi - self.x_lo) * span

    def y(self, value: float) -> float:
        """Pixel row of data ``value`` (up is larger)."""
        span = HEIGHT - MARGIN_TOP - MARGIN_BOTTOM
        return HEIGHT - MARGIN_BOTTOM - (value - self.y_lo) / (self.y_hi - self.y_lo) * span

    def points(self, xs: Sequence[float], ys: Sequence[float]) -> str:
        """The ``points`` attribute of a polyline through (xs, ys)."""
        return " ".join(f"{self.x(a):.1f},{self.y(b):.1f}" for a, b in zip(xs, ys, strict=True))


def _axes(
    frame: _Frame, x_ticks: Sequence[float], y_ticks: Sequence[float], x_label: str, y_label: str
) -> str:
    """Grid lines, tick labels and the axis labels (y at the top left)."""
    # The y label sits above the plot, right of the tick labels: clear of the top tick.
    parts = [
        f'<text class="axis-label" x="{MARGIN_LEFT}" y="{MARGIN_TOP - 9}">{escape(y_label)}</text>'
    ]
    for v in y_ticks:
        y = frame.y(v)
        parts.append(
            f'<line class="grid" x1="{MARGIN_LEFT}" x2="{WIDTH - MARGIN_RIGHT}" '
            f'y1="{y:.1f}" y2="{y:.1f}"/>'
            f'<text class="tick" x="{MARGIN_LEFT - 6}" y="{y + 4:.1f}" '
            f'text-anchor="end">{v:g}</text>'
        )
    for v in x_ticks:
        x = frame.x(v)
        parts.append(
            f'<text class="tick" x="{x:.1f}" y="{HEIGHT - MARGIN_BOTTOM + 14}" '
            f'text-anchor="middle">{v:g}</text>'
        )
    parts.append(
        f'<text class="axis-label" x="{WIDTH - MARGIN_RIGHT}" y="{HEIGHT - 3}" '
        f'text-anchor="end">{escape(x_label)}</text>'
    )
    return "".join(parts)


def _svg(title: str, body: str) -> str:
    """Wrap chart elements in an accessible ``<svg>`` element."""
    return (
        f'<svg class="chart" viewBox="0 0 {WIDTH} {HEIGHT}" role="img" '
        f'xmlns="http://www.w3.org/2000/svg"><title>{escape(title)}</title>{body}</svg>'
    )


def _empty(title: str, message: str) -> str:
    """A chart with only a centred message (no data yet)."""
    return _svg(
        title,
        f'<text class="empty" x="{WIDTH / 2}" y="{HEIGHT / 2}" text-anchor="middle">'
        f"{escape(message)}</text>",
    )


def rating_history_svg(history: Sequence[tuple[float, float]]) -> str:
    """A rating history chart.

    Args:
        history: (μ, σ) oldest first: the prior, then the rating after each rated race.

    Returns:
        An ``<svg>`` string: x = rated races so far, a band μ ± 3σ, the μ line and the
        ordinal μ − 3σ line, with a legend.
    """
    title = "Rating history: μ, μ ± 3σ band and ordinal μ − 3σ after each race"
    if not history:
        return _empty(title, "no rated races yet")
    mus = [float(m) for m, _ in history]
    sigmas = [float(s) for _, s in history]
    xs = [float(i) for i in range(len(history))]
    upper = [m + 3 * s for m, s in zip(mus, sigmas, strict=True)]
    lower = [m - 3 * s for m, s in zip(mus, sigmas, strict=True)]
    y_ticks = nice_ticks(min(lower), max(upper))
    x_ticks = [t for t in nice_ticks(0.0, max(xs[-1], 1.0)) if t == int(t)]
    frame = _Frame(0.0, max(xs[-1], 1.0), y_ticks[0], y_ticks[-1])
    band = frame.points(xs + xs[::-1], upper + lower[::-1])
    body = (
        _axes(frame, x_ticks, y_ticks, "rated races", "rating")
        + f'<polygon points="{band}" fill="{BAND_COLOUR}" fill-opacity="0.12" stroke="none"/>'
        + f'<polyline class="series" points="{frame.points(xs, mus)}" stroke="{MU_COLOUR}"/>'
        + f'<polyline class="series" points="{frame.points(xs, lower)}" '
        f'stroke="{ORDINAL_COLOUR}" stroke-dasharray="5 4"/>'
        + _legend([("μ", MU_COLOUR), ("ordinal μ − 3σ", ORDINAL_COLOUR)])
    )
    return _svg(title, body)


def lap_time_svg(cars: Sequence[tuple[str, Sequence[float]]]) -> str:
    """A lap-time chart, one line (with dots) per car.

    Args:
        cars: (name, lap times in s) per car, in car order (car i gets car i's colour).

    Returns:
        An ``<svg>`` string: x = lap number, y = lap time in seconds.
    """
    title = "Lap times per car (s)"
    laps = [(i, name, [float(t) for t in times]) for i, (name, times) in enumerate(cars) if times]
    if not laps:
        return _empty(title, "no completed laps")
    all_times = [t for _, _, times in laps for t in times]
    n_laps = max(len(times) for _, _, times in laps)
    y_ticks = nice_ticks(min(all_times), max(all_times))
    frame = _Frame(0.75, n_laps + 0.25, y_ticks[0], y_ticks[-1])
    parts = [_axes(frame, [float(k) for k in range(1, n_laps + 1)], y_ticks, "lap", "s")]
    for i, _name, times in laps:
        colour = car_hex(i)
        xs = [float(k) for k in range(1, len(times) + 1)]
        parts.append(
            f'<polyline class="series" points="{frame.points(xs, times)}" stroke="{colour}"/>'
        )
        parts.extend(
            f'<circle cx="{frame.x(a):.1f}" cy="{frame.y(b):.1f}" r="3" fill="{colour}"/>'
            for a, b in zip(xs, times, strict=True)
        )
    parts.append(_legend([(name, car_hex(i)) for i, name, _ in laps]))
    return _svg(title, "".join(parts))


def _legend(entries: Sequence[tuple[str, str]]) -> str:
    """A one-row legend at the top right: (label, colour) per entry."""
    parts = []
    x = WIDTH - MARGIN_RIGHT
    for label, colour in reversed(entries):
        text = escape(label)
        width = 7 * len(label) + 22
        x -= width
        parts.append(
            f'<rect x="{x}" y="{MARGIN_TOP}" width="12" height="4" fill="{colour}"/>'
            f'<text class="legend" x="{x + 16}" y="{MARGIN_TOP + 6}">{text}</text>'
        )
    return "".join(parts)
