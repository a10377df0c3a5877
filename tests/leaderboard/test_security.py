"""The service's front door under attack (issue 13): body caps, auth before the body, timeouts,
rate limits, quotas, concurrent uploads, overflowing ids, headers, hosts, the viewer's leash.

The attacks are the ones issue 13's outside review ran against ``slipstream serve``: a 3000 MiB
chunked multipart body to ``POST /api/submissions`` without a token, an authenticated oversize
chunked upload, 300 bad-token requests, five uploads in a row, six parallel uploads of one new
name, ids of 2^31 and 2^63, ``/viewer/?playbackPath=<another server>``. The body tests run a
real uvicorn server on 127.0.0.1 whose HTTP protocol counts the bytes it reads off each socket,
and a client that streams over a raw socket.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session

from leaderboard.app import create_app
from leaderboard.models import SubmissionVersion
from leaderboard.serving import uvicorn_config
from leaderboard.settings import Settings
from tests.leaderboard.conftest import Account

MiB = 1 << 20
ATTACK_BYTES = 3000 * MiB  # the size the outside review streamed


# ---- a real server that counts what it reads --------------------------------------------------


@dataclass
class Served:
    """A uvicorn server in a thread, and the bytes its HTTP protocol read off all sockets."""

    host: str
    port: int
    read: list[int]

    @property
    def url(self) -> str:
        """Base URL."""
        return f"http://{self.host}:{self.port}"


@contextmanager
def serve(app: FastAPI) -> Iterator[Served]:
    """Run ``app`` as ``slipstream serve`` does (:func:`leaderboard.serving.uvicorn_config`)
    on a free loopback port, its HTTP protocol counting the bytes it reads."""
    import uvicorn

    read = [0]
    settings: Settings = app.state.settings
    config = uvicorn_config(app, settings, "127.0.0.1", 0)

    class CountingH11(config.http):  # type: ignore[name-defined,misc]
        def data_received(self, data: bytes) -> None:
            read[0] += len(data)
            super().data_received(data)

    config.http = CountingH11
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.02)
    try:
        yield Served("127.0.0.1", port, read)
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()


def stream_chunked(
    served: Served, path: str, headers: dict[str, str], total: int, *, limit: int
) -> tuple[bytes, int]:
    """POST a chunked multipart body of ``total`` bytes until the server answers and hangs up.

    Stops early once the server has answered and closed, or after ``limit`` bytes (the test
    then fails: the server kept reading). Returns (the raw response, bytes the client sent).
    """
    boundary = "slipstreamattack"
    head = (
        f"POST {path} HTTP/1.1\r\nHost: {served.host}\r\nTransfer-Encoding: chunked\r\n"
        f"Content-Type: multipart/form-data; boundary={boundary}\r\n"
        + "".join(f"{k}: {v}\r\n" for k, v in headers.items())
        + "\r\n"
    ).encode()
    part = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="b.zip"\r\n'
        "Content-Type: application/zip\r\n\r\n"
    ).encode()
    block = os.urandom(64 * 1024)
    sent = 0
    response = b""
    with socket.create_connection((served.host, served.port), timeout=10) as conn:
        conn.sendall(head)
        first = part + block
        try:
            conn.sendall(f"{len(first):x}\r\n".encode() + first + b"\r\n")
            sent += len(first)
            conn.settimeout(0.0)
            while sent < min(total, limit):
                try:
                    chunk = conn.recv(65536)
                    if chunk:
                        response += chunk
                    elif response:
                        break  # answered and closed
                except BlockingIOError:
                    pass
                try:
                    n = conn.send(f"{len(block):x}\r\n".encode() + block + b"\r\n")
                    sent += max(0, n - 8)
                except BlockingIOError:
                    time.sleep(0.002)
        except (BrokenPipeError, ConnectionResetError):
            pass
        conn.settimeout(5.0)
        try:
            while chunk := conn.recv(65536):
                response += chunk
        except (ConnectionResetError, TimeoutError, OSError):
            pass
    return response, sent


def _status(raw: bytes) -> int:
    assert raw.startswith(b"HTTP/1.1 "), raw[:200]
    return int(raw.split(b" ", 2)[1])


def test_unauthenticated_chunked_upload_is_refused_after_reading_under_1_mib(
    settings: Settings,
) -> None:
    with serve(create_app(settings)) as served:
        raw, sent = stream_chunked(served, "/api/submissions", {}, ATTACK_BYTES, limit=256 * MiB)
        read = served.read[0]
    assert _status(raw) == 401 and b"missing API token" in raw
    assert b"connection: close" in raw.lower()
    assert read <= 1 * MiB, f"the server read {read} bytes of an unauthenticated upload"
    assert sent < 256 * MiB  # the server hung up; the client did not push the whole limit
    assert not any(settings.bundles_dir.rglob("*.zip"))


def test_bad_token_chunked_upload_is_refused_after_reading_under_1_mib(
    settings: Settings,
) -> None:
    with serve(create_app(settings)) as served:
        bad = {"Authorization": "Bearer slp_not-a-real-token"}
        raw, _ = stream_chunked(served, "/api/submissions", bad, ATTACK_BYTES, limit=256 * MiB)
        read = served.read[0]
    assert _status(raw) == 401 and b"invalid or revoked" in raw
    assert read <= 1 * MiB


def test_upload_past_the_daily_quota_is_refused_before_its_body(
    settings: Settings, alice: Account, bundle_zip: Callable[..., Path]
) -> None:
    one = settings.model_copy(update={"max_uploads_per_day": 1})
    app = create_app(one)
    with TestClient(app) as c:
        assert _upload(c, bundle_zip("first"), alice).status_code == 201
    with serve(app) as served:
        raw, _ = stream_chunked(
            served, "/api/submissions", alice.headers, ATTACK_BYTES, limit=256 * MiB
        )
        read = served.read[0]
    assert _status(raw) == 429 and b"last 24 hours" in raw and b"retry-after" in raw.lower()
    assert read <= 1 * MiB, read


def test_uploads_in_flight_per_user_are_bounded(settings: Settings, alice: Account) -> None:
    """Two uploads of one user still being received: a third is refused (429) at once, so one
    account cannot make the server hold many bodies at the same time."""
    app = create_app(settings.model_copy(update={"max_concurrent_uploads": 2}))
    head = (
        f"POST /api/submissions HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {alice.token}\r\nTransfer-Encoding: chunked\r\n"
        "Content-Type: multipart/form-data; boundary=b\r\n\r\n"
    ).encode()
    with serve(app) as served:
        slow = [socket.create_connection((served.host, served.port), timeout=10) for _ in "ab"]
        try:
            for conn in slow:
                conn.sendall(head + b"5\r\n--b\r\n\r\n")  # one chunk: the first boundary
            time.sleep(1.0)  # both are authenticated and receiving
            third = httpx.post(
                served.url + "/api/submissions",
                headers=alice.headers,
                files={"file": ("b.zip", b"PK", "application/zip")},
                timeout=30,
            )
        finally:
            for conn in slow:
                conn.close()
        assert third.status_code == 429 and "still being received" in third.json()["detail"]
        assert int(third.headers["retry-after"]) >= 1
        time.sleep(1.0)  # the two are gone: uploads are accepted again
        again = httpx.post(
            served.url + "/api/submissions",
            headers=alice.headers,
            files={"file": ("b.zip", b"not a zip", "application/zip")},
            timeout=30,
        )
        assert again.status_code == 422


def test_authenticated_oversize_chunked_upload_is_413_and_stores_nothing(
    settings: Settings, alice: Account
) -> None:
    small = settings.model_copy(update={"max_upload_mb": 1.0})
    cap = small.max_upload_bytes + (1 << 20)  # the bundle limit plus the multipart slack
    with serve(create_app(small)) as served:
        raw, _ = stream_chunked(
            served, "/api/submissions", alice.headers, ATTACK_BYTES, limit=256 * MiB
        )
        read = served.read[0]
    assert _status(raw) == 413 and b"larger than" in raw
    # The cap, plus what the socket had buffered when the cut came (well under 1 MiB).
    assert read <= cap + 1 * MiB, read
    assert not any(settings.bundles_dir.rglob("*.zip"))
    assert not any((settings.bundles_dir / ".incoming").glob("*"))


def test_declared_oversize_length_is_refused_before_the_body(
    client: TestClient, alice: Account
) -> None:
    headers = {**alice.headers, "content-length": str(10**12), "content-type": "application/zip"}
    r = client.post("/api/submissions", headers=headers, content=b"x")
    assert r.status_code == 413 and r.headers["connection"] == "close"
    # A small JSON route has a small cap, whatever the framing.
    big = json.dumps({"label": "x" * 200_000})
    r = client.post("/api/tokens", headers=alice.headers, content=big)
    assert r.status_code == 413
    r = client.post(
        "/api/tokens", headers=alice.headers, content=iter([big.encode()])
    )  # chunked: no Content-Length
    assert r.status_code == 413


def test_a_stalled_body_times_out_with_408(settings: Settings, alice: Account) -> None:
    quick = settings.model_copy(update={"body_idle_timeout_s": 0.5})
    with (
        serve(create_app(quick)) as served,
        socket.create_connection((served.host, served.port), timeout=10) as conn,
    ):
        conn.sendall(
            (
                f"POST /api/submissions HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                f"Authorization: Bearer {alice.token}\r\nContent-Length: 100000\r\n"
                "Content-Type: multipart/form-data; boundary=b\r\n\r\n--b\r\n"
            ).encode()
        )
        start = time.monotonic()
        raw = b""
        while chunk := conn.recv(65536):  # until the server hangs up (head and body)
            raw += chunk
        waited = time.monotonic() - start
    assert _status(raw) == 408 and b"not received within" in raw
    assert waited < 5.0


def test_a_trickled_body_outside_uploads_times_out_in_the_idle_limit(
    settings: Settings, alice: Account
) -> None:
    """One byte every 0.2 s never trips the idle wait; a small JSON body still has to arrive
    within ``body_idle_timeout_s`` in all (uploads get ``upload_timeout_s``)."""
    quick = settings.model_copy(update={"body_idle_timeout_s": 1.0})
    with (
        serve(create_app(quick)) as served,
        socket.create_connection((served.host, served.port), timeout=10) as conn,
    ):
        conn.sendall(
            (
                f"POST /api/tokens HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                f"Authorization: Bearer {alice.token}\r\nContent-Length: 60000\r\n"
                "Content-Type: application/json\r\n\r\n"
            ).encode()
        )
        conn.settimeout(0.2)
        start, raw = time.monotonic(), b""
        while not raw and time.monotonic() - start < 10:
            try:
                conn.sendall(b" ")
                raw = conn.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                break
        waited = time.monotonic() - start
    assert _status(raw) == 408, raw[:100]
    assert waited < 4.0


def _closed_within(conn: socket.socket, seconds: float, trickle: bytes = b"") -> float | None:
    """Seconds until the server closes ``conn`` (sending ``trickle`` every 0.2 s), or None."""
    start = time.monotonic()
    conn.settimeout(0.2)
    while time.monotonic() - start < seconds:
        try:
            if trickle:
                conn.sendall(trickle)
            if conn.recv(65536) == b"":
                return time.monotonic() - start
        except TimeoutError:
            continue
        except OSError:
            return time.monotonic() - start
    return None


def test_slow_request_heads_are_cut_off(settings: Settings) -> None:
    """Slowloris (a connection that sends nothing, or one header line at a time) no longer
    holds a connection slot; a keep-alive client that is quick is not affected."""
    quick = settings.model_copy(update={"header_timeout_s": 1.0, "keep_alive_s": 5.0})
    with serve(create_app(quick)) as served:
        with socket.create_connection((served.host, served.port), timeout=10) as idle:
            closed = _closed_within(idle, 8.0)
        assert closed is not None and closed < 4.0, closed
        with socket.create_connection((served.host, served.port), timeout=10) as slow:
            slow.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
            closed = _closed_within(slow, 8.0, trickle=b"X-a: b\r\n")
        assert closed is not None and closed < 4.0, closed
        # A second request on a kept-alive connection, its head sent slowly after the first
        # answer, gets the same deadline (uvicorn's keep-alive timer stops at its first byte).
        with socket.create_connection((served.host, served.port), timeout=10) as kept:
            kept.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert _status(kept.recv(65536)) == 200
            kept.sendall(b"GET / HTTP/1.1\r\n")
            closed = _closed_within(kept, 8.0, trickle=b"X-a: b\r\n")
        assert closed is not None and closed < 4.0, closed
        with httpx.Client(base_url=served.url) as client:  # quick requests, one connection
            for _ in range(3):
                assert client.get("/api/health").status_code == 200
                time.sleep(0.6)


# ---- rate limits and quotas ----------------------------------------------------------------


def test_failed_website_sign_ins_get_429(settings: Settings) -> None:
    """The sign-in form takes a token in its body: its failures count like bad bearer tokens."""
    app = create_app(settings.model_copy(update={"rate_limit_auth_failures": "3/minute"}))
    with TestClient(app) as c:
        form = c.get("/signin")
        csrf = form.cookies.get("slipstream_csrf") or ""
        codes = [
            c.post("/signin", data={"token": f"slp_guess{i}", "csrf": csrf}).status_code
            for i in range(5)
        ]
        assert codes == [401, 401, 401, 429, 429]
        assert c.get("/api/leaderboard").status_code == 200


def test_bad_tokens_get_429_with_retry_after(settings: Settings) -> None:
    app = create_app(settings.model_copy(update={"rate_limit_auth_failures": "5/minute"}))
    with TestClient(app) as c:
        bad = {"Authorization": "Bearer slp_guess"}
        codes = [c.get("/api/users/me", headers=bad).status_code for _ in range(8)]
        assert codes[:5] == [401] * 5 and codes[5:] == [429] * 3
        r = c.get("/api/users/me", headers=bad)
        assert r.status_code == 429 and 1 <= int(r.headers["retry-after"]) <= 60
        assert "failed authentications" in r.json()["detail"]
        assert c.get("/api/leaderboard").status_code == 200  # anonymous reads still work


def test_per_address_and_per_token_limits(settings: Settings, alice: Account, bob: Account) -> None:
    app = create_app(
        settings.model_copy(update={"rate_limit_ip": "12/minute", "rate_limit_token": "3/minute"})
    )
    with TestClient(app) as c:
        codes = [c.get("/api/users/me", headers=alice.headers).status_code for _ in range(4)]
        assert codes == [200, 200, 200, 429]
        assert c.get("/api/users/me", headers=bob.headers).status_code == 200  # another token
        codes = [c.get("/api/health").status_code for _ in range(10)]
        assert codes.count(429) >= 1 and codes[0] == 200
        r = c.get("/api/health")
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1


def _upload(c: TestClient, path: Path, account: Account, url: str = "/api/submissions") -> Any:
    with path.open("rb") as f:
        return c.post(
            url, headers=account.headers, files={"file": (path.name, f, "application/zip")}
        )


def test_upload_quotas_and_duplicates(
    settings: Settings, alice: Account, bundle_zip: Callable[..., Path]
) -> None:
    app = create_app(
        settings.model_copy(update={"max_uploads_per_day": 3, "max_active_submissions": 2})
    )
    with TestClient(app) as c:
        first = bundle_zip("one")
        assert _upload(c, first, alice).status_code == 201
        again = _upload(c, first, alice)  # the same bytes
        assert again.status_code == 409 and "identical" in again.json()["detail"]
        assert _upload(c, bundle_zip("two"), alice).status_code == 201
        third = _upload(c, bundle_zip("three"), alice)  # a third live submission
        assert third.status_code == 409 and "pending or active" in third.json()["detail"]
        assert _upload(c, bundle_zip("two", extra=b"v2"), alice).status_code == 201
        over = _upload(c, bundle_zip("two", extra=b"v3"), alice)  # a fourth upload today
        assert over.status_code == 429 and "last 24 hours" in over.json()["detail"]
        assert 3000 < int(over.headers["retry-after"]) <= 86400


def _parallel_uploads(app: FastAPI, account: Account, paths: list[Path]) -> list[int]:
    with serve(app) as served:
        barrier = threading.Barrier(len(paths))
        codes: list[int] = [0] * len(paths)

        def one(i: int) -> None:
            data = paths[i].read_bytes()
            barrier.wait()
            r = httpx.post(
                served.url + "/api/submissions",
                headers=account.headers,
                files={"file": ("b.zip", data, "application/zip")},
                timeout=60,
            )
            codes[i] = r.status_code

        threads = [threading.Thread(target=one, args=(i,)) for i in range(len(paths))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    return codes


def test_six_parallel_uploads_of_one_new_name_never_500(
    app: FastAPI, db: Session, alice: Account, bundle_zip: Callable[..., Path]
) -> None:
    paths = [bundle_zip("same", extra=f"copy {i}".encode()) for i in range(6)]
    codes = _parallel_uploads(app, alice, paths)
    assert set(codes) <= {201, 409} and codes.count(201) >= 1, codes
    versions = sorted(v.version for v in db.scalars(select(SubmissionVersion)))
    assert versions == list(range(1, codes.count(201) + 1))  # one submission, no gaps


def test_six_parallel_uploads_on_postgresql(
    tmp_path: Path, pg_url: str, alice_factory: Callable[[FastAPI], Account], bundle_zip: Any
) -> None:
    settings = Settings(data_dir=tmp_path / "pg", database_url=pg_url, tracks=["oval"])
    app = create_app(settings)
    paths = [bundle_zip("same", extra=f"copy {i}".encode()) for i in range(6)]
    codes = _parallel_uploads(app, alice_factory(app), paths)
    assert set(codes) <= {201, 409} and codes.count(201) >= 1, codes


@pytest.fixture
def alice_factory() -> Callable[[FastAPI], Account]:
    """``alice_factory(app)``: user alice with a token on ``app``'s database."""
    from leaderboard import auth

    def make(app: FastAPI) -> Account:
        session = app.state.sessionmaker()
        try:
            _, token = auth.create_user(session, name="alice")
            session.commit()
        finally:
            session.close()
        return Account("alice", token)

    return make


