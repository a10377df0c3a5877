"""Local races with the baselines: every built-in track, DNFs, the result document, the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from agents.baselines import make_baseline
from agents.cli import results_table
from arena.observations import ObservationLayout
from arena.race import RESULT_SCHEMA, run_race
from arena.sim import CarParams
from leaderboard.cli import EXIT_USER_ERROR, main
from tracks import Track, list_tracks, load_track

LAYOUT = ObservationLayout(64, 3)
GRAVITY = 9.81  # m/s²


def ideal_lap_time(track: Track, car: CarParams) -> float:
    """Seconds for a lap at the limit everywhere: min(top speed, √(μ g / |κ|)) along the line."""
    limit = np.sqrt(car.friction * GRAVITY / np.maximum(np.abs(track.curvature), 1e-9))
    speed = np.minimum(car.top_speed, limit)
    return float(np.sum(track.segment_lengths / speed))


@pytest.mark.parametrize("track", list_tracks())
def test_four_pursuit_cars_finish_every_builtin_track(track: str) -> None:
    result, _ = run_race(
        [make_baseline("pursuit", LAYOUT) for _ in range(4)],
        track=track,
        laps=1,
        seed=0,
        record=False,
    )
    ideal = ideal_lap_time(load_track(track), CarParams())
    assert sorted(c.position for c in result.cars) == [1, 2, 3, 4]
    for car in result.cars:
        assert car.status == "finished", (track, car)
        assert car.laps_completed == 1
        (lap,) = car.lap_times
        # Physics floor: no lap beats the grip- and top-speed-limited time; pursuit, which
        # brakes for bends by a margin and starts from standstill, stays within 60 % of it
        # (measured 1.09-1.49x on the built-in tracks).
        assert ideal < lap < 1.6 * ideal, (track, lap, ideal)
    # Finishing order follows total time.
    ordered = result.by_position()
    times = [c.total_time for c in ordered]
    assert all(t is not None for t in times)
    assert times == sorted(times)


def test_random_car_ends_dnf_with_a_reason() -> None:
    result, _ = run_race(
        [make_baseline("pursuit", LAYOUT), make_baseline("random", LAYOUT, seed=3)],
        track="oval",
        laps=1,
        seed=1,
        record=False,
    )
    by_name = {c.name: c for c in result.cars}
    assert by_name["pursuit"].status == "finished"
    assert by_name["pursuit"].position == 1
    rnd = by_name["random"]
    assert rnd.status == "dnf"
    assert rnd.dnf_reason in ("stuck", "off_track", "flipped", "time_limit")
    assert rnd.position == 2
    assert rnd.total_time is None


def test_gap_follower_completes_a_lap() -> None:
    result, _ = run_race([make_baseline("gap", LAYOUT)], track="bean", laps=1, seed=0, record=False)
    (car,) = result.cars
    assert car.status == "finished"
    assert car.off_track == 0


def test_result_json_validates_against_schema(tmp_path: Path) -> None:
    result, replay = run_race(
        [make_baseline(n, LAYOUT, seed=2) for n in ("pursuit", "gap", "random")],
        track="technical",
        laps=1,
        seed=4,
        ranked=True,
    )
    out = tmp_path / "result.json"
    result.to_json(out)
    doc = json.loads(out.read_text())
    jsonschema.validate(doc, RESULT_SCHEMA)
    broken = json.loads(out.read_text())
    broken["cars"][0]["status"] = "won"
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(broken, RESULT_SCHEMA)
    assert replay is not None
    assert {e["type"] for e in replay.events} >= {"lap", "finish"}


def test_cli_race_table_json_and_replay(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, rep = tmp_path / "r.json", tmp_path / "r.replay.json.gz"
    code = main(
        [
            "race",
            "--track",
            "oval",
            "--agents",
            "pursuit,random",
            "--laps",
            "1",
            "--seed",
            "5",
            "--json",
            str(out),
            "--replay",
            str(rep),
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "pursuit" in printed and "finished" in printed
    doc = json.loads(out.read_text())
    jsonschema.validate(doc, RESULT_SCHEMA)
    assert rep.stat().st_size > 0


def test_cli_race_bad_agent_is_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["race", "--agents", "pursuit,no-such-driver.zip", "--laps", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_USER_ERROR
    assert len(err) == 1 and err[0].startswith("slipstream: error: ")


def test_results_table_title_counts_laps_in_english() -> None:
    # `slipstream race --laps 1` titled its table "hangar · 1 laps · seed 0".
    car = {"position": 1, "name": "pursuit", "laps_completed": 1, "best_lap": 25.75}
    car |= {"total_time": 25.75, "penalties": 0.0, "status": "finished", "dnf_reason": None}
    base = {"track": "hangar", "seed": 0, "ranked": False, "cars": [car]}
    assert results_table(base | {"laps": 1}).title == "hangar · 1 lap · seed 0"
    assert results_table(base | {"laps": 2, "ranked": True}).title == (
        "hangar · 2 laps · seed 0 · ranked"
    )


@pytest.mark.component("stable-baselines3")
def test_cli_race_says_why_a_policy_left_the_race(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A checkpoint trained on other observations (32 lidar rays) fails at its first action:
    the race goes on for the others, and the table is followed by the reason, not only
    ``dnf (error)``."""
    from agents.checkpoint import export_sb3
    from tests.agents.models import make_ppo, vector_space

    narrow = ObservationLayout(32, 3)
    ckpt = export_sb3(
        make_ppo(obs_space=vector_space(narrow)), tmp_path / "narrow.zip", name="narrow",
        env_config={"lidar_rays": 32},
    )  # fmt: skip
    assert main(["race", "--track", "oval", "--laps", "1", "--agents", f"{ckpt},pursuit"]) == 0
    out = capsys.readouterr().out
    assert "dnf (error)" in out
    assert f"expects observation shape ({narrow.size},), got ({LAYOUT.size},)" in out
    assert "narrow: dnf (error) at 0.00 s: CheckpointError" in out
