"""Importing files shaped like the published F1TENTH and DeepRacer tracks.

The shapes follow the real collections:

* F1TENTH centre lines (github.com/f1tenth/f1tenth_racetracks, e.g.
  ``Spielberg/Spielberg_centerline.csv``): ``# x_m,y_m,w_tr_right_m,w_tr_left_m`` then one
  comma-separated row per point about 0.2 m apart, with a constant 1.1 m half-width on both
  sides, wider than the radius of their tightest hairpins.
* F1TENTH race lines (same repository, ``Spielberg/Spielberg_raceline.csv``): two ``#`` id
  lines, then ``# s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps; ax_mps2`` and
  semicolon-separated rows 0.2 m apart, the first point repeated at the end.
* ForzaETH race-stack waypoint CSVs, as MapZoo (github.com/zhouhengli/MapZoo) publishes the
  F1TENTH maps: ``Spielberg/Spielberg_centerline.csv`` and ``..._racing_line.csv`` start with
  a bare header ``id; s_m; d_m; x_m; y_m; d_right; d_left; psi_rad; kappa_radpm; vx_mps;
  ax_mps2`` (no ``#``), then semicolon-separated rows 0.1 m apart with 8 decimals and
  half-widths that vary along the lap (Spielberg: d_right 1.55-1.71, d_left 1.49-1.58 m in
  its first 14 m); the centre line's speed columns are zero.
* DeepRacer tracks (the DeepRacer simulation's ``routes/*.npy``, as in
  aws-deepracer-community/deepracer-race-data ``raw_data/tracks/npy``): an (N, 6) float array of
  centre, inner and outer points 0.2-0.6 m apart, closed by repeating the first row; several
  files also repeat one row in the middle.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.tracks.builders import bone_points, hairpin_points, stadium_points
from tests.tracks.test_formats import assert_same_track, distance_to_polyline
from tracks import Track, TrackError
from tracks.formats import (
    ImportOptions,
    read_deepracer,
    read_f1tenth,
    read_raceline,
    read_track_file,
    write_json,
)
from tracks.geometry import TIGHTEN_TOLERANCE, three_point_curvature
from tracks.plot import plot_track, raceline_collection
from tracks.validation import FOLD_FRACTION, fit_widths

HAIRPIN_S = 12.0 + np.pi * 0.6 / 2  # m: the apex of hairpin_points()


def write_f1tenth_centreline(path: Path, points: np.ndarray, half_width: float = 1.1) -> Path:
    """An F1TENTH ``*_centerline.csv``: their header and a constant half-width."""
    rows = [f"{x:.7f},{y:.7f},{half_width:.7f},{half_width:.7f}" for x, y in points]
    path.write_text("# x_m,y_m,w_tr_right_m,w_tr_left_m\n" + "\n".join(rows) + "\n")
    return path


def normals(points: np.ndarray) -> np.ndarray:
    """(K, 2) left unit normals of a closed polyline (central differences)."""
    tan = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    tan /= np.linalg.norm(tan, axis=1)[:, None]
    return np.column_stack([-tan[:, 1], tan[:, 0]])


def deepracer_rows(points: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """DeepRacer (K, 6) rows of an anticlockwise centre line: inner border on the left."""
    n = normals(points)
    return np.column_stack([points, points + inner * n, points - outer * n])


def save_npy(path: Path, rows: np.ndarray) -> Path:
    np.save(path, np.vstack([rows, rows[:1]]))  # closed, as DeepRacer's files are
    return path


# ---- F1TENTH: a constant 1.1 m half-width around a 0.6 m hairpin -----------------------------


def test_constant_width_wider_than_a_hairpin_is_narrowed_not_refused(tmp_path: Path) -> None:
    csv = write_f1tenth_centreline(tmp_path / "Hairpin_centerline.csv", hairpin_points(0.6))
    with pytest.raises(TrackError, match="too tight for its width"):
        Track(hairpin_points(0.6), 1.1, 1.1)  # built as given, the inner edge folds over
    track = read_f1tenth(csv)
    inner = np.where(track.curvature > 0, track.width_left, track.width_right)
    assert (inner * np.abs(track.curvature) <= FOLD_FRACTION + 1e-6).all()
    apex = int(np.argmin(np.abs(track.s - HAIRPIN_S)))
    assert track.width_left[apex] < 0.6  # the inner (left) side is cut at the hairpin ...
    assert track.width_right[apex] == pytest.approx(1.1)  # ... the outer side is not
    assert track.width_left[int(np.argmin(np.abs(track.s - 5.0)))] == pytest.approx(1.1)
    # The summary says where and by how much.
    note = next(n for n in track.import_notes if "left half-width" in n)
    lo, hi = (float(v) for v in note.split("s=")[1].split(" m")[0].split("-"))
    assert lo < HAIRPIN_S < hi
    assert "1.10 ->" in note


def test_roads_that_would_overlap_are_narrowed_not_refused(tmp_path: Path) -> None:
    # Two straights 2.5 m apart with 1.5 m half-widths (as a constant-width file around a
    # tight infield gives): built as given the surfaces overlap; imported they are cut.
    with pytest.raises(TrackError, match="road overlaps itself"):
        Track(bone_points(gap=2.5), 1.5, 1.5)
    csv = write_f1tenth_centreline(tmp_path / "bone.csv", bone_points(gap=2.5), 1.5)
    track = read_f1tenth(csv)  # validated: no longer overlapping
    middle = np.abs(track.centre[:, 0]) < 5.0  # on the two straights
    sides = np.stack([track.width_left[middle], track.width_right[middle]])
    np.testing.assert_allclose(sides.max(axis=0), 1.5)  # the outer sides keep their width
    assert sides.min(axis=0).max() <= 0.45 * 2.5 + 1e-4  # the facing ones fit the gap
    assert any("narrowed" in n for n in track.import_notes)


def test_max_width_and_width_options(tmp_path: Path) -> None:
    csv = write_f1tenth_centreline(tmp_path / "c.csv", hairpin_points(0.6))
    capped = read_f1tenth(csv, options=ImportOptions(max_width=0.8))
    assert capped.width.max() <= 1.6 + 1e-9
    const = read_f1tenth(csv, options=ImportOptions(width=0.4))
    np.testing.assert_allclose(const.width_right, 0.4)
    with pytest.raises(TrackError, match="--scale must be a positive number"):
        ImportOptions(scale=0.0)


def test_scale_option_scales_length_and_widths(tmp_path: Path) -> None:
    csv = write_f1tenth_centreline(tmp_path / "big.csv", stadium_points(100.0, 30.0, 2.0), 11.0)
    full = read_f1tenth(csv)
    model = read_f1tenth(csv, options=ImportOptions(scale=0.1))
    assert model.length == pytest.approx(0.1 * full.length, rel=1e-3)
    assert model.width_left.mean() == pytest.approx(1.1, abs=1e-3)


def test_f1tenth_track_is_named_without_the_centerline_suffix(tmp_path: Path) -> None:
    # f1tenth_racetracks: Spielberg/Spielberg_centerline.csv is the track "Spielberg".
    path = write_f1tenth_centreline(tmp_path / "Spielberg_centerline.csv", stadium_points(20, 5))
    assert read_f1tenth(path).name == "Spielberg"
    assert read_f1tenth(path, name="Red Bull Ring").name == "Red Bull Ring"


def test_consecutive_repeated_row_is_dropped(tmp_path: Path) -> None:
    pts = hairpin_points(0.6)
    pts = np.insert(pts, 40, pts[40], axis=0)  # one row written twice
    track = read_f1tenth(write_f1tenth_centreline(tmp_path / "dup.csv", pts))
    assert "dropped 1 repeated row(s)" in track.import_notes


# ---- ForzaETH / MapZoo waypoint CSVs: columns picked by their header's names ---------------

MAPZOO_HEADER = "id; s_m; d_m; x_m; y_m; d_right; d_left; psi_rad; kappa_radpm; vx_mps; ax_mps2"


def write_mapzoo(path: Path, points: np.ndarray, speed: float = 0.0) -> tuple[Path, np.ndarray]:
    """A MapZoo ``*_centerline.csv`` (speed 0) or ``*_racing_line.csv``: its bare header and
    11 columns; returns the path and the rows' (K, 3) ``s, d_right, d_left``."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    phase = 2 * np.pi * s / s[-1]
    d_right, d_left = 1.6 + 0.1 * np.sin(phase), 1.4 + 0.1 * np.cos(phase)
    lines = [MAPZOO_HEADER]
    for i, ((x, y), si, r, left) in enumerate(zip(points, s, d_right, d_left, strict=True)):
        lines.append(
            f"{i};{si:.8f};0.00000000;{x:.8f};{y:.8f};{r:.8f};{left:.8f};"
            f"0.00000000;0.10000000;{speed:.8f};0.00000000"
        )
    path.write_text("\n".join(lines) + "\n")
    return path, np.column_stack([s, d_right, d_left])


