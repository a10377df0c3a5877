"""The built-in track library: every track loads and is drivable by 1/10 cars; names resolve."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from tracks import Track, TrackError, list_tracks, load_track
from tracks.geometry import CORNER_CURVATURE
from tracks.library import DATA_DIR
from tracks.validation import grid_fits, segment_crossings, validate_track

REQUIRED = ("oval", "bean", "hairpins", "chicanes", "speedway", "technical", "spielberg", "monza")
BUILTINS = list_tracks()
RADIUS_MARGIN = 1.3  # radius of curvature / inner half-width a car can actually drive round


def bend_turns(track: Track) -> list[float]:
    """Signed heading change (degrees) of each bend tighter than the corner curvature."""
    tight = np.abs(track.curvature) > CORNER_CURVATURE
    order = np.roll(np.arange(track.n_points), -int(np.argmin(tight)))  # start on a straight
    turns, turn = [], 0.0
    for i in order:
        if tight[i]:
            turn += track.curvature[i] * track.segment_lengths[i]
        elif turn:
            turns.append(math.degrees(turn))
            turn = 0.0
    return turns + ([math.degrees(turn)] if turn else [])


def test_library_has_the_required_kinds() -> None:
    assert len(BUILTINS) >= 8
    assert set(REQUIRED) <= set(BUILTINS)


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_track_is_valid_for_a_tenth_scale_car(name: str) -> None:
    track = load_track(name)
    validate_track(track)
    assert track.name == name
    assert 30.0 <= track.length <= 150.0
    assert track.width.min() >= 2.0
    assert track.width.max() <= 4.0
    assert segment_crossings(track.centre) == []
    assert grid_fits(track, 8)


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_bends_leave_room_to_drive(name: str) -> None:
    track = load_track(name)
    inner = np.where(track.curvature > 0, track.width_left, track.width_right)
    assert (np.abs(track.curvature) * inner).max() < 1.0 / RADIUS_MARGIN


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_grid_stands_on_a_straight(name: str) -> None:
    track = load_track(name)
    behind = track.curvature_at(-np.linspace(0.0, 5.0, 51))
    assert np.abs(behind).max() < CORNER_CURVATURE


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_file_is_small_and_declares_its_direction(name: str) -> None:
    data = json.loads((DATA_DIR / f"{name}.json").read_text(encoding="utf-8"))
    assert data["schema_version"] == 1
    assert data["units"] == "m"
    assert data["name"] == name
    assert data["description"]
    assert 10 <= len(data["centre_line"]) <= 400
    coords = np.asarray(data["centre_line"], dtype=np.float64)
    np.testing.assert_array_equal(coords, np.round(coords, 3))  # millimetres
    assert data["direction"] == load_track(name).orientation


def test_both_directions_are_represented() -> None:
    directions = [load_track(name).orientation for name in BUILTINS]
    assert directions.count("ccw") >= 2
    assert directions.count("cw") >= 2


def test_oval_length_matches_the_stadium_closed_form() -> None:
    oval = load_track("oval")
    found = re.search(r"straight ([\d.]+) m, radius ([\d.]+) m", oval.description)
    assert found, oval.description
    straight, radius = (float(v) for v in found.groups())
    assert oval.length == pytest.approx(2 * straight + 2 * math.pi * radius, rel=1e-3)


def test_corner_counts_fit_each_kind() -> None:
    corners = {name: load_track(name).n_corners for name in REQUIRED}
    assert corners["oval"] == 2
    assert corners["speedway"] <= 4
    assert corners["chicanes"] >= 12
    assert corners["technical"] >= 10
    assert 9 <= corners["spielberg"] <= 11  # the real circuit has 10 turns
    assert 10 <= corners["monza"] <= 12  # the real circuit has 11


def test_hairpins_has_at_least_two_hairpins() -> None:
    hairpins = [t for t in bend_turns(load_track("hairpins")) if abs(t) >= 150.0]
    assert len(hairpins) >= 2


def test_bean_has_a_concave_side() -> None:
    bean = load_track("bean")
    sense = 1.0 if bean.orientation == "ccw" else -1.0
    assert min(sense * t for t in bend_turns(bean)) <= -60.0  # a real bend against the lap


def test_technical_is_narrow_and_speedway_is_long_and_fast() -> None:
    technical, speedway = load_track("technical"), load_track("speedway")
    assert technical.width.max() <= 2.2
    assert 140.0 <= speedway.length <= 150.0
    assert 1.0 / np.abs(speedway.curvature).max() > 3.0 / np.abs(technical.curvature).max()


@pytest.mark.parametrize("name", ["spielberg", "monza"])
def test_real_circuits_say_what_they_are_modelled_on(name: str) -> None:
    assert "modelled on the layout of" in load_track(name).description.lower()


def test_unknown_name_lists_the_builtin_tracks() -> None:
    with pytest.raises(TrackError) as err:
        load_track("no-such-track")
    message = str(err.value)
    assert "no-such-track" in message
    for name in BUILTINS:
        assert name in message
