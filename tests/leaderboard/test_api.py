"""The JSON API on a temporary database: uploads, auth, ownership, limits, reads, replays."""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from leaderboard.errors import PayloadTooLarge
from leaderboard.models import Job, Race, Submission, SubmissionVersion
from leaderboard.settings import Settings
from leaderboard.uploads import save_stream
from tests.leaderboard.conftest import Account, Seeded

MakeZip = Callable[..., Path]


def _upload(client: TestClient, path: Path, account: Account | None, url: str = "/api/submissions"):  # type: ignore[no-untyped-def]
    headers = account.headers if account else {}
    with path.open("rb") as f:
        return client.post(url, headers=headers, files={"file": (path.name, f, "application/zip")})


def test_upload_stores_version_and_queues_validation(
    client: TestClient, db: Session, settings: Settings, alice: Account, bundle_zip: MakeZip
) -> None:
    r = _upload(client, bundle_zip("zoom"), alice)
    assert r.status_code == 201, r.text
    body = r.json()
    assert (body["name"], body["version"], body["status"]) == ("zoom", 1, "pending")
    version = db.scalar(select(SubmissionVersion))
    assert version is not None and Path(version.source).is_file()
    assert Path(version.source).is_relative_to(settings.bundles_dir.resolve())
    race = db.get(Race, body["validation_race_id"])
    assert race is not None and race.kind == "validation" and race.status == "queued"
    assert [e.source for e in race.entries] == [version.source, settings.validation_opponent]
    assert db.scalar(select(Job.priority).where(Job.race_id == race.id)) == 0
    # Same name again (other bytes): a second version of the same submission.
    again = _upload(client, bundle_zip("zoom", extra=b"second"), alice).json()
    assert (again["submission_id"], again["version"]) == (body["submission_id"], 2)
    detail = client.get(f"/api/submissions/{body['submission_id']}").json()
    assert [v["version"] for v in detail["versions"]] == [2, 1]
    assert detail["author"] == "alice" and detail["status"] == "pending"


def test_missing_or_bad_token_is_401(client: TestClient, bundle_zip: MakeZip) -> None:
    path = bundle_zip()
    r = _upload(client, path, None)
    assert r.status_code == 401 and "missing API token" in r.json()["detail"]
    assert r.headers["www-authenticate"] == "Bearer"
    r = _upload(client, path, Account("mallory", "slp_not-a-real-token"))
    assert r.status_code == 401 and "invalid" in r.json()["detail"]
    assert client.get("/api/users/me").status_code == 401


def test_revoked_token_is_refused(client: TestClient, alice: Account) -> None:
    assert client.get("/api/users/me", headers=alice.headers).json()["name"] == "alice"
    second = client.post("/api/tokens", headers=alice.headers, json={"label": "ci"}).json()
    other = Account("alice", second["token"])
    assert client.get("/api/users/me", headers=other.headers).status_code == 200
    # The second token is id 2 (the first was issued with the user).
    assert client.delete("/api/tokens/2", headers=alice.headers).status_code == 204
    assert client.get("/api/users/me", headers=other.headers).status_code == 401
    assert client.get("/api/users/me", headers=alice.headers).status_code == 200


def test_tokens_are_stored_hashed(client: TestClient, db: Session, alice: Account) -> None:
    from leaderboard.models import ApiToken

    stored = db.scalars(select(ApiToken.token_hash)).all()
    assert stored and alice.token not in stored
    assert all(len(h) == 64 for h in stored)


