"""Ratings: OpenSkill PlackettLuce on the finishing order, DNFs tied for last, applied once."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from leaderboard import queue
from leaderboard.models import SIGMA0, Race, RaceEntry, RatingHistory, Submission, TrackRecord
from leaderboard.ratings import ordinal, ranks_for, rate
from leaderboard.settings import Settings
from tests.leaderboard import factories


def test_dnfs_tie_for_last_whatever_their_position() -> None:
    cars = [
        {"status": "dnf", "position": 4},
        {"status": "finished", "position": 2},
        {"status": "dnf", "position": 3},
        {"status": "finished", "position": 1},
    ]
    assert ranks_for(cars) == [3, 2, 3, 1]
    assert ranks_for([{"status": "dnf", "position": 1}, {"status": "dnf", "position": 2}]) == [1, 1]


def test_tied_dnfs_get_identical_updates_and_the_winner_gains() -> None:
    start = [(25.0, SIGMA0)] * 4
    new = rate(start, [1, 2, 3, 3])
    assert new[2] == pytest.approx(new[3])
    assert new[0][0] > new[1][0] > 25.0 > new[2][0]
    assert all(s < SIGMA0 for _, s in new)
    # The reference's worked example (openskill 6.2, PlackettLuce): blue, red, gold, green.
    mus = [round(m, 2) for m, _ in rate(start, [1, 2, 3, 4])]
    assert mus == [27.80, 26.55, 24.69, 20.96]


def _ranked_race(db: Session, settings: Settings, n_subs: int = 3) -> Race:
    factories.seed(db, settings, n_submissions=n_subs, n_races=0)
    subs = db.scalars(select(Submission).order_by(Submission.id)).all()
    race = Race(
        kind="ranked",
        track="oval",
        laps=2,
        entries=[
            RaceEntry(
                car=i, submission_id=s.id, version_id=s.active_version_id, name=s.name, source="x"
            )
            for i, s in enumerate(subs)
        ],
    )
    db.add(race)
    queue.enqueue(db, race)
    db.commit()
    return race


def test_result_updates_ratings_history_and_records(db: Session, settings: Settings) -> None:
    race = _ranked_race(db, settings)
    lease = queue.claim(db, owner="t", lease_s=30)
    assert lease is not None
    result = factories.fake_result(race, order=[2, 0, 1], dnf={1})
    assert queue.complete(db, lease, result)
    db.expire_all()
    subs = {s.id: s for s in db.scalars(select(Submission))}
    entries = {e.car: e for e in db.get(Race, race.id).entries}  # type: ignore[union-attr]
    assert [entries[c].rank for c in (0, 1, 2)] == [2, 3, 1]
    winner = subs[entries[2].submission_id]  # type: ignore[index]
    assert (winner.races, winner.wins) == (1, 1)
    for e in entries.values():
        sub = subs[e.submission_id]  # type: ignore[index]
        assert (e.mu_before, e.sigma_before) == (25.0, SIGMA0)
        assert (sub.mu, sub.sigma) == (e.mu_after, e.sigma_after)
        assert sub.ordinal == pytest.approx(ordinal(sub.mu, sub.sigma))
    assert db.scalar(select(func.count(RatingHistory.id))) == 3
    # Records: finishers only, best lap each.
    records = db.scalars(select(TrackRecord).order_by(TrackRecord.best_lap)).all()
    assert [r.submission_id for r in records] == [
        entries[2].submission_id,
        entries[0].submission_id,
    ]


def test_validation_race_accepts_or_rejects_the_version(db: Session, settings: Settings) -> None:
    from leaderboard import auth, uploads

    user, _ = auth.create_user(db, name="v")
    good = uploads.add_baseline(db, settings, user=user, baseline="pursuit", name="good")
    bad = uploads.add_baseline(db, settings, user=user, baseline="gap", name="bad")
    db.commit()
    for version, crash in ((good, False), (bad, True)):
        lease = queue.claim(db, owner="t", lease_s=30)
        assert lease is not None
        race = db.get(Race, lease.race_id)
        assert race is not None and race.kind == "validation"
        car = next(e.car for e in race.entries if e.version_id == version.id)
        queue.complete(db, lease, factories.fake_result(race, dnf={car} if crash else set()))
    db.expire_all()
    assert db.get(Submission, good.submission_id).status == "active"  # type: ignore[union-attr]
    rejected = db.get(Submission, bad.submission_id)
    assert rejected is not None and rejected.status == "rejected"
    assert "dnf (error)" in (db.get(type(bad), bad.id).error or "")  # type: ignore[union-attr]
    # Validation races are unrated.
    assert db.scalar(select(func.count(RatingHistory.id))) == 0


def test_provisional_submissions_rank_after_established_ones(
    db: Session, settings: Settings
) -> None:
    """Issue 13: a submission that never raced (ordinal 0) ranked above established ones with
    negative ordinals. Below k rated races it is provisional and listed after them."""
    from leaderboard import queries

    factories.seed(db, settings, n_submissions=3, n_races=0)
    veteran, newcomer, middle = db.scalars(select(Submission).order_by(Submission.id)).all()
    for sub, races, ordinal_ in ((veteran, 12, -2.0), (newcomer, 0, 0.0), (middle, 4, 5.0)):
        sub.races, sub.ordinal = races, ordinal_
    db.commit()
    rows = queries.leaderboard(db, provisional_races=5).items
    assert [(r.submission_id, r.provisional) for r in rows] == [
        (veteran.id, False),
        (middle.id, True),
        (newcomer.id, True),
    ]
    assert [queries.submission_rank(db, s) for s in (veteran, middle, newcomer)] == [1, 2, 3]
    # k = 0: nobody is provisional, the plain ordinal order.
    rows = queries.leaderboard(db, provisional_races=0).items
    assert [r.submission_id for r in rows] == [middle.id, newcomer.id, veteran.id]
    assert not any(r.provisional for r in rows)


def test_cached_head_to_head_follows_new_races(db: Session, settings: Settings) -> None:
    """The head-to-head record is cached under the submission's rated race count: every
    ranked race it finishes shows at once, and the cached record is the computed one."""
    from leaderboard import queries

    subs, _ = factories.seed(db, settings, n_submissions=3, n_races=2)
    first = queries.head_to_head(db, subs[0])
    assert first == queries._head_to_head(db, subs[0], 2000)
    factories.seed(db, settings, n_submissions=0, n_races=4, seed=1)
    db.expire_all()
    again = queries.head_to_head(db, subs[0])
    assert again == queries._head_to_head(db, subs[0], 2000)
    assert sum(h.races for h in again) > sum(h.races for h in first)
