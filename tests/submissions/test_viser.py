""".viser replays: a valid viser 1.1.1 recording, one frame per output frame, cars where the
replay log has them, hidden once out of the race."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from arena.replay import ReplayLog
from submissions.errors import SubmissionError
from submissions.viser_replay import read_viser, sample_poses, write_viser, yaw_to_wxyz
from tracks import load_track

DT = 0.05  # s between replay frames (20 Hz)


def synthetic_replay(n_frames: int = 41, out_at: int = 30) -> ReplayLog:
    """Two cars driving along the oval's centre line; car_1 retires at frame ``out_at``."""
    track = load_track("oval")
    replay = ReplayLog(
        track=track,
        dt=DT,
        cars=[
            {"agent": "car_0", "name": "alpha", "colour": [230, 57, 70]},
            {"agent": "car_1", "name": "beta", "colour": [29, 53, 87]},
        ],
        env_version="0.1",
    )
    for k in range(n_frames):
        s = np.array([0.1 * k, 0.08 * k + 1.0]) * 5
        xy = track.to_cartesian(np.stack([s, np.zeros(2)], axis=1))
        yaw = track.heading_at(s)
        poses = np.concatenate([xy, yaw[:, None]], axis=1)
        present = np.array([True, k < out_at])
        replay.add_frame(k * DT, poses, np.zeros(2), np.full(2, 5.0), present)
    return replay


def positions_by_time(doc: dict[str, Any], node: str) -> list[tuple[float, list[float]]]:
    return [
        (t, m["position"])
        for t, m in doc["messages"]
        if m["type"] == "SetPositionMessage" and m["name"] == node
    ]


def state_at(updates: list[tuple[float, Any]], t: float) -> Any:
    """The last value set at or before ``t`` (how the static player applies messages)."""
    value = None
    for ut, v in updates:
        if ut <= t + 1e-9:
            value = v
    return value


def test_one_frame_per_replay_frame(tmp_path: Path) -> None:
    replay = synthetic_replay()
    out = write_viser(replay, tmp_path / "r.viser", fps=1 / DT)
    doc = read_viser(out)
    assert doc["viserVersion"] == "1.1.1"
    assert doc["durationSeconds"] == pytest.approx(replay.n_frames * DT)
    car0 = positions_by_time(doc, "/cars/car_0")
    times = [t for t, _ in car0]
    assert len(times) == replay.n_frames  # car_0 moves every frame
    assert times == pytest.approx([k * DT for k in range(replay.n_frames)])
    poses = replay.pose_array()
    for k, (_, pos) in enumerate(car0):
        assert pos[:2] == pytest.approx(poses[k, 0, :2], abs=1e-4)
    turns = [
        (t, m["wxyz"])
        for t, m in doc["messages"]
        if m["type"] == "SetOrientationMessage" and m["name"] == "/cars/car_0"
    ]  # sent only when the heading changes: rebuild the heading at each frame time
    for k in range(replay.n_frames):
        q = np.asarray(state_at(turns, k * DT) or [1.0, 0.0, 0.0, 0.0])  # default: identity
        assert abs(q @ yaw_to_wxyz(poses[k, 0, 2])) == pytest.approx(1.0, abs=1e-4)


def test_resampled_to_the_chosen_fps(tmp_path: Path) -> None:
    replay = synthetic_replay()
    doc = read_viser(write_viser(replay, tmp_path / "r.viser", fps=30))
    duration = replay.t[-1] - replay.t[0]
    n_out = math.floor(duration * 30 + 1e-6) + 1
    assert doc["durationSeconds"] == pytest.approx(n_out / 30)
    times = [t for t, _ in positions_by_time(doc, "/cars/car_0")]
    assert len(times) == n_out
    assert np.allclose(np.diff(times), 1 / 30)
    # Midway between two replay frames the car is midway between their positions.
    _, poses = sample_poses(replay, 1 / (0.5 * DT))
    mid = 0.5 * (replay.pose_array()[0, 0, :2] + replay.pose_array()[1, 0, :2])
    assert poses[1, 0, :2] == pytest.approx(mid)