def test_only_the_owner_can_update_or_withdraw(
    client: TestClient, db: Session, alice: Account, bob: Account, bundle_zip: MakeZip
) -> None:
    sub_id = _upload(client, bundle_zip("mine"), alice).json()["submission_id"]
    r = _upload(client, bundle_zip("mine"), bob, url=f"/api/submissions/{sub_id}/versions")
    assert r.status_code == 403 and "another user" in r.json()["detail"]
    assert client.delete(f"/api/submissions/{sub_id}", headers=bob.headers).status_code == 403
    # Bob uploading the same name makes his own submission, not a version of Alice's.
    bobs = _upload(client, bundle_zip("mine", extra=b"bob"), bob).json()
    assert bobs["submission_id"] != sub_id and bobs["version"] == 1
    # The owner can.
    r = _upload(
        client, bundle_zip("mine", extra=b"v2"), alice, url=f"/api/submissions/{sub_id}/versions"
    )
    assert r.status_code == 201 and r.json()["version"] == 2
    r = client.delete(f"/api/submissions/{sub_id}", headers=alice.headers)
    assert r.status_code == 200 and r.json()["status"] == "withdrawn"
    assert client.delete("/api/submissions/999", headers=alice.headers).status_code == 404


def test_oversize_upload_is_413_and_nothing_is_stored(
    alice: Account, bundle_zip: MakeZip, settings: Settings
) -> None:
    from leaderboard.app import create_app

    small = settings.model_copy(update={"max_upload_mb": 0.05})  # 51 KiB
    with TestClient(create_app(small)) as c:
        # 256 KiB: under the header check's framing slack, stopped while it is saved.
        r = _upload(c, bundle_zip("big", extra=os.urandom(256 << 10)), alice)
        assert r.status_code == 413 and "larger than" in r.json()["detail"]
        # 2 MiB: refused from its Content-Length before the body is read.
        r = _upload(c, bundle_zip("huge", extra=os.urandom(2 << 20)), alice)
        assert r.status_code == 413 and "larger than" in r.json()["detail"]
        assert _upload(c, bundle_zip("fits"), alice).status_code == 201
    stored = list(settings.bundles_dir.rglob("*.zip"))
    assert len(stored) == 1
    names = [n for n in zipfile.ZipFile(stored[0]).namelist()]
    assert "pad.bin" not in names


def test_stream_cap_stops_a_body_without_length(tmp_path: Path) -> None:
    dest = tmp_path / "up.zip"
    with pytest.raises(PayloadTooLarge):
        save_stream(io.BytesIO(b"x" * 5000), dest, max_bytes=4096)
    assert not dest.exists()
    assert save_stream(io.BytesIO(b"x" * 100), dest, max_bytes=4096)[0] == 100


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"this is not a zip", "invalid bundle"),
        ("no-manifest", "no manifest.json"),
        ("bad-manifest", "manifest"),
        ("traversal", "invalid bundle"),
    ],
)
def test_invalid_bundle_is_422_with_the_reason(
    client: TestClient, db: Session, alice: Account, tmp_path: Path, content: object, reason: str
) -> None:
    path = tmp_path / "bad.zip"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        with zipfile.ZipFile(path, "w") as zf:
            if content == "bad-manifest":
                zf.writestr("manifest.json", json.dumps({"schema": 1, "name": "x"}))
            elif content == "traversal":
                zf.writestr("manifest.json", "{}")
                zf.writestr("../evil.py", "print('hi')")
            else:
                zf.writestr("agent.py", "class Policy: pass\n")
    r = _upload(client, path, alice)
    assert r.status_code == 422, r.text
    assert reason in r.json()["detail"]
    assert db.scalar(select(Submission)) is None
    assert db.scalar(select(Race)) is None


def test_leaderboard_is_ordered_by_ordinal_and_paginated(
    client: TestClient, db: Session, seeded: Seeded
) -> None:
    rows = client.get("/api/leaderboard").json()
    assert rows["total"] == 5
    # Established submissions (>= 5 rated races) first, then provisional ones; by ordinal.
    keys = [(r["provisional"], -r["ordinal"]) for r in rows["items"]]
    assert keys == sorted(keys)
    assert all(r["provisional"] == (r["races"] < 5) for r in rows["items"])
    assert [r["rank"] for r in rows["items"]] == [1, 2, 3, 4, 5]
    for r in rows["items"]:
        assert r["ordinal"] == pytest.approx(r["mu"] - 3 * r["sigma"])
        assert r["win_rate"] == pytest.approx(r["wins"] / r["races"] if r["races"] else 0.0)
    page2 = client.get("/api/leaderboard", params={"page": 2, "per_page": 2}).json()
    assert [r["rank"] for r in page2["items"]] == [3, 4]
    assert [r["submission_id"] for r in page2["items"]] == [
        r["submission_id"] for r in rows["items"][2:4]
    ]
    assert client.get("/api/leaderboard", params={"per_page": 0}).status_code == 422
    # A withdrawn submission leaves the leaderboard.
    top = rows["items"][0]["submission_id"]
    sub = db.get(Submission, top)
    assert sub is not None
    sub.status = "withdrawn"
    db.commit()
    after = client.get("/api/leaderboard").json()
    assert after["total"] == 4 and top not in [r["submission_id"] for r in after["items"]]


