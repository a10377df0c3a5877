"""Critical paths of the ranking that an outside mutation audit found untested.

Each test pins one decision that, if wrong, corrupts production data for good (ratings are
applied once and never recomputed): every submission gets exactly ``rate(before, ranks)`` for
its own rank; a live lease is never taken away; a heartbeat keeps a job unclaimable; a new
version restarts its σ; a slower lap never replaces a track record.
"""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from sqlalchemy import select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session

from leaderboard import auth, queue, uploads
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.matchmaking import RANKED_PRIORITY
from leaderboard.migrations import upgrade
from leaderboard.models import (
    SIGMA0,
    Job,
    Race,
    RaceEntry,
    Submission,
    SubmissionVersion,
    TrackRecord,
    utcnow,
)
from leaderboard.ratings import ordinal, rate
from leaderboard.results import accept_version
from leaderboard.settings import Settings
from tests.leaderboard import factories


def _race(db: Session, subs: list[Submission], cars: list[int], *, laps: int = 1) -> Race:
    """A ranked race where submission ``subs[k]`` drives car ``cars[k]``."""
    race = factories.race_for(subs, cars, laps=laps)
    db.add(race)
    queue.enqueue(db, race)
    db.commit()
    return race


def _run(db: Session, race: Race, order: list[int], dnf: set[int] | None = None) -> None:
    lease = queue.claim(db, owner="t", lease_s=30)
    assert lease is not None and lease.race_id == race.id
    assert queue.complete(db, lease, factories.fake_result(race, order=order, dnf=dnf))
    db.expire_all()


def test_each_submission_gets_exactly_rate_of_its_own_rank(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 4)
    # Distinct starting ratings, so a rating given to the wrong submission shows.
    start = [(30.0, 5.0), (25.0, SIGMA0), (20.0, 3.0), (27.0, 6.0)]
    for sub, (mu, sigma) in zip(subs, start, strict=True):
        sub.mu, sub.sigma, sub.ordinal = mu, sigma, ordinal(mu, sigma)
    db.commit()
    # Cars in an order unrelated to the submission order; car 1 retires.
    cars = [2, 0, 3, 1]
    race = _race(db, subs, cars)
    _run(db, race, order=[3, 0, 2, 1], dnf={1})
    rank_of_car = {3: 1, 0: 2, 2: 3, 1: 4}
    ranks = [rank_of_car[c] for c in cars]
    expected = rate(start, ranks)
    for sub, (mu, sigma) in zip(subs, expected, strict=True):
        got = db.get(Submission, sub.id)
        assert got is not None
        assert (got.mu, got.sigma) == pytest.approx((mu, sigma), abs=1e-9)
        assert got.ordinal == pytest.approx(ordinal(mu, sigma))


def test_a_live_lease_on_its_last_attempt_survives_expire(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, [0, 1])
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None
    job.max_attempts = 1
    db.commit()
    lease = queue.claim(db, owner="w", lease_s=60)
    assert lease is not None and lease.attempt == 1
    assert queue.expire(db) == 0  # still leased, still alive
    assert db.get(Job, lease.job_id).status == "leased"  # type: ignore[union-attr]
    # Once the lease has run out, the job has no attempt left: it fails for good.
    assert queue.expire(db, now=utcnow() + timedelta(seconds=120)) == 1
    db.expire_all()
    assert db.get(Job, lease.job_id).status == "failed"  # type: ignore[union-attr]
    # Failed is final: a later expire() finds nothing to fail again (its lease time is old).
    assert queue.expire(db, now=utcnow() + timedelta(seconds=240)) == 0


def test_an_expired_lease_with_attempts_left_is_reclaimed_not_failed(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, [0, 1])
    first = queue.claim(db, owner="w1", lease_s=1)
    assert first is not None
    later = utcnow() + timedelta(seconds=30)
    assert queue.expire(db, now=later) == 0
    second = queue.claim(db, owner="w2", lease_s=60, now=later)
    assert second is not None and second.race_id == race.id and second.attempt == 2
    # The first worker's lease is gone: its result is discarded.
    assert not queue.complete(db, first, factories.fake_result(race))