def test_retired_car_is_hidden(tmp_path: Path) -> None:
    replay = synthetic_replay(out_at=30)
    doc = read_viser(write_viser(replay, tmp_path / "r.viser", fps=1 / DT))
    vis = [
        (t, m["visible"])
        for t, m in doc["messages"]
        if m["type"] == "SetSceneNodeVisibilityMessage" and m["name"] == "/cars/car_1"
    ]
    assert state_at(vis, 29 * DT) is True
    assert state_at(vis, 30 * DT) is False
    assert max(t for t, _ in positions_by_time(doc, "/cars/car_1")) < 30 * DT


def test_scene_holds_track_and_named_cars(tmp_path: Path) -> None:
    doc = read_viser(write_viser(synthetic_replay(), tmp_path / "r.viser"))
    kinds = Counter(m["type"] for _, m in doc["messages"])
    assert kinds["MeshMessage"] >= 1  # the road surface
    assert kinds["LineSegmentsMessage"] == 3  # two kerbs and the start line
    labels = [m for _, m in doc["messages"] if m["type"] == "LabelMessage"]
    cars = {m["name"]: m["props"]["text"] for m in labels if m["name"].startswith("/cars/")}
    assert cars == {"/cars/car_0/label": "P1 alpha", "/cars/car_1/label": "P2 beta"}
    assert any(m["name"] == "/standings" for m in labels)  # the board
    # every car has a marker in its colour, larger than the car on a whole-track view
    markers = [
        m
        for _, m in doc["messages"]
        if m["type"] == "MeshMessage" and str(m.get("name", "")).endswith("/marker")
    ]
    assert len(markers) == 2


def test_real_race_replay(tmp_path: Path) -> None:
    from agents.loading import load_policy
    from arena.race import run_race

    _, replay = run_race([load_policy("pursuit"), load_policy("gap")], track="oval", laps=1)
    assert replay is not None
    saved = ReplayLog.load(replay.save(tmp_path / "race.replay.json.gz"))
    doc = read_viser(write_viser(saved, tmp_path / "race.viser", fps=1 / saved.dt))
    assert doc["durationSeconds"] == pytest.approx(saved.n_frames * saved.dt)
    assert (tmp_path / "race.viser").stat().st_size < 500_000


def test_errors(tmp_path: Path) -> None:
    empty = synthetic_replay(n_frames=0)
    with pytest.raises(SubmissionError, match="no frames"):
        write_viser(empty, tmp_path / "e.viser")
    with pytest.raises(SubmissionError, match="fps must be a positive number"):
        write_viser(synthetic_replay(), tmp_path / "e.viser", fps=0)
    (tmp_path / "junk.viser").write_bytes(b"\x10" + b"\0" * 7 + b"garbage" * 4)
    with pytest.raises(SubmissionError, match=r"not a \.viser recording"):
        read_viser(tmp_path / "junk.viser")


# ---- watching: the default view, labels, standings ----------------------------------------


def overtaking_replay() -> ReplayLog:
    """Two cars, one lap of the oval: beta starts ahead, alpha passes it at t = 1 s and wins.

    Events shaped as arena.race's recorder writes them (``lap`` with ``lap``, then ``finish``).
    """
    track = load_track("oval")
    replay = ReplayLog(
        track=track,
        dt=0.1,
        cars=[
            {"agent": "car_0", "name": "alpha", "colour": [230, 57, 70]},
            {"agent": "car_1", "name": "beta", "colour": [29, 53, 87]},
        ],
        env_version="0.1",
        laps=1,
    )
    for k in range(60):
        t = 0.1 * k
        s = np.array([-1.0 + 20.0 * t, 4.0 + 15.0 * t])  # m; alpha passes beta at t = 1
        xy = track.to_cartesian(np.stack([track.wrap_s(s), np.zeros(2)], axis=1))
        poses = np.column_stack([xy, track.heading_at(track.wrap_s(s))])
        replay.add_frame(t, poses, np.zeros(2), np.array([20.0, 15.0]), np.ones(2, dtype=bool))
    finish = (track.length + 1.0) / 20.0
    replay.add_event(finish, "lap", "car_0", lap=1, lap_time=finish)
    replay.add_event(finish, "finish", "car_0")
    return replay


