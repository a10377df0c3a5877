"""The ``raceline`` baseline: finds itself from the vector observation and drives the line.

The race line is shaped like an F1TENTH ``*_raceline.csv`` (f1tenth/f1tenth_racetracks): a
closed loop of points 0.2 m apart with a speed per point; here the centre line of the
``oval`` track moved 0.5 m to one side, at a constant 5 m/s.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.baselines import RacelinePolicy, make_baseline
from agents.policy import PolicyError
from arena import RacingEnv
from tracks import load_track
from tracks.geometry import Raceline, Track

OFFSET = 0.5  # m to the left of the centre line


def oval_with_raceline() -> Track:
    base = load_track("oval")
    s = np.arange(0.0, base.length, 0.2)
    line = base.to_cartesian(np.column_stack([s, np.full_like(s, OFFSET)]))
    track = Track(base.centre, base.width_left, base.width_right, name="oval-rl", smooth=False)
    track.raceline = Raceline(line, np.full(len(line), 5.0))
    return track


@pytest.mark.parametrize("direction", ["forward", "reverse"])
def test_raceline_baseline_follows_the_line_for_a_lap(direction: str) -> None:
    track = oval_with_raceline()
    env = RacingEnv(track=track, n_cars=1, laps=1)
    policy = make_baseline("raceline", env.layout, env.params, track=track)
    assert isinstance(policy, RacelinePolicy)
    obs, _ = env.reset(seed=0, options={"direction": direction})
    offsets, errors = [], []
    done = False
    steps = 0
    while not done:
        vector = np.asarray(obs["car_0"], dtype=np.float32)
        action = policy.act(vector)
        true = env.sim_state.poses[0]
        errors.append(float(np.hypot(*(policy.locate(vector)[:2] - true[:2]))))
        obs, _, term, trunc, infos = env.step({"car_0": action})
        done = term["car_0"] or trunc["car_0"]
        offsets.append(float(env.track.project(env.sim_state.poses[:1, :2]).d[0]))
        steps += 1
    assert infos["car_0"].get("dnf_reason") is None, infos["car_0"]
    assert term["car_0"]
    # The line lies 0.5 m left of the centre line driven forward, right of it reversed.
    side = OFFSET if direction == "forward" else -OFFSET
    assert abs(float(np.median(offsets)) - side) < 0.2
    assert float(np.median(errors)) < 0.1  # localised within 10 cm
    assert steps < 1000


def test_raceline_baseline_needs_a_race_line() -> None:
    env = RacingEnv(track="oval", n_cars=1)
    with pytest.raises(PolicyError, match="no race line"):
        make_baseline("raceline", env.layout, env.params, track=load_track("oval"))
    with pytest.raises(PolicyError, match="needs the track"):
        make_baseline("raceline", env.layout, env.params)


def test_cli_races_the_raceline_baseline_on_a_track_file_with_a_race_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from leaderboard.cli import main
    from tracks.formats import write_json

    path = tmp_path / "oval-rl.json"
    write_json(oval_with_raceline(), path)
    out = tmp_path / "result.json"
    code = main(["race", "--track", str(path), "--agents", "raceline,pursuit", "--laps", "1",
                 "--json", str(out)])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    cars = {c["name"]: c for c in json.loads(out.read_text())["cars"]}
    assert cars["raceline"]["status"] == "finished"


def test_cli_raceline_without_a_race_line_is_a_one_line_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from leaderboard.cli import EXIT_USER_ERROR, main

    code = main(["race", "--track", "oval", "--agents", "raceline", "--laps", "1"])
    assert code == EXIT_USER_ERROR
    err = capsys.readouterr().err.strip()
    assert "race line" in err and "\n" not in err


def test_cli_races_the_deepracer_car(tmp_path: Path) -> None:
    from leaderboard.cli import main

    out = tmp_path / "result.json"
    code = main(["race", "--track", "oval", "--agents", "pursuit", "--car", "deepracer",
                 "--laps", "1", "--json", str(out)])  # fmt: skip
    assert code == 0
    (car,) = json.loads(out.read_text())["cars"]
    assert car["status"] == "finished"
