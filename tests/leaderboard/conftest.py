"""Fixtures for the leaderboard tests: an app on a temporary database, users with tokens,
bundles built on the fly, seeded rows, and a real PostgreSQL server for the tests that need one.

Reusable by every test under ``tests/leaderboard``:

* ``settings`` — :class:`Settings` on a fresh data folder (SQLite, a copy of an empty database
  migrated once per session), tracks ``oval``/``bean``.
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
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import make_url
from sqlalchemy.orm import Session

from leaderboard import auth, localpg
from leaderboard.app import create_app
from leaderboard.db import make_engine
from leaderboard.migrations import upgrade
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


@pytest.fixture(scope="session")
def migrated_sqlite(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An empty SQLite database migrated to ``head``, made once per test session (worker).

    Each ``settings`` starts from a copy of it, so ``create_app`` finds the schema at head
    (~0.02 s) instead of migrating from nothing (~0.2-0.4 s a test). Migrating an empty or
    old database is what ``test_migrations.py`` checks, on its own databases.
    """
    path = tmp_path_factory.mktemp("migrated") / "leaderboard.db"
    url = f"sqlite:///{path}"
    engine = make_engine(url)
    try:
        upgrade(url, engine=engine)
    finally:
        engine.dispose()  # the last connection closed: the WAL is folded into the file
    return path


@pytest.fixture
def settings(tmp_path: Path, migrated_sqlite: Path) -> Settings:
    """Settings on a fresh data folder (SQLite database inside it, empty, at ``head``)."""
    settings = Settings(
        data_dir=tmp_path / "data",
        tracks=["oval", "bean"],
        admin_token="test-admin-token-0123456789",
    )
    database = Path(make_url(settings.db_url).database or "")
    database.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(migrated_sqlite, database)
    return settings


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


@pytest.fixture(scope="session")
def pg_server() -> Iterator[str]:
    """A PostgreSQL server for this test session (:func:`leaderboard.localpg.throwaway_server`:
    initdb + pg_ctl in a temporary folder, a Unix socket only). Yields an SQLAlchemy URL of its
    ``postgres`` database."""
    try:
        with localpg.throwaway_server() as url:
            yield url
    except localpg.PostgresUnavailable as err:  # raised before the yield only
        pytest.skip(str(err))


@pytest.fixture
def pg_url(pg_server: str) -> Iterator[str]:
    """A fresh, empty PostgreSQL database for one test (dropped afterwards)."""
    url = localpg.create_database(pg_server)
    try:
        yield url
    finally:
        localpg.drop_database(pg_server, url)
