"""What :func:`leaderboard.results.store_result` keeps of a worker's result, at its edges.

Written for the survivors of a mutation run over ``leaderboard/results.py`` (``make mutate``):
defaults of a sparse car record, owner-only logs and replay events, cars the race does not
have, records per track and their holder, a robustness run's own path.
"""

from __future__ import annotations

import gzip
import json
import warnings
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select
from sqlalchemy.exc import SAWarning
from sqlalchemy.orm import Session

from leaderboard import queue
from leaderboard.models import (
    Race,
    RaceEntry,
    RaceLog,
    Submission,
    SubmissionVersion,
    TrackRecord,
)
from leaderboard.results import (
    MAX_DETAIL,
    MAX_LOG_TEXT,
    PRIVATE_CAR_FIELDS,
    fail_race,
    split_private,
    store_result,
)
from leaderboard.settings import Settings
from tests.leaderboard import factories


def _race(
    db: Session, subs: list[Submission], *, kind: str = "ranked", track: str = "oval"
) -> Race:
    race = factories.race_for(subs, kind=kind, track=track)
    db.add(race)
    db.flush()
    return race


def _store(db: Session, race: Race, result: dict, **kw: object) -> Race:
    store_result(db, race, result, **kw)  # type: ignore[arg-type]
    db.commit()
    db.expire_all()
    stored = db.get(Race, race.id)
    assert stored is not None
    return stored


def test_a_sparse_car_record_takes_the_documented_defaults(db: Session, settings: Settings) -> None:
    # The fields others read are required (agent, position, status); the rest may be absent,
    # as in a result written by an older worker.
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    full = factories.fake_result(race)["cars"][0]
    full.update(race_time=31.5, penalties=5.0, collisions=2, laps_completed=1)
    sparse = {"agent": "car_1", "position": 2, "status": "dnf", "dnf_reason": "stuck"}
    stored = _store(db, race, {"track": "oval", "cars": [full, sparse]})
    by_car = {e.car: e for e in stored.entries}
    got = by_car[1]
    assert (got.laps_completed, got.collisions, got.at_fault_collisions, got.off_track) == (
        0, 0, 0, 0,
    )  # fmt: skip
    assert (got.penalties, got.lap_times, got.race_time, got.best_lap) == (0.0, [], None, None)
    kept = by_car[0]
    assert (kept.race_time, kept.penalties, kept.collisions, kept.laps_completed) == (
        31.5, 5.0, 2, 1,
    )  # fmt: skip


def test_owner_logs_and_replay_events_are_stored_apart_from_the_public_result(
    db: Session, settings: Settings, tmp_path: Path
) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    events = [{"t": 1.5, "type": "lap", "car": 0}, {"t": 3.0, "type": "finish", "car": 0}]
    replay = tmp_path / "race.replay.json.gz"
    replay.write_bytes(gzip.compress(json.dumps({"events": events}).encode()))
    result = factories.fake_result(race, order=[0, 1], dnf={1})
    result["cars"][1]["dnf_detail"] = "Traceback: boom"  # a private field inside the result
    logs = {"car_0": {"stdout": "hello", "sandbox_mode": "bwrap"}}
    stored = _store(db, race, result, replay_path=str(replay), logs=logs)
    assert stored.events == events
    assert all("dnf_detail" not in car for car in stored.result["cars"])  # type: ignore[index]
    rows = {r.car: r for r in db.scalars(select(RaceLog).where(RaceLog.race_id == race.id))}
    assert set(rows) == {0, 1}
    assert rows[1].dnf_detail == "Traceback: boom"
    assert rows[0].output is not None and "hello" in rows[0].output
    assert rows[0].sandbox_mode == "bwrap"


