"""Robustness on the leaderboard: queued once per ranked version, stored unrated, shown as a
column, a second ordering and a grid on the submission page; run for real by a worker.

The unit tests store made-up runs through the real queue (:func:`tests.leaderboard.site_data.
fake_robustness`, shaped like :func:`submissions.robustness.run_robustness_job`'s documents);
the end-to-end tests run real sandboxed bundles.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from agents.robustness import GRID, NOMINAL
from arena.version import ENV_VERSION
from leaderboard import matchmaking, queue, robustness
from leaderboard.models import Job, Race, RatingHistory, Submission, SubmissionVersion
from leaderboard.settings import Settings
from leaderboard.worker import Worker, race_job
from submissions.bundle import Manifest, make_bundle
from submissions.errors import SubmissionError
from submissions.jobs import Entrant, RaceJob, run_race_job
from submissions.robustness import leaderboard_grid
from tests.leaderboard import factories
from tests.leaderboard.conftest import Account
from tests.leaderboard.site_data import fake_robustness


def run_queued_robustness(db: Session, settings: Settings) -> dict[int, float]:
    """Claim every queued job (robustness runs first, by priority) and complete the
    robustness runs with made-up results; returns version id → stored score."""
    scores: dict[int, float] = {}
    while (lease := queue.claim(db, owner="t", lease_s=60)) is not None:
        race = db.get(Race, lease.race_id)
        assert race is not None
        if race.kind != "robustness":
            queue.fail(db, lease, "not this test's")
            continue
        doc = fake_robustness(race_job(race, settings)).result
        assert queue.complete(db, lease, doc)
        scores[race.entries[0].version_id or 0] = doc["score"]
    return scores


# ---- the grid and the job --------------------------------------------------------------------


def test_the_grid_is_the_corners_of_slipstream_robustness_grid() -> None:
    points = leaderboard_grid()
    assert len(points) == 8 and len({tuple(p.values()) for p in points}) == 8
    for p in points:
        assert set(p) == set(NOMINAL)
        for name in ("friction", "motor", "steer_offset"):
            assert p[name] in (min(GRID[name]), max(GRID[name]))
        assert p["latency"] == 1.0  # GRID's middle latency, steps
    assert NOMINAL not in points  # the nominal lap is run apart, not scored in the grid


def test_a_robustness_job_takes_one_entrant_and_round_trips(tmp_path: Path) -> None:
    one = (Entrant("a", "pursuit"),)
    grid = tuple(leaderboard_grid())
    job = RaceJob("r", one, "oval", str(tmp_path), laps=1, robustness=grid)
    again = RaceJob.from_dict(job.to_dict())
    assert again == job and again.robustness == grid
    with pytest.raises(SubmissionError, match="one entrant"):
        RaceJob("r", one * 2, "oval", str(tmp_path), robustness=grid)
    with pytest.raises(SubmissionError, match="one entrant and at least one point"):
        RaceJob("r", one, "oval", str(tmp_path), robustness=())


# ---- queueing and storing --------------------------------------------------------------------


def test_each_ranked_version_is_queued_once(db: Session, settings: Settings) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=3, n_races=0)
    races = robustness.schedule_robustness(db, settings)
    db.commit()
    assert len(races) == 3
    pool = ["oval", "bean"]  # the fixture's ranked tracks
    for race in races:
        (entry,) = race.entries
        version = db.get(SubmissionVersion, entry.version_id)
        assert version is not None and version.status == "validated"
        assert race.kind == "robustness" and race.laps == 1 and race.seed == 0
        assert race.track == pool[version.id % 2] and race.car == version.car
        job = db.scalar(select(Job).where(Job.race_id == race.id))
        assert job is not None and job.priority == robustness.ROBUSTNESS_PRIORITY
        built = race_job(race, settings)
        assert built.robustness == tuple(leaderboard_grid()) and not built.record_viser
    assert robustness.schedule_robustness(db, settings) == []  # queued: not again
    # A withdrawn submission's version is not scored; a new validated version is.
    db.get(Submission, subs[0]).status = "withdrawn"  # type: ignore[union-attr]
    from leaderboard import auth, uploads

    user = auth.get_user(db, "house")
    uploads.add_baseline(db, settings, user=user, baseline="gap", name="gap-1")  # v2 of subs[1]
    db.commit()
    assert robustness.schedule_robustness(db, settings) == []  # v2 not validated yet
    factories.finish_queue(db, settings, random.Random(0))  # its validation (and the runs)
    (new,) = robustness.schedule_robustness(db, settings)
    assert new.entries[0].submission_id == subs[1]
    version = db.get(SubmissionVersion, new.entries[0].version_id)
    assert version is not None and version.version == 2


def test_a_run_is_stored_on_its_version_unrated(
    client: TestClient, db: Session, settings: Settings
) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=3, n_races=2)
    before = {s.id: (s.mu, s.sigma, s.races) for s in db.scalars(select(Submission))}
    history = db.scalar(select(func.count(RatingHistory.id)))
    robustness.schedule_robustness(db, settings)
    db.commit()
    scores = run_queued_robustness(db, settings)
    db.expire_all()
    assert len(scores) == 3
    for version_id, score in scores.items():
        version = db.get(SubmissionVersion, version_id)
        assert version is not None and version.robust_score == pytest.approx(score)
        run = db.get(Race, version.robust_race_id)
        assert run is not None and run.kind == "robustness" and run.status == "finished"
    after = {s.id: (s.mu, s.sigma, s.races) for s in db.scalars(select(Submission))}
    assert after == before and db.scalar(select(func.count(RatingHistory.id))) == history
    # The API and the page show the grid of the racing version.
    sub_id = subs[0]
    detail = client.get(f"/api/submissions/{sub_id}").json()
    rob = detail["robustness"]
    assert rob["status"] == "finished" and len(rob["points"]) == 9
    assert rob["points"][0]["perturbation"] == {k: float(v) for k, v in NOMINAL.items()}
    assert rob["score"] == pytest.approx(min(p["score"] for p in rob["points"][1:]))
    page = client.get(f"/submissions/{sub_id}").text
    assert 'id="robust-grid"' in page and f"{rob['score']:.2f} m/s" in page
    # Runs are not races: race lists leave them out unless asked for.
    listed = client.get("/api/races", params={"per_page": 200}).json()["items"]
    assert all(r["kind"] != "robustness" for r in listed)
    runs = client.get("/api/races", params={"kind": "robustness"}).json()
    assert runs["total"] == 3
    assert all(r["kind"] != "robustness" for r in detail["recent_races"])
    race_page = client.get(f"/races/{rob['race_id']}").text
    assert 'id="robustness-run"' in race_page and f"/submissions/{sub_id}#robustness" in race_page


def test_the_leaderboard_orders_by_robustness(
    client: TestClient, db: Session, settings: Settings
) -> None:
    factories.seed(db, settings, n_submissions=4, n_races=3)
    robustness.schedule_robustness(db, settings)
    db.commit()
    scores = run_queued_robustness(db, settings)
    # One submission not scored yet: it comes last.
    unscored = next(iter(scores))
    version = db.get(SubmissionVersion, unscored)
    assert version is not None
    version.robust_score = None
    db.commit()
    rows = client.get("/api/leaderboard", params={"order": "robust"}).json()["items"]
    got = [r["robust_score"] for r in rows]
    assert got[-1] is None and got[:-1] == sorted(got[:-1], reverse=True)
    assert [r["rank"] for r in rows] == [1, 2, 3, 4]
    by_rating = client.get("/api/leaderboard").json()["items"]
    assert {r["submission_id"]: r["robust_score"] for r in by_rating} == {
        r["submission_id"]: r["robust_score"] for r in rows
    }
    page = client.get("/", params={"order": "robust"}).text
    assert "<strong>robustness</strong>" in page
    for row in rows:
        if row["robust_score"] is not None:
            assert f">{row['robust_score']:.2f}</a>" in page
    assert client.get("/api/leaderboard", params={"order": "fastest"}).status_code == 422


def test_a_failed_run_is_not_queued_again(
    client: TestClient, db: Session, settings: Settings
) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=2, n_races=0)
    robustness.schedule_robustness(db, settings)
    db.commit()
    for _ in range(settings.max_attempts):
        lease = queue.claim(db, owner="t", lease_s=60)
        assert lease is not None
        queue.fail(db, lease, "the node died")
    db.expire_all()
    failed = db.scalars(select(Race).where(Race.status == "failed")).all()
    assert [r.kind for r in failed] == ["robustness"]
    assert robustness.schedule_robustness(db, settings) == []
    (sub_id,) = [s for s in subs if s == failed[0].entries[0].submission_id]
    assert client.get(f"/api/submissions/{sub_id}").json()["robustness"]["status"] == "failed"
    assert "robustness run of v1 failed: the node died" in client.get(f"/submissions/{sub_id}").text


def test_the_ladder_keeps_running_beside_robustness_runs(db: Session, settings: Settings) -> None:
    factories.seed(db, settings, n_submissions=3, n_races=0)
    robustness.schedule_robustness(db, settings)
    db.commit()
    assert queue.pending(db) == 3
    assert matchmaking.top_up(db, settings, target=2, rng=random.Random(0)) == 2


# ---- for real --------------------------------------------------------------------------------


CRASH_ON_SECOND_RESET = b'''
class Policy:
    """Drives slowly straight on, and raises when its second lap (the first grid point) starts."""

    def __init__(self, env_spec=None):
        self.resets = 0

    def reset(self, seed=None):
        self.resets += 1
        if self.resets == 2:  # reset 1 starts the nominal lap
            raise RuntimeError("boom under perturbation")

    def act(self, obs):
        return [0.0, 0.3]
'''


@pytest.mark.slow
def test_a_policy_failure_ends_the_run(tmp_path: Path) -> None:
    """A sandboxed bundle that raises at its first grid point: that lap and every later one
    score 0 with reason ``error``; the traceback stays in the owner-only field."""
    manifest = Manifest(
        name="brittle", author="tests", format="python", entry="agent.py", env_version=ENV_VERSION
    )
    bundle = make_bundle(tmp_path / "b.zip", manifest, {"agent.py": CRASH_ON_SECOND_RESET})
    grid = tuple(leaderboard_grid())
    res = run_race_job(
        RaceJob("brittle", (Entrant("b", str(bundle)),), "oval", str(tmp_path), laps=1,
                robustness=grid)
    )  # fmt: skip
    assert res.ok, res.error
    doc = res.result
    assert res.sandbox in ("bwrap", "seccomp-weak")
    nominal, *rest = doc["points"]
    assert nominal["dnf_reason"] != "error" and nominal["distance"] > 0
    assert [p["dnf_reason"] for p in rest] == ["error"] * 8 and doc["score"] == 0.0
    (car,) = doc["cars"]
    assert car["status"] == "dnf" and "boom under perturbation" in car["dnf_detail"]


@pytest.mark.slow
def test_a_worker_scores_an_uploaded_bundle(
    client: TestClient, db: Session, settings: Settings, alice: Account, bundle_zip
) -> None:
    """Upload → sandboxed validation race → sandboxed robustness run, stored and shown."""
    settings = settings.model_copy(update={"tracks": ["oval"]})
    with bundle_zip("sturdy").open("rb") as f:
        r = client.post("/api/submissions", headers=alice.headers, files={"file": ("s.zip", f)})
    assert r.status_code == 201
    sub_id = r.json()["submission_id"]
    worker = Worker(settings, workers=1)
    try:
        stats = worker.run(max_races=2)  # alone in the pool: no ranked race is drawn
    finally:
        worker.close()
    assert (stats.completed, stats.failed) == (2, 0)
    db.expire_all()
    version = db.scalar(select(SubmissionVersion).where(SubmissionVersion.submission_id == sub_id))
    assert version is not None and version.robust_score is not None
    run = db.get(Race, version.robust_race_id)
    assert run is not None and run.track == "oval" and run.sandbox in ("bwrap", "seccomp-weak")
    assert run.result is not None and len(run.result["points"]) == 9
    # The test bundle drives like pursuit: it finishes the nominal lap, and the worst corner
    # is slower than the nominal car.
    nominal = run.result["points"][0]
    assert nominal["finished"] and 0 < version.robust_score < nominal["score"]
    row = client.get("/api/leaderboard", params={"order": "robust"}).json()["items"][0]
    assert row["robust_score"] == pytest.approx(version.robust_score)
