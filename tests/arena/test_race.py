"""Whole races: finishing order, failing policies, ranked penalties, results and replays."""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.baselines import PursuitPolicy
from arena import ENV_VERSION
from arena.observations import ObservationLayout
from arena.race import COLLISION_PENALTY, OFF_TRACK_PENALTY, RaceResult, run_race
from arena.replay import ReplayError, ReplayLog

LAYOUT = ObservationLayout(n_rays=64, k_opponents=3)  # the env's default layout
CAR_FIELDS: dict[str, type | tuple[type, ...]] = {
    "agent": str,
    "name": str,
    "position": int,
    "status": str,
    "dnf_reason": (str, type(None)),
    "laps_completed": int,
    "lap_times": list,
    "best_lap": (float, type(None)),
    "total_time": (float, type(None)),
    "collisions": int,
    "at_fault_collisions": int,
    "off_track": int,
}


def pursuit(name: str = "pursuit") -> PursuitPolicy:
    """A pure-pursuit driver for the default layout."""
    return PursuitPolicy(LAYOUT, name=name)


class Crasher:
    """Raises on its 10th call."""

    name = "crasher"

    def reset(self, seed: int | None = None) -> None:
        self.calls = 0

    def act(self, obs: Any) -> Any:
        self.calls += 1
        if self.calls == 10:
            raise RuntimeError("boom")
        return np.array([0.0, 0.5], dtype=np.float32)


class Fixed:
    """Returns the same (possibly bad) action every step after a few good ones."""

    def __init__(self, bad: Any, name: str) -> None:
        self.bad, self.name = bad, name

    def reset(self, seed: int | None = None) -> None:
        self.calls = 0

    def act(self, obs: Any) -> Any:
        self.calls += 1
        return self.bad if self.calls > 5 else np.array([0.0, 0.5], dtype=np.float32)


class Rammer(PursuitPolicy):
    """Pure pursuit that never lifts for the car in front."""

    def _follow_speed(self, obs: Any, v: float) -> float:
        return math.inf


class Cruiser(PursuitPolicy):
    """Pure pursuit capped at 4 m/s: something to catch."""

    def _speed_limit(self, pts: Any, v: float) -> float:
        return min(4.0, super()._speed_limit(pts, v))


class Wanderer(PursuitPolicy):
    """Pure pursuit that drifts off the road for one second (steps 150–169), then recovers."""

    def reset(self, seed: int | None = None) -> None:
        self.calls = 0

    def act(self, obs: Any) -> Any:
        self.calls += 1
        action = super().act(obs)
        if 150 <= self.calls < 170:
            action[0] = -0.1
        return action


@pytest.fixture(scope="module")
def four_pursuit() -> tuple[RaceResult, ReplayLog]:
    """A one-lap race of four pure-pursuit cars on the oval, with its replay."""
    result, replay = run_race([pursuit(f"p{i}") for i in range(4)], track="oval", seed=3)
    assert replay is not None
    return result, replay


def test_four_pursuit_cars_all_finish_in_order(four_pursuit: Any) -> None:
    result, _ = four_pursuit
    cars = result.by_position()
    assert [c.position for c in cars] == [1, 2, 3, 4]
    assert all(c.status == "finished" and c.dnf_reason is None for c in cars)
    times = [c.total_time for c in cars]
    assert times == sorted(times)
    for c in cars:
        assert c.laps_completed == 1 and len(c.lap_times) == 1
        assert c.best_lap == c.lap_times[0] == c.total_time == c.race_time
        assert c.penalties == 0.0
    assert result.sim_time == pytest.approx(max(times))
    assert result.steps == round(result.sim_time * 20)


def test_a_policy_that_raises_is_retired_and_the_race_goes_on() -> None:
    result, replay = run_race([pursuit(), Crasher(), pursuit()], track="oval", seed=0)
    crasher = result.cars[1]
    assert crasher.status == "dnf" and crasher.dnf_reason == "error"
    assert crasher.position == 3
    assert [c.status for c in (result.cars[0], result.cars[2])] == ["finished", "finished"]
    assert replay is not None
    (event,) = [e for e in replay.events if e["type"] == "dnf"]
    assert event["car"] == "car_1" and event["reason"] == "error"
    assert "boom" in event["detail"]
    assert replay.poses[-1][1] is None  # the retired car is gone from the replay's frames


@pytest.mark.parametrize(
    "bad",
    [
        np.array([np.nan, 0.5]),
        np.array([0.0, np.inf]),
        np.zeros(3),
        np.zeros((2, 1)),
        "left",
        None,
    ],
    ids=["nan", "inf", "shape3", "shape2x1", "text", "none"],
)
def test_invalid_actions_retire_the_car(bad: Any) -> None:
    result, _ = run_race([pursuit(), Fixed(bad, "bad")], track="oval", seed=0, record=False)
    assert result.cars[1].status == "dnf" and result.cars[1].dnf_reason == "invalid"
    assert result.cars[0].status == "finished" and result.cars[0].position == 1


@pytest.fixture(scope="module")
def incident_races() -> dict[bool, RaceResult]:
    """The same race, ranked and not: a rear-end shunt and an off-track excursion."""
    out = {}
    for ranked in (False, True):
        policies = [
            Cruiser(LAYOUT, name="cruiser"),
            Rammer(LAYOUT, name="rammer"),
            Wanderer(LAYOUT, name="wanderer"),
        ]
        out[ranked], _ = run_race(policies, track="oval", seed=0, ranked=ranked, record=False)
    return out


