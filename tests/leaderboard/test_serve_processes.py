"""``slipstream serve --web-workers 2``: server processes sharing one port (issue 13, load).

One real server is started the way an operator starts it (the console command, a fresh SQLite
database it must migrate itself, before its workers start), then hit over fresh connections —
the kernel hands each new connection to either process — as the website's visitors and an
API client do: a race worker's rating writes and an API write are seen by the next read
whichever process answers it, and the per-token rate limit still holds with each process
counting on its own (each enforces its share, ``floor(limit / 2)``).
"""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import limits
import pytest
from sqlalchemy import Engine, select
from sqlalchemy.orm import Session

from leaderboard import auth, matchmaking
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.limits import process_share, share_of_rate
from leaderboard.models import Submission
from leaderboard.serving import SETTINGS_ENV, settings_json
from leaderboard.settings import Settings
from tests.leaderboard import factories
from tests.leaderboard.test_migrations import head_revision

WORKERS = 2
TOKEN_LIMIT = 20  # per hour: each of the two processes lets 10 through
# (an hour's window, not a minute's: on a loaded machine the test's 51 requests outlasted a
# minute, the first ones aged out of the moving window, and the 429 it waits for never came)
READS = 12  # fresh connections per check: both processes answer some (kernel's choice)


@dataclass
class Server:
    """A ``slipstream serve --web-workers 2`` process tree and its database."""

    url: str
    settings: Settings
    proc: subprocess.Popen[bytes]
    engine: Engine

    def session(self) -> Session:
        """A session on the server's database (as a race worker would open)."""
        return make_sessionmaker(self.engine)()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The server on a fresh data folder (no schema yet: the parent migrates it once)."""
    data_dir = tmp_path_factory.mktemp("serve-processes")
    port = _free_port()
    env = {
        **os.environ,
        "SLIPSTREAM_RATE_LIMIT_TOKEN": f"{TOKEN_LIMIT}/hour",
        "SLIPSTREAM_RATE_LIMIT_IP": "100000/minute",
        "SLIPSTREAM_ROBUSTNESS": "false",
    }
    cmd = [sys.executable, "-m", "leaderboard.cli", "serve", "--port", str(port),
           "--data-dir", str(data_dir), "--web-workers", str(WORKERS)]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, start_new_session=True, stderr=subprocess.PIPE)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 90
    try:
        while True:
            assert proc.poll() is None, (proc.stderr.read() if proc.stderr else b"").decode()
            try:
                if httpx.get(f"{url}/api/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "the server did not answer within 90 s"
            time.sleep(0.2)
        settings = Settings(data_dir=data_dir, robustness=False)
        engine = make_engine(settings.db_url)
        yield Server(url, settings, proc, engine)
        engine.dispose()
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)


def _children(pid: int) -> list[int]:
    """Ids of the live processes whose parent is ``pid`` (from /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rpartition(")")[2].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def _cmdline(pid: int) -> str:
    return (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode()


def test_two_processes_serve_one_migrated_database(server: Server) -> None:
    """The supervisor runs two worker processes; the schema it migrated is at head."""
    workers = [p for p in _children(server.proc.pid) if "spawn_main" in _cmdline(p)]
    assert len(workers) == WORKERS
    health = httpx.get(f"{server.url}/api/health", timeout=10).json()
    assert health["revision"] == head_revision("sqlite://")


def test_writes_are_seen_by_every_process(server: Server) -> None:
    """A race worker's rating writes, then an API write: every following read sees them,
    whichever process answers (each keeps its own leaderboard snapshot)."""
    rng = random.Random(0)
    with server.session() as db:
        subs, _ = factories.seed(db, server.settings, n_submissions=4, n_races=2)
    ladder = f"{server.url}/api/leaderboard"
    for _ in range(READS):  # every process caches the ladder as it is now
        assert httpx.get(ladder, timeout=10).status_code == 200

    with server.session() as db:  # what `slipstream worker` does: more rated races
        matchmaking.schedule_ranked(db, server.settings, 3, rng)
        db.commit()
        factories.finish_queue(db, server.settings, rng)
        want = {
            s.id: round(s.ordinal, 9)
            for s in db.scalars(select(Submission).where(Submission.id.in_(subs)))
        }
        _, token = auth.create_user(db, name="reader")
        db.commit()
    for _ in range(READS):
        rows = httpx.get(ladder, timeout=10).json()["items"]
        assert {r["submission_id"]: round(r["ordinal"], 9) for r in rows} == want

    headers = {"Authorization": f"Bearer {token}"}
    made = httpx.post(
        f"{server.url}/api/tokens", json={"label": "laptop"}, headers=headers, timeout=10
    )
    assert made.status_code == 201
    for _ in range(TOKEN_LIMIT // WORKERS - 1):  # with the POST, within one process's share
        listed = httpx.get(f"{server.url}/api/tokens", headers=headers, timeout=10)
        assert listed.status_code == 200, listed.text
        assert "laptop" in {t["label"] for t in listed.json()}


def test_rate_limit_holds_across_processes(server: Server) -> None:
    """40 requests with one token, on fresh connections spread over both processes: at most
    the configured 20 get through, at least one process's share (10); the rest get 429. Then
    one keep-alive connection (one process) gets 429 with Retry-After once its share is spent."""
    with server.session() as db:
        _, token = auth.create_user(db, name="hammer")
        db.commit()
    headers = {"Authorization": f"Bearer {token}"}
    codes = [
        httpx.get(f"{server.url}/api/users/me", headers=headers, timeout=10).status_code
        for _ in range(2 * TOKEN_LIMIT)
    ]
    assert set(codes) <= {200, 429}
    assert TOKEN_LIMIT // WORKERS <= codes.count(200) <= TOKEN_LIMIT
    with httpx.Client(base_url=server.url, headers=headers, timeout=10) as one_connection:
        answers = [one_connection.get("/api/users/me") for _ in range(TOKEN_LIMIT // WORKERS + 1)]
    refused = answers[-1]
    assert refused.status_code == 429 and int(refused.headers["retry-after"]) >= 1
    assert "share" in refused.json()["detail"]


def test_shares_never_add_up_to_more_than_the_limit() -> None:
    """Each of n processes enforces floor(limit / n) (at least 1), same window."""
    for amount in (1, 2, 3, 20, 299, 600):
        for n in (1, 2, 3, 4, 7):
            share = process_share(amount, n)
            assert share >= 1
            assert share * n <= max(amount, n)  # the limit holds (one each if fewer than n)
            assert share * n > amount - n  # and each process gets its full share
    item = share_of_rate(limits.parse("600/minute"), 4)
    assert (item.amount, item.GRANULARITY.seconds) == (150, 60)
    assert share_of_rate(limits.parse("20 per 10 seconds"), 1) == limits.parse("20/10 seconds")


def test_a_server_process_exempts_its_startup_objects_from_gc_scans(tmp_path: Path) -> None:
    """A worker process builds its app, then freezes what is alive (``gc.freeze``): the full
    collections that stalled every request in flight (40-160 ms each, the 8-client p99 of
    ``bench/leaderboard_load.py``) no longer walk the app's ~150k startup objects. Run in a
    fresh interpreter, as a ``--web-workers`` process starts (a frozen heap in the test
    process would outlive the test)."""
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'lb.db'}", data_dir=tmp_path, secret_key="x" * 32
    )
    code = (
        "import gc; from leaderboard.serving import worker_app; "
        "before = gc.get_freeze_count(); app = worker_app(); "
        "print(before, gc.get_freeze_count(), len(gc.get_objects()))"
    )
    env = {**os.environ, SETTINGS_ENV: settings_json(settings)}
    out = subprocess.run(
        [sys.executable, "-c", code],
        check=False,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    before, frozen, scanned = (int(n) for n in out.stdout.split())
    assert before == 0
    assert frozen > 50_000  # the app, its modules and routes …
    assert scanned < frozen // 10  # … and what a full collection still walks is a fraction
