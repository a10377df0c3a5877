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


def test_migrations_keep_the_rows_and_their_references_on_sqlite(tmp_path: Path) -> None:
    """SQLite batch migrations (copy, drop, rename) on a database with data: with foreign keys
    on, dropping ``submission_versions`` failed (``submissions.active_version_id`` points at it)
    or nulled the references of ``race_entries`` and ``track_records`` first. Down to 0003
    and up again keeps every row and every reference."""
    from sqlalchemy import text
    from sqlalchemy.orm import Session

    from leaderboard.settings import Settings
    from tests.leaderboard import factories

    url = f"sqlite:///{tmp_path / 'lb.db'}"
    settings = Settings(data_dir=tmp_path / "data", database_url=url, tracks=["oval"])
    engine = make_engine(url)
    snapshot = {
        "submissions": "SELECT id, status, active_version_id FROM submissions ORDER BY id",
        "entries": "SELECT id, race_id, submission_id, version_id FROM race_entries ORDER BY id",
        "records": "SELECT id, submission_id, version_id, race_id FROM track_records ORDER BY id",
        "jobs": "SELECT id, race_id, status FROM jobs ORDER BY id",
    }
    try:
        upgrade(url, engine=engine)
        with Session(engine) as session:
            factories.seed(session, settings, n_submissions=3, n_races=3)
        with engine.connect() as conn:
            before = {k: conn.execute(text(q)).all() for k, q in snapshot.items()}
        assert before["records"] and any(v for _, _, _, v in before["entries"])
        downgrade(url, "0003", engine=engine)
        upgrade(url, engine=engine)
        with engine.connect() as conn:
            after = {k: conn.execute(text(q)).all() for k, q in snapshot.items()}
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1  # back on
        assert after == before
    finally:
        engine.dispose()


# A migration run killed half-way through a batch operation: SQLite batch mode copies the
# table into ``_alembic_tmp_<table>``, drops the original and renames the copy (Alembic's
# batch docs); this kills the process (SIGKILL: nothing gets to clean up) just before the
# rename, when the original table is already gone.
KILL_BEFORE_BATCH_RENAME = """
import os, signal, sys
from alembic.ddl.impl import DefaultImpl
from leaderboard.migrations import upgrade

rename = DefaultImpl.rename_table

def killed(self, old, new, schema=None):
    if old.startswith("_alembic_tmp_"):
        os.kill(os.getpid(), signal.SIGKILL)
    rename(self, old, new, schema)

DefaultImpl.rename_table = killed
upgrade(sys.argv[1])
"""


def test_a_migration_killed_mid_batch_leaves_the_database_as_it_was(tmp_path: Path) -> None:
    """SQLite migrations run in one transaction: SIGKILLed during the batch rebuild of
    ``races`` (0005 → 0006), the database is still at 0005 with every row, no
    ``_alembic_tmp_*`` table is left, and the next start migrates to head."""
    import signal
    import subprocess
    import sys

    from sqlalchemy import text
    from sqlalchemy.orm import Session

    from leaderboard.app import create_app
    from leaderboard.settings import Settings
    from tests.leaderboard import factories

    url = f"sqlite:///{tmp_path / 'lb.db'}"
    settings = Settings(data_dir=tmp_path / "data", database_url=url, tracks=["oval"])
    engine = make_engine(url)
    rows = "SELECT id, kind, status, track, seed FROM races ORDER BY id"
    try:
        upgrade(url, engine=engine)
        with Session(engine) as session:
            factories.seed(session, settings, n_submissions=3, n_races=3)
        downgrade(url, "0005", engine=engine)
        with engine.connect() as conn:
            before = conn.execute(text(rows)).all()
        assert before
        engine.dispose()  # the killed process must not find our connection mid-transaction

        run = subprocess.run(
            [sys.executable, "-c", KILL_BEFORE_BATCH_RENAME, url],
            capture_output=True,
            timeout=300,
            check=False,
        )
        assert run.returncode == -signal.SIGKILL, run.stderr.decode()[-2000:]

        assert current(url, engine=engine) == "0005"
        tables = set(inspect(engine).get_table_names())
        assert not {t for t in tables if t.startswith("_alembic_tmp_")}, tables
        assert "tournaments" not in tables  # 0006's new tables went with the rest
        with engine.connect() as conn:
            assert conn.execute(text(rows)).all() == before
        engine.dispose()

        create_app(settings)  # the next start: migrates to head
        assert current(url, engine=engine) == head_revision(url)
        with engine.connect() as conn:
            assert conn.execute(text(rows)).all() == before
    finally:
        engine.dispose()
