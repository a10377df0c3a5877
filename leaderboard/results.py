"""Storing a finished race: the result JSON, each car's outcome, then its consequences.

A ranked race updates ratings (:mod:`leaderboard.ratings`) and track records; a validation
race decides whether the new version may enter ranked races; a robustness run records its
version's score (:mod:`leaderboard.robustness`); a tournament heat changes nothing else
(tournaments are unrated). Everything happens in the
caller's transaction: :func:`leaderboard.queue.complete` calls :func:`store_result` right after
it has checked the worker still holds the job's lease, and commits once.
"""

from __future__ import annotations

import gzip
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from leaderboard.models import (
    SIGMA0,
    Race,
    RaceEntry,
    RaceLog,
    Submission,
    SubmissionVersion,
    TrackRecord,
    utcnow,
)
from leaderboard.ratings import ordinal, rate_race

# DNF reasons that mean the policy itself is broken: a validation race with one fails it.
POLICY_FAILURES = frozenset({"error", "invalid", "timeout"})
_CAR = re.compile(r"^car_(\d+)$")
# DeepRacer's time penalties in ranked races, s (arena.race's constants; a test keeps them
# equal: the web process does not import the simulator).
PENALTY_SECONDS = {"off_track": 2.0, "collision": 5.0}
MAX_EVENTS = 5000  # events kept per race for the timeline
MAX_LOG_TEXT = 16 * 1024  # characters kept of a car's output (the worker keeps head + tail)
MAX_DETAIL = 4 * 1024  # characters of a DNF detail (the worker caps it at 4 KiB)
# Per-car fields of a result that only the owner may see: stored in race_logs, not in the
# public result document.
PRIVATE_CAR_FIELDS = ("dnf_detail", "output", "stdout", "stderr", "sandbox_mode")


def store_result(
    session: Session,
    race: Race,
    result: Mapping[str, Any],
    *,
    replay_path: str | None = None,
    viser_path: str | None = None,
    sandbox: str | None = None,
    duration_s: float | None = None,
    logs: Mapping[str, Mapping[str, Any]] | None = None,
) -> None:
    """Record a race result (``RaceResult.to_dict()``) and apply what follows from it.

    Args:
        session: the transaction that also marks the job done.
        race: the race, with its entries (car ``i`` is ``car_i`` in the result).
        result: the race result document.
        replay_path: the raw replay log (``.replay.json.gz``) the worker wrote.
        viser_path: the 3D replay (``.viser``), if recorded.
        sandbox: how the policies were isolated (``bwrap``, ``seccomp`` or ``none``).
        duration_s: wall time of the race, s.
        logs: owner-only logs by agent (``car_i``): ``dnf_detail``, ``output`` (or
            ``stdout``/``stderr``), ``sandbox_mode``; the same keys inside a result's car
            dicts are taken too, and removed from the stored (public) result.
    """
    public, private = split_private(result, logs)
    race.result = public
    race.events = read_events(replay_path)
    race.logs = [RaceLog(race_id=race.id, car=car, **fields) for car, fields in private.items()]
    race.status = "finished"
    race.finished_at = utcnow()
    race.replay_path = replay_path
    race.viser_path = viser_path
    race.sandbox = sandbox
    race.duration_s = duration_s
    race.error = None
    if race.kind == "robustness":  # solo laps over a grid: no placings, no rating
        # Imported here: leaderboard.robustness schedules through the queue, which imports us.
        from leaderboard.robustness import store_robustness  # noqa: PLC0415

        store_robustness(session, race)
        return
    by_car = {e.car: e for e in race.entries}
    for car in public.get("cars", []):
        match = _CAR.match(str(car.get("agent", "")))
        entry = by_car.get(int(match.group(1))) if match else None
        if entry is not None:
            _fill_entry(entry, car)
    if race.kind == "validation":
        _judge_validation(session, race)
    elif race.kind == "ranked":
        rate_race(session, race)
        _update_records(session, race)
    # Tournament heats are unrated: leaderboard.tournaments reads their entries.


def _fill_entry(entry: RaceEntry, car: Mapping[str, Any]) -> None:
    entry.position = int(car["position"])
    entry.status = str(car["status"])
    entry.dnf_reason = car.get("dnf_reason")
    entry.laps_completed = int(car.get("laps_completed", 0))
    entry.best_lap = car.get("best_lap")
    entry.total_time = car.get("total_time")
    entry.race_time = car.get("race_time")
    entry.penalties = float(car.get("penalties") or 0.0)
    entry.lap_times = [float(t) for t in car.get("lap_times", [])]
    entry.collisions = int(car.get("collisions", 0))
    entry.at_fault_collisions = int(car.get("at_fault_collisions", 0))
    entry.off_track = int(car.get("off_track", 0))


