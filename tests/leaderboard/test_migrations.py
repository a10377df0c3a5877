"""Alembic migrations up and down, on SQLite and on a real PostgreSQL; they match the models."""

from __future__ import annotations

from pathlib import Path

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect

from leaderboard.db import make_engine
from leaderboard.migrations import alembic_config, current, downgrade, upgrade
from leaderboard.models import Base

TABLES = {
    "users",
    "api_tokens",
    "submissions",
    "submission_versions",
    "races",
    "race_entries",
    "rating_history",
    "jobs",
    "track_records",
}


def head_revision(url: str) -> str:
    """The newest revision of the migration scripts."""
    head = ScriptDirectory.from_config(alembic_config(url)).get_current_head()
    assert head is not None
    return head


def test_revisions_form_one_chain_through_the_hardening_step(tmp_path: Path) -> None:
    script = ScriptDirectory.from_config(alembic_config(f"sqlite:///{tmp_path / 'x.db'}"))
    chain = [rev.revision for rev in script.walk_revisions()]  # head first
    assert chain[-2:] == ["0002", "0001"]
    assert len(script.get_heads()) == 1


def _round_trip(url: str) -> None:
    engine = make_engine(url)
    try:
        upgrade(url, engine=engine)
        assert current(url, engine=engine) == head_revision(url)
        assert set(inspect(engine).get_table_names()) >= TABLES
        with engine.connect() as conn:  # the schema the migrations build is the models' schema
            assert compare_metadata(MigrationContext.configure(conn), Base.metadata) == []
        downgrade(url, "base", engine=engine)
        assert current(url, engine=engine) is None
        assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
        upgrade(url, engine=engine)  # and up again
        assert set(inspect(engine).get_table_names()) >= TABLES
    finally:
        engine.dispose()


def test_migrations_up_and_down_on_sqlite(tmp_path: Path) -> None:
    _round_trip(f"sqlite:///{tmp_path / 'lb.db'}")


def test_migrations_up_and_down_on_postgresql(pg_url: str) -> None:
    _round_trip(pg_url)


def test_sqlite_runs_in_wal_mode(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'lb.db'}")
    with engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    engine.dispose()
