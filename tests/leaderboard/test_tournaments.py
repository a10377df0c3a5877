"""Tournaments: planning, queueing beside the ladder, standings, the API, the pages, the
command line, and a worker running a real one.

Results of the unit tests are stored through the real queue with made-up race results
(:func:`tests.leaderboard.factories.fake_result`, cars finishing in a chosen order); the
end-to-end test races a sandboxed bundle against a baseline.
"""

from __future__ import annotations

import json
import random
from collections import Counter
from itertools import combinations
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from leaderboard import matchmaking, queue, tournaments
from leaderboard.cli import main
from leaderboard.errors import Conflict, NotFound
from leaderboard.models import (
    Job,
    Race,
    RatingHistory,
    Submission,
    Tournament,
    TrackRecord,
)
from leaderboard.settings import Settings
from leaderboard.tournaments import (
    POINTS,
    TournamentError,
    create_tournament,
    plan_round_robin,
    points_for,
    split_heats,
)
from leaderboard.worker import Worker, race_job
from submissions.jobs import Entrant, RaceJob, run_race_job
from tests.leaderboard import factories
from tests.leaderboard.conftest import Account

ADMIN = {"Authorization": "Bearer test-admin-token-0123456789"}  # conftest's admin token


def run_tournament(
    db: Session, settings: Settings, tournament_id: int, order_of: dict[int, int]
) -> list[Race]:
    """Feed the tournament's races to the queue and complete each with cars finishing in
    ``order_of`` (submission id → strength, higher first); trials get times by strength.
    Other queued races (ranked ones) are completed too, cars in grid order. Returns the
    races in the order they ran."""
    ran: list[Race] = []
    for _ in range(200):
        tournaments.advance(db, settings, slots=2)
        db.commit()
        if db.get(Tournament, tournament_id).status == "finished":  # type: ignore[union-attr]
            return ran
        lease = queue.claim(db, owner="t", lease_s=60)
        assert lease is not None, "a running tournament with nothing to run"
        race = db.get(Race, lease.race_id)
        assert race is not None
        if race.kind != "tournament":
            assert queue.complete(db, lease, factories.fake_result(race))
            ran.append(race)
            continue
        cars = sorted(race.entries, key=lambda e: -order_of[e.submission_id or 0])
        result = factories.fake_result(race, [e.car for e in cars])
        if race.stage == "trial":  # solo: its time says how strong it is
            (car,) = result["cars"]
            lap = 30.0 - order_of[race.entries[0].submission_id or 0]
            car["lap_times"] = [lap] * race.laps
            car["best_lap"], car["total_time"] = lap, lap * race.laps
        assert queue.complete(db, lease, result)
        ran.append(race)
    raise AssertionError("the tournament did not finish")


# ---- planning ----------------------------------------------------------------------------------


def test_points_and_heat_sizes() -> None:
    assert [points_for(p, True) for p in range(1, 10)] == [*POINTS, 0]
    assert points_for(1, False) == 0 and points_for(None, True) == 0
    for n in range(2, 40):
        for size in range(2, 9):
            sizes = split_heats(n, size)
            assert sum(sizes) == n and min(sizes) >= 2  # nobody races alone
            odd_duels = size == 2 and n % 2 == 1 and sizes.count(3) == 1  # one heat of 3
            assert max(sizes) <= size or (odd_duels and max(sizes) == 3)
            assert max(sizes) - min(sizes) <= 1


def test_round_robin_races_everyone_once_per_round_and_mixes_them() -> None:
    plan = plan_round_robin(9, rounds=6, heat_size=4, seed=3)
    met: Counter[frozenset[int]] = Counter()
    for heats in plan:
        assert sorted(i for heat in heats for i in heat) == list(range(9))
        assert sorted(len(h) for h in heats) == [3, 3, 3]
        for heat in heats:
            met.update(frozenset(p) for p in combinations(heat, 2))
    assert len(met) > 9 * 2  # groups change: far more pairs meet than one fixed grouping's 9
    assert plan == plan_round_robin(9, rounds=6, heat_size=4, seed=3)  # seeded
    # Everyone in one heat: the grid rotates, each entrant on pole once in n rounds.
    poles = [heats[0][0] for heats in plan_round_robin(4, rounds=4, heat_size=4)]
    assert sorted(poles) == [0, 1, 2, 3]


# ---- creating ----------------------------------------------------------------------------------


