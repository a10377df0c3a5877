"""Building the batched simulator's maps faster must not change them by a bit.

A generated training track is rebuilt every rollout of a ``--procedural`` run (its maps and
its reversed twin's), so the build is on the training path; these tests hold the shortcuts
to the plain computation: the lidar table's cells take the fine grid's projections where
their centres coincide, and the centre line's k-d tree is built with other parameters.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial import cKDTree

from arena.batch.maps import Grid, _project_cells
from tests.bench_scripts import REPO, load_bench
from tracks import Track, load_track

GENERATED = "random:2:length=100,difficulty=0.6,hairpin=0.6"  # like a training draw


@pytest.fixture(scope="module")
def track() -> Track:
    return load_track(GENERATED)


def _grids(track: Track, fine_cell: float, coarse_cell: float) -> tuple[Grid, Grid]:
    lo, hi = track.centre.min(axis=0) - 2.0, track.centre.max(axis=0) + 2.0
    return Grid.covering(lo, hi, fine_cell), Grid.covering(lo, hi, coarse_cell)


@pytest.mark.parametrize("coarse_cell", [0.2, 0.3])
def test_lidar_cells_project_exactly_as_the_track_does(
    track: Track, coarse_cell: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """0.2 m over 0.1 m (the defaults): every centre but the last row and column is a fine
    centre bit for bit and reuses its projection; 0.3 m: ``ix · 0.3`` and ``3 ix · 0.1``
    round apart, so the cells are projected anew. Both equal ``track.project`` exactly."""
    fine, coarse = _grids(track, 0.1, coarse_cell)
    fine_points, points = fine.centres(), coarse.centres()
    fine_proj = track.project(fine_points)
    expected = track.project(points)
    asked: list[int] = []
    project = Track.project

    def counting(self: Track, pts: Any) -> Any:
        asked.append(len(pts))
        return project(self, pts)

    monkeypatch.setattr(Track, "project", counting)
    s, d, segment = _project_cells(track, coarse, points, fine, fine_points, fine_proj)
    np.testing.assert_array_equal(s, expected.s)
    np.testing.assert_array_equal(d, expected.d)
    np.testing.assert_array_equal(segment, expected.segment)
    h, w = coarse.shape
    if coarse_cell == 0.2:
        assert sum(asked) <= h + w  # at most the cells past the fine grid's last row and column
    else:
        assert sum(asked) > len(points) // 2


def test_the_centre_line_tree_answers_as_scipys_default_tree(track: Track) -> None:
    """The tuned k-d tree (leaves of 32, midpoint splits, uncompacted) is still exact: the two
    nearest centre-line vertices of every map cell are the default tree's."""
    fine, _ = _grids(track, 0.1, 0.2)
    points = fine.centres()
    dist, nearest = track._tree.query(points, k=2)
    dist_ref, nearest_ref = cKDTree(track.centre).query(points, k=2)
    np.testing.assert_array_equal(nearest, nearest_ref)
    np.testing.assert_array_equal(dist, dist_ref)


def test_the_bench_holds_a_checkout_to_the_same_maps(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """``bench/map_build.py --baseline-tree`` builds in a child process on the other tree's
    packages and reports whether each map is bit for bit the same: this very tree against
    itself must be, in both directions; a folder without ``arena/`` is refused by name."""
    bench = load_bench("map_build")
    argv = ["--tracks", GENERATED, "--repeats", "1", "--clock", "cpu", "--json"]
    assert bench.main([*argv, "--baseline-tree", str(REPO)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["direction"] for r in doc["results"]] == ["forward", "reversed"]
    assert all(r["same_maps"] and r["seconds"] > 0 for r in doc["results"])
    assert doc["results"][0]["digest"] != doc["results"][1]["digest"]  # other maps reversed
    with pytest.raises(SystemExit):
        bench.main([*argv, "--baseline-tree", str(tmp_path)])
    assert "no arena/ package there" in capsys.readouterr().err