# ---- ids, pages, tokens ---------------------------------------------------------------------

HUGE = [2**31, 2**63, 10**30]


@pytest.mark.parametrize("number", HUGE)
def test_huge_ids_and_pages_are_4xx(client: TestClient, alice: Account, number: int) -> None:
    for url in (
        f"/api/races/{number}",
        f"/api/submissions/{number}",
        f"/api/submissions/{number}/races",
        f"/races/{number}",
        f"/submissions/{number}",
        f"/api/leaderboard?page={number}",
        f"/?page={number}",
        f"/api/races?page={number}",
    ):
        assert client.get(url).status_code in (404, 422), url
    assert client.delete(f"/api/tokens/{number}", headers=alice.headers).status_code in (404, 422)


def test_huge_ids_on_postgresql(tmp_path: Path, pg_url: str) -> None:
    settings = Settings(data_dir=tmp_path / "pg", database_url=pg_url, tracks=["oval"])
    with TestClient(create_app(settings)) as c:
        for url in ("/api/races/2147483648", "/races/2147483648", "/api/submissions/2147483648"):
            assert c.get(url).status_code in (404, 422), url


def test_tokens_are_listed_and_revoked_by_their_owner_only(
    client: TestClient, alice: Account, bob: Account
) -> None:
    made = client.post("/api/tokens", headers=alice.headers, json={"label": "laptop"})
    assert made.status_code == 201
    new = made.json()
    assert set(new) == {"id", "token"} and new["token"].startswith("slp_")
    mine = client.get("/api/tokens", headers=alice.headers).json()
    assert [t["label"] for t in mine] == ["created with the user", "laptop"]
    assert all("token" not in t and not t["revoked"] for t in mine)
    assert new["token"].startswith(mine[1]["prefix"])
    # Bob sees only his own, and cannot revoke Alice's (404, as if it did not exist).
    assert [t["id"] for t in client.get("/api/tokens", headers=bob.headers).json()] != [
        t["id"] for t in mine
    ]
    assert client.delete(f"/api/tokens/{new['id']}", headers=bob.headers).status_code == 404
    assert client.delete(f"/api/tokens/{new['id']}", headers=alice.headers).status_code == 204
    listed = {
        t["id"]: t["revoked"] for t in client.get("/api/tokens", headers=alice.headers).json()
    }
    assert listed[new["id"]] is True
    laptop = {"Authorization": f"Bearer {new['token']}"}
    assert client.get("/api/users/me", headers=laptop).status_code == 401


