"""Race standings frame by frame, from what a replay log holds (poses and events).

Used by the 3D replays and the live viewer (:mod:`arena.viser_scene`) to show each car's
position and lap counter while a race plays. The order at a moment ``t``:

1. cars that have finished (a ``finish`` event at or before ``t``), by finishing time;
2. cars still racing, by race progress (m along the centre line, unwrapped; a car that starts
   behind the line starts with negative progress);
3. cars out of the race (a ``dnf`` event, or no pose any more), by the progress they made.

Laps completed come from the ``lap`` events (``lap`` field), so they match the results.
The race's lap count is :attr:`arena.replay.ReplayLog.laps` when recorded; otherwise the most
laps any car completed before a ``finish`` event, or 0 (unknown).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tracks import Track

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Standing:
    """One moment's standings.

    Attributes:
        order: car indices, leader first (n,).
        laps: laps completed per car (n,).
        finished: per car, whether it has finished (n,).
        out: per car, whether it is out of the race (DNF or no pose) (n,).
    """

    order: tuple[int, ...]
    laps: tuple[int, ...]
    finished: tuple[bool, ...]
    out: tuple[bool, ...]

    def position(self, car: int) -> int:
        """1-based position of car index ``car``."""
        return self.order.index(car) + 1


class StandingsTracker:
    """Follows a race frame by frame and tells its standings.

    Args:
        track: the race's track.
        agents: the cars' agent names (``car_0`` …), in car-index order; events name cars so.

    Feed events with :meth:`event` (in time order) and frames with :meth:`frame`.

    >>> from tracks import load_track
    >>> track = load_track("oval")
    >>> st = StandingsTracker(track, ["car_0", "car_1"])
    >>> xy = track.to_cartesian(np.array([[5.0, 0.0], [3.0, 0.0]]))
    >>> st.frame(0.0, np.column_stack([xy, np.zeros(2)])).order
    (0, 1)
    """

    def __init__(self, track: Track, agents: list[str]) -> None:
        self.track = track
        self.index = {a: i for i, a in enumerate(agents)}
        n = len(agents)
        self.progress = np.full(n, np.nan)  # m, unwrapped
        self.last_s = np.full(n, np.nan)  # m, on the track
        self.laps = [0] * n
        self.finish_t = [float("inf")] * n
        self.dnf = [False] * n
        self.present = [False] * n

    def event(self, e: dict[str, Any]) -> None:
        """Take one event of the replay log (``lap``, ``finish``, ``dnf``; others ignored)."""
        car = self.index.get(str(e.get("car")))
        if car is None:
            return
        kind = e.get("type")
        if kind == "lap":
            self.laps[car] = max(self.laps[car], int(e.get("lap", self.laps[car] + 1)))
        elif kind == "finish":
            self.finish_t[car] = min(self.finish_t[car], float(e.get("t", 0.0)))
        elif kind == "dnf":
            self.dnf[car] = True

    def frame(self, t: float, poses: FloatArray) -> Standing:
        """Advance to a frame: poses (n, 3) [x m, y m, yaw rad], NaN rows for cars out."""
        poses = np.asarray(poses, dtype=np.float64)
        here = ~np.isnan(poses[:, 0])
        if here.any():
            s = self.track.to_frenet(poses[here, :2])[:, 0]
            last = self.last_s[here]
            prog = self.progress[here]
            first = np.isnan(last)
            half = 0.5 * self.track.length
            start = np.where(s > half, s - self.track.length, s)  # behind the line: negative
            step = self.track.delta_s(s, np.where(first, s, last))
            self.progress[here] = np.where(first, start, prog + step)
            self.last_s[here] = s
        self.present = [bool(h) for h in here]
        n = len(self.present)
        finished = [self.finish_t[c] <= t for c in range(n)]
        out = [not finished[c] and (self.dnf[c] or not self.present[c]) for c in range(n)]
        prog = np.nan_to_num(self.progress, nan=-np.inf)

        def key(c: int) -> tuple[int, float]:
            if finished[c]:
                return (0, self.finish_t[c])
            return (2 if out[c] else 1, -float(prog[c]))

        order = tuple(sorted(range(n), key=key))
        return Standing(order, tuple(self.laps), tuple(finished), tuple(out))


def race_laps(events: list[dict[str, Any]], recorded: int = 0) -> int:
    """The race's lap count: ``recorded`` if known (> 0), else inferred from the events.

    >>> race_laps([{"type": "lap", "car": "car_0", "lap": 2}, {"type": "finish", "car": "car_0"}])
    2
    >>> race_laps([{"type": "lap", "car": "car_0", "lap": 1}])
    0
    """
    if recorded > 0:
        return recorded
    finishers = {e.get("car") for e in events if e.get("type") == "finish"}
    laps = [
        int(e.get("lap", 0)) for e in events if e.get("type") == "lap" and e.get("car") in finishers
    ]
    return max(laps, default=0)


def standings_text(standing: Standing, names: list[str], laps: int) -> str:
    """The standings as lines ``P1 name  lap 2/3`` (``finished`` / ``out`` when so).

    >>> st = Standing((1, 0), (1, 2), (False, True), (False, False))
    >>> print(standings_text(st, ["a", "b"], 2))
    P1 b  finished
    P2 a  lap 2/2
    """
    lines = []
    for pos, c in enumerate(standing.order, start=1):
        if standing.finished[c]:
            state = "finished"
        elif standing.out[c]:
            state = "out"
        else:
            lap = standing.laps[c] + 1
            state = f"lap {min(lap, laps)}/{laps}" if laps > 0 else f"lap {lap}"
        lines.append(f"P{pos} {names[c]}  {state}")
    return "\n".join(lines)


__all__ = ["Standing", "StandingsTracker", "race_laps", "standings_text"]