def test_mapzoo_centre_line_is_read_by_its_column_names(tmp_path: Path) -> None:
    # Was refused: "row 1 has 1 columns; an F1TENTH track has 4" (split on ',' only, and
    # the bare header taken for data).
    path, cols = write_mapzoo(tmp_path / "Spielberg_centerline.csv", stadium_points(30, 8, 0.1))
    track = read_track_file(path)  # .csv: the F1TENTH importer
    assert track.name == "Spielberg"
    assert track.length == pytest.approx(cols[-1, 0], rel=0.01)
    # d_right and d_left (not the d_m, psi or kappa columns) are the half-widths, per point
    period = cols[-1, 0]
    right = np.interp(track.s, cols[:, 0], cols[:, 1], period=period)
    left = np.interp(track.s, cols[:, 0], cols[:, 2], period=period)
    np.testing.assert_allclose(track.width_right, right, atol=0.02)
    np.testing.assert_allclose(track.width_left, left, atol=0.02)


def test_mapzoo_racing_line_speed_is_the_vx_column(tmp_path: Path) -> None:
    pts = stadium_points(30, 8, 0.1)
    path, _ = write_mapzoo(tmp_path / "Spielberg_racing_line.csv", pts, speed=6.5)
    line = read_raceline(path)
    assert len(line.points) == len(pts)
    np.testing.assert_allclose(line.points, pts, atol=1e-7)
    np.testing.assert_allclose(line.speed, 6.5)


