"""Car classes: a bundle declares its car, and the leaderboard keeps one ladder per car.

A manifest's optional ``car`` names an :mod:`arena.cars` preset; a submission's versions all
drive the same car; matchmaking never mixes classes in a race; validation and ranked races
carry the car to the worker's job and the job to the simulator; the leaderboard filters by
class (``/?car=deepracer``, ``/api/leaderboard?car=...``) and the race page shows the car.
"""

from __future__ import annotations

import gzip
import json
import random
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from arena import cars
from arena.version import ENV_VERSION
from leaderboard import matchmaking, models
from leaderboard.matchmaking import Candidate, pick_entrants
from leaderboard.models import Race, SubmissionVersion
from leaderboard.settings import Settings
from leaderboard.worker import race_job
from submissions import bundle
from submissions.bundle import Manifest, make_bundle
from submissions.errors import BundleError, SubmissionError
from submissions.jobs import Entrant, RaceJob, job_car, run_race_job
from tests.leaderboard import factories
from tests.leaderboard.conftest import Account


def car_bundle(out: Path, name: str, car: str | None) -> Path:
    """The test bundle of :mod:`tests.leaderboard.factories` (drives like pursuit) declaring
    ``car`` (None: no ``car`` key, as every bundle made before car classes); each one
    different (its description names its file), so none is refused as a duplicate."""
    extra = {} if car is None else {"car": car}
    manifest = Manifest(
        name=name, author="tests", format="python", entry="agent.py",
        env_version=ENV_VERSION, description=out.name, **extra,
    )  # fmt: skip
    return make_bundle(out, manifest, {"agent.py": factories.AGENT_PY})


def upload(client: TestClient, who: Account, path: Path) -> dict[str, object]:
    with path.open("rb") as fh:
        r = client.post("/api/submissions", headers=who.headers, files={"file": ("b.zip", fh)})
    assert r.status_code == 201, r.text
    doc: dict[str, object] = r.json()
    return doc


# ---- the manifest ----------------------------------------------------------------------------


def test_the_defaults_match_the_car_presets() -> None:
    assert bundle.DEFAULT_CAR == models.DEFAULT_CAR == cars.DEFAULT_CAR
    assert bundle.car_names() == tuple(cars.CAR_PRESETS)


def test_a_manifest_declares_its_car_and_round_trips() -> None:
    base = {
        "schema": 1, "name": "dr", "author": "ada", "format": "python", "entry": "agent.py",
        "obs_mode": "vector", "action_mode": "continuous", "env_version": ENV_VERSION,
    }  # fmt: skip
    old = Manifest.from_dict(base)  # written before car classes: the F1TENTH car
    assert old.car == "f1tenth" and "car" not in old.to_dict()
    dr = Manifest.from_dict(base | {"car": "deepracer"})
    assert dr.car == "deepracer"
    assert Manifest.from_dict(dr.to_dict()) == dr
    for bad in ("DeepRacer", "f1tenth ", "kart", 1, None):
        with pytest.raises(BundleError, match="car"):
            Manifest.from_dict(base | {"car": bad})


# ---- jobs ------------------------------------------------------------------------------------


def test_a_job_races_its_car_or_the_one_its_bundles_declare(tmp_path: Path) -> None:
    job = RaceJob("j", (Entrant("a", "pursuit"), Entrant("b", "gap")), "oval", str(tmp_path))
    assert job_car(job, []) == "f1tenth"
    assert job_car(job, ["deepracer", "deepracer"]) == "deepracer"
    with pytest.raises(BundleError, match="different cars"):
        job_car(job, ["deepracer", "f1tenth"])
    dr = RaceJob.from_dict(job.to_dict() | {"car": "deepracer"})
    assert dr.car == "deepracer" and RaceJob.from_dict(dr.to_dict()) == dr
    with pytest.raises(BundleError, match="'f1tenth' car; this race runs 'deepracer'"):
        job_car(dr, ["f1tenth"])
    with pytest.raises(SubmissionError, match="unknown car"):
        RaceJob("j", job.entrants, "oval", str(tmp_path), car="kart")


def test_a_deepracer_job_drives_the_deepracer_car(tmp_path: Path) -> None:
    """Two pursuit baselines, one lap of the oval, in the DeepRacer car: the replay's speeds
    stay under its 4 m/s motor (the F1TENTH car's pursuit goes well past that)."""
    job = RaceJob(
        "dr", (Entrant("a", "pursuit"), Entrant("b", "pursuit")), "oval", str(tmp_path),
        laps=1, record_viser=False, car="deepracer",
    )  # fmt: skip
    res = run_race_job(job)
    assert res.ok and res.result["car"] == "deepracer"
    with gzip.open(res.replay_path, "rb") as fh:
        speeds = np.array(json.loads(fh.read())["frames"]["speed"], dtype=float)
    top = np.nanmax(speeds)
    assert 2.0 < top <= cars.DEEPRACER.max_speed + 0.05, top


