"""Lap counting by ordered checkpoints, vectorised over cars.

A lap counts only when a car passes every gate of the lap in order, each in the driving
direction. Gate 0 is the start/finish line. Crossing a gate backwards, re-crossing one already
passed, or "jumping" over one (the projected progress changing by more than ``max_jump`` metres
in one update, which happens when a car cuts across the infield) does not count.

A car that starts on the grid (just behind the line) begins with ``laps = -1``: its first
crossing of the line only starts lap 1, so lap 1 is timed from the start signal, as in a
standing-start race.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tracks.geometry import DEFAULT_CHECKPOINTS, FloatArray, Track


class LapCounter:
    """Per-car lap state for ``n_cars`` cars on one track.

    Attributes:
        next_gate: (n_cars,) index of the next gate each car must cross.
        laps: (n_cars,) completed laps (``-1`` until a grid car first crosses the line).
        s: (n_cars,) last progress seen, m.
    """

    def __init__(
        self,
        track: Track,
        s_start: ArrayLike,
        *,
        n_gates: int = DEFAULT_CHECKPOINTS,
        max_jump: float = 3.0,
    ) -> None:
        """Start counting from progress ``s_start`` (n_cars,) m."""
        self.track = track
        self.gate_s: FloatArray = track.checkpoint_s(n_gates)
        if max_jump >= 0.5 * track.length / n_gates:
            max_jump = 0.45 * track.length / n_gates
        self.max_jump = max_jump
        s0 = track.wrap_s(s_start)
        self.s: FloatArray = s0.copy()
        # First gate strictly ahead of each car; cars start "before" their first line crossing.
        ahead = np.searchsorted(self.gate_s, s0, side="right")
        self.next_gate: NDArray[np.int64] = (ahead % n_gates).astype(np.int64)
        self.laps: NDArray[np.int64] = np.full(len(s0), -1, dtype=np.int64)

    def update(self, s_new: ArrayLike) -> NDArray[np.bool_]:
        """Advance with new progress (n_cars,) m; returns (n_cars,) True where a lap completed."""
        s1 = self.track.wrap_s(s_new)
        step = self.track.delta_s(s1, self.s)
        gate = self.gate_s[self.next_gate]
        before = self.track.delta_s(gate, self.s)  # how far ahead the gate was, m
        crossed = (step > 0) & (step <= self.max_jump) & (before > 0) & (before <= step)
        finish_line = crossed & (self.next_gate == 0)
        lap_done = finish_line & (self.laps >= 0)
        self.laps = np.where(finish_line, self.laps + 1, self.laps)
        self.next_gate = np.where(crossed, (self.next_gate + 1) % len(self.gate_s), self.next_gate)
        self.s = s1
        return lap_done

    @property
    def laps_completed(self) -> NDArray[np.int64]:
        """(n_cars,) laps completed, never negative."""
        return np.maximum(self.laps, 0)
