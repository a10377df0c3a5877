"""Lap counting at its boundaries: the jump limit, landing exactly on a gate, short tracks.

These pin the comparisons in :class:`tracks.LapCounter` that ordinary laps never touch (an
outside mutation audit found boundary and direction mutants surviving): a progress jump of
exactly ``max_jump`` still counts and a hair more is a cut; a car that lands exactly on a gate
has crossed it; on a short track with many gates the limit shrinks below half a gate spacing.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.tracks.builders import stadium
from tracks import LapCounter, Track


@pytest.fixture(scope="module")
def track() -> Track:
    return stadium()  # about 122.8 m: ten gates 12.3 m apart


def _counter_before_gate(track: Track, gate: int, gap: float, n_gates: int = 10) -> LapCounter:
    start = float(track.checkpoint_s(n_gates)[gate]) - gap
    counter = LapCounter(track, [start], n_gates=n_gates)
    assert counter.next_gate[0] == gate
    return counter


@pytest.mark.parametrize(("jump", "counts"), [(3.0, True), (3.01, False), (2.9, True)])
def test_a_jump_of_exactly_max_jump_counts_and_more_is_a_cut(
    track: Track, jump: float, counts: bool
) -> None:
    counter = _counter_before_gate(track, 3, gap=0.1)  # default max_jump: 3.0 m
    counter.update(counter.s + jump)
    assert bool(counter.next_gate[0] == 4) is counts


def test_landing_exactly_on_a_gate_crosses_it(track: Track) -> None:
    gate_s = float(track.checkpoint_s()[3])
    counter = _counter_before_gate(track, 3, gap=0.3)
    counter.update([gate_s])
    assert counter.next_gate[0] == 4
    counter.update([gate_s + 0.2])  # and it is not counted twice
    assert counter.next_gate[0] == 4


def test_standing_still_or_reversing_never_crosses(track: Track) -> None:
    counter = _counter_before_gate(track, 3, gap=0.2)
    s = float(counter.s[0])
    for value in (s, s, s - 0.5, s):
        counter.update([value])
    assert counter.next_gate[0] == 3


def test_the_jump_limit_shrinks_on_short_gate_spacings(track: Track) -> None:
    n_gates = 100  # 1.23 m apart: a 3 m limit would let a car skip two gates
    spacing = track.length / n_gates
    counter = LapCounter(track, [0.0], n_gates=n_gates)
    assert counter.max_jump == pytest.approx(0.45 * spacing)
    # A limit of exactly half a spacing is already too much and is clamped too.
    clamped = LapCounter(track, [0.0], n_gates=n_gates, max_jump=0.5 * spacing)
    assert clamped.max_jump == pytest.approx(0.45 * spacing)
    kept = LapCounter(track, [0.0], n_gates=n_gates, max_jump=0.4 * spacing)
    assert kept.max_jump == pytest.approx(0.4 * spacing)
    # Behaviour: a step of 0.44 spacing over a gate counts, 0.46 spacing does not.
    for frac, counts in ((0.44, True), (0.46, False)):
        c = _counter_before_gate(track, 50, gap=0.01, n_gates=n_gates)
        assert c.max_jump == pytest.approx(0.45 * spacing)
        c.update(c.s + frac * spacing)
        assert bool(c.next_gate[0] == 51) is counts, frac


def test_laps_are_integers_starting_at_minus_one(track: Track) -> None:
    counter = LapCounter(track, [-0.5, -1.5])
    assert counter.laps.dtype == np.int64
    assert counter.laps.tolist() == [-1, -1]


def test_a_gate_reached_by_a_cut_is_not_counted_when_the_car_drives_on(track: Track) -> None:
    # The cut lands exactly on the gate (a jump over the limit: not counted). The next, legal
    # step starts *on* the gate: the gate is not ahead of the car (0 m), so it is still not
    # crossed; counting it would let a car cut to a gate and collect it on its next step.
    gate_s = float(track.checkpoint_s()[3])
    counter = _counter_before_gate(track, 3, gap=5.0)  # 5 m > the 3 m jump limit
    counter.update([gate_s])
    assert counter.next_gate[0] == 3
    counter.update([gate_s + 0.5])
    assert counter.next_gate[0] == 3