def test_race_endpoints(client: TestClient, seeded: Seeded) -> None:
    races = client.get("/api/races", params={"kind": "ranked"}).json()
    assert races["total"] == len(seeded.race_ids)
    assert [r["id"] for r in races["items"]] == sorted(seeded.race_ids, reverse=True)
    race = client.get(f"/api/races/{seeded.race_ids[0]}").json()
    assert race["status"] == "finished" and 2 <= race["n_cars"] <= 4
    assert race["viser_url"] == f"/replays/{race['id']}.viser"
    positions = sorted(e["position"] for e in race["entries"])
    assert positions == list(range(1, race["n_cars"] + 1))
    for e in race["entries"]:
        assert e["lap_times"] and e["mu_after"] is not None and e["author"] == "house"
    winner = next(e for e in race["entries"] if e["position"] == 1)
    assert race["winner"] == winner["name"] and winner["mu_after"] > winner["mu_before"]
    assert client.get("/api/races/99999").status_code == 404
    sub = client.get(f"/api/submissions/{winner['submission_id']}").json()
    assert race["id"] in [r["id"] for r in sub["recent_races"]]
    assert len(sub["rating_history"]) == sub["races"] and sub["rank"] >= 1


def test_track_endpoints(client: TestClient, seeded: Seeded) -> None:
    tracks = {t["name"]: t for t in client.get("/api/tracks").json()}
    assert set(tracks) == {"oval", "bean"}
    assert sum(t["races"] for t in tracks.values()) >= len(seeded.race_ids)
    oval = client.get("/api/tracks/oval").json()
    laps = [r["best_lap"] for r in oval["records"]]
    assert laps == sorted(laps) and len({r["submission_id"] for r in oval["records"]}) == len(laps)
    assert oval["record"] == laps[0]
    assert client.get("/api/tracks/no-such-track").status_code == 404


def test_replay_is_served_with_the_right_content_type(client: TestClient, seeded: Seeded) -> None:
    race = client.get(f"/api/races/{seeded.race_ids[0]}").json()
    r = client.get(race["viser_url"])
    assert r.status_code == 200 and r.content == b"viser-test"
    assert r.headers["content-type"] == "application/octet-stream"


def test_users_are_created_by_an_admin_only(
    client: TestClient, settings: Settings, alice: Account
) -> None:
    assert settings.admin_token is not None
    admin = {"Authorization": f"Bearer {settings.admin_token.get_secret_value()}"}
    r = client.post("/api/users", headers=admin, json={"name": "carol"})
    assert r.status_code == 201
    carol = Account("carol", r.json()["token"])
    assert client.get("/api/users/me", headers=carol.headers).json()["name"] == "carol"
    assert client.post("/api/users", headers=alice.headers, json={"name": "x"}).status_code == 403
    assert client.post("/api/users", headers=admin, json={"name": "carol"}).status_code == 409
    assert client.post("/api/users", headers=admin, json={"name": "bad name"}).status_code == 422
    assert client.get("/api/users/carol").json()["submissions"]["total"] == 0


def test_default_secret_is_refused(tmp_path: Path) -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="placeholder"):
        Settings(data_dir=tmp_path, admin_token="changethis")