def updates_of(doc: dict[str, Any], node: str) -> list[tuple[float, str]]:
    """A label's text over time: its creation, then every text update."""
    out = []
    for t, m in doc["messages"]:
        if m.get("name") != node:
            continue
        if m["type"] == "LabelMessage":
            out.append((t, m["props"]["text"]))
        elif m["type"] == "SceneNodeUpdateMessage" and "text" in m["updates"]:
            out.append((t, m["updates"]["text"]))
    return out


def test_labels_and_board_follow_the_standings(tmp_path: Path) -> None:
    replay = overtaking_replay()
    doc = read_viser(write_viser(replay, tmp_path / "r.viser", fps=10))
    alpha = updates_of(doc, "/cars/car_0/label")
    assert state_at(alpha, 0.5) == "P2 alpha"  # beta leads off the grid
    assert state_at(alpha, 1.5) == "P1 alpha"  # after the pass
    assert state_at(updates_of(doc, "/cars/car_1/label"), 1.5) == "P2 beta"
    board = updates_of(doc, "/standings")
    assert state_at(board, 0.5) == "Lap 1/1\nP1 beta  lap 1/1\nP2 alpha  lap 1/1"
    finish = (replay.track.length + 1.0) / 20.0
    assert state_at(board, finish + 0.2) == "Finished\nP1 alpha  finished\nP2 beta  lap 1/1"
    # the labels change only when the standings do: a handful of updates, not one per frame
    assert len(board) < 6


def test_lap_count_is_inferred_without_a_recorded_one(tmp_path: Path) -> None:
    replay = overtaking_replay()
    replay.laps = 0  # a log from before the field existed: the finisher's laps tell it
    saved = ReplayLog.load(replay.save(tmp_path / "r.replay.json.gz"))
    assert saved.laps == 0
    doc = read_viser(write_viser(saved, tmp_path / "r.viser", fps=10))
    assert state_at(updates_of(doc, "/standings"), 0.5).startswith("Lap 1/1\n")


@pytest.mark.parametrize("name", ["oval", "bean", "spielberg", "monza", "hairpins"])
def test_default_view_frames_the_track_and_every_car_is_large(name: str) -> None:
    """At 1280x720 the whole track is in the frame and each marker is >= 15 px long."""
    from arena.sim import CarParams
    from arena.viser_scene import fit_view, marker_length, project

    track = load_track(name)
    view = fit_view(track)
    border = np.concatenate([track.left_border, track.right_border])
    px = project(view, np.column_stack([border, np.zeros(len(border))]))
    assert px[:, 0].min() >= 0 and px[:, 0].max() <= 1280
    assert px[:, 1].min() >= 0 and px[:, 1].max() <= 720
    # the track fills the frame: at least 70 % of the width or of the height
    assert max(np.ptp(px[:, 0]) / 1280, np.ptp(px[:, 1]) / 720) > 0.7
    marker = marker_length(track, CarParams())
    for s in np.linspace(0, track.length, 24, endpoint=False):  # anywhere on the lap
        xy = track.to_cartesian(np.array([[s, 0.0]]))[0]
        yaw = float(track.heading_at(s))
        ends = np.array([[np.cos(yaw), np.sin(yaw)], [-np.cos(yaw), -np.sin(yaw)]])
        tips = np.column_stack([xy + 0.5 * marker * ends, np.zeros(2)])
        length = float(np.linalg.norm(np.diff(project(view, tips), axis=0)))
        assert length >= 15.0, (name, s, length)


@pytest.mark.parametrize("name", ["oval", "spielberg", "monza"])
def test_start_grid_labels_do_not_overlap(name: str) -> None:
    """Eight cars on the start grid (tracks' own start_grid): their labels' screen boxes
    (bottom-left anchored, ~7.5 px per character, 16 px tall at 1280x720) do not intersect."""
    from arena.viser_scene import fit_view, pole_heights, project

    track = load_track(name)
    grid = track.start_grid(8)
    heights = pole_heights(track, grid)
    anchors = project(fit_view(track), np.column_stack([grid[:, :2], heights]))
    width = 7.5 * len("P8 baseline-pursuit")
    boxes = [(x, y - 16.0, x + width, y) for x, y in anchors]
    for i in range(8):
        for j in range(i + 1, 8):
            a, b = boxes[i], boxes[j]
            overlap = a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
            assert not overlap, (name, i, j, a, b)
