"""Alembic environment: runs migrations on the engine given in the config (or from its URL).

Alembic executes this file; imported any other way (``pytest --doctest-modules``) it does
nothing.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager, nullcontext

from alembic import context
from sqlalchemy import Connection, event

from leaderboard.db import is_sqlite, make_engine
from leaderboard.models import Base

target_metadata = Base.metadata


def run_migrations_offline() -> None:
    """Emit SQL to stdout (``alembic upgrade --sql``) without connecting."""
    url = context.config.get_main_option("sqlalchemy.url")
    context.configure(
        url=url,
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=bool(url and is_sqlite(url)),
    )
    with context.begin_transaction():
        context.run_migrations()


@contextmanager
def _sqlite_own_transactions(connection: Connection) -> Iterator[None]:
    """Let SQLAlchemy, not Python's sqlite3 module, delimit this connection's transactions.

    In its legacy transaction mode, sqlite3 opens a transaction only before ``INSERT``,
    ``UPDATE``, ``DELETE`` and ``REPLACE``, so the ``CREATE TABLE _alembic_tmp_...`` of a
    batch migration committed on its own: a migration killed half-way left that table behind
    and the next start failed on it. SQLAlchemy's recipe for pysqlite (serializable isolation
    / savepoints / transactional DDL): turn the driver's handling off and emit ``BEGIN`` when
    SQLAlchemy begins; then every statement, DDL included, is in the transaction and a crash
    rolls all of it back. Only this (migration) connection, and only while it migrates.
    """
    driver = connection.connection.driver_connection
    before = driver.isolation_level  # type: ignore[union-attr]

    def begin(conn: Connection) -> None:
        conn.exec_driver_sql("BEGIN")

    driver.isolation_level = None  # type: ignore[union-attr]
    event.listen(connection, "begin", begin)
    try:
        yield
    finally:
        event.remove(connection, "begin", begin)
        driver.isolation_level = before  # type: ignore[union-attr]


def run_migrations_online() -> None:
    """Migrate through a connection of the configured engine, all revisions in one
    transaction (on SQLite too: a migration killed half-way leaves the database as it was).

    On SQLite, foreign keys are off while the migrations run and checked afterwards: a batch
    migration copies a table, drops the old one and renames the copy, and with foreign keys
    on, that ``DROP TABLE`` deletes every row first — failing on rows still referenced
    (``submissions.active_version_id``), or running the referencing tables' ``ON DELETE``
    actions (nulling or deleting their rows) before failing, a scan per row on large tables
    (Alembic's documented recipe for SQLite batch mode).
    """
    engine = context.config.attributes.get("engine")
    url = context.config.get_main_option("sqlalchemy.url") or ""
    owned = engine is None
    if engine is None:
        engine = make_engine(url)
    try:
        with engine.connect() as connection:
            sqlite = connection.dialect.name == "sqlite"
            if sqlite:  # a no-op inside a transaction: set before the migrations' one
                connection.exec_driver_sql("PRAGMA foreign_keys=OFF")
                connection.commit()
            try:
                with _sqlite_own_transactions(connection) if sqlite else nullcontext():
                    context.configure(
                        connection=connection,
                        target_metadata=target_metadata,
                        render_as_batch=sqlite,  # SQLite cannot ALTER much
                        compare_type=True,
                        # Alembic takes SQLite's DDL as non-transactional (one transaction per
                        # revision at most); with the driver out of the way it is.
                        transactional_ddl=True if sqlite else None,
                    )
                    with context.begin_transaction():
                        context.run_migrations()
                        if sqlite:
                            broken = connection.exec_driver_sql(
                                "PRAGMA foreign_key_check"
                            ).fetchall()
                            if broken:  # roll the migration back rather than keep them
                                raise RuntimeError(f"migration broke foreign keys: {broken[:5]}")
            finally:
                if sqlite:
                    connection.rollback()  # nothing is pending here; PRAGMA needs no transaction
                    connection.exec_driver_sql("PRAGMA foreign_keys=ON")
                    connection.commit()
    finally:
        if owned:
            engine.dispose()


if not hasattr(context, "config"):  # not run by Alembic
    pass
elif context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