def test_cars_the_race_does_not_have_are_ignored(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    result = factories.fake_result(race)
    stray = dict(result["cars"][0], agent="nature_car_0")  # an adversary, not a race entry
    nameless = {k: v for k, v in result["cars"][1].items() if k != "agent"}
    missing = dict(result["cars"][1], agent="car_7")  # no such car in this race
    result["cars"] += [stray, nameless, missing]
    stored = _store(db, race, result)
    assert sorted((e.car, e.position) for e in stored.entries) == [(0, 1), (1, 2)]


def test_a_result_without_cars_is_stored_and_rates_nobody(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    stored = _store(db, race, {"track": "oval", "error": "the simulator gave up"})
    assert stored.status == "finished" and stored.result == {
        "track": "oval",
        "error": "the simulator gave up",
    }
    assert all(e.position is None and e.status is None for e in stored.entries)
    assert all(s.races == 0 for s in db.scalars(select(Submission)))


def test_records_are_per_track_and_name_the_version_that_set_them(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)
    first = _race(db, subs, track="bean")
    _store(db, first, factories.fake_result(first, order=[0, 1]))  # bean: 21.0 and 22.0
    on_oval = _race(db, subs, track="oval")
    result = factories.fake_result(on_oval, order=[0, 1])
    for car in result["cars"]:  # slower than the bean records: a new track, new records
        car["best_lap"] += 10.0
    _store(db, on_oval, result)
    records = {(r.track, r.submission_id): r for r in db.scalars(select(TrackRecord))}
    assert records[("bean", subs[0].id)].best_lap == pytest.approx(21.0)
    assert records[("oval", subs[0].id)].best_lap == pytest.approx(31.0)
    assert records[("oval", subs[0].id)].race_id == on_oval.id
    for record in records.values():
        sub = db.get(Submission, record.submission_id)
        assert sub is not None and record.version_id == sub.active_version_id is not None


def test_an_equal_lap_leaves_the_record_with_whoever_set_it_first(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 2)
    first = _race(db, subs)
    _store(db, first, factories.fake_result(first, order=[0, 1]))
    again = _race(db, subs)
    _store(db, again, factories.fake_result(again, order=[0, 1]))  # the same laps again
    held = {r.submission_id: r.race_id for r in db.scalars(select(TrackRecord))}
    assert held == {subs[0].id: first.id, subs[1].id: first.id}


def test_a_faster_lap_moves_the_record_to_the_new_version(db: Session, settings: Settings) -> None:
    subs = factories.submissions(db, settings, 2)
    first = _race(db, subs)
    _store(db, first, factories.fake_result(first, order=[0, 1]))
    old = db.get(SubmissionVersion, subs[0].active_version_id)
    assert old is not None
    newer = SubmissionVersion(
        submission_id=subs[0].id, version=old.version + 1, status="validated",
        source=old.source, format=old.format, manifest=old.manifest, sha256="1" * 64,
    )  # fmt: skip
    db.add(newer)
    db.flush()
    faster = _race(db, subs)
    faster.entries[0].version_id = newer.id
    result = factories.fake_result(faster, order=[0, 1])
    result["cars"][0]["best_lap"] = 19.0
    _store(db, faster, result)
    record = db.scalar(select(TrackRecord).where(TrackRecord.submission_id == subs[0].id))
    assert record is not None
    assert (record.best_lap, record.version_id, record.race_id) == (19.0, newer.id, faster.id)


def test_a_robustness_run_scores_its_version_and_rates_nobody(
    db: Session, settings: Settings
) -> None:
    subs = factories.submissions(db, settings, 1)
    run = _race(db, subs, kind="robustness")
    queue.enqueue(db, run)
    db.commit()
    before = (subs[0].mu, subs[0].sigma, subs[0].races)
    car = {"agent": "car_0", "status": "finished", "position": 1, "dnf_reason": None}
    doc = {"track": "oval", "score": 2.75, "cars": [car]}
    stored = _store(db, run, doc)
    version = db.get(SubmissionVersion, subs[0].active_version_id)
    assert version is not None
    assert (version.robust_score, version.robust_race_id) == (2.75, run.id)
    assert stored.entries[0].status == "finished" and stored.entries[0].position is None
    sub = db.get(Submission, subs[0].id)
    assert sub is not None and (sub.mu, sub.sigma, sub.races) == before


def test_failing_a_validation_race_with_a_baseline_car_looks_up_no_null_version(
    db: Session, settings: Settings
) -> None:
    # The baseline opponent has no version: looking one up by a NULL key is an SQLAlchemy
    # warning today ("may raise an error in a future release"), so it must not happen.
    subs = factories.submissions(db, settings, 1)
    version = db.get(SubmissionVersion, subs[0].active_version_id)
    assert version is not None
    version.status = "pending"
    race = _race(db, subs, kind="validation")
    race.entries.append(RaceEntry(car=1, name="pursuit", source="pursuit"))
    db.flush()
    with warnings.catch_warnings():
        warnings.simplefilter("error", SAWarning)
        fail_race(db, race, "worker lost")
    db.commit()
    assert version.status == "rejected" and version.error is not None
    assert "worker lost" in version.error


# ---- owner-only fields (split_private): exact texts at the caps, labelled streams, rows --

CUT = "\n[…]\n"


def private_row(fields: dict[str, Any], agent: str = "car_0") -> dict[str, Any] | None:
    """The private row of ``agent`` when its logs are ``fields`` (None: no row)."""
    _, private = split_private({"cars": [{"agent": agent}]}, {agent: fields})
    rows = list(private.values())
    return rows[0] if rows else None


def test_a_text_at_the_cap_is_kept_whole_and_one_more_is_cut_head_and_tail() -> None:
    at_cap = "a" * (MAX_DETAIL - 1) + "z"
    row = private_row({"dnf_detail": at_cap})
    assert row is not None and row["dnf_detail"] == at_cap
    over = "h" * (MAX_DETAIL // 2) + "m" + "t" * (MAX_DETAIL // 2)  # one character over
    row = private_row({"dnf_detail": over})
    assert row is not None
    assert row["dnf_detail"] == "h" * (MAX_DETAIL // 2) + CUT + "t" * (MAX_DETAIL // 2)


def test_output_is_cut_at_its_own_cap_not_the_detail_cap() -> None:
    text = "o" * MAX_LOG_TEXT
    row = private_row({"output": text})
    assert row is not None and row["output"] == text  # 16 KiB kept whole (detail cap: 4 KiB)
    row = private_row({"output": text + "!"})
    assert row is not None
    assert row["output"] == "o" * (MAX_LOG_TEXT // 2) + CUT + "o" * (MAX_LOG_TEXT // 2 - 1) + "!"


def test_a_structured_detail_is_stored_as_its_json() -> None:
    row = private_row({"dnf_detail": {"error": "boom", "step": 3}})
    assert row is not None and row["dnf_detail"] == '{"error": "boom", "step": 3}'


@pytest.mark.parametrize("empty", [None, ""])
def test_empty_fields_make_no_row(empty: str | None) -> None:
    fields = {"dnf_detail": empty, "output": empty, "stdout": empty, "stderr": empty}
    assert private_row(fields) is None
    assert private_row({**fields, "sandbox_mode": empty}) is None


def test_stdout_and_stderr_are_labelled_in_that_order() -> None:
    row = private_row({"stderr": "warn\n", "stdout": "hello"})
    assert row is not None
    assert row["output"] == "--- stdout ---\nhello\n--- stderr ---\nwarn\n"
    row = private_row({"stderr": "only the errors"})
    assert row is not None and row["output"] == "--- stderr ---\nonly the errors"


def test_an_output_field_wins_over_the_streams() -> None:
    row = private_row({"output": "combined", "stdout": "ignored", "stderr": "ignored"})
    assert row is not None and row["output"] == "combined"


def test_worker_captures_join_head_and_tail_and_skip_what_is_missing() -> None:
    """The worker keeps a stream's first and last bytes: ``{"head", "tail", "bytes"}``."""
    both = {"head": "first lines", "tail": "last lines", "bytes": 123456}
    row = private_row({"stdout": both, "stderr": {"head": "", "tail": "only a tail", "bytes": 9}})
    assert row is not None
    assert row["output"] == (
        "--- stdout ---\nfirst lines" + CUT + "last lines\n--- stderr ---\nonly a tail"
    )
    assert private_row({"stdout": {"head": None, "tail": "", "bytes": 0}}) is None


def test_the_combined_streams_are_cut_at_the_log_cap() -> None:
    row = private_row({"stdout": "s" * MAX_LOG_TEXT})
    assert row is not None
    label = "--- stdout ---\n"
    whole = label + "s" * MAX_LOG_TEXT
    assert row["output"] == whole[: MAX_LOG_TEXT // 2] + CUT + whole[-(MAX_LOG_TEXT // 2) :]


def test_sandbox_mode_is_kept_to_16_characters() -> None:
    row = private_row({"sandbox_mode": "seccomp-fallback-without-landlock"})
    assert row == {"dnf_detail": None, "output": None, "sandbox_mode": "seccomp-fallback"}


def test_private_fields_leave_the_public_cars_and_logs_outrank_the_result() -> None:
    result = {
        "track": "oval",
        "cars": [
            {"agent": "car_0", "status": "dnf", "dnf_detail": "from the result", "laps": 1},
            {"agent": "car_1", "status": "finished", "stdout": "s", "stderr": "e"},
        ],
    }
    logs = {"car_0": {"dnf_detail": "from the logs"}}
    public, private = split_private(result, logs)
    assert public == {
        "track": "oval",
        "cars": [
            {"agent": "car_0", "status": "dnf", "laps": 1},
            {"agent": "car_1", "status": "finished"},
        ],
    }
    assert private[0]["dnf_detail"] == "from the logs"
    assert private[1]["output"] == "--- stdout ---\ns\n--- stderr ---\ne"
    assert set(PRIVATE_CAR_FIELDS) & set(public["cars"][1]) == set()


def test_only_car_agents_get_rows_indexed_by_their_number() -> None:
    logs = {  # the others come first: each is skipped, none ends the loop
        "nature_car_0": {"output": "a nature"},
        "car_x": {"output": "no number"},
        "xcar_1": {"output": "prefixed"},
        "car_3_": {"output": "suffixed"},
        "car_12": {"output": "twelve"},
    }
    public, private = split_private({"track": "oval"}, logs)
    assert public == {"track": "oval"}  # no cars key is added
    assert private == {12: {"dnf_detail": None, "output": "twelve", "sandbox_mode": None}}


def test_a_car_without_an_agent_name_gets_no_row() -> None:
    public, private = split_private({"cars": [{"dnf_detail": "orphan", "status": "dnf"}]})
    assert public == {"cars": [{"status": "dnf"}]}
    assert private == {}


def test_a_replay_log_without_events_gives_an_empty_timeline(
    db: Session, settings: Settings, tmp_path: Path
) -> None:
    """A readable replay log with no ``events`` key (an older writer): no events, which is
    not the same as no replay (None)."""
    subs = factories.submissions(db, settings, 2)
    race = _race(db, subs)
    replay = tmp_path / "race.replay.json.gz"
    replay.write_bytes(gzip.compress(json.dumps({"frames": []}).encode()))
    stored = _store(db, race, factories.fake_result(race), replay_path=str(replay))
    assert stored.events == []
    other = _race(db, subs)
    assert _store(db, other, factories.fake_result(other), replay_path=None).events is None