# ---- headers, hosts, HEAD, compression, docs ---------------------------------------------------


@pytest.mark.parametrize(
    ("method", "url"),
    [
        ("GET", "/"),
        ("GET", "/api/leaderboard"),
        ("GET", "/api/races/999"),
        ("GET", "/static/style.css"),
        ("POST", "/api/submissions"),
        ("GET", "/docs"),
    ],
)
def test_security_headers_on_every_response(client: TestClient, method: str, url: str) -> None:
    r = client.request(method, url)
    csp = r.headers["content-security-policy"]
    assert "frame-ancestors 'self'" in csp and "unsafe-eval" not in csp
    assert r.headers["x-content-type-options"] == "nosniff"
    assert r.headers["referrer-policy"] == "same-origin"
    if url == "/":
        assert "script-src 'self';" in csp and "connect-src 'self'" in csp


def test_unknown_hosts_are_refused(settings: Settings) -> None:
    real = settings.model_copy(update={"allowed_hosts": ["127.0.0.1", "localhost"]})
    with TestClient(create_app(real), base_url="http://127.0.0.1") as c:
        assert c.get("/api/health").status_code == 200
        assert c.get("/api/health", headers={"host": "evil.example"}).status_code == 400
        # A redirect names an allowed host, never one the request made up.
        r = c.get("/viewer", headers={"host": "evil.example"}, follow_redirects=False)
        assert r.status_code == 400 and "evil.example" not in r.headers.get("location", "")


