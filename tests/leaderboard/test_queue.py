"""The queue: claims with leases, expiry, exactly-once completion, matchmaking (SQLite and
PostgreSQL)."""

from __future__ import annotations

import random
import threading
from collections import Counter
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from leaderboard import matchmaking, queue
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.migrations import upgrade
from leaderboard.models import Job, Race, RatingHistory, Submission, utcnow
from leaderboard.settings import Settings
from tests.leaderboard import factories


def _queue_ranked(db: Session, settings: Settings, n_races: int, n_subs: int = 4) -> list[Race]:
    factories.seed(db, settings, n_submissions=n_subs, n_races=0)
    races = matchmaking.schedule_ranked(db, settings, n_races, random.Random(1))
    db.commit()
    return races


def test_claims_follow_priority_then_age(db: Session, settings: Settings) -> None:
    from leaderboard import auth, uploads

    ranked = _queue_ranked(db, settings, 2)
    user, _ = auth.create_user(db, name="late")
    late = uploads.add_baseline(db, settings, user=user, baseline="random", name="late")
    db.commit()
    first = queue.claim(db, owner="w", lease_s=30)
    assert first is not None
    race = db.get(Race, first.race_id)
    assert race is not None and race.kind == "validation" and race.status == "running"
    assert any(e.version_id == late.id for e in race.entries)
    rest = [queue.claim(db, owner="w", lease_s=30) for _ in range(3)]
    assert [lease.race_id for lease in rest if lease] == [r.id for r in ranked]
    assert rest[-1] is None


def test_a_lost_lease_result_is_discarded_and_the_rating_applied_once(
    db: Session, settings: Settings
) -> None:
    (race,) = _queue_ranked(db, settings, 1)
    a = queue.claim(db, owner="a", lease_s=30)
    assert a is not None and a.attempt == 1
    # Worker a goes silent; once its lease is past, worker b takes the race over.
    later = utcnow() + timedelta(seconds=31)
    assert queue.claim(db, owner="b", lease_s=30, now=utcnow()) is None  # still held
    b = queue.claim(db, owner="b", lease_s=30, now=later)
    assert b is not None and b.job_id == a.job_id and b.attempt == 2 and b.token != a.token
    result = factories.fake_result(race)
    assert not queue.heartbeat(db, a, lease_s=30)
    assert not queue.complete(db, a, result)  # late result of the dead worker: discarded
    assert queue.complete(db, b, result)
    assert not queue.complete(db, b, result)  # a duplicate delivery changes nothing
    n_cars = len(race.entries)
    assert db.scalar(select(func.count(RatingHistory.id))) == n_cars
    assert db.scalar(select(func.sum(Submission.races))) == n_cars
    job = db.get(Job, a.job_id)
    assert job is not None and (job.status, job.attempts) == ("done", 2)


def test_leases_expire_into_failure_after_max_attempts(db: Session, settings: Settings) -> None:
    (race,) = _queue_ranked(db, settings, 1)
    now = utcnow()
    for attempt in range(settings.max_attempts):
        lease = queue.claim(db, owner="w", lease_s=1, now=now + timedelta(seconds=10 * attempt))
        assert lease is not None and lease.attempt == attempt + 1
    assert queue.claim(db, owner="w", lease_s=1, now=now + timedelta(seconds=100)) is None
    assert queue.expire(db, now=now + timedelta(seconds=100)) == 1
    db.expire_all()
    failed = db.get(Race, race.id)
    assert failed is not None and failed.status == "failed" and "lease lost" in (failed.error or "")


def test_fail_requeues_until_attempts_run_out(db: Session, settings: Settings) -> None:
    (race,) = _queue_ranked(db, settings, 1)
    for attempt in range(1, settings.max_attempts + 1):
        lease = queue.claim(db, owner="w", lease_s=30)
        assert lease is not None and lease.attempt == attempt
        assert queue.fail(db, lease, "boom")
    assert queue.claim(db, owner="w", lease_s=30) is None
    db.expire_all()
    assert db.get(Race, race.id).status == "failed"  # type: ignore[union-attr]


def _concurrent_claims(url: str, settings: Settings, n_jobs: int, n_threads: int) -> list[int]:
    engine = make_engine(url)
    upgrade(url, engine=engine)
    sessions = make_sessionmaker(engine)
    with sessions() as db:
        _queue_ranked(db, settings.model_copy(update={"database_url": url}), n_jobs)
    claimed: list[int] = []
    lock = threading.Lock()

    def work(i: int) -> None:
        with sessions() as s:
            while (lease := queue.claim(s, owner=f"t{i}", lease_s=60)) is not None:
                with lock:
                    claimed.append(lease.job_id)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    engine.dispose()
    return claimed


def test_concurrent_workers_never_share_a_job_sqlite(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, tracks=["oval"])
    claimed = _concurrent_claims(settings.db_url, settings, 12, 4)
    assert len(claimed) == 12
    assert max(Counter(claimed).values()) == 1