def _text(value: Any, limit: int) -> str | None:
    if value is None or value == "":
        return None
    text = value if isinstance(value, str) else json.dumps(value)
    return text if len(text) <= limit else text[: limit // 2] + "\n[…]\n" + text[-limit // 2 :]


def _output(fields: Mapping[str, Any]) -> str | None:
    """One text of a car's output: ``output``, or ``stdout`` and ``stderr`` labelled."""
    if fields.get("output"):
        return _text(fields["output"], MAX_LOG_TEXT)
    parts = []
    for stream in ("stdout", "stderr"):
        value = fields.get(stream)
        if isinstance(value, Mapping):  # {"head": ..., "tail": ..., "bytes": n}
            value = "\n[…]\n".join(
                str(value.get(k) or "") for k in ("head", "tail") if value.get(k)
            )
        if value:
            parts.append(f"--- {stream} ---\n{value}")
    return _text("\n".join(parts), MAX_LOG_TEXT) if parts else None


def split_private(
    result: Mapping[str, Any], logs: Mapping[str, Mapping[str, Any]] | None = None
) -> tuple[dict[str, Any], dict[int, dict[str, Any]]]:
    """A result without its owner-only fields, and those fields by car index.

    >>> pub, priv = split_private({"cars": [{"agent": "car_1", "dnf_detail": "Traceback"}]})
    >>> pub, priv[1]["dnf_detail"]
    ({'cars': [{'agent': 'car_1'}]}, 'Traceback')
    """
    public = dict(result)
    private: dict[int, dict[str, Any]] = {}
    merged: dict[str, dict[str, Any]] = {k: dict(v) for k, v in (logs or {}).items()}
    cars = []
    for car in result.get("cars", []):
        agent = str(car.get("agent", ""))
        own = {k: car[k] for k in PRIVATE_CAR_FIELDS if k in car}
        merged[agent] = own | merged.get(agent, {})
        cars.append({k: v for k, v in car.items() if k not in PRIVATE_CAR_FIELDS})
    if "cars" in result:
        public["cars"] = cars
    for agent, fields in merged.items():
        match = _CAR.match(agent)
        if match is None:
            continue
        row = {
            "dnf_detail": _text(fields.get("dnf_detail"), MAX_DETAIL),
            "output": _output(fields),
            "sandbox_mode": str(fields["sandbox_mode"])[:16]
            if fields.get("sandbox_mode")
            else None,
        }
        if any(row.values()):
            private[int(match.group(1))] = row
    return public, private


def read_events(replay_path: str | None) -> list[dict[str, Any]] | None:
    """The events of a replay log (``.replay.json.gz``), at most :data:`MAX_EVENTS`; None if
    the file is missing or unreadable (the race is stored anyway)."""
    if not replay_path:
        return None
    try:
        with gzip.open(Path(replay_path), "rb") as fh:
            doc = json.loads(fh.read().decode("utf-8"))
        events = doc.get("events", [])
    except (OSError, EOFError, ValueError, AttributeError):
        return None
    if not isinstance(events, list):
        return None
    return [e for e in events if isinstance(e, dict)][:MAX_EVENTS]


def _judge_validation(session: Session, race: Race) -> None:
    """Validated if each version in the race drove without a policy failure."""
    for entry in race.entries:
        if entry.version_id is None:
            continue
        version = session.get(SubmissionVersion, entry.version_id)
        if version is None or version.status != "pending":
            continue
        if entry.dnf_reason in POLICY_FAILURES:
            reject_version(session, version, f"validation race {race.id}: dnf ({entry.dnf_reason})")
        else:
            accept_version(session, version)


def accept_version(session: Session, version: SubmissionVersion) -> None:
    """Make a validated version the one its submission races with.

    A newer version keeps the submission's μ but starts again from the initial σ, so
    matchmaking favours it until its rating settles.
    """
    version.status = "validated"
    version.error = None
    sub = session.get(Submission, version.submission_id)
    if sub is None:
        return
    current = (
        session.get(SubmissionVersion, sub.active_version_id) if sub.active_version_id else None
    )
    if current is None or current.version < version.version:
        if current is not None:
            sub.sigma = max(sub.sigma, SIGMA0)
            sub.ordinal = ordinal(sub.mu, sub.sigma)
        sub.active_version_id = version.id
    if sub.status in ("pending", "rejected"):
        sub.status = "active"
    sub.updated_at = utcnow()


def reject_version(session: Session, version: SubmissionVersion, reason: str) -> None:
    """Mark a version rejected; a submission with no validated version is rejected too."""
    version.status = "rejected"
    version.error = reason
    sub = session.get(Submission, version.submission_id)
    if sub is not None and sub.active_version_id is None and sub.status == "pending":
        sub.status = "rejected"
        sub.updated_at = utcnow()


def _update_records(session: Session, race: Race) -> None:
    """Keep each submission's best lap per track (one query for the race's records)."""
    ids = [e.submission_id for e in race.entries if e.submission_id is not None]
    records = {
        r.submission_id: r
        for r in session.scalars(
            select(TrackRecord).where(
                TrackRecord.track == race.track, TrackRecord.submission_id.in_(ids)
            )
        )
    }
    for entry in race.entries:
        sub_id, lap = entry.submission_id, entry.best_lap
        if sub_id is None or lap is None:
            continue
        record = records.get(sub_id)
        if record is None:
            records[sub_id] = TrackRecord(
                track=race.track,
                submission_id=sub_id,
                version_id=entry.version_id,
                race_id=race.id,
                best_lap=lap,
            )
            session.add(records[sub_id])
        elif lap < record.best_lap:
            record.best_lap = lap
            record.version_id = entry.version_id
            record.race_id = race.id
            record.set_at = utcnow()


def fail_race(session: Session, race: Race, error: str) -> None:
    """Mark a race failed for good; a validation race that cannot run rejects its versions."""
    race.status, race.error, race.finished_at = "failed", error, utcnow()
    if race.kind != "validation":
        return
    for entry in race.entries:
        version = session.get(SubmissionVersion, entry.version_id) if entry.version_id else None
        if version is not None and version.status == "pending":
            reject_version(session, version, f"validation race {race.id} failed: {error}")
