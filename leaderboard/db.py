"""Database engine and sessions: SQLite (WAL, zero set-up) by default, PostgreSQL by URL.

Nothing connects at import time; :func:`make_engine` is called by ``create_app``, the worker
and the command line with the URL from :class:`leaderboard.settings.Settings`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

SQLITE_BUSY_TIMEOUT_MS = 30_000  # writers wait for each other instead of failing at once
# Connections kept open per engine. The web app answers requests from a pool of threads; with
# SQLAlchemy's default of 5, the 6th concurrent request opened (and then closed) a connection
# of its own every time — a new PostgreSQL backend process, or SQLite's pragmas — which
# showed in the tail latencies with 8 clients (issue 13). Opened only as needed.
POOL_SIZE = 16
POOL_OVERFLOW = 16  # more at once still work, on short-lived connections


def is_sqlite(url: str) -> bool:
    """Whether an SQLAlchemy URL points at SQLite."""
    return make_url(url).get_backend_name() == "sqlite"


def make_engine(url: str, **kwargs: Any) -> Engine:
    """An engine for ``url``; SQLite connections get WAL, foreign keys and a busy timeout.

    WAL lets the web process read while a worker writes; ``foreign_keys=ON`` makes SQLite
    enforce the same constraints as PostgreSQL.
    """
    if make_url(url).database not in (None, "", ":memory:"):  # in-memory SQLite has no pool
        kwargs.setdefault("pool_size", POOL_SIZE)
        kwargs.setdefault("max_overflow", POOL_OVERFLOW)
    if is_sqlite(url):
        kwargs.setdefault("connect_args", {"check_same_thread": False, "timeout": 30})
        engine = create_engine(url, **kwargs)

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
            cur.close()

        return engine
    kwargs.setdefault("pool_pre_ping", True)
    return create_engine(url, **kwargs)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    """A session factory bound to ``engine`` (objects stay usable after commit)."""
    return sessionmaker(bind=engine, expire_on_commit=False)


@contextmanager
def connect(url: str, *, migrate: bool = False) -> Iterator[sessionmaker[Session]]:
    """A session factory on a new engine for ``url``, disposed on exit (for commands).

    With ``migrate``, the schema is first brought up to ``head``.
    """
    engine = make_engine(url)
    try:
        if migrate:
            from leaderboard.migrations import upgrade  # noqa: PLC0415 - alembic, when asked

            upgrade(url, engine=engine)
        yield make_sessionmaker(engine)
    finally:
        engine.dispose()


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """One transaction: commit on success, roll back on any exception."""
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()
