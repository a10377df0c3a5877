"""The submission page and ``/api/submissions/{id}`` (issue 13: a first view in ~10 prebuilt
statements, head to head as one SQL aggregate, the answer cached with its JSON or HTML):
what they show is checked against the rows, counted here the plain way."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from leaderboard import auth, queries
from leaderboard.models import Race, RaceEntry, Submission, User
from leaderboard.settings import Settings
from leaderboard.web import pages
from tests.leaderboard import factories

Outcome = tuple[str | None, int | None]  # a car's (status, position)


def _race(
    db: Session,
    subs: list[Submission],
    outcome: list[Outcome],
    *,
    kind: str = "ranked",
    status: str = "finished",
    baseline: Outcome | None = None,
) -> None:
    """A race of ``subs`` whose cars ended as ``outcome`` (and a house baseline car, with no
    submission, if ``baseline`` says how it ended)."""
    race = factories.race_for(subs, kind=kind)
    race.status = status
    for entry, (car_status, position) in zip(race.entries, outcome, strict=True):
        entry.status, entry.position = car_status, position
    if baseline is not None:
        race.entries.append(
            RaceEntry(
                car=len(subs),
                submission_id=None,
                name="pursuit",
                source="pursuit",
                status=baseline[0],
                position=baseline[1],
            )
        )
    db.add(race)


def _by_hand(db: Session, submission_id: int, last: int) -> dict[int, list[int]]:
    """Opponent id → [ahead, behind, both DNF] over its ``last`` finished ranked races."""
    mine = []
    for entry in db.scalars(select(RaceEntry).where(RaceEntry.submission_id == submission_id)):
        race = db.get(Race, entry.race_id)
        assert race is not None
        if race.kind == "ranked" and race.status == "finished":
            mine.append((race.id, entry.status, entry.position))
    record: dict[int, list[int]] = {}
    for race_id, status, position in sorted(mine, reverse=True)[:last]:
        race = db.get(Race, race_id)
        assert race is not None
        for other in race.entries:
            if other.submission_id is None or other.submission_id == submission_id:
                continue
            counts = record.setdefault(other.submission_id, [0, 0, 0])
            done, other_done = status == "finished", other.status == "finished"
            if done and (not other_done or (position or 0) < (other.position or 0)):
                counts[0] += 1
            elif not done and not other_done:
                counts[2] += 1
            else:
                counts[1] += 1
    return record


def test_head_to_head_counts_every_kind_of_finish(db: Session, settings: Settings) -> None:
    """DNFs (behind every finisher, two draw), cars without a position, a baseline car, and
    races that do not count (failed, queued, validation), over all races and the latest 2."""
    a, b, c, d = factories.submissions(db, settings, 4)
    _race(db, [a, b, c], [("finished", 1), ("finished", 2), ("dnf", None)])
    _race(db, [a, b, c], [("dnf", None), ("finished", 1), ("dnf", None)], baseline=("dnf", 4))
    _race(db, [c, a], [("finished", 2), ("finished", 1)], baseline=("finished", 3))
    _race(db, [a, d], [(None, None), (None, None)], status="failed")
    _race(db, [a, d], [(None, None), (None, None)], status="queued")
    _race(db, [a, d], [("finished", 1), ("finished", 2)], kind="validation")
    _race(db, [d, a, b], [("finished", 1), ("dnf", 3), ("finished", 2)])
    _race(db, [a, b], [("finished", None), ("finished", 1)])  # a missing position counts as 0
    db.commit()
    names = {s.id: s.name for s in (a, b, c, d)}
    for sub in (a, b, c, d):
        for last in (2000, 2):
            got = queries._head_to_head(db, sub.id, last)
            expected = _by_hand(db, sub.id, last)
            assert {h.submission_id: [h.wins, h.losses, h.draws] for h in got} == expected
            assert all(h.races == h.wins + h.losses + h.draws for h in got)
            assert [h.submission_id for h in got] == sorted(
                expected, key=lambda i: (-sum(expected[i]), names[i], i)
            )
    assert {h.submission_id: (h.name, h.author) for h in queries._head_to_head(db, a.id, 9)} == {
        s.id: (s.name, "house") for s in (b, c, d)
    }


def _opponent_rows(html: str) -> list[str]:
    return re.findall(r'<tr><td><a href="/submissions/\d+">.*?</tr>', html)


def test_page_lists_the_opponents_met_most_and_links_to_all(
    client: TestClient, db: Session, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(pages, "HEAD_TO_HEAD_ROWS", 2)
    subs, _ = factories.seed(db, settings, n_submissions=5, n_races=8)
    met = {sid: queries._head_to_head(db, sid, 2000) for sid in subs}
    sid = max(subs, key=lambda s: len(met[s]))
    assert len(met[sid]) > 2
    short = client.get(f"/submissions/{sid}").text
    full = client.get(f"/submissions/{sid}?opponents=all").text
    assert len(_opponent_rows(full)) == len(met[sid])
    assert _opponent_rows(short) == _opponent_rows(full)[:2]
    for row, h in zip(_opponent_rows(full), met[sid], strict=True):
        assert f'href="/submissions/{h.submission_id}"' in row and f">{h.races}<" in row
    link = f"/submissions/{sid}?opponents=all#head-to-head"
    assert link in short and f"of {len(met[sid])}" in short
    assert link not in full
    assert client.get(f"/submissions/{sid}?opponents=some").status_code == 422


def test_signed_in_owner_gets_its_own_page_after_visitors(
    client: TestClient, db: Session, settings: Settings
) -> None:
    """Visitors share one rendering of the page; the owner's (signed in) is not that one."""
    subs, _ = factories.seed(db, settings, n_submissions=2, n_races=1)
    house = db.scalar(select(User).where(User.name == "house"))
    assert house is not None
    _, token = auth.create_token(db, user=house, label="test")
    db.commit()
    visitor = client.get(f"/submissions/{subs[0]}").text
    assert client.get(f"/submissions/{subs[0]}").text == visitor  # the cached rendering
    assert "This is yours" not in visitor
    form = client.get("/signin")
    csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)
    assert csrf is not None
    signed = client.post("/signin", data={"token": token, "csrf": csrf.group(1)})
    assert signed.status_code == 200
    owner = client.get(f"/submissions/{subs[0]}").text
    assert "This is yours" in owner and 'id="signed-in-as"' in owner
    assert _opponent_rows(owner) == _opponent_rows(visitor)