def test_a_heartbeat_keeps_the_job_unclaimable(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    _race(db, subs, [0, 1])
    lease = queue.claim(db, owner="w1", lease_s=1)
    assert lease is not None
    before = utcnow().replace(tzinfo=None)
    assert queue.heartbeat(db, lease, lease_s=600)
    beat = db.get(Job, lease.job_id)
    assert beat is not None and beat.updated_at.replace(tzinfo=None) >= before  # seen alive
    later = utcnow() + timedelta(seconds=30)
    assert queue.claim(db, owner="w2", lease_s=60, now=later) is None
    job = db.get(Job, lease.job_id)
    assert job is not None and job.lease_expires_at is not None
    assert job.lease_expires_at.replace(tzinfo=None) > later.replace(tzinfo=None)


def test_a_new_version_restarts_sigma_and_keeps_mu(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 1)
    sub = subs[0]
    sub.mu, sub.sigma = 31.0, 2.0
    sub.ordinal = ordinal(31.0, 2.0)
    current = db.get(SubmissionVersion, sub.active_version_id)
    assert current is not None
    newer = SubmissionVersion(
        submission_id=sub.id, version=current.version + 1, status="pending",
        source=current.source, format=current.format, manifest=current.manifest, sha256="0" * 64,
    )  # fmt: skip
    db.add(newer)
    db.flush()
    accept_version(db, newer)
    db.commit()
    db.expire_all()
    got = db.get(Submission, sub.id)
    assert got is not None
    assert got.active_version_id == newer.id
    assert (got.mu, got.sigma) == (31.0, SIGMA0)
    assert got.ordinal == pytest.approx(ordinal(31.0, SIGMA0))


def test_a_slower_lap_never_replaces_a_track_record(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    fast = _race(db, subs, [0, 1])
    _run(db, fast, order=[0, 1])  # car 0 wins: lap 21.0, car 1: 22.0
    record = {r.submission_id: r.best_lap for r in db.scalars(select(TrackRecord))}
    assert record == {subs[0].id: pytest.approx(21.0), subs[1].id: pytest.approx(22.0)}
    slow = _race(db, subs, [0, 1])
    _run(db, slow, order=[1, 0])  # now car 0 is second: a slower 22.0
    record = {r.submission_id: r.best_lap for r in db.scalars(select(TrackRecord))}
    assert record == {subs[0].id: pytest.approx(21.0), subs[1].id: pytest.approx(21.0)}
    held = db.scalar(select(TrackRecord).where(TrackRecord.submission_id == subs[0].id))
    assert held is not None and held.race_id == fast.id


def test_ordinal_is_mu_minus_three_sigma() -> None:
    assert ordinal(25.0, 25.0 / 3.0) == pytest.approx(0.0)
    assert ordinal(30.0, 2.0) == pytest.approx(24.0)


def test_rate_matches_openskill_for_uneven_ratings() -> None:
    from openskill.models import PlackettLuce

    start = [(30.0, 5.0), (20.0, 3.0), (27.0, 6.0)]
    model = PlackettLuce()
    want = model.rate([[model.rating(mu=m, sigma=s)] for m, s in start], ranks=[2, 1, 3])
    got = rate(start, [2, 1, 3])
    flat = [x for t in want for x in (t[0].mu, t[0].sigma)]
    assert [x for pair in got for x in pair] == pytest.approx(flat, abs=1e-12)


def test_a_baseline_in_the_grid_ranks_but_is_not_rated(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = Race(
        kind="ranked",
        track="oval",
        laps=1,
        entries=[
            RaceEntry(car=0, submission_id=subs[0].id, version_id=subs[0].active_version_id,
                      name="a", source="x"),
            RaceEntry(car=1, submission_id=None, version_id=None, name="pursuit", source="pursuit"),
            RaceEntry(car=2, submission_id=subs[1].id, version_id=subs[1].active_version_id,
                      name="b", source="x"),
        ],
    )  # fmt: skip
    db.add(race)
    queue.enqueue(db, race)
    db.commit()
    _run(db, race, order=[2, 1, 0])  # sub b wins, the baseline is second, sub a third
    expected = rate([(25.0, SIGMA0), (25.0, SIGMA0)], [3, 1])
    for sub, (mu, sigma) in zip(subs, expected, strict=True):
        got = db.get(Submission, sub.id)
        assert got is not None and (got.mu, got.sigma) == pytest.approx((mu, sigma))
        assert got.races == 1


def test_a_submission_twice_in_one_race_is_rated_once(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, [subs[0], subs[0], subs[1]], [0, 1, 2])
    _run(db, race, order=[0, 2, 1])
    got = db.get(Submission, subs[0].id)
    assert got is not None and got.races == 1 and got.wins == 1
    # Its first (best) car's rank counts: 1st against sub 1's 2nd.
    mu, sigma = rate([(25.0, SIGMA0), (25.0, SIGMA0)], [1, 2])[0]
    assert (got.mu, got.sigma) == pytest.approx((mu, sigma))


def test_races_and_wins_accumulate_and_an_all_dnf_race_has_no_winner(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)
    _run(db, _race(db, subs, [0, 1]), order=[0, 1])
    _run(db, _race(db, subs, [0, 1]), order=[0, 1])
    _run(db, _race(db, subs, [0, 1]), order=[0, 1], dnf={0, 1})
    first, second = (db.get(Submission, s.id) for s in subs)
    assert first is not None and second is not None
    assert (first.races, first.wins) == (3, 2)
    assert (second.races, second.wins) == (3, 0)


def test_queue_stats_count_every_status_from_zero(db: Session, settings: Settings) -> None:
    # What /health reports: every status, counted exactly (an absent status is 0).
    assert queue.stats(db) == {"queued": 0, "leased": 0, "done": 0, "failed": 0}
    subs = factories.submissions(db, settings, 2)  # their two validation races have run: 2 done
    assert queue.stats(db) == {"queued": 0, "leased": 0, "done": 2, "failed": 0}
    assert queue.pending(db) == 0
    for _ in range(3):
        _race(db, subs, [0, 1])
    assert queue.stats(db) == {"queued": 3, "leased": 0, "done": 2, "failed": 0}
    assert queue.pending(db) == 3
    lease = queue.claim(db, owner="w", lease_s=60)
    assert lease is not None
    assert queue.stats(db) == {"queued": 2, "leased": 1, "done": 2, "failed": 0}
    assert queue.pending(db) == 3
    # The claimed race fails on each of its 3 attempts (failed for good); the others finish.
    assert queue.fail(db, lease, "boom")
    while (nxt := queue.claim(db, owner="w", lease_s=60)) is not None:
        race = db.get(Race, nxt.race_id)
        assert race is not None
        if nxt.race_id == lease.race_id:
            assert queue.fail(db, nxt, "boom")
        else:
            assert queue.complete(db, nxt, factories.fake_result(race))
    assert queue.stats(db) == {"queued": 0, "leased": 0, "done": 4, "failed": 1}
    assert queue.pending(db) == 0


def test_a_lease_holds_up_to_its_expiry_instant(db: Session, settings: Settings) -> None:
    # Expired means strictly past the expiry time, for taking a job over and for failing it.
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, [0, 1])
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None
    job.max_attempts = 2
    db.commit()
    lease = queue.claim(db, owner="w1", lease_s=30)
    assert lease is not None
    assert queue.claim(db, owner="w2", lease_s=30, now=lease.expires_at) is None
    later = lease.expires_at + timedelta(microseconds=1)
    second = queue.claim(db, owner="w2", lease_s=30, now=later)
    assert second is not None and second.attempt == 2  # its last attempt
    assert queue.expire(db, now=second.expires_at) == 0
    assert queue.expire(db, now=second.expires_at + timedelta(microseconds=1)) == 1


def test_a_finished_job_with_a_stale_lease_time_is_never_claimed(
    db: Session, settings: Settings
) -> None:
    # Only a *leased* job can be taken over: a done job whose row still carries a lease time
    # (written by an older worker, or a manual repair) stays done.
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, [0, 1])
    _run(db, race, order=[0, 1])
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None and job.status == "done"
    job.lease_expires_at = utcnow() - timedelta(hours=1)
    db.commit()
    assert queue.claim(db, owner="w", lease_s=60) is None
    assert queue.expire(db) == 0


def test_a_validation_race_lost_on_its_last_attempt_rejects_the_version(
    db: Session, settings: Settings
) -> None:
    settings.ensure_dirs()
    user, _ = auth.create_user(db, name="lost")
    version = uploads.add_baseline(db, settings, user=user, baseline="pursuit", name="lost")
    db.commit()
    job = db.scalar(select(Job).join(Race).where(Race.kind == "validation"))
    assert job is not None
    job.max_attempts = 1
    db.commit()
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None and lease.race_id == job.race_id
    assert queue.expire(db, now=lease.expires_at + timedelta(seconds=1)) == 1
    db.expire_all()
    got = db.get(SubmissionVersion, version.id)
    assert got is not None and got.status == "rejected"
    assert got.error is not None and "failed" in got.error and "lease lost" in got.error
    sub = db.get(Submission, version.submission_id)
    assert sub is not None and sub.status == "rejected"  # it has no validated version


def test_a_race_queued_without_a_priority_is_a_ranked_one(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, [0, 1])  # enqueue(session, race): the defaults
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None and job.priority == RANKED_PRIORITY and job.max_attempts == 3


class _Flaky:
    """Stands in for ``queue._claim_once``: raises SQLite's "database is locked" ``fails``
    times, then claims for real."""

    def __init__(self, fails: int) -> None:
        self.fails, self.calls = fails, 0
        self.real = queue._claim_once

    def __call__(self, session: Session, **kw: Any) -> queue.Lease | None:
        self.calls += 1
        if self.calls <= self.fails:
            raise OperationalError("UPDATE jobs ...", {}, Exception("database is locked"))
        return self.real(session, **kw)


def test_a_locked_sqlite_claim_is_retried_with_growing_waits_then_gives_up(
    db: Session, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, [0, 1])
    waits: list[float] = []
    monkeypatch.setattr(queue.time, "sleep", waits.append)
    flaky = _Flaky(fails=2)
    monkeypatch.setattr(queue, "_claim_once", flaky)
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None and lease.race_id == race.id
    # Linear back-off in 50 ms steps: short against a writer's commit, bounded in total.
    assert flaky.calls == 3 and waits == pytest.approx([0.05, 0.10])
    # Locked every time: the error surfaces after the last retry, not a silent None.
    stuck = _Flaky(fails=10**6)
    monkeypatch.setattr(queue, "_claim_once", stuck)
    with pytest.raises(OperationalError):
        queue.claim(db, owner="w", lease_s=30)
    assert stuck.calls == queue._SQLITE_RETRIES
    assert sum(waits) < 10.0  # seconds, all retries together


def test_a_failed_claim_on_postgresql_is_not_retried(
    db: Session, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    # SKIP LOCKED never waits there: an OperationalError is a real error, raised at once.
    postgres = SimpleNamespace(dialect=SimpleNamespace(name="postgresql"))
    monkeypatch.setattr(db, "get_bind", lambda *a, **k: postgres)
    monkeypatch.setattr(queue.time, "sleep", lambda s: pytest.fail("slept before raising"))
    flaky = _Flaky(fails=1)
    monkeypatch.setattr(queue, "_claim_once", flaky)
    with pytest.raises(OperationalError):
        queue.claim(db, owner="w", lease_s=30)
    assert flaky.calls == 1


def test_a_claim_on_postgresql_takes_the_next_job_while_another_claim_holds_the_first(
    pg_url: str, tmp_path: Path
) -> None:
    # SKIP LOCKED: a worker never waits for another worker's open claim transaction. The
    # claimer gives up on any row lock after 2 s, so waiting (FOR UPDATE without SKIP LOCKED,
    # or the SQLite statement) shows as an error instead of a slow pass.
    settings = Settings(data_dir=tmp_path, tracks=["oval"], database_url=pg_url)
    engine = make_engine(pg_url)
    upgrade(pg_url, engine=engine)
    impatient = make_engine(pg_url, connect_args={"options": "-c lock_timeout=2000"})
    try:
        with make_sessionmaker(engine)() as db:
            subs = factories.submissions(db, settings, 2)
            first, second = _race(db, subs, [0, 1]).id, _race(db, subs, [0, 1]).id
        with make_sessionmaker(engine)() as holder, make_sessionmaker(impatient)() as other:
            # A worker mid-claim: the first job's row is locked until it commits.
            holder.execute(select(Job.id).where(Job.race_id == first).with_for_update()).all()
            lease = queue.claim(other, owner="w2", lease_s=60)
            assert lease is not None and lease.race_id == second
            holder.rollback()
            again = queue.claim(other, owner="w2", lease_s=60)  # the lock is gone: the first
            assert again is not None and again.race_id == first
    finally:
        impatient.dispose()
        engine.dispose()


def test_a_job_done_after_a_failed_attempt_clears_its_error(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, [0, 1])
    first = queue.claim(db, owner="w1", lease_s=60)
    assert first is not None and queue.fail(db, first, "worker crashed")
    job = db.get(Job, first.job_id)
    assert job is not None and job.status == "queued" and job.error == "worker crashed"
    second = queue.claim(db, owner="w2", lease_s=60)
    assert second is not None and second.job_id == first.job_id
    before = utcnow().replace(tzinfo=None)
    assert queue.complete(db, second, factories.fake_result(race))
    db.expire_all()
    job = db.get(Job, first.job_id)
    assert job is not None and (job.status, job.error, job.lease_token) == ("done", None, None)
    assert job.updated_at.replace(tzinfo=None) >= before