def test_head_is_answered_like_get(client: TestClient) -> None:
    for url in ("/", "/api/leaderboard", "/tracks"):
        r = client.head(url)
        assert r.status_code == 200 and r.content == b"", url
    assert client.head("/races/999").status_code == 404


def test_viewer_is_gzipped_and_pages_have_etags(client: TestClient) -> None:
    r = client.get("/viewer/", headers={"accept-encoding": "gzip"})
    assert r.status_code == 200 and r.headers["content-encoding"] == "gzip"
    # Bytes on the wire vs decoded; the player is mostly zstd already, so gzip saves ~18%.
    assert r.num_bytes_downloaded < 0.9 * len(r.content)
    page = client.get("/api/leaderboard")
    etag = page.headers["etag"]
    again = client.get("/api/leaderboard", headers={"if-none-match": etag})
    assert again.status_code == 304 and again.content == b""
    assert client.get("/", headers={"if-none-match": etag}).status_code == 200


def test_docs_are_served_from_the_package(client: TestClient) -> None:
    for url in ("/docs", "/redoc"):
        r = client.get(url)
        assert r.status_code == 200
        assert "cdn." not in r.text and "fonts.googleapis" not in r.text
        for asset in ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js"):
            if asset in r.text:
                assert client.get(f"/static-docs/{asset}").status_code == 200