def test_creating_checks_what_it_is_given(db: Session, settings: Settings) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=4, n_races=0)
    ok = {"name": "cup", "entrants": subs[:2]}
    for bad, err in [
        ({"tracks": ["atlantis"]}, "unknown track"),
        ({"fmt": "knockout"}, "format"),
        ({"laps": 0}, "laps"),
        ({"heat_size": 9}, "heat size"),
        ({"seeds": []}, "seeds"),
        ({"top": 2}, "either"),
        ({"entrants": [subs[0]]}, "2 to 64 entrants"),
        ({"entrants": [subs[0], subs[0]]}, "twice"),
        ({"name": " "}, "name"),
        ({"seeds": list(range(20)), "tracks": ["oval", "bean"] * 11, "heat_size": 2}, "races"),
    ]:
        with pytest.raises(TournamentError, match=err):
            create_tournament(db, settings, **(ok | bad))  # type: ignore[arg-type]
    with pytest.raises(NotFound):
        create_tournament(db, settings, name="cup", entrants=[subs[0], 9999])
    db.get(Submission, subs[1]).status = "withdrawn"  # type: ignore[union-attr]
    with pytest.raises(Conflict, match="not ranked"):
        create_tournament(db, settings, name="cup", entrants=subs[:2])
    with pytest.raises(Conflict, match="different cars"):
        create_tournament(db, settings, name="cup", entrants=[subs[0], subs[2]], car="deepracer")


def test_top_n_takes_the_ladder_in_order(db: Session, settings: Settings) -> None:
    factories.seed(db, settings, n_submissions=5, n_races=6)
    from leaderboard import queries

    ladder = [r.submission_id for r in queries.leaderboard(db, max_age_s=0).items]
    cup = create_tournament(db, settings, name="top3", top=3, tracks=["oval"], seeds=[1, 2])
    db.commit()
    assert [e.submission_id for e in cup.entrants] == ladder[:3]
    assert [e.seed_rank for e in cup.entrants] == [1, 2, 3]
    races = db.scalars(select(Race).where(Race.tournament_id == cup.id)).all()
    assert len(races) == 2 and all(len(r.entries) == 3 for r in races)  # 2 rounds, 1 heat each
    assert {r.seed for r in races} == {1, 2} and {r.kind for r in races} == {"tournament"}
    assert db.scalar(select(func.count(Job.id)).where(Job.race_id.in_([r.id for r in races]))) == 0


# ---- running -----------------------------------------------------------------------------------


def test_a_round_robin_runs_beside_the_ladder_unrated(db: Session, settings: Settings) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=5, n_races=3)
    strength = {s: i for i, s in enumerate(subs)}  # the last submission is the strongest
    cup = create_tournament(
        db, settings, name="spring cup", entrants=subs, tracks=["oval", "bean"], heat_size=3
    )
    db.commit()
    # Two rounds of heats of 3 and 2; at most `slots` of them in the queue at once, and the
    # ladder's top-up does not count them.
    assert tournaments.advance(db, settings, slots=2) == 2
    db.commit()
    assert tournaments.advance(db, settings, slots=2) == 0
    assert matchmaking.top_up(db, settings, target=2, rng=random.Random(0)) == 2
    db.commit()
    ran = run_tournament(db, settings, cup.id, strength)
    kinds = [r.kind for r in ran]
    assert kinds.count("tournament") == 4 and kinds.count("ranked") == 2
    assert kinds.index("ranked") < len(kinds) - 1 - kinds[::-1].index("tournament")  # beside
    db.expire_all()
    heats = db.scalars(select(Race).where(Race.tournament_id == cup.id)).all()
    assert len(heats) == 4 and all(r.status == "finished" for r in heats)
    # Unrated: no rating change, history or record comes from a heat.
    heat_ids = [r.id for r in heats]
    for table in (RatingHistory, TrackRecord):
        assert not db.scalar(select(func.count(table.id)).where(table.race_id.in_(heat_ids)))
    assert all(e.mu_after is None and e.rank is None for r in heats for e in r.entries)
    assert db.scalar(select(func.sum(Submission.races))) == db.scalar(
        select(func.count(RatingHistory.id))
    )
    # Standings: points per place summed over the heats, by hand.
    expected: Counter[int] = Counter()
    for race in heats:
        for e in race.entries:
            expected[e.submission_id or 0] += points_for(e.position, e.status == "finished")
    detail = tournaments.tournament_detail(db, cup.id)
    assert detail.status == "finished" and detail.races_done == detail.races == 4
    assert {r.submission_id: r.points for r in detail.standings} == dict(expected)
    points = [r.points for r in detail.standings]
    assert points == sorted(points, reverse=True)
    assert detail.standings[0].submission_id == subs[-1]  # the strongest won every heat
    assert detail.standings[0].wins == 2 and detail.leader_submission_id == subs[-1]
    assert detail.final is None