def test_bare_comma_header_in_its_own_order_is_read_by_name(tmp_path: Path) -> None:
    # What pandas' to_csv(index=False) writes for a centre line kept as a DataFrame: a
    # header without '#', and here the columns in another order.
    pts = stadium_points(30, 8, 0.2)
    rows = [f"{y:.6f},{x:.6f},1.3,1.2" for x, y in pts]
    path = tmp_path / "t.csv"
    path.write_text("y_m,x_m,w_tr_left_m,w_tr_right_m\n" + "\n".join(rows) + "\n")
    track = read_f1tenth(path)
    assert track.length == pytest.approx(Track(pts, 1.0, 1.0).length, rel=1e-3)
    np.testing.assert_allclose(track.width_left, 1.3, atol=1e-6)
    np.testing.assert_allclose(track.width_right, 1.2, atol=1e-6)


def test_mapzoo_row_cut_short_is_a_clear_error(tmp_path: Path) -> None:
    path, _ = write_mapzoo(tmp_path / "cut.csv", stadium_points(30, 8, 0.1))
    lines = path.read_text().splitlines()
    lines[5] = lines[5].rsplit(";", 1)[0]  # the 5th data row loses its last field
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(TrackError, match=r"row 5 has 10 columns; an F1TENTH track has 11 by"):
        read_f1tenth(path)
    missing = tmp_path / "nowidth.csv"  # a header without widths: the 4-column layout applies
    missing.write_text("id; x_m; y_m\n0; 1; 2\n")
    with pytest.raises(TrackError, match="row 1 has 3 columns; an F1TENTH track has 4"):
        read_f1tenth(missing)