def test_concurrent_workers_never_share_a_job_postgresql(pg_url: str, tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, tracks=["oval"], database_url=pg_url)
    claimed = _concurrent_claims(pg_url, settings, 12, 4)
    assert len(claimed) == 12
    assert max(Counter(claimed).values()) == 1


def test_matchmaking_builds_varied_races_of_similar_ratings(
    db: Session, settings: Settings
) -> None:
    settings = settings.model_copy(update={"max_cars": 8})
    factories.seed(db, settings, n_submissions=10, n_races=0)
    # Spread the ratings: submission i has μ = 10 + 3 i.
    subs = db.scalars(select(Submission).order_by(Submission.id)).all()
    for i, s in enumerate(subs):
        s.mu, s.sigma = 10.0 + 3 * i, 2.0
    db.commit()
    races = matchmaking.schedule_ranked(db, settings, 40, random.Random(3))
    db.commit()
    assert len(races) == 40
    sizes = [len(r.entries) for r in races]
    assert min(sizes) >= 2 and max(sizes) <= 8 and len(set(sizes)) > 2
    for r in races:
        ids = [e.submission_id for e in r.entries]
        assert len(set(ids)) == len(ids)
    tracks = Counter(r.track for r in races)
    assert set(tracks) == {"oval", "bean"} and abs(tracks["oval"] - tracks["bean"]) <= 1


def test_opponents_are_drawn_near_the_seed_rating() -> None:
    pool = [
        matchmaking.Candidate(i, i, f"s{i}", "pursuit", mu=float(i), sigma=3.0, races=5, queued=0)
        for i in range(60)
    ]
    rng = random.Random(0)
    gaps = []
    for _ in range(500):
        cars = matchmaking.pick_entrants(pool, rng, min_cars=2, max_cars=2)
        gaps.append(abs(cars[0].mu - cars[1].mu))
    uniform = sum(abs(a - b) for a in range(60) for b in range(60) if a != b) / (60 * 59)
    assert sum(gaps) / len(gaps) < 0.4 * uniform  # mostly close …
    assert max(gaps) > 10  # … and now and then far (no closed groups)


def test_matchmaking_favours_underplayed_and_uncertain(db: Session, settings: Settings) -> None:
    factories.seed(db, settings, n_submissions=6, n_races=0)
    subs = db.scalars(select(Submission).order_by(Submission.id)).all()
    fresh = subs[0]
    for s in subs[1:]:
        s.races, s.sigma = 50, 2.0
    db.commit()
    pool = matchmaking.candidates(db)
    rng = random.Random(0)
    weights = {c.submission_id: c.weight for c in pool}
    assert weights[fresh.id] > 100 * max(w for k, w in weights.items() if k != fresh.id)
    counts: Counter[int] = Counter()
    for _ in range(200):
        counts.update(c.submission_id for c in matchmaking.pick_entrants(pool, rng, max_cars=2))
    assert counts[fresh.id] == max(counts.values())


def test_too_small_a_pool_schedules_nothing(db: Session, settings: Settings) -> None:
    factories.seed(db, settings, n_submissions=1, n_races=0)
    assert matchmaking.schedule_ranked(db, settings, 5) == []


@pytest.mark.parametrize("target", [0, 3])
def test_top_up_fills_the_queue_to_the_target(db: Session, settings: Settings, target: int) -> None:
    factories.seed(db, settings, n_submissions=3, n_races=0)
    matchmaking.top_up(db, settings, target, random.Random(0))
    db.commit()
    assert queue.pending(db) == target


def test_validation_is_fair_queued_per_user(db: Session, settings: Settings) -> None:
    """Issue 13: one user's five uploads in a row put five validation races ahead of every
    ranked race. Now a user's first waiting validation goes first, the rest queue with the
    ranked races in arrival order, and another user's upload still goes ahead of them."""
    from leaderboard import auth, uploads

    ranked = _queue_ranked(db, settings, 2)
    burst, _ = auth.create_user(db, name="burst")
    mine = [
        uploads.add_baseline(db, settings, user=burst, baseline="random", name=f"b{i}")
        for i in range(4)
    ]
    other, _ = auth.create_user(db, name="other")
    theirs = uploads.add_baseline(db, settings, user=other, baseline="gap", name="o")
    db.commit()

    def race_of(version_id: int) -> int:
        return int(
            db.scalar(
                select(Race.id)
                .join(Race.entries)
                .where(Race.kind == "validation")
                .where(Race.entries.any(version_id=version_id))
            )
            or 0
        )

    claimed = []
    while (lease := queue.claim(db, owner="w", lease_s=30)) is not None:
        claimed.append(lease.race_id)
    expected = [race_of(mine[0].id), race_of(theirs.id), *(r.id for r in ranked)]
    expected += [race_of(v.id) for v in mine[1:]]
    assert claimed == expected
