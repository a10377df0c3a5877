"""Ratings: OpenSkill PlackettLuce over a race's finishing order, DNFs tied for last.

Each ranked race updates the (μ, σ) of every submission in it; the leaderboard sorts by the
ordinal μ − 3σ (a conservative estimate: a new submission starts at 25 − 3·25/3 = 0 and climbs
as its σ shrinks). The update happens in the caller's transaction, together with storing the
result (see :func:`leaderboard.results.store_result`), so it is applied exactly once.

>>> ranks_for([{"status": "finished", "position": 2}, {"status": "dnf", "position": 3},
...            {"status": "finished", "position": 1}, {"status": "dnf", "position": 4}])
[2, 3, 1, 3]
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import cache
from typing import Any

from openskill.models import PlackettLuce
from sqlalchemy import select
from sqlalchemy.orm import Session

from leaderboard.models import Race, RaceEntry, RatingHistory, Submission, utcnow

ORDINAL_Z = 3.0  # ordinal = μ − z·σ


@cache
def model() -> PlackettLuce:
    """The rating model (OpenSkill defaults: μ 25, σ 25/3, β 25/6, τ 25/300)."""
    return PlackettLuce()


def ordinal(mu: float, sigma: float) -> float:
    """The conservative skill estimate the leaderboard ranks by: μ − 3σ."""
    return mu - ORDINAL_Z * sigma


def ranks_for(cars: Sequence[Mapping[str, Any]]) -> list[int]:
    """Rating ranks (1 = best) for cars in the given order.

    Finishers rank by finishing position; every car that did not finish shares the rank after
    the last finisher, whatever its distance or reason (a crash and a timeout count the same).
    """
    finished = sorted(
        (int(c["position"]), i) for i, c in enumerate(cars) if c.get("status") == "finished"
    )
    ranks = [len(finished) + 1] * len(cars)
    for rank, (_, i) in enumerate(finished, start=1):
        ranks[i] = rank
    return ranks


def rate(ratings: Sequence[tuple[float, float]], ranks: Sequence[int]) -> list[tuple[float, float]]:
    """New (μ, σ) of each player after one race (one player per team; lower rank is better).

    >>> [(round(m, 2), round(s, 2)) for m, s in rate([(25, 25 / 3)] * 2, [1, 2])]
    [(27.64, 8.07), (22.36, 8.07)]
    """
    m = model()
    teams = [[m.rating(mu=mu, sigma=sigma)] for mu, sigma in ratings]
    new = m.rate(teams, ranks=list(ranks))
    return [(float(team[0].mu), float(team[0].sigma)) for team in new]


def rate_race(session: Session, race: Race) -> None:
    """Update the ratings of the submissions in a finished ranked race (entries filled in).

    Writes each entry's μ/σ before and after, the submissions' new rating, race and win
    counts, and a :class:`RatingHistory` row per submission. Entries without a submission
    (a baseline filling a grid) take part in the ranks but are not rated. The submission rows
    are locked (``FOR UPDATE`` on PostgreSQL) so concurrent results cannot lose an update.
    """
    entries = [e for e in race.entries if e.status is not None]
    ranks = ranks_for([{"status": e.status, "position": e.position} for e in entries])
    for entry, rank in zip(entries, ranks, strict=True):
        entry.rank = rank
    rated: list[tuple[RaceEntry, int]] = []
    seen: set[int] = set()
    for entry, rank in zip(entries, ranks, strict=True):
        if entry.submission_id is not None and entry.submission_id not in seen:
            seen.add(entry.submission_id)
            rated.append((entry, rank))
    if len(rated) < 2:
        return
    subs = {
        s.id: s
        for s in session.scalars(
            select(Submission)
            .where(Submission.id.in_([e.submission_id for e, _ in rated]))
            .with_for_update()
        )
    }
    before = [(subs[e.submission_id].mu, subs[e.submission_id].sigma) for e, _ in rated]  # type: ignore[index]
    after = rate(before, [rank for _, rank in rated])
    now = utcnow()
    for (entry, _), (mu0, s0), (mu1, s1) in zip(rated, before, after, strict=True):
        sub = subs[entry.submission_id]  # type: ignore[index]
        entry.mu_before, entry.sigma_before, entry.mu_after, entry.sigma_after = mu0, s0, mu1, s1
        sub.mu, sub.sigma, sub.ordinal = mu1, s1, ordinal(mu1, s1)
        sub.races += 1
        sub.wins += int(entry.status == "finished" and entry.position == 1)
        sub.updated_at = now
        session.add(
            RatingHistory(
                submission_id=sub.id,
                race_id=race.id,
                mu=mu1,
                sigma=s1,
                ordinal=sub.ordinal,
                created_at=now,
            )
        )