def test_a_time_trial_qualifies_the_fastest_for_its_final(db: Session, settings: Settings) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=4, n_races=0)
    # Strength: subs[2] fastest, then subs[0], subs[3], subs[1].
    strength = {subs[2]: 9, subs[0]: 7, subs[3]: 5, subs[1]: 3}
    cup = create_tournament(
        db, settings, name="tt", fmt="time_trial", entrants=subs, tracks=["oval"],
        seeds=[4], laps=1, final_size=3,
    )  # fmt: skip
    db.commit()
    trials = db.scalars(select(Race).where(Race.tournament_id == cup.id)).all()
    assert [r.stage for r in trials] == ["trial"] * 4 and all(len(r.entries) == 1 for r in trials)
    assert all(race_job(r, settings).solo for r in trials)
    ran = run_tournament(db, settings, cup.id, strength)
    assert [r.stage for r in ran] == ["trial"] * 4 + ["final"]
    final = ran[-1]
    # The fastest three, the fastest on pole (car 0), on the first track and seed.
    assert [e.submission_id for e in sorted(final.entries, key=lambda e: e.car)] == [
        subs[2],
        subs[0],
        subs[3],
    ]
    assert (final.track, final.seed, final.laps) == ("oval", 4, 1)
    detail = tournaments.tournament_detail(db, cup.id)
    assert detail.status == "finished" and detail.final is not None
    assert detail.final.race_id == final.id
    table = [(r.submission_id, r.finalist, r.final_position, r.points) for r in detail.standings]
    assert table == [
        (subs[2], True, 1, 25),
        (subs[0], True, 2, 18),
        (subs[3], True, 3, 15),
        (subs[1], False, None, 0),
    ]
    times = [r.qualifying_time for r in detail.standings]
    assert times == sorted(times)  # qualifying agrees with the final here


def test_the_cached_pages_follow_every_heat(db: Session, settings: Settings) -> None:
    """The standings are cached under the tournament's progress: a view with nothing changed
    is served from the cache (the same object), and a heat started, handed back by its
    worker, finished (its result stored) or the tournament finished shows at once — the
    cached detail and list line always equal freshly computed ones."""
    subs, _ = factories.seed(db, settings, n_submissions=4, n_races=0)
    cup = create_tournament(
        db, settings, name="cached cup", entrants=subs, tracks=["oval"], seeds=[1, 2],
        heat_size=2,
    )  # fmt: skip
    db.commit()

    def view() -> tournaments.TournamentDetail:
        db.expire_all()
        cached = tournaments.tournament_detail(db, cup.id)
        assert tournaments.tournament_detail(db, cup.id) is cached  # nothing changed: a hit
        assert cached == tournaments.tournament_detail(db, cup.id, max_age_s=0.0)
        (line,) = tournaments.tournament_list(db).items
        assert tournaments.tournament_list(db).items[0] is line
        assert line == tournaments.tournament_list(db, max_age_s=0.0).items[0]
        assert (line.races_done, line.leader) == (cached.races_done, cached.leader)
        return cached

    seen = [view()]
    handed_back = False
    while seen[-1].status != "finished":
        tournaments.advance(db, settings, slots=1)
        db.commit()
        lease = queue.claim(db, owner="t", lease_s=60)
        if lease is None:  # all run: the next advance finishes it
            seen.append(view())
            continue
        race = db.get(Race, lease.race_id)
        assert race is not None
        started = view()
        assert {h.race_id: h.status for h in started.heats}[race.id] == "running"
        if not handed_back:  # a worker stopping hands the heat back: queued again
            assert queue.fail(db, lease, "worker stopped")
            handed_back = True
            assert {h.race_id: h.status for h in view().heats}[race.id] == "queued"
            continue
        cars = sorted(race.entries, key=lambda e: -subs.index(e.submission_id or 0))
        assert queue.complete(db, lease, factories.fake_result(race, [e.car for e in cars]))
        seen.append(view())
        heat = {h.race_id: h for h in seen[-1].heats}[race.id]
        assert heat.status == "finished" and sorted(c.points for c in heat.cars) == [18, 25]
    done = [s.races_done for s in seen]
    assert done == sorted(done) and done[-1] == seen[-1].races == 4 and handed_back
    assert seen[0].leader is None and seen[-1].leader_submission_id == subs[-1]
    assert sum(r.points for r in seen[-1].standings) == 4 * (25 + 18)


def test_a_solo_trial_job_races_one_car(tmp_path: Path) -> None:
    job = RaceJob(
        "trial", (Entrant("p", "pursuit"),), "oval", str(tmp_path), laps=1,
        record_viser=False, solo=True,
    )  # fmt: skip
    res = run_race_job(job)
    assert res.ok, res.error
    (car,) = res.result["cars"]
    assert car["status"] == "finished" and car["position"] == 1 and car["total_time"] > 0
    with pytest.raises(Exception, match="2 to 8 entrants"):
        RaceJob("race", job.entrants, "oval", str(tmp_path))


# ---- the API, the pages, the command line ------------------------------------------------------


