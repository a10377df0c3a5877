"""Lap counting by ordered checkpoints: real laps count; reversing and cutting never do."""

from __future__ import annotations

import numpy as np
import pytest

from tests.tracks.builders import stadium
from tracks import LapCounter, Track
from tracks.geometry import FloatArray

STEP = 0.4  # m of progress per update (a car at 4 m/s, 10 Hz)


@pytest.fixture(scope="module")
def track() -> Track:
    return stadium()  # about 122.8 m: ten gates 12.3 m apart


def drive(counter: LapCounter, path: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Feed progress values (T, n_cars); returns lap_done (T, n_cars) and laps (T, n_cars)."""
    done, laps = [], []
    for s in path:
        done.append(counter.update(s))
        laps.append(counter.laps.copy())
    return np.array(done), np.array(laps)


def forward(s0: float, distance: float, step: float = STEP) -> FloatArray:
    """Unwrapped progress values from ``s0`` (exclusive) over ``distance`` m, (T,)."""
    n = round(abs(distance) / step)
    return s0 + np.sign(distance) * step * np.arange(1, n + 1)


def line_crossings(track: Track, s0: float, path: FloatArray) -> list[int]:
    """Indices into ``path`` (unwrapped progress) where it passes the start line forwards."""
    lap = np.floor(np.concatenate([[s0], path]) / track.length)
    return np.flatnonzero(np.diff(lap) > 0).tolist()


def test_grid_start_first_crossing_starts_lap_one(track: Track) -> None:
    s0 = track.length - 1.0  # on the grid, 1 m behind the line
    counter = LapCounter(track, [s0])
    path = forward(s0, 1.0 + 1.5 * track.length)
    done, laps = drive(counter, path[:, None])
    crossed_at = line_crossings(track, s0, path)
    assert len(crossed_at) == 2  # line crossings after 1 m and after 1 m + one lap
    # First crossing: lap 1 starts (laps -1 -> 0), nothing completes.
    assert (laps[: crossed_at[0], 0] == -1).all()
    assert laps[crossed_at[0], 0] == 0 and not done[crossed_at[0], 0]
    # The next crossing, one full lap later, completes lap 1: exactly once.
    assert np.flatnonzero(done[:, 0]).tolist() == [crossed_at[1]]
    assert laps[-1, 0] == 1
    assert counter.laps_completed.tolist() == [1]


def test_all_gates_passed_in_order_counts_each_lap(track: Track) -> None:
    s0 = 0.5 * track.length  # a rolling start half way round
    counter = LapCounter(track, [s0])
    done, _ = drive(counter, forward(s0, 3.6 * track.length)[:, None])
    # Half a lap to the line (laps 0), then three full laps.
    assert done.sum() == 3
    assert counter.laps_completed.tolist() == [3]


def test_driving_backwards_never_counts(track: Track) -> None:
    for s0 in (1.0, track.length - 1.0, 0.3 * track.length):
        counter = LapCounter(track, [s0])
        done, laps = drive(counter, forward(s0, -3.3 * track.length)[:, None])
        assert not done.any()
        assert (laps == -1).all()


def test_turning_back_before_the_line_does_not_count(track: Track) -> None:
    s0 = track.length - 1.0
    counter = LapCounter(track, [s0])
    out = forward(s0, 1.0 + 0.7 * track.length)  # cross the line, 70% of lap 1
    back = forward(out[-1], -0.7 * track.length - 3.0)  # reverse back over the line
    again = forward(back[-1], 5.0)  # and forward over it again
    done, laps = drive(counter, np.concatenate([out, back, again])[:, None])
    assert not done.any()
    assert laps[-1, 0] == 0
    # Gates already passed stay passed: the lap completes on reaching the line after gate 9.
    on = forward(again[-1], track.length)
    done, _ = drive(counter, on[:, None])
    first = int(np.flatnonzero(done[:, 0])[0])
    assert done.sum() == 1
    assert track.wrap_s(on[first]) < 1.0 and track.wrap_s(on[first - 1]) > track.length - 1.0


def test_a_cut_across_a_gate_is_not_counted(track: Track) -> None:
    s0 = track.length - 1.0
    counter = LapCounter(track, [s0])
    gate_3 = counter.gate_s[3]
    first = forward(s0, 1.0 + gate_3 - 4.0)  # to 4 m before gate 3
    jumped = first[-1] + 8.0  # one update 8 m on (> max_jump): over gate 3
    rest = forward(jumped, track.length + 1.0 - (jumped - s0))  # on across the line
    done, laps = drive(counter, np.concatenate([first, [jumped], rest])[:, None])
    assert counter.max_jump < 8.0
    assert not done.any(), "a lap with a skipped gate must not count"
    assert laps[-1, 0] == 0
    assert counter.next_gate[0] == 3, "the car still owes gate 3"


def test_a_fast_step_below_max_jump_still_counts(track: Track) -> None:
    s0 = track.length - 1.0
    counter = LapCounter(track, [s0])
    step = 0.9 * counter.max_jump  # a fast car: big but plausible steps
    done, _ = drive(counter, forward(s0, 1.0 + track.length + step, step)[:, None])
    assert done.sum() == 1


def test_vectorised_over_cars_with_different_behaviour(track: Track) -> None:
    length = track.length
    grid = np.array([length - 0.5, length - 1.0, length - 1.5, length - 2.0])
    counter = LapCounter(track, grid)
    steps = round(2.3 * length / STEP)
    driven = STEP * np.arange(1, steps + 1)
    racer = grid[0] + driven
    reverser = grid[1] - driven
    parked = np.full(steps, grid[3])
    # The cutter jumps 0.4 lap ahead (across the infield) after every 0.6 lap it drives.
    cuts = np.maximum(0.0, np.floor((driven - 0.3 * length) / (0.6 * length)) + 1)
    cutter = grid[2] + driven + 0.4 * length * cuts
    path = np.column_stack([racer, reverser, cutter, parked])
    done, laps = drive(counter, path)
    assert done.sum(axis=0).tolist() == [2, 0, 0, 0]
    assert counter.laps_completed.tolist() == [2, 0, 0, 0]
    assert laps[-1].tolist() == [2, -1, 0, -1]
    # The racer's laps complete exactly when its progress wraps past the line.
    wraps = line_crossings(track, grid[0], racer)
    assert len(wraps) == 3
    assert np.flatnonzero(done[:, 0]).tolist() == wraps[1:]