# ---- DeepRacer .npy: repeated rows, borders from the file --------------------------------------


def test_deepracer_repeated_row_is_dropped_and_waypoints_are_the_files(tmp_path: Path) -> None:
    # The repeat leaves the geometry, but not the waypoints: DeepRacer's params["waypoints"]
    # are every centre row of the file (deepracer-simapp track_data.py,
    # ``list(LinearRing(rows[:, 0:2]).coords)``; logged waypoints of the Fumiaki and Cumulo
    # tracks show their repeated row), so a reward function keyed to waypoint indices past
    # the repeat reads the same indices here as in DeepRacer.
    pts = stadium_points(6.0, 1.5, 0.3)
    rows = deepracer_rows(pts, 0.38, 0.38)
    rows = np.insert(rows, 17, rows[17], axis=0)  # the full six values repeated
    track = read_deepracer(save_npy(tmp_path / "reInvent2018.npy", rows))
    assert "dropped 1 repeated row(s)" in track.import_notes
    assert track.waypoints is not None
    file_rows = np.vstack([rows, rows[:1]])[:, :2]  # as saved: closed, the repeat kept
    np.testing.assert_allclose(track.waypoints, file_rows)
    again = tmp_path / "again.json"
    write_json(track, again)
    np.testing.assert_allclose(read_track_file(again).waypoints, file_rows, atol=1e-6)


def test_deepracer_borders_closer_than_the_spline_offset(tmp_path: Path) -> None:
    # Each inner point sits 0.45 m to the left and 0.4 m ahead of its centre point: 0.60 m
    # from it, but the inner border polyline runs 0.45 m from the centre line. The road is
    # what the file's borders say, not the point-to-point distance laid along the normals.
    pts = stadium_points(8.0, 2.0, 0.3)
    n = normals(pts)
    tan = np.column_stack([n[:, 1], -n[:, 0]])
    inner = pts + 0.45 * n + 0.4 * tan
    outer = pts - 0.5 * n
    rows = np.column_stack([pts, inner, outer])
    assert np.linalg.norm(inner - pts, axis=1).min() > 0.59
    track = read_deepracer(save_npy(tmp_path / "oblique.npy", rows))
    np.testing.assert_allclose(
        track.width_left, distance_to_polyline(track.centre, inner), atol=0.01
    )
    assert track.width_left.max() < 0.47  # 0.45 m on the straights, less in the bends
    np.testing.assert_allclose(track.width_right, 0.5, atol=0.01)
    assert distance_to_polyline(track.left_border, inner).max() < 0.01


@pytest.mark.parametrize("clockwise", [False, True])
def test_deepracer_hairpin_round_trip_does_not_tighten(tmp_path: Path, clockwise: bool) -> None:
    # A hairpin whose inner border is close to folding (0.5 m from a 0.6 m-radius centre
    # line): the JSON written by import must load again as the same track (re:Invent 2018
    # did not: re-fitting the resampled points tightened the bend past its width).
    pts = hairpin_points(0.6, spacing=0.35)
    rows = deepracer_rows(pts, 0.5, 0.5)
    if clockwise:
        rows = np.column_stack([rows[::-1, 0:2], rows[::-1, 4:6], rows[::-1, 2:4]])
    track = read_deepracer(save_npy(tmp_path / "hairpin.npy", rows))
    out = tmp_path / "hairpin.json"
    write_json(track, out)
    back = read_track_file(out)
    assert_same_track(track, back, tol=2e-3)
    assert np.abs(back.curvature).max() == pytest.approx(np.abs(track.curvature).max(), rel=0.05)
    assert back.waypoints is not None and track.waypoints is not None
    np.testing.assert_allclose(back.waypoints, track.waypoints, atol=1e-6)