def test_ranked_penalties_add_to_total_time(incident_races: dict[bool, RaceResult]) -> None:
    ranked = incident_races[True]
    cruiser, rammer, wanderer = ranked.cars
    assert rammer.at_fault_collisions >= 1 and cruiser.at_fault_collisions == 0
    assert cruiser.collisions >= 1  # being hit is a collision, not a fault
    assert wanderer.off_track >= 1
    for car in ranked.cars:
        assert car.status == "finished"
        assert car.race_time is not None and car.total_time is not None
        penalty = OFF_TRACK_PENALTY * car.off_track + COLLISION_PENALTY * car.at_fault_collisions
        assert car.penalties == pytest.approx(penalty)
        assert car.total_time == pytest.approx(car.race_time + penalty)
    by_total = sorted(ranked.cars, key=lambda c: c.total_time or math.inf)
    assert [c.position for c in by_total] == [1, 2, 3]


def test_unranked_race_has_no_penalties(incident_races: dict[bool, RaceResult]) -> None:
    unranked, ranked = incident_races[False], incident_races[True]
    for plain, penalised in zip(unranked.cars, ranked.cars, strict=True):
        assert plain.penalties == 0.0
        assert plain.total_time == plain.race_time == penalised.race_time  # same race
        assert plain.collisions == penalised.collisions
    # The penalties change the order: the rammer beats the wanderer on the road only.
    names = [c.name for c in unranked.by_position()]
    assert names.index("rammer") < names.index("wanderer")
    names = [c.name for c in ranked.by_position()]
    assert names.index("rammer") > names.index("wanderer")


def test_result_json_has_the_documented_fields(four_pursuit: Any, tmp_path: Path) -> None:
    result, _ = four_pursuit
    path = tmp_path / "result.json"
    text = result.to_json(path)
    doc = json.loads(path.read_text(encoding="utf-8"))
    assert doc == json.loads(text)
    assert doc["track"] == "oval" and doc["seed"] == 3 and doc["laps"] == 1
    assert doc["env_version"] == ENV_VERSION
    assert len(doc["cars"]) == 4
    for car in doc["cars"]:
        for key, kind in CAR_FIELDS.items():
            assert isinstance(car[key], kind), key
        assert car["status"] in ("finished", "dnf")
        assert all(isinstance(t, float) for t in car["lap_times"])
    assert sorted(c["agent"] for c in doc["cars"]) == [f"car_{i}" for i in range(4)]


def test_replay_round_trip_keeps_frames_and_events(four_pursuit: Any, tmp_path: Path) -> None:
    _, replay = four_pursuit
    path = replay.save(tmp_path / "race.replay.json.gz")
    back = ReplayLog.load(path)
    assert back.n_frames == replay.n_frames > 100
    assert back.t == replay.t
    assert back.poses == replay.poses
    assert back.steering == replay.steering and back.speed == replay.speed
    assert back.events == replay.events
    assert back.cars == replay.cars and back.dt == replay.dt
    assert (
        back.car == replay.car == {"name": "f1tenth", "length": 0.5, "width": 0.3, "height": 0.12}
    )
    assert back.env_version == ENV_VERSION
    np.testing.assert_allclose(back.track.centre, replay.track.centre, atol=1e-6)
    kinds = {e["type"] for e in back.events}
    assert {"lap", "finish"} <= kinds
    poses = back.pose_array()
    assert poses.shape == (back.n_frames, 4, 3)


def test_replays_record_the_car_they_were_raced_with() -> None:
    """A DeepRacer-car race replays with 0.26 m cars, not the default 0.5 m ones (viser)."""
    from arena.viser_scene import replay_car

    class Still:  # stands on the grid until the stuck rule retires it (4 s)
        def reset(self, seed: int | None = None) -> None:
            pass

        def act(self, obs: Any) -> Any:
            return np.zeros(2, dtype=np.float32)

    _, replay = run_race([Still()], track="oval", laps=1, env_kwargs={"car": "deepracer"})
    assert replay is not None and replay.car["name"] == "deepracer"
    assert replay_car(ReplayLog.from_dict(replay.to_dict()).car).length == pytest.approx(0.26)
    old = {k: v for k, v in replay.to_dict().items() if k != "car"}  # a log from before
    assert replay_car(ReplayLog.from_dict(old).car).length == 0.5


def write_gz(path: Path, payload: bytes) -> Path:
    """``payload`` gzip-compressed at ``path``."""
    with gzip.open(path, "wb") as fh:
        fh.write(payload)
    return path


def test_corrupt_replays_raise_replay_error(four_pursuit: Any, tmp_path: Path) -> None:
    _, replay = four_pursuit
    good = replay.to_dict()
    wrong_version = {**good, "version": 99}
    no_frames = {k: v for k, v in good.items() if k != "frames"}
    bad_track = {**good, "track": {"name": "x"}}
    bad_car = {**good, "car": {"name": "f1tenth", "length": -1.0}}
    cases = {
        "garbage.gz": b"\x00not gzip at all",
        "half.gz": gzip.compress(json.dumps(good).encode())[:200],
    }
    for name, raw in cases.items():
        (tmp_path / name).write_bytes(raw)
    write_gz(tmp_path / "text.gz", b"{not json")
    write_gz(tmp_path / "list.gz", b"[1, 2, 3]")
    for name, doc in {
        "version.gz": wrong_version,
        "frames.gz": no_frames,
        "track.gz": bad_track,
        "car.gz": bad_car,
    }.items():
        write_gz(tmp_path / name, json.dumps(doc).encode())
    names = [*cases, "text.gz", "list.gz", "version.gz", "frames.gz", "track.gz", "car.gz"]
    for name in names:
        with pytest.raises(ReplayError):
            ReplayLog.load(tmp_path / name)
    with pytest.raises(ReplayError):
        ReplayLog.load(tmp_path / "missing.replay.json.gz")
