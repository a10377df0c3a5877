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
    labels = {m["props"]["text"] for _, m in doc["messages"] if m["type"] == "LabelMessage"}
    assert labels == {"alpha", "beta"}


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
