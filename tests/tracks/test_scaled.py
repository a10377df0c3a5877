"""Scaled tracks: ``Track.scaled`` and ``NAME@<factor>`` names (a road for a smaller car)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.tracks.builders import circle_points
from tracks import Raceline, Track, TrackError, load_track
from tracks.formats import write_json
from tracks.generator import generate_track
from tracks.library import split_scale

# The AWS DeepRacer car (0.26 m long, arena.cars) on roads drawn for the 0.5 m F1TENTH car.
DEEPRACER = 0.26 / 0.5


@pytest.mark.parametrize("name", ["hairpins", "technical"])
def test_scaled_track_has_every_length_scaled_and_every_angle_kept(name: str) -> None:
    track = load_track(name)
    small = track.scaled(DEEPRACER)
    assert small.name == f"{name}@0.52"
    assert small.n_points == track.n_points
    assert small.length == pytest.approx(DEEPRACER * track.length, rel=1e-12)
    np.testing.assert_allclose(small.width_left, DEEPRACER * track.width_left, rtol=1e-12)
    np.testing.assert_allclose(small.width_right, DEEPRACER * track.width_right, rtol=1e-12)
    np.testing.assert_allclose(small.curvature, track.curvature / DEEPRACER, rtol=1e-12)
    np.testing.assert_array_equal(small.headings, track.headings)
    assert small.orientation == track.orientation
    assert small.n_corners == track.n_corners  # corners are found by curvature
    # The same road in Frenet terms: a point at (s, d) lands at (f s, f d).
    rng = np.random.default_rng(0)
    s = rng.uniform(0.0, track.length, 500)
    left, right = track.widths_at(s)
    d = rng.uniform(-0.9 * right, 0.9 * left)
    xy = track.to_cartesian(np.column_stack([s, d]))
    back = small.project(DEEPRACER * xy)
    np.testing.assert_allclose(small.delta_s(back.s, DEEPRACER * s), 0.0, atol=1e-9)
    np.testing.assert_allclose(back.d, DEEPRACER * d, atol=1e-9)
    # Scaling and reversing commute; scaling back restores the track.
    np.testing.assert_allclose(small.reversed().centre, track.reversed().scaled(0.52).centre)
    np.testing.assert_allclose(small.scaled(1 / DEEPRACER).centre, track.centre, atol=1e-12)


def test_waypoints_and_raceline_scale_with_the_track() -> None:
    # A DeepRacer-like ring with the file's own waypoints and an F1TENTH-style race line.
    points = circle_points(10.0, 60)
    line = Raceline(circle_points(10.3, 80), np.full(80, 6.0))
    track = Track(points, 1.0, 1.0, name="ring", waypoints=points, raceline=line)
    small = track.scaled(0.25)
    assert track.waypoints is not None and small.waypoints is not None
    np.testing.assert_allclose(small.waypoints, 0.25 * track.waypoints)
    assert small.raceline is not None
    np.testing.assert_allclose(small.raceline.points, 0.25 * line.points)
    np.testing.assert_allclose(small.raceline.speed, 3.0)  # Froude: same v²/r in the bends


@pytest.mark.parametrize(
    ("factor", "message"),
    [
        (0.0, "positive"),
        (-0.5, "positive"),
        (float("nan"), "positive"),
        (float("inf"), "positive"),
        ("half", "positive"),
        (0.04, "long"),  # oval: 94 m -> 3.8 m, under the 5 m minimum
        (60.0, "implausible"),  # 60 m half-widths and more: a unit mistake
    ],
)
def test_bad_scales_are_clear_track_errors(factor: object, message: str) -> None:
    with pytest.raises(TrackError, match=message):
        load_track("oval").scaled(factor)  # type: ignore[arg-type]


def test_scaled_names_load_back_for_builtin_random_and_file_tracks(tmp_path: Path) -> None:
    hairpins = load_track("hairpins@0.52")
    np.testing.assert_array_equal(hairpins.centre, load_track("hairpins").scaled(0.52).centre)
    # A generated track with real-track-like hairpins, scaled: its name is the spec again.
    spec = "random:7:length=80,difficulty=0.7,hairpin=0.6"
    small = generate_track(7, 80.0, 0.7, hairpin=0.6).scaled(DEEPRACER)
    assert small.name == spec.replace("length=80,", "") + "@0.52"  # 80 m is the default
    again = load_track(small.name)
    np.testing.assert_array_equal(again.centre, small.centre)
    np.testing.assert_array_equal(again.width_left, small.width_left)
    assert load_track(spec + "@0.52").length == pytest.approx(41.6, abs=1e-6)
    # Unscaled names are unchanged (the generator's names and tracks stay bit-identical).
    assert generate_track(7, 80.0, 0.7, hairpin=0.6).name == "random:7:difficulty=0.7,hairpin=0.6"
    # A file: scaled by name; an "@" elsewhere in a path is part of the path.
    bean = load_track("bean")
    (tmp_path / "runs@3").mkdir()
    for path in (tmp_path / "loop.json", tmp_path / "loop@2.json", tmp_path / "runs@3" / "b.json"):
        write_json(bean, path)
        assert split_scale(str(path)) == (str(path), None)
        assert load_track(path).length == pytest.approx(bean.length)
        assert load_track(f"{path}@0.5").length == pytest.approx(0.5 * bean.length)
    with pytest.raises(TrackError, match="@<factor>"):
        load_track("oval@small")