# ---- the viewer's leash, and the replays we write ---------------------------------------------


@pytest.mark.parametrize(
    "query",
    [
        "playbackPath=https://evil.example/x.viser",
        "playbackPath=//evil.example/replays/1.viser",
        "playbackPath=/replays/../leaderboard.db",
        "playbackPath=/replays/1.viser&websocket=ws://evil.example:8080",
        "websocket=ws://evil.example:8080",
        "playbackPath=/replays/1.viser&playbackPath=https://evil.example/x.viser",
        "playbackPath=/replays/1.viser&initialCameraPosition=alert(1)",
        "playbackPath=/replays/1.viser%0a",  # "$" matches before a trailing newline
    ],
)
def test_viewer_refuses_foreign_sources(client: TestClient, query: str) -> None:
    # /viewer//: the static files serve the player for it too (found by the second review).
    for page in ("/viewer/", "/viewer//", "/viewer/./", "/viewer/index.html"):
        assert client.get(f"{page}?{query}").status_code == 400, (page, query)
        assert client.get(f"{page}?playbackPath=/replays/1.viser").status_code == 200


def test_viewer_policy(client: TestClient) -> None:
    r = client.get("/viewer/?playbackPath=/replays/7.viser&hideViserLogo")
    assert r.status_code == 200
    csp = r.headers["content-security-policy"]
    scripts = csp.split("script-src ")[1].split(";")[0].split()
    assert "connect-src 'self'" in csp
    assert "'unsafe-eval'" not in scripts and "'unsafe-inline'" not in scripts
    assert "'wasm-unsafe-eval'" in scripts  # WebAssembly (its zstd decoder), not eval
    assert sum(s.startswith("'sha256-") for s in scripts) == 2  # loader + unpacked code