def test_the_api_creates_lists_and_shows_tournaments(
    client: TestClient, db: Session, settings: Settings, alice: Account
) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=3, n_races=0)
    body = {"name": "api cup", "entrants": subs, "tracks": ["oval"], "seeds": [1, 2]}
    assert client.post("/api/tournaments", json=body).status_code == 401
    assert client.post("/api/tournaments", json=body, headers=alice.headers).status_code == 403
    bad = client.post("/api/tournaments", json=body | {"tracks": ["atlantis"]}, headers=ADMIN)
    assert bad.status_code == 422 and "unknown track" in bad.json()["detail"]
    r = client.post("/api/tournaments", json=body, headers=ADMIN)
    assert r.status_code == 201, r.text
    created = r.json()
    assert created["format"] == "round_robin" and created["races"] == 2
    assert [s["seed_rank"] for s in created["standings"]] == [1, 2, 3]
    assert client.get("/api/tournaments").json()["items"][0]["id"] == created["id"]
    tid = created["id"]
    run_tournament(db, settings, tid, {s: i for i, s in enumerate(subs)})
    doc = client.get(f"/api/tournaments/{tid}").json()
    assert doc["status"] == "finished" and doc["points"] == list(POINTS)
    assert len(doc["heats"]) == 2 and all(h["status"] == "finished" for h in doc["heats"])
    assert client.get("/api/tournaments/999").status_code == 404
    # The pages: the list, the standings, every heat with its race (and replay) link.
    listing = client.get("/tournaments").text
    assert f'href="/tournaments/{tid}"' in listing and "api cup" in listing
    page = client.get(f"/tournaments/{tid}").text
    assert 'id="standings"' in page and 'id="heats"' in page
    for heat in doc["heats"]:
        assert f'href="/races/{heat["race_id"]}"' in page
    assert "25" in page and "a car that does not finish scores 0" in page
    assert client.get("/tournaments/999").status_code == 404


def test_the_command_line_creates_and_shows_tournaments(
    db: Session, settings: Settings, capsys: pytest.CaptureFixture[str]
) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=3, n_races=3)
    data = ["--data-dir", str(settings.data_dir)]
    ids = ",".join(map(str, subs))
    code = main(
        ["tournament", "create", "--name", "cli cup", "--format", "time-trial",
         "--entrants", ids, "--tracks", "oval,bean", "--seeds", "3", "--laps", "1",
         "--final-size", "2", "--json", *data]
    )  # fmt: skip
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["format"], doc["races"], doc["final_size"]) == ("time_trial", 6, 2)
    assert main(["tournament", "list", *data]) == 0
    assert "cli cup" in capsys.readouterr().out
    assert main(["tournament", "show", str(doc["id"]), "--json", *data]) == 0
    assert json.loads(capsys.readouterr().out)["id"] == doc["id"]
    # A user error: one line on stderr, exit 2.
    code = main(
        ["tournament", "create", "--name", "x", "--top", "2", "--tracks", "atlantis", *data]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("slipstream: error: unknown track 'atlantis'")
    assert len(err.strip().splitlines()) == 1
    assert main(["tournament", "show", "999", *data]) == 2


# ---- for real ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_worker_runs_a_tournament(
    client: TestClient, db: Session, settings: Settings, alice: Account, bundle_zip
) -> None:
    """A sandboxed bundle (drives like pursuit) and the gap baseline: one round-robin heat on
    the oval, run by a worker beside nothing else, with its replay."""
    settings = settings.model_copy(update={"robustness": False})
    subs, _ = factories.seed(db, settings, n_submissions=2, n_races=0)  # pursuit-0, gap-1
    with bundle_zip("challenger").open("rb") as f:
        r = client.post("/api/submissions", headers=alice.headers, files={"file": ("c.zip", f)})
    assert r.status_code == 201
    challenger = r.json()["submission_id"]
    worker = Worker(settings, workers=1, schedule=False)
    try:
        assert worker.run(max_races=1).completed == 1  # its validation race
        cup = create_tournament(
            db, settings, name="e2e", entrants=[challenger, subs[1]], tracks=["oval"], laps=1
        )
        db.commit()
        stats = worker.run(max_races=1)
        worker.prepare()  # the next cycle marks the tournament finished
    finally:
        worker.close()
    assert (stats.completed, stats.failed) == (1, 0)
    db.expire_all()  # the worker wrote through its own sessions
    detail = tournaments.tournament_detail(db, cup.id)
    assert detail.status == "finished"
    (heat,) = detail.heats
    assert heat.status == "finished" and heat.viser_url is not None
    assert client.get(heat.viser_url).status_code == 200
    race = db.get(Race, heat.race_id)
    assert race is not None and race.sandbox in ("bwrap", "seccomp-weak")
    assert sorted(c.points for c in heat.cars) in ([0, 25], [18, 25])
    assert {r.submission_id for r in detail.standings} == {challenger, subs[1]}