# ---- the leaderboard -------------------------------------------------------------------------


@pytest.fixture
def two_classes(
    client: TestClient, db: Session, settings: Settings, alice: Account, tmp_path: Path
) -> dict[str, list[int]]:
    """Three baselines (f1tenth) and three DeepRacer uploads of alice, all validated."""
    factories.seed(db, settings, n_submissions=3, n_races=0)
    for i in range(3):
        upload(client, alice, car_bundle(tmp_path / f"dr{i}.zip", f"dr{i}", "deepracer"))
    factories.finish_queue(db, settings, random.Random(0))
    classes: dict[str, list[int]] = {}
    for version in db.scalars(select(SubmissionVersion)):
        assert version.status == "validated"
        classes.setdefault(version.car, []).append(version.submission_id)
    return classes


def test_validation_races_drive_the_uploaded_car(
    client: TestClient, db: Session, settings: Settings, alice: Account, tmp_path: Path
) -> None:
    doc = upload(client, alice, car_bundle(tmp_path / "dr.zip", "dr", "deepracer"))
    race = db.get(Race, int(str(doc["validation_race_id"])))
    assert race is not None and race.car == "deepracer"
    assert race_job(race, settings).car == "deepracer"
    old = upload(client, alice, car_bundle(tmp_path / "old.zip", "old", None))
    race = db.get(Race, int(str(old["validation_race_id"])))
    assert race is not None and race.car == "f1tenth"


def test_a_submission_keeps_its_car(
    client: TestClient, db: Session, alice: Account, tmp_path: Path
) -> None:
    upload(client, alice, car_bundle(tmp_path / "v1.zip", "mine", "deepracer"))
    with (car_bundle(tmp_path / "v2.zip", "mine", "f1tenth")).open("rb") as fh:
        r = client.post("/api/submissions", headers=alice.headers, files={"file": ("b.zip", fh)})
    assert r.status_code == 409 and "'deepracer' car" in r.json()["detail"]
    assert len(db.scalars(select(SubmissionVersion)).all()) == 1  # nothing stored
    upload(client, alice, car_bundle(tmp_path / "v3.zip", "mine", "deepracer"))  # same car: ok


def test_ranked_races_never_mix_car_classes(
    db: Session, settings: Settings, two_classes: dict[str, list[int]]
) -> None:
    races = matchmaking.schedule_ranked(db, settings, 24, random.Random(3))
    db.commit()
    assert len(races) == 24
    car_of = {sid: car for car, ids in two_classes.items() for sid in ids}
    for race in races:
        assert {car_of[e.submission_id] for e in race.entries} == {race.car}
        assert race_job(race, settings).car == race.car
    assert {r.car for r in races} == {"f1tenth", "deepracer"}


def test_a_class_too_small_for_a_race_is_not_matched() -> None:
    def cand(i: int, car: str) -> Candidate:
        return Candidate(i, i, f"s{i}", "pursuit", 25.0, 8.3, 0, 0, car)

    pool = [cand(1, "f1tenth"), cand(2, "f1tenth"), cand(3, "deepracer")]
    rng = random.Random(0)
    for _ in range(50):
        assert {c.car for c in pick_entrants(pool, rng)} == {"f1tenth"}
    assert pick_entrants([cand(1, "f1tenth"), cand(3, "deepracer")], rng) == []


def test_the_leaderboard_filters_by_car_class(
    client: TestClient, db: Session, settings: Settings, two_classes: dict[str, list[int]]
) -> None:
    matchmaking.schedule_ranked(db, settings, 8, random.Random(5))
    db.commit()
    factories.finish_queue(db, settings, random.Random(5))
    everyone = client.get("/api/leaderboard").json()
    assert everyone["total"] == 6
    for car, ids in two_classes.items():
        doc = client.get("/api/leaderboard", params={"car": car}).json()
        assert doc["total"] == 3 and {r["submission_id"] for r in doc["items"]} == set(ids)
        assert [r["rank"] for r in doc["items"]] == [1, 2, 3]
        assert {r["car"] for r in doc["items"]} == {car}
        html = client.get("/", params={"car": car}).text
        assert all(f'href="/submissions/{i}"' in html for i in ids)
        others = [i for c, ids2 in two_classes.items() if c != car for i in ids2]
        assert not any(f'href="/submissions/{i}"' in html for i in others)
        # A submission's rank is its rank in its own ladder.
        top = doc["items"][0]["submission_id"]
        assert client.get(f"/api/submissions/{top}").json()["rank"] == 1
    assert client.get("/api/leaderboard", params={"car": "kart"}).status_code == 404
    assert client.get("/", params={"car": "kart"}).status_code == 404
    race_id = db.scalar(select(Race.id).where(Race.car == "deepracer", Race.kind == "ranked"))
    page = client.get(f"/races/{race_id}").text
    assert 'id="race-car"' in page and 'href="/?car=deepracer"' in page
    assert client.get(f"/api/races/{race_id}").json()["car"] == "deepracer"