def test_written_replays_hold_no_script_messages(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from submissions.viser_replay import read_viser, write_viser
    from tests.leaderboard.site_data import fake_replay

    job = SimpleNamespace(
        track="oval", entrants=[SimpleNamespace(name=n) for n in ("pursuit:v1", "gap:v1")]
    )
    out = write_viser(fake_replay(job, seconds=1.0), tmp_path / "1.viser")  # type: ignore[arg-type]
    doc = read_viser(out)
    types = {message["type"] for _t, message in doc["messages"]}
    assert types and not {t for t in types if "Javascript" in t or t.startswith("Gui")}
    text = json.dumps(doc["messages"], default=lambda _o: None)
    assert "<script" not in text and "javascript:" not in text.lower()


# ---- smaller defects ----------------------------------------------------------------------


def test_bundle_errors_do_not_name_server_files(client: TestClient, alice: Account) -> None:
    r = client.post(
        "/api/submissions",
        headers=alice.headers,
        files={"file": ("checkpoint.zip", b"not a zip at all", "application/zip")},
    )
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert ".incoming" not in detail and "/tmp" not in detail and "tmp" not in detail
    assert "the uploaded bundle" in detail or "zip" in detail


def test_a_bare_checkpoint_upload_gets_a_hint(client: TestClient, alice: Account) -> None:
    """The shipped PPO checkpoint posted as it is (curl, not `slipstream submit`)."""
    shipped = Path(__file__).resolve().parents[2] / "agents" / "data" / "ppo_racer.zip"
    with shipped.open("rb") as f:
        r = client.post(
            "/api/submissions",
            headers=alice.headers,
            files={"file": ("ppo_racer.zip", f, "application/zip")},
        )
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert "no manifest.json" in detail and "slipstream submit" in detail
    assert "bundle wrap" in detail and str(shipped.parent) not in detail


def test_random_track_pictures_are_bounded(tmp_path: Path, client: TestClient) -> None:
    from leaderboard.web.trackplots import track_image
    from tracks.errors import TrackError

    with pytest.raises(TrackError, match="seeds lie in"):
        track_image(f"random:{2**40}", tmp_path)
    for seed in (1, 2, 3):
        track_image(f"random:{seed}", tmp_path, max_random=2)
    assert len(list((tmp_path / "cache" / "tracks").glob("random-*.png"))) == 2
    assert client.get(f"/tracks/random:{2**40}/plot.png").status_code == 404


def test_gzip_skips_replays(client: TestClient, settings: Settings) -> None:
    (settings.replays_dir / "5.viser").write_bytes(os.urandom(4096))
    r = client.get("/replays/5.viser", headers={"accept-encoding": "gzip"})
    assert r.status_code == 200 and "content-encoding" not in r.headers