def test_import_does_not_tighten_bends_beyond_the_raw_radius(tmp_path: Path) -> None:
    # A straight running into a 0.6 m arc: the file's three-point radius is never under
    # 0.6 m, but a C2 curve through the points must bend tighter where the curvature jumps
    # (the issue: 0.48 m on the spline where the raw radius is 0.64 m).
    pts = hairpin_points(0.6)
    assert 1 / np.abs(three_point_curvature(pts)).max() == pytest.approx(0.6, rel=1e-3)
    plain = Track(pts, 0.3, 0.3)  # the periodic cubic spline
    assert 1 / np.abs(plain.curvature).max() < 0.53
    track = read_f1tenth(write_f1tenth_centreline(tmp_path / "c.csv", pts, 0.3))
    assert 1 / np.abs(track.curvature).max() >= 0.6 / TIGHTEN_TOLERANCE  # the arc spline
    assert not [n for n in track.import_notes if "tighter than the file's points" in n]
    # The fit still passes through the file's points (up to the 0.1 m resampling's chords).
    assert np.abs(track.project(pts).d).max() < 3e-3
    assert track.length == pytest.approx(plain.length, rel=2e-3)


# ---- round trips: import -> save -> load on every format ---------------------------------------


@pytest.mark.parametrize("fmt", ["f1tenth", "deepracer", "json"])
def test_import_save_load_is_the_same_track(tmp_path: Path, fmt: str) -> None:
    pts = hairpin_points(0.6)
    if fmt == "f1tenth":
        src = write_f1tenth_centreline(tmp_path / "in.csv", pts)
    elif fmt == "deepracer":
        src = save_npy(tmp_path / "in.npy", deepracer_rows(pts, 0.45, 0.5))
    else:
        src = tmp_path / "in.json"
        write_json(read_f1tenth(write_f1tenth_centreline(tmp_path / "c.csv", pts)), src)
    first = read_track_file(src)
    saved = tmp_path / "saved.json"
    write_json(first, saved)
    second = read_track_file(saved)
    assert_same_track(first, second, tol=2e-3)
    write_json(second, tmp_path / "again.json")
    assert_same_track(second, read_track_file(tmp_path / "again.json"), tol=2e-3)


# ---- the F1TENTH race line ----------------------------------------------------------------------


