"""Track files: round trips through every format, orientation handling, hostile inputs."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.tracks.builders import bone_points, circle_points, wavy_stadium
from tracks import Track, TrackError
from tracks.formats import (
    FORMATS,
    TrackFormat,
    read_deepracer,
    read_f1tenth,
    read_json,
    read_track_file,
    track_from_dict,
    track_to_dict,
    write_track_file,
)

SUFFIX = {"json": ".json", "f1tenth": ".csv", "deepracer": ".npy"}


def assert_same_track(a: Track, b: Track, tol: float = 1e-3) -> None:
    """Same road within ``tol`` m: centre lines on each other, lengths, start, widths, sides."""
    assert abs(a.length - b.length) < tol
    assert a.orientation == b.orientation
    assert np.linalg.norm(a.centre[0] - b.centre[0]) < tol, "start line moved"
    on_b = b.project(a.centre)
    assert np.abs(on_b.d).max() < tol
    assert np.abs(a.project(b.centre).d).max() < tol
    assert np.abs(b.delta_s(on_b.s, a.s)).max() < tol, "progress differs"
    left, right = b.widths_at(on_b.s)
    assert np.abs(left - a.width_left).max() < tol
    assert np.abs(right - a.width_right).max() < tol


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("direction", ["ccw", "cw"])
def test_export_import_round_trip(tmp_path: Path, fmt: TrackFormat, direction: str) -> None:
    track = wavy_stadium()  # anticlockwise, left and right widths vary differently
    if direction == "cw":
        track = track.reversed()
    assert track.orientation == direction
    path = tmp_path / f"track{SUFFIX[fmt]}"
    write_track_file(track, path, fmt)
    back = read_track_file(path, fmt)
    assert_same_track(track, back)
    assert_same_track(track, read_track_file(path))  # format guessed from the suffix


def ring_npy(path: Path, *, clockwise: bool, inner: float = 0.8, outer: float = 1.6) -> Path:
    """A DeepRacer-style ring of radius 10 m with the inner border ``inner`` m in."""
    th = np.linspace(0.0, 2 * np.pi, 60, endpoint=False)
    if clockwise:
        th = -th
    unit = np.column_stack([np.cos(th), np.sin(th)])
    rows = np.column_stack([10.0 * unit, (10.0 - inner) * unit, (10.0 + outer) * unit])
    np.save(path, np.vstack([rows, rows[:1]]))  # DeepRacer repeats the first row
    return path


def distance_to_polyline(points: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """(M,) m from each point to the closed polyline ``ring`` (K, 2)."""
    a, b = ring, np.roll(ring, -1, axis=0)
    ab = b - a
    ap = points[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("mkj,kj->mk", ap, ab) / np.einsum("kj,kj->k", ab, ab), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1).min(axis=1)


@pytest.mark.parametrize("clockwise", [False, True])
def test_deepracer_inner_and_outer_become_left_and_right(tmp_path: Path, clockwise: bool) -> None:
    track = read_deepracer(ring_npy(tmp_path / "ring.npy", clockwise=clockwise))
    assert track.orientation == ("cw" if clockwise else "ccw")
    # Anticlockwise the inner border is on the left; clockwise it is on the right.
    inner_side, outer_side = (
        (track.right_border, track.left_border)
        if clockwise
        else (track.left_border, track.right_border)
    )
    # The road's edges are the file's own border polylines (60 chords of the 9.2 m and
    # 11.6 m circles), not offsets of the smoothed centre line.
    th = np.linspace(0.0, 2 * np.pi, 60, endpoint=False)
    unit = np.column_stack([np.cos(th), np.sin(th)])
    assert distance_to_polyline(inner_side, 9.2 * unit).max() < 5e-3
    assert distance_to_polyline(outer_side, 11.6 * unit).max() < 5e-3
    inner_w, outer_w = (
        (track.width_right, track.width_left)
        if clockwise
        else (track.width_left, track.width_right)
    )
    np.testing.assert_allclose(inner_w, 0.8, atol=0.015)
    np.testing.assert_allclose(outer_w, 1.6, atol=0.02)
    assert track.waypoints is not None and len(track.waypoints) == 61  # the file's own points


def ring_dict(**extra: Any) -> dict[str, Any]:
    """Our JSON for an anticlockwise ring of radius 10 m: 1 m to the left, 2 m to the right."""
    return {
        "schema_version": 1,
        "name": "ring",
        "centre_line": circle_points(10.0, 48).tolist(),
        "width_left": 1.0,
        "width_right": 2.0,
        **extra,
    }


def test_json_direction_opposite_to_stored_order_is_read_reversed() -> None:
    ccw = track_from_dict(ring_dict(direction="ccw", start={"s": 5.0}))
    cw = track_from_dict(ring_dict(direction="cw", start={"s": 5.0}))
    assert (ccw.orientation, cw.orientation) == ("ccw", "cw")
    assert cw.length == pytest.approx(ccw.length, abs=1e-6)
    # The road itself is unchanged: its inner edge at 9 m, outer at 12 m, whichever way round.
    np.testing.assert_allclose(np.linalg.norm(ccw.left_border, axis=1), 9.0, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(ccw.right_border, axis=1), 12.0, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(cw.left_border, axis=1), 12.0, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(cw.right_border, axis=1), 9.0, atol=1e-3)
    # And so is the start line: 5 m from the first stored point (within one 0.1 m spacing).
    for track in (ccw, cw):
        assert np.arctan2(track.centre[0, 1], track.centre[0, 0]) * 10.0 == pytest.approx(
            5.0, abs=0.11
        )
    assert track_from_dict(ring_dict()).orientation == "ccw"  # direction defaults to ccw


def test_json_round_trip_of_a_dict_keeps_the_geometry() -> None:
    track = wavy_stadium().reversed()
    data = json.loads(json.dumps(track_to_dict(track)))
    assert data["direction"] == "cw"
    assert_same_track(track, track_from_dict(data))


# ---- hostile and broken inputs ---------------------------------------------------------------


def write_csv(path: Path, rows: list[str]) -> Path:
    path.write_text("# x_m, y_m, w_tr_right_m, w_tr_left_m\n" + "\n".join(rows) + "\n")
    return path


def circle_rows(n: int = 40, w_right: str = "1.0", w_left: str = "1.0") -> list[str]:
    return [f"{x:.4f},{y:.4f},{w_right},{w_left}" for x, y in circle_points(10.0, n)]


def test_too_few_points(tmp_path: Path) -> None:
    with pytest.raises(TrackError, match="too few centre-line points: 3"):
        read_f1tenth(write_csv(tmp_path / "t.csv", circle_rows(3)))
    with pytest.raises(TrackError, match="too few centre-line points"):
        track_from_dict(ring_dict(centre_line=[[0, 0], [10, 0], [0, 10]]))


def test_self_intersecting_centre_line() -> None:
    t = np.linspace(0.0, 2 * np.pi, 80, endpoint=False)
    figure_eight = np.column_stack([20 * np.cos(t), 10 * np.sin(2 * t)])
    with pytest.raises(TrackError, match="centre line intersects itself"):
        Track(figure_eight, 1.0, 1.0)


@pytest.mark.parametrize(
    ("w_right", "w_left", "message"),
    [
        ("0.0", "1.0", "right width must be positive, got 0 m"),
        ("1.0", "-0.5", "left width must be positive, got -0.5 m"),
        ("nan", "1.0", "right width is NaN or infinite"),
        ("1.0", "inf", "left width is NaN or infinite"),
        ("1.0", "120", "implausible"),
    ],
)
def test_bad_widths(tmp_path: Path, w_right: str, w_left: str, message: str) -> None:
    rows = circle_rows()
    rows[7] = ",".join([*rows[7].split(",")[:2], w_right, w_left])
    with pytest.raises(TrackError, match=message) as err:
        read_f1tenth(write_csv(tmp_path / "t.csv", rows))
    assert "at point 7" in str(err.value)


def test_nan_coordinates(tmp_path: Path) -> None:
    rows = circle_rows()
    rows[5] = "nan,1.0,1.0,1.0"
    with pytest.raises(TrackError, match="NaN or infinite coordinates at point 5"):
        read_f1tenth(write_csv(tmp_path / "t.csv", rows))
    with pytest.raises(TrackError, match="NaN or infinite coordinates"):
        Track(np.where(np.arange(40)[:, None] == 3, np.nan, circle_points(10.0, 40)), 1.0, 1.0)


def test_missing_file(tmp_path: Path) -> None:
    for fmt in FORMATS:
        with pytest.raises(TrackError, match="track file not found"):
            read_track_file(tmp_path / f"nothing{SUFFIX[fmt]}", fmt)


def test_f1tenth_wrong_number_of_columns(tmp_path: Path) -> None:
    rows = circle_rows()
    rows[2] = "1.0,2.0,1.0"
    with pytest.raises(TrackError, match="row 3 has 3 columns; an F1TENTH track has 4"):
        read_f1tenth(write_csv(tmp_path / "t.csv", rows))


def test_f1tenth_non_numeric_cell(tmp_path: Path) -> None:
    rows = circle_rows()
    rows[4] = "1.0,two,1.0,1.0"
    with pytest.raises(TrackError, match=r"not a number.*'two'"):
        read_f1tenth(write_csv(tmp_path / "t.csv", rows))


def test_f1tenth_empty_file(tmp_path: Path) -> None:
    with pytest.raises(TrackError, match="no data rows"):
        read_f1tenth(write_csv(tmp_path / "t.csv", []))


@pytest.mark.parametrize("shape", [(40, 4), (40, 6, 1), (240,)])
def test_deepracer_wrong_shape(tmp_path: Path, shape: tuple[int, ...]) -> None:
    path = tmp_path / "t.npy"
    np.save(path, np.ones(shape))
    with pytest.raises(TrackError, match=r"expected an \(N, 6\) numeric array"):
        read_deepracer(path)


UNPICKLED: list[str] = []


def _record(what: str) -> str:
    UNPICKLED.append(what)
    return what


class Payload:
    """Unpickling this calls ``_record``: proof that a loader ran code from the file."""

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return _record, ("unpickled",)


def test_deepracer_refuses_pickled_object_arrays(tmp_path: Path) -> None:
    path = tmp_path / "evil.npy"
    np.save(path, np.array([Payload()] * 6, dtype=object).reshape(1, 6), allow_pickle=True)
    with pytest.raises(TrackError, match=r"not a numpy \.npy array.*allow_pickle"):
        read_deepracer(path)
    assert UNPICKLED == []
    np.load(path, allow_pickle=True)  # the payload is live: loading it unsafely runs it
    assert UNPICKLED == ["unpickled"]


def npz_bytes() -> bytes:
    buf = io.BytesIO()
    np.savez(buf, waypoints=np.ones((40, 6)))
    return buf.getvalue()


@pytest.mark.parametrize(
    "content",
    [b"", b"\x93NUMPY\x01\x00", b"PK\x03\x04 a broken zip", b"1,2,3,4,5,6\n", npz_bytes()],
    ids=["empty", "truncated", "broken-zip", "text", "npz"],
)
def test_deepracer_not_an_npy_file(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "t.npy"
    path.write_bytes(content)
    with pytest.raises(TrackError, match=r"not a numpy \.npy array"):
        read_deepracer(path)


def test_invalid_json(tmp_path: Path) -> None:
    path = tmp_path / "t.json"
    path.write_text('{"schema_version": 1, "name": ')
    with pytest.raises(TrackError, match="not valid JSON"):
        read_json(path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"schema_version": 2}, "at schema_version"),
        ({"width_left": "wide"}, "at width_left"),
        ({"centre_line": [[0, 0, 0]] * 5}, "is too long"),
        ({"direction": "sideways"}, "at direction"),
        ({"colour": "red"}, "'colour' was unexpected"),
        ({"name": ""}, "at name"),
    ],
)
def test_json_failing_the_schema(tmp_path: Path, change: dict[str, Any], message: str) -> None:
    path = tmp_path / "t.json"
    path.write_text(json.dumps(ring_dict(**change)))
    with pytest.raises(TrackError, match="invalid track JSON") as err:
        read_json(path)
    assert message in str(err.value)


def test_json_missing_required_field(tmp_path: Path) -> None:
    data = ring_dict()
    del data["width_right"]
    with pytest.raises(TrackError, match="invalid track JSON at top level: 'width_right'"):
        track_from_dict(data)


def test_road_overlapping_itself() -> None:
    # Two parallel straights 2.5 m apart with 1.5 m half-widths: the surfaces overlap.
    with pytest.raises(TrackError, match="road overlaps itself"):
        Track(bone_points(gap=2.5), 1.5, 1.5)
    Track(bone_points(gap=4.0), 1.5, 1.5)  # 4 m apart they clear each other


def test_bend_too_tight_for_its_width() -> None:
    with pytest.raises(TrackError, match="too tight for its width"):
        Track(circle_points(3.0), 3.5, 1.0)  # the left (inner) edge folds over the centre
