"""The queue's and the result store's contracts, field by field.

A worker hands back a result once; what it stores is what every page and rating reads
afterwards, so each stored field, each refusal of a lost lease and each failure path is pinned
here (an outside mutation audit found most of them unchecked).
"""

from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from leaderboard import queue
from leaderboard.models import Job, Race, RaceEntry, Submission, SubmissionVersion, utcnow
from leaderboard.settings import Settings
from tests.leaderboard import factories


def _race(db: Session, subs: list[Submission], *, kind: str = "ranked", **job: int) -> Race:
    race = factories.race_for(subs, kind=kind, laps=2)
    db.add(race)
    queue.enqueue(db, race, **job)
    db.commit()
    return race


def _job(db: Session, race: Race) -> Job:
    db.expire_all()
    job = db.scalar(select(Job).where(Job.race_id == race.id))
    assert job is not None
    return job


def test_complete_stores_every_field_of_the_result(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None
    result = factories.fake_result(race, order=[1, 0])
    result["cars"][0].update(collisions=3, at_fault_collisions=2, off_track=4)
    assert queue.complete(
        db, lease, result, replay_path="r.json.gz", viser_path="r.viser", sandbox="bwrap",
        duration_s=12.5,
    )  # fmt: skip
    db.expire_all()
    stored = db.get(Race, race.id)
    assert stored is not None
    assert stored.status == "finished" and stored.error is None
    assert stored.finished_at is not None and stored.started_at is not None
    assert (stored.replay_path, stored.viser_path) == ("r.json.gz", "r.viser")
    assert (stored.sandbox, stored.duration_s) == ("bwrap", 12.5)
    assert stored.result == result
    by_car = {e.car: e for e in stored.entries}
    for car in result["cars"]:
        entry = by_car[int(car["agent"].removeprefix("car_"))]
        assert entry.position == car["position"] and entry.status == car["status"]
        assert entry.laps_completed == car["laps_completed"] == 2
        assert entry.lap_times == car["lap_times"] and len(car["lap_times"]) == 2
        assert entry.total_time == pytest.approx(car["total_time"])
        assert entry.best_lap == pytest.approx(car["best_lap"])
        assert (entry.collisions, entry.at_fault_collisions, entry.off_track) == (
            car["collisions"], car["at_fault_collisions"], car["off_track"],
        )  # fmt: skip
    assert (by_car[1].collisions, by_car[1].at_fault_collisions, by_car[1].off_track) == (3, 2, 4)
    job = _job(db, race)
    assert (job.status, job.lease_token, job.lease_expires_at, job.error) == (
        "done",
        None,
        None,
        None,
    )


def test_a_lost_lease_changes_nothing(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    lease = queue.claim(db, owner="w1", lease_s=1)
    assert lease is not None
    later = utcnow() + timedelta(seconds=30)
    taken = queue.claim(db, owner="w2", lease_s=60, now=later)
    assert taken is not None and taken.owner == "w2" and taken.expires_at > later
    assert not queue.heartbeat(db, lease, lease_s=60)
    assert not queue.complete(db, lease, factories.fake_result(race))
    assert not queue.fail(db, lease, "boom")
    job = _job(db, race)
    assert (job.status, job.lease_owner, job.lease_token) == ("leased", "w2", taken.token)
    assert job.error is None
    stored = db.get(Race, race.id)
    assert stored is not None and stored.status == "running" and stored.result is None


def test_claim_marks_the_race_running_and_takes_the_lowest_priority_oldest_first(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)
    first = _race(db, subs, priority=5)
    second = _race(db, subs, priority=5)
    urgent = _race(db, subs, priority=1)
    got = [queue.claim(db, owner="w", lease_s=30) for _ in range(3)]
    assert [g.race_id for g in got if g] == [urgent.id, first.id, second.id]
    assert queue.claim(db, owner="w", lease_s=30) is None
    stored = db.get(Race, urgent.id)
    assert stored is not None and stored.status == "running" and stored.started_at is not None


def test_fail_requeues_until_the_third_attempt_then_fails_the_race(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)  # default: three attempts
    for attempt in (1, 2, 3):
        lease = queue.claim(db, owner="w", lease_s=30)
        assert lease is not None and lease.attempt == attempt
        assert queue.fail(db, lease, "x" * 5000)
        job = _job(db, race)
        assert job.error == "x" * 2000  # capped
        assert job.lease_token is None and job.lease_expires_at is None
        want = "failed" if attempt == 3 else "queued"
        assert job.status == want
        stored = db.get(Race, race.id)
        assert stored is not None and stored.status == want
    assert queue.claim(db, owner="w", lease_s=30) is None
    assert queue.stats(db)["failed"] == 1 and queue.pending(db) == 0


def _pending_version(
    db: Session, sub: Submission, *, error: str | None = None
) -> SubmissionVersion:
    """A new pending version of ``sub`` (a copy of its newest), flushed."""
    newest = max(sub.versions, key=lambda v: v.version)
    version = SubmissionVersion(
        submission_id=sub.id, version=newest.version + 1, status="pending", error=error,
        source=newest.source, format=newest.format, manifest=newest.manifest,
    )  # fmt: skip
    db.add(version)
    db.flush()
    return version


def test_a_failed_validation_race_rejects_its_pending_versions_only(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)  # both active, their versions validated
    sub = subs[0]
    current = db.get(SubmissionVersion, sub.active_version_id)
    assert current is not None
    pending = _pending_version(db, sub)
    race = Race(
        kind="validation",
        track="oval",
        laps=1,
        entries=[
            RaceEntry(car=0, submission_id=sub.id, version_id=pending.id, name="n", source="x"),
            RaceEntry(car=1, submission_id=subs[1].id, version_id=subs[1].active_version_id,
                      name="o", source="x"),
        ],
    )  # fmt: skip
    db.add(race)
    queue.enqueue(db, race, max_attempts=1)
    db.commit()
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None
    assert queue.fail(db, lease, "sandbox crashed")
    db.expire_all()
    rejected = db.get(SubmissionVersion, pending.id)
    assert rejected is not None and rejected.status == "rejected"
    assert "sandbox crashed" in (rejected.error or "")
    other = db.get(SubmissionVersion, subs[1].active_version_id)
    assert other is not None and other.status == "validated"  # not pending: untouched
    # The submission keeps racing with its validated version.
    kept = db.get(Submission, sub.id)
    assert kept is not None and kept.status == "active" and kept.active_version_id == current.id


def test_a_failed_ranked_race_rejects_nothing(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs, max_attempts=1)
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None
    assert queue.fail(db, lease, "worker died")
    db.expire_all()
    for s in subs:
        v = db.get(SubmissionVersion, s.active_version_id)
        assert v is not None and v.status == "validated"
    stored = db.get(Race, race.id)
    assert stored is not None and stored.status == "failed" and stored.error == "worker died"


def test_a_validation_race_judges_every_pending_version_behind_a_baseline(
    db: Session, settings: Settings
) -> None:
    from leaderboard import auth, uploads

    user, _ = auth.create_user(db, name="v")
    good = uploads.add_baseline(db, settings, user=user, baseline="pursuit", name="good")
    bad = uploads.add_baseline(db, settings, user=user, baseline="gap", name="bad")
    db.commit()
    # One validation race holding a baseline car (no version) first, then both versions.
    for job in db.scalars(select(Job)):
        job.status = "done"
    race = Race(
        kind="validation",
        track="oval",
        laps=1,
        entries=[
            RaceEntry(car=0, submission_id=None, version_id=None, name="pursuit", source="p"),
            RaceEntry(car=1, submission_id=good.submission_id, version_id=good.id, name="g",
                      source="x"),
            RaceEntry(car=2, submission_id=bad.submission_id, version_id=bad.id, name="b",
                      source="x"),
        ],
    )  # fmt: skip
    db.add(race)
    queue.enqueue(db, race)
    db.commit()
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None and lease.race_id == race.id
    assert queue.complete(db, lease, factories.fake_result(race, dnf={2}))
    db.expire_all()
    assert db.get(SubmissionVersion, good.id).status == "validated"  # type: ignore[union-attr]
    assert db.get(SubmissionVersion, bad.id).status == "rejected"  # type: ignore[union-attr]
    assert db.get(Submission, good.submission_id).status == "active"  # type: ignore[union-attr]
    assert db.get(Submission, bad.submission_id).status == "rejected"  # type: ignore[union-attr]


def _validate(db: Session, entries: list[tuple[Submission, SubmissionVersion]]) -> None:
    """Run one validation race of ``entries`` (car i = entries[i]) to a clean finish."""
    for job in db.scalars(select(Job)):
        job.status = "done"
    race = Race(
        kind="validation",
        track="oval",
        laps=1,
        entries=[
            RaceEntry(car=i, submission_id=s.id, version_id=v.id, name=s.name, source="x")
            for i, (s, v) in enumerate(entries)
        ],
    )
    db.add(race)
    queue.enqueue(db, race)
    db.commit()
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None and lease.race_id == race.id
    assert queue.complete(db, lease, factories.fake_result(race))
    db.expire_all()


def test_a_validation_race_judges_only_pending_versions_and_all_of_them(
    db: Session, settings: Settings
) -> None:
    """Every car finishes cleanly. A version rejected meanwhile (say by an operator) stays
    rejected; a version judged earlier does not stop the cars after it from being judged;
    an accepted version's old error is cleared (None, not an empty string)."""
    a, b, c = factories.submissions(db, settings, 3)
    active_a = db.get(SubmissionVersion, a.active_version_id)
    assert active_a is not None
    withdrawn = _pending_version(db, b)
    withdrawn.status, withdrawn.error = "rejected", "withdrawn by an operator"
    fresh = _pending_version(db, c, error="a note from an earlier attempt")
    db.commit()
    _validate(db, [(a, active_a), (b, withdrawn), (c, fresh)])
    still = db.get(SubmissionVersion, withdrawn.id)
    assert still is not None and still.status == "rejected"
    assert still.error == "withdrawn by an operator"
    judged = db.get(SubmissionVersion, fresh.id)
    assert judged is not None and (judged.status, judged.error) == ("validated", None)
    newer = db.get(Submission, c.id)
    assert newer is not None and newer.active_version_id == fresh.id


def test_a_rejected_submission_whose_new_version_passes_races_again(
    db: Session, settings: Settings
) -> None:
    """A submission rejected for its first version becomes active once a new one validates."""
    (sub,) = factories.submissions(db, settings, 1)
    first = db.get(SubmissionVersion, sub.active_version_id)
    assert first is not None
    first.status, sub.status, sub.active_version_id = "rejected", "rejected", None
    second = _pending_version(db, sub)
    db.commit()
    _validate(db, [(sub, second)])
    again = db.get(Submission, sub.id)
    assert again is not None
    assert (again.status, again.active_version_id) == ("active", second.id)


def test_complete_stores_the_owner_logs_it_is_given(db: Session, settings: Settings) -> None:
    """``complete(logs=...)`` (a worker's ``JobResult.logs``) reaches ``race_logs``."""
    from leaderboard.models import RaceLog

    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    lease = queue.claim(db, owner="w", lease_s=30)
    assert lease is not None
    logs = {"car_1": {"output": "policy says hi", "sandbox_mode": "bwrap"}}
    assert queue.complete(db, lease, factories.fake_result(race), logs=logs)
    db.expire_all()
    rows = list(db.scalars(select(RaceLog).where(RaceLog.race_id == race.id)))
    assert [(r.car, r.output, r.sandbox_mode) for r in rows] == [(1, "policy says hi", "bwrap")]
