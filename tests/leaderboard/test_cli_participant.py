"""``slipstream status | logs | tokens`` against a seeded leaderboard's real API.

The CLI's HTTP calls (``httpx.request``) are routed to the app in-process (a Starlette
TestClient), so the commands see exactly the server's answers without a socket. The seeded
site is :func:`tests.leaderboard.site_data.seed_site`: the house user owns the three
baselines; the fake runner stores a traceback for the ``random`` car, as a worker would.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from leaderboard.app import create_app
from leaderboard.cli import main
from tests.leaderboard.site_data import Site, seed_site

SERVER = "http://testserver"


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Site:
    """Three baselines and three ranked races."""
    return seed_site(tmp_path_factory.mktemp("cli-site"), ranked=3)


@pytest.fixture
def api(site: Site, monkeypatch: pytest.MonkeyPatch) -> Iterator[TestClient]:
    """httpx.request → the app (what the CLI calls)."""
    with TestClient(create_app(site.settings)) as client:

        def request(method: str, url: str, **kwargs: Any) -> httpx.Response:
            kwargs.pop("timeout", None)
            return client.request(method, url.removeprefix(SERVER), **kwargs)

        monkeypatch.setattr(httpx, "request", request)
        yield client


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_status_lists_my_submissions_with_ranks(api: TestClient, site: Site, capsys) -> None:
    code, out, _ = _run(capsys, "status", "--server", SERVER, "--token", site.token, "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["user"] == "house"
    board = api.get("/api/leaderboard").json()["items"]
    ranks = {row["name"]: row["rank"] for row in board}
    assert {s["name"]: s["rank"] for s in doc["submissions"]} == ranks
    # the matchmaker queued the next races: they show as waiting, each one of mine
    queued = api.get("/api/races", params={"status": "queued"}).json()["items"]
    assert {r["id"] for r in doc["waiting"]} == {r["id"] for r in queued}
    code, out, _ = _run(capsys, "status", "--server", SERVER, "--token", site.token)
    assert code == 0 and "pursuit" in out and "waiting: race" in out


def test_logs_shows_my_traceback_and_output(api: TestClient, site: Site, capsys) -> None:
    race = next(
        int(j.job_id)
        for j in site.runner.jobs
        if any(e.name.startswith("random") for e in j.entrants)
    )
    code, out, _ = _run(capsys, "logs", str(race), "--server", SERVER, "--token", site.token)
    assert code == 0
    assert "dnf (time_limit)" in out and "ZeroDivisionError" in out
    assert "says hello" in out and "sandbox bwrap" in out
    sub = next(s for s in api.get("/api/leaderboard").json()["items"] if s["name"] == "gap")
    code, out, _ = _run(
        capsys,
        "logs",
        str(race),
        "--submission",
        str(sub["submission_id"]),
        "--server",
        SERVER,
        "--token",
        site.token,
        "--json",
    )
    assert code == 0 and {c["name"].split(":")[0] for c in json.loads(out)} <= {"gap"}


def test_logs_of_someone_elses_race_and_bad_token(api: TestClient, site: Site, capsys) -> None:
    from leaderboard import auth
    from leaderboard.db import make_engine, make_sessionmaker

    engine = make_engine(site.settings.db_url)
    with make_sessionmaker(engine)() as session:
        _, eve = auth.create_user(session, name="eve_cli")
        session.commit()
    engine.dispose()
    code, _, err = _run(capsys, "logs", "4", "--server", SERVER, "--token", eve)
    assert code == 2 and err.strip() == "slipstream: error: race 4 has no cars of yours"
    code, _, err = _run(capsys, "logs", "4", "--server", SERVER, "--token", "wrong")
    assert code == 2 and "401" in err and err.count("\n") == 1
    code, _, err = _run(capsys, "logs", "99999", "--server", SERVER, "--token", eve)
    assert code == 2 and "404" in err


def test_tokens_create_list_revoke(api: TestClient, site: Site, capsys) -> None:
    common = ("--server", SERVER, "--token", site.token)
    code, out, _ = _run(capsys, "tokens", "create", "--label", "laptop", *common, "--json")
    assert code == 0
    new = json.loads(out)
    code, out, _ = _run(capsys, "tokens", "list", *common, "--json")
    listed = {t["id"]: t for t in json.loads(out)}
    assert listed[new["id"]]["label"] == "laptop" and not listed[new["id"]]["revoked"]
    # the new token works, then stops working once revoked
    assert (
        api.get("/api/users/me", headers={"Authorization": f"Bearer {new['token']}"}).status_code
        == 200
    )
    code, out, _ = _run(capsys, "tokens", "revoke", str(new["id"]), *common)
    assert code == 0 and f"token {new['id']} revoked" in out
    assert (
        api.get("/api/users/me", headers={"Authorization": f"Bearer {new['token']}"}).status_code
        == 401
    )
    code, out, _ = _run(capsys, "tokens", "list", *common)
    assert code == 0 and "laptop" in out


def test_commands_need_a_token(capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SLIPSTREAM_TOKEN", raising=False)
    code, _, err = _run(capsys, "status", "--server", SERVER, "--token", "")
    assert code == 2 and "API token is needed" in err


# ---- replay and watch -------------------------------------------------------------------------


def _replay_file(tmp_path) -> Any:  # type: ignore[no-untyped-def]
    from submissions.jobs import Entrant, RaceJob
    from tests.leaderboard.site_data import fake_replay

    job = RaceJob("1", (Entrant("a", "pursuit"), Entrant("b", "gap")), "oval", str(tmp_path))
    log = fake_replay(job, seconds=1.0)
    return log, log.save(tmp_path / "r.replay.json.gz")  # type: ignore[attr-defined]


def test_replay_plays_a_log_and_serves_a_viser_file(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from submissions.viser_replay import write_viser

    log, path = _replay_file(tmp_path)
    code, out, _ = _run(capsys, "replay", str(path), "--port", "0", "--once", "--speed", "0")
    assert code == 0 and "replay of r.replay.json.gz at http://127.0.0.1:" in out
    viser = write_viser(log, tmp_path / "r.viser")
    code, out, _ = _run(capsys, "replay", str(viser), "--port", "0", "--once")
    assert code == 0 and "?playbackPath=/replay.viser" in out
    code, _, err = _run(capsys, "replay", str(tmp_path / "missing.viser"))
    assert code == 2 and "no such replay file" in err


def test_live_watcher_follows_a_real_race() -> None:
    """What ``race --watch`` does: every recorded frame of a real race reaches the scene."""
    import numpy as np

    from agents.loading import load_policy
    from arena.colours import car_colour
    from arena.race import run_race
    from arena.replay import observe
    from arena.viser_scene import LiveScene, LiveWatcher
    from tracks import load_track

    cars = [{"agent": f"car_{i}", "name": n, "colour": car_colour(i)} for i, n in enumerate("ab")]
    scene = LiveScene(load_track("oval"), cars, port=0)
    frames: list[float] = []
    watcher = LiveWatcher(scene, speed=0)
    try:
        with observe(lambda log: (watcher(log), frames.append(log.t[-1]))):
            _, replay = run_race(
                [load_policy("pursuit"), load_policy("gap")], track="oval", laps=1, record=True
            )
        assert replay is not None and frames == replay.t
        for c, node in enumerate(scene.nodes):  # each car where it was last seen
            last = next(row[c] for row in reversed(replay.poses) if row[c] is not None)
            np.testing.assert_allclose(node.position[:2], last[:2], atol=1e-6)
        # cars that finished are hidden, as on the site
        assert scene.shown == [row is not None for row in replay.poses[-1]]
    finally:
        scene.close()
