"""Fixtures for the leaderboard tests: an app on a temporary database, users with tokens,
bundles built on the fly, seeded rows, and a real PostgreSQL server for the tests that need one.

Reusable by every test under ``tests/leaderboard``:

* ``settings`` — :class:`Settings` on a fresh data folder (SQLite), tracks ``oval``/``bean``.
* ``app`` / ``client`` — ``create_app(settings)`` and a ``TestClient`` on it.
* ``db`` — a session on the app's database (closed after the test).
* ``alice`` / ``bob`` — :class:`Account` (user name, token, ``headers`` for requests).
* ``bundle_zip(name=..., extra=b"")`` — a valid python-format bundle zip (its agent drives
  like the pursuit baseline, inside the sandbox).
* ``seeded`` — a :class:`Seeded` leaderboard: 5 submissions, 6 finished ranked races (with
  replay files), ratings applied through the real code path.
* ``pg_url`` — a database URL on a throwaway PostgreSQL database (skips if the binaries are
  missing).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text
from sqlalchemy.orm import Session

from leaderboard import auth
from leaderboard.app import create_app
from leaderboard.settings import Settings
from tests.leaderboard import factories

PG_BIN_GLOB = "/usr/lib/postgresql/*/bin"


@dataclass(frozen=True)
class Account:
    """A user and one of their API tokens."""

    name: str
    token: str

    @property
    def headers(self) -> dict[str, str]:
        """The ``Authorization`` header for this user."""
        return {"Authorization": f"Bearer {self.token}"}


# Starlette's TestClient sends "Host: testserver"; the service serves 127.0.0.1/localhost only.
TEST_HOSTS = ["127.0.0.1", "localhost", "testserver"]


@pytest.fixture(autouse=True, scope="session")
def _test_hosts() -> Iterator[None]:
    """Let every app built in these tests (TestClient included) answer the test hosts."""
    before = os.environ.get("SLIPSTREAM_ALLOWED_HOSTS")
    os.environ["SLIPSTREAM_ALLOWED_HOSTS"] = json.dumps(TEST_HOSTS)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("SLIPSTREAM_ALLOWED_HOSTS", None)
        else:
            os.environ["SLIPSTREAM_ALLOWED_HOSTS"] = before


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    """Settings on a fresh data folder (SQLite database inside it)."""
    return Settings(
        data_dir=tmp_path / "data",
        tracks=["oval", "bean"],
        admin_token="test-admin-token-0123456789",
    )


@pytest.fixture
def app(settings: Settings) -> FastAPI:
    """The leaderboard app on the temporary database."""
    return create_app(settings)


@pytest.fixture
def client(app: FastAPI) -> Iterator[TestClient]:
    """A test client for ``app``."""
    with TestClient(app) as c:
        yield c


@pytest.fixture
def db(app: FastAPI) -> Iterator[Session]:
    """A session on the app's database."""
    session: Session = app.state.sessionmaker()
    try:
        yield session
    finally:
        session.close()


def _account(db: Session, name: str) -> Account:
    _, token = auth.create_user(db, name=name)
    db.commit()
    return Account(name=name, token=token)


@pytest.fixture
def alice(db: Session) -> Account:
    """A user with a token."""
    return _account(db, "alice")


@pytest.fixture
def bob(db: Session) -> Account:
    """Another user with a token."""
    return _account(db, "bob")


@pytest.fixture
def bundle_zip(tmp_path: Path) -> Callable[..., Path]:
    """``bundle_zip(name="racer", extra=b"")``: a valid python bundle zip (``extra``: an
    additional ``pad.bin`` member, to make it large)."""
    return lambda name="racer", extra=b"": factories.python_bundle(
        tmp_path / f"{name}-{uuid.uuid4().hex[:6]}.zip", name=name, extra=extra
    )


@dataclass
class Seeded:
    """What the ``seeded`` fixture put in the database."""

    submission_ids: list[int] = field(default_factory=list)
    race_ids: list[int] = field(default_factory=list)


@pytest.fixture
def seeded(db: Session, settings: Settings) -> Seeded:
    """Five baseline submissions of user ``house`` and six finished ranked races."""
    subs, races = factories.seed(db, settings, n_submissions=5, n_races=6)
    return Seeded(submission_ids=subs, race_ids=races)


# ---- PostgreSQL --------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="session")
def pg_server() -> Iterator[str]:
    """A PostgreSQL server for this test session (initdb + pg_ctl in a temporary folder).

    Runs as the ``postgres`` system user when the tests run as root (initdb refuses root).
    Listens on a Unix socket only. Yields an SQLAlchemy URL of its ``postgres`` database.
    """
    bins = sorted(Path("/").glob(PG_BIN_GLOB.lstrip("/")))
    if not bins or not (bins[-1] / "initdb").exists():
        pytest.skip("PostgreSQL binaries not found (Debian: apt-get install postgresql)")
    bindir = bins[-1]
    root = Path(tempfile.mkdtemp(prefix="slipstream-pg-", dir="/tmp"))
    data, sock = root / "data", root / "sock"
    sock.mkdir()
    prefix: list[str] = []
    if os.geteuid() == 0:
        if shutil.which("runuser") is None:
            pytest.skip("running as root without runuser: cannot start PostgreSQL")
        shutil.chown(root, "postgres")
        shutil.chown(sock, "postgres")
        prefix = ["runuser", "-u", "postgres", "--"]
    port = _free_port()

    def run(*cmd: str) -> None:
        subprocess.run([*prefix, *cmd], check=True, capture_output=True, timeout=120)

    run(str(bindir / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres", "--no-sync")
    opts = f"-p {port} -k {sock} -c listen_addresses='' -c fsync=off -c full_page_writes=off"
    run(str(bindir / "pg_ctl"), "-D", str(data), "-o", opts, "-l", str(root / "log"), "-w", "start")
    try:
        yield f"postgresql+psycopg://postgres@/postgres?host={sock}&port={port}"
    finally:
        subprocess.run(
            [*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
            capture_output=True,
            timeout=60,
            check=False,
        )
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def pg_url(pg_server: str) -> Iterator[str]:
    """A fresh, empty PostgreSQL database for one test (dropped afterwards)."""
    name = f"t_{uuid.uuid4().hex[:12]}"
    admin = create_engine(pg_server, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield pg_server.replace("/postgres?", f"/{name}?")
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()
