"""Test data: bundles, synthetic race results, and a seeded leaderboard (no simulator).

Used by the leaderboard tests (API, pages, queue). Results are written through the real
code path (:func:`leaderboard.queue.complete`), so ratings and records are what a worker
would store.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from arena.version import ENV_VERSION
from leaderboard import auth, matchmaking, queue, uploads
from leaderboard.models import Race, RaceEntry, Submission, User
from leaderboard.settings import Settings
from submissions.bundle import Manifest, make_bundle

AGENT_PY = b'''
from agents.baselines import make_baseline
from arena.observations import ObservationLayout


class Policy:
    """Drives like the pursuit baseline."""

    def __init__(self, env_spec=None):
        spec = env_spec or {"lidar_rays": 64, "k_opponents": 3}
        layout = ObservationLayout(spec["lidar_rays"], spec["k_opponents"])
        self.inner = make_baseline("pursuit", layout)

    def reset(self, seed=None):
        self.inner.reset(seed)

    def act(self, obs):
        return self.inner.act(obs)
'''


def python_bundle(out: Path, *, name: str = "racer", extra: bytes = b"") -> Path:
    """A valid python-format bundle zip for the current env version."""
    manifest = Manifest(
        name=name,
        author="tests",
        format="python",
        entry="agent.py",
        env_version=ENV_VERSION,
        description=f"{name}: a test bundle",
    )
    files: dict[str, Path | bytes] = {"agent.py": AGENT_PY}
    if extra:
        files["pad.bin"] = extra
    return make_bundle(out, manifest, files)


def fake_result(
    race: Race, order: list[int] | None = None, dnf: set[int] | None = None
) -> dict[str, Any]:
    """A race result document for ``race``: cars finish in ``order`` (car indices, default
    by car index), cars in ``dnf`` retire with reason ``error``. Lap times grow with position."""
    cars = sorted(e.car for e in race.entries)
    order = order if order is not None else cars
    dnf = dnf or set()
    finishers = [c for c in order if c not in dnf]
    ranking = finishers + [c for c in order if c in dnf]
    out = []
    for pos, car in enumerate(ranking, start=1):
        done = car not in dnf
        laps = [20.0 + pos + 0.1 * lap for lap in range(race.laps)] if done else []
        out.append(
            {
                "agent": f"car_{car}",
                "name": f"car {car}",
                "position": pos,
                "status": "finished" if done else "dnf",
                "dnf_reason": None if done else "error",
                "laps_completed": race.laps if done else 0,
                "lap_times": laps,
                "best_lap": min(laps) if laps else None,
                "total_time": sum(laps) if laps else None,
                "race_time": sum(laps) if laps else None,
                "penalties": 0.0,
                "collisions": 0,
                "at_fault_collisions": 0,
                "off_track": 0,
                "distance": 100.0,
            }
        )
    return {
        "track": race.track,
        "seed": race.seed,
        "laps": race.laps,
        "env_version": "test",
        "ranked": race.penalties,
        "steps": 100,
        "sim_time": 60.0,
        "cars": out,
    }


def finish_queue(session: Session, settings: Settings, rng: random.Random) -> list[int]:
    """Run every queued job with a fake result (random finishing order); the race ids."""
    done = []
    while (lease := queue.claim(session, owner="factory", lease_s=60)) is not None:
        race = session.get(Race, lease.race_id)
        assert race is not None
        order = sorted(e.car for e in race.entries)
        rng.shuffle(order)
        replay = settings.replays_dir / f"{race.id}.viser"
        replay.write_bytes(b"viser-test")
        queue.complete(session, lease, fake_result(race, order), viser_path=str(replay))
        done.append(race.id)
    return done


def seed(
    session: Session, settings: Settings, *, n_submissions: int = 5, n_races: int = 6, seed: int = 0
) -> tuple[list[int], list[int]]:
    """Baseline submissions of user ``house``, validated, and ``n_races`` ranked races.

    Returns (submission ids, ranked race ids).
    """
    rng = random.Random(seed)
    settings.ensure_dirs()
    user = session.scalar(select(User).where(User.name == "house"))
    if user is None:
        user, _ = auth.create_user(session, name="house")
    subs = []
    for i in range(n_submissions):
        baseline = uploads.BASELINES[i % len(uploads.BASELINES)]
        version = uploads.add_baseline(
            session, settings, user=user, baseline=baseline, name=f"{baseline}-{i}"
        )
        subs.append(version.submission_id)
    session.commit()
    finish_queue(session, settings, rng)  # validation races
    matchmaking.schedule_ranked(session, settings, n_races, rng)
    session.commit()
    return subs, finish_queue(session, settings, rng)


def submissions(db: Session, settings: Settings, n: int) -> list[Submission]:
    """``n`` seeded submissions (no races), in id order."""
    seed(db, settings, n_submissions=n, n_races=0)
    return list(db.scalars(select(Submission).order_by(Submission.id)))


def race_for(
    subs: list[Submission],
    cars: list[int] | None = None,
    *,
    kind: str = "ranked",
    track: str = "oval",
    laps: int = 1,
) -> Race:
    """A race (not yet added) where ``subs[k]`` drives car ``cars[k]`` (default: car k)."""
    cars = list(range(len(subs))) if cars is None else cars
    return Race(
        kind=kind,
        track=track,
        laps=laps,
        entries=[
            RaceEntry(car=c, submission_id=s.id, version_id=s.active_version_id, name=s.name,
                      source="x")
            for s, c in zip(subs, cars, strict=True)
        ],
    )  # fmt: skip