def test_api_answer_is_the_detail_and_follows_new_races(
    client: TestClient, db: Session, settings: Settings
) -> None:
    subs, _ = factories.seed(db, settings, n_submissions=3, n_races=2)

    def detail(sid: int, races: int = 20) -> object:
        db.expire_all()
        k = settings.provisional_races
        return queries._submission_detail(db, sid, races, k).model_dump(mode="json")

    for sid in subs:
        response = client.get(f"/api/submissions/{sid}")
        assert response.headers["content-type"] == "application/json"
        assert response.json() == detail(sid)
        assert client.get(f"/api/submissions/{sid}?races=1").json() == detail(sid, 1)
    before = [client.get(f"/api/submissions/{sid}").json() for sid in subs]
    factories.seed(db, settings, n_submissions=0, n_races=3, seed=1)
    after = [client.get(f"/api/submissions/{sid}").json() for sid in subs]
    assert after == [detail(sid) for sid in subs]  # not the answers cached before the races
    assert after != before
    assert client.get("/api/submissions/999999").status_code == 404


def test_race_table_counts_its_races_on_every_page(db: Session, settings: Settings) -> None:
    """The pager's total comes with the rows; a page past the end still counts them all."""
    subs, _ = factories.seed(db, settings, n_submissions=3, n_races=4)
    house = db.scalar(select(User).where(User.name == "house"))
    assert house is not None
    fresh = Submission(user_id=house.id, name="never-raced")  # no version, no race yet
    db.add(fresh)
    db.commit()
    for sid in [*subs, fresh.id]:
        every = [r.id for r in queries.submission_races(db, sid, per_page=200).items]
        assert bool(every) == (sid != fresh.id)  # validation and ranked races, or none
        for page in (1, 2, 50):
            got = queries.submission_entries(db, sid, page=page, per_page=2)
            assert got.total == len(every)
            assert [r.race_id for r in got.items] == every[(page - 1) * 2 : page * 2]