def test_openapi_docs_and_health(client: TestClient) -> None:
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    for p in ("/api/leaderboard", "/api/submissions", "/api/races/{race_id}", "/api/tracks"):
        assert p in paths
    health = client.get("/api/health").json()
    from tests.leaderboard.test_migrations import head_revision

    assert health["status"] == "ok" and health["revision"] == head_revision("sqlite://")


def test_cached_job_counts_follow_the_queue(
    client: TestClient, db: Session, settings: Settings, seeded: Seeded
) -> None:
    """/api/jobs is served from the snapshot cache; every queue move shows at once."""
    from leaderboard import queue

    def counts() -> dict[str, int]:
        jobs = client.get("/api/jobs").json()
        assert client.get("/api/health").json()["queue"] == jobs
        return jobs

    def truth() -> dict[str, int]:
        db.expire_all()
        return queue.stats(db)

    assert counts() == truth()
    race = Race(kind="ranked", track="oval", seed=1, laps=1)
    db.add(race)
    db.flush()
    queue.enqueue(db, race, max_attempts=2)
    db.commit()
    assert counts() == truth() and truth()["queued"] == 1
    lease = queue.claim(db, owner="t", lease_s=60)
    assert lease is not None and counts() == truth() and truth()["leased"] == 1
    assert queue.fail(db, lease, "boom")  # attempts left: queued again
    assert counts() == truth() and truth()["queued"] == 1
    lease = queue.claim(db, owner="t", lease_s=60)
    assert lease is not None and queue.fail(db, lease, "boom again")  # the last attempt
    assert counts() == truth() and truth()["failed"] >= 1 and truth()["queued"] == 0


def test_race_lists_agree_with_each_race(client: TestClient, seeded: Seeded) -> None:
    """Lists read races as plain rows (issue 13's speed-up); each summary must say what the
    race's own page says (winner, car count and every stored field)."""
    listed = client.get("/api/races?per_page=200").json()["items"]
    listed += client.get(f"/api/submissions/{seeded.submission_ids[0]}/races").json()["items"]
    assert len({r["id"] for r in listed}) >= len(seeded.race_ids)
    for summary in listed:
        detail = client.get(f"/api/races/{summary['id']}").json()
        assert summary == {k: detail[k] for k in summary}, summary["id"]
        assert summary["n_cars"] == len(detail["entries"])


@pytest.mark.parametrize("k", [0, 3, 50])
def test_a_submissions_rank_is_its_leaderboard_place(tmp_path: Path, k: int) -> None:
    """The rank on a submission's page is its row in the leaderboard, for any
    ``provisional_races`` (it used to count the default of 5), and follows rating changes."""
    from leaderboard.app import create_app
    from tests.leaderboard import factories

    settings = Settings(data_dir=tmp_path / "data", tracks=["oval"], provisional_races=k)
    app = create_app(settings)
    session = app.state.sessionmaker()
    factories.seed(session, settings, n_submissions=6, n_races=4)

    def check(c: TestClient) -> None:
        rows = c.get("/api/leaderboard").json()["items"]
        assert len(rows) == 6
        for row in rows:
            assert c.get(f"/api/submissions/{row['submission_id']}").json()["rank"] == row["rank"]

    with TestClient(app) as c:
        check(c)
        factories.seed(session, settings, n_submissions=0, n_races=3, seed=1)  # ratings move
        check(c)
    session.close()


def test_tracks_count_finished_ranked_races_only(
    client: TestClient, db: Session, seeded: Seeded
) -> None:
    rows = {t["name"]: t for t in client.get("/api/tracks").json()}
    ranked = Counter(
        db.scalars(select(Race.track).where(Race.kind == "ranked", Race.status == "finished"))
    )
    assert {name: t["races"] for name, t in rows.items()} == {n: ranked[n] for n in rows}
    validations = db.scalar(select(func.count(Race.id)).where(Race.kind == "validation"))
    assert validations and sum(t["races"] for t in rows.values()) == len(seeded.race_ids)
    detail = client.get("/api/tracks/oval").json()
    assert detail["races"] == ranked["oval"]
    assert all(r["kind"] == "ranked" for r in detail["recent_races"])