def write_raceline(path: Path, points: np.ndarray, speed: float = 8.0) -> Path:
    """An F1TENTH ``*_raceline.csv``: id lines, the column header, closed loop."""
    closed = np.vstack([points, points[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    lines = [
        "# 17b4de0d-c737-4d0b-b937-32bd2ef0c95b",
        "# 603fd3987364b09f9aacb70d1ed12c268e24dd56",
        "# s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps; ax_mps2",
    ]
    for si, (x, y) in zip(s, closed, strict=True):
        lines.append(f"{si:.7f}; {x:.7f}; {y:.7f}; 1.8326155; 0.0000525; {speed:.7f}; 0.0")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_raceline_is_read_stored_saved_and_drawn(tmp_path: Path) -> None:
    pts = stadium_points(30.0, 10.0, 0.2)
    line = read_raceline(write_raceline(tmp_path / "Oval_raceline.csv", pts))
    assert len(line.points) == len(pts)  # the closing repeat dropped
    np.testing.assert_allclose(line.speed, 8.0)
    track = Track(stadium_points(30.0, 10.0, 0.5), 1.5, 1.5, raceline=line)
    out = tmp_path / "t.json"
    write_json(track, out)
    back = read_track_file(out)
    assert back.raceline is not None
    np.testing.assert_allclose(back.raceline.points, line.points, atol=1e-6)
    rev = back.reversed()
    assert rev.raceline is not None and rev.is_reversed
    np.testing.assert_allclose(rev.raceline.points[1], line.points[-1])
    drawn = raceline_collection(back)
    assert drawn is not None and len(drawn.get_segments()) == len(line.points)
    assert raceline_collection(Track(stadium_points(30.0, 10.0, 0.5), 1.5, 1.5)) is None
    assert plot_track(back, tmp_path / "t.png").stat().st_size > 10_000


def test_raceline_with_wrong_columns_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("# s_m; x_m; y_m\n0; 1; 2\n")
    with pytest.raises(TrackError, match="row 1 has 3 columns; an F1TENTH race line has 7"):
        read_raceline(bad)


def test_wall_offsets_keep_walls_off_the_road(tmp_path: Path) -> None:
    # Walls 0.4 m outside the edges: on a built-in track the full run-off everywhere; around
    # an imported 0.6 m hairpin the inner wall would cross the bend's centre onto the road
    # beyond (offset 0.9 m > radius 0.6 m), so its run-off is shortened there.
    oval = Track(stadium_points(30.0, 10.0, 0.5), 1.5, 1.5)
    left, right = oval.wall_offsets(0.4)
    np.testing.assert_allclose(left, 1.9)
    np.testing.assert_allclose(right, 1.9)
    track = read_f1tenth(write_f1tenth_centreline(tmp_path / "h.csv", hairpin_points(0.6)))
    left, right = track.wall_offsets(0.4)
    assert (left >= track.width_left - 1e-12).all() and (right >= track.width_right).all()
    naive = track.centre + (track.width_left + 0.4)[:, None] * track.normals
    walls = track.centre + left[:, None] * track.normals
    edge = track.left_border
    # No more wall points inside the road than the road's own edge has (where the narrowed
    # inner edge meets itself at the apex); the naive offset puts many more there.
    assert track.on_road(walls, -0.02).sum() <= track.on_road(edge, -0.02).sum()
    assert track.on_road(naive, -0.02).sum() > track.on_road(edge, -0.02).sum() + 10


def test_cuts_under_five_millimetres_share_one_note(tmp_path: Path) -> None:
    # MapZoo's Spielberg (0.1 m points, slightly noisy) gave lines such as "narrowed the left
    # half-width at s=20.8-20.9 m by up to 0.00 m": cuts of 1-4 mm. They are still made, but
    # counted in one line; every listed cut shows a figure of at least 0.01 m.
    stadium_pts = stadium_points(30.0, 10.0, 0.2)  # anticlockwise: left is the inside
    kappa = Track(stadium_pts, 1.0, 1.0).curvature.max()
    fold = FOLD_FRACTION / kappa  # the inner half-width its tightest point allows
    for extra, listed in ((0.003, False), (0.05, True)):
        track = Track(stadium_pts, fold + extra, 1.0, validate=False)
        fitted, notes = fit_widths(track)
        assert fitted.width_left.min() == pytest.approx(fold, abs=1e-3)  # cut either way
        assert not any("0.00 m" in n for n in notes)
        assert any("by under 5 mm at" in n for n in notes), notes  # the two 3 mm bends
        assert any(f"by up to {extra:.2f} m" in n for n in notes) == listed, notes


@pytest.mark.parametrize("header", ["# x_m,y_m,w_tr_right_m,w_tr_left_m\n", ""])
def test_a_byte_order_mark_loses_no_point(tmp_path: Path, header: str) -> None:
    # Excel's "CSV UTF-8" and Windows editors start the file with a BOM (U+FEFF): it was
    # refused ("not a number"), and a reader looking for a header line would take the
    # first row for names and drop that point.
    pts = stadium_points(30, 8, 0.5)
    rows = "\n".join(f"{x:.6f},{y:.6f},1.2,1.2" for x, y in pts)
    path = tmp_path / "bom.csv"
    path.write_bytes(("\ufeff" + header + rows + "\n").encode("utf-8"))
    plain = tmp_path / "plain.csv"
    plain.write_text(header + rows + "\n")
    np.testing.assert_allclose(read_f1tenth(path).centre, read_f1tenth(plain).centre)
    as_json = tmp_path / "t.json"
    write_json(read_f1tenth(plain), as_json)
    bom_json = tmp_path / "bom.json"
    bom_json.write_bytes(b"\xef\xbb\xbf" + as_json.read_bytes())
    assert read_track_file(bom_json).length == pytest.approx(read_track_file(as_json).length)
