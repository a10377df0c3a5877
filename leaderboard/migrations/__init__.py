"""Alembic migrations of the leaderboard database, configured in code (no ``alembic.ini``).

>>> from leaderboard.migrations import alembic_config
>>> alembic_config("sqlite://").get_main_option("script_location")
'leaderboard:migrations'

``create_app`` runs :func:`upgrade` to ``head`` on start; the ``alembic`` command works too,
with ``-c`` pointing at no file: ``python -m leaderboard.migrations upgrade|downgrade REV URL``.
"""

from __future__ import annotations

import sys

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine

SCRIPT_LOCATION = "leaderboard:migrations"


def alembic_config(url: str, engine: Engine | None = None) -> Config:
    """An Alembic configuration for the database at ``url`` (reusing ``engine`` if given)."""
    cfg = Config()
    cfg.set_main_option("script_location", SCRIPT_LOCATION)
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    if engine is not None:
        cfg.attributes["engine"] = engine
    return cfg


def upgrade(url: str, revision: str = "head", engine: Engine | None = None) -> None:
    """Migrate the database at ``url`` up to ``revision``."""
    command.upgrade(alembic_config(url, engine), revision)


def downgrade(url: str, revision: str = "base", engine: Engine | None = None) -> None:
    """Migrate the database at ``url`` down to ``revision`` (``base``: no tables)."""
    command.downgrade(alembic_config(url, engine), revision)


def current(url: str, engine: Engine | None = None) -> str | None:
    """The revision the database at ``url`` is at (None: not under migration control)."""
    from alembic.runtime.migration import MigrationContext  # noqa: PLC0415 - rarely needed

    from leaderboard.db import make_engine  # noqa: PLC0415 - keeps this module light

    eng = engine or make_engine(url)
    with eng.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


if __name__ == "__main__":  # pragma: no cover - a thin command line for operators
    if len(sys.argv) != 4 or sys.argv[1] not in ("upgrade", "downgrade"):
        sys.exit("usage: python -m leaderboard.migrations upgrade|downgrade REVISION URL")
    (upgrade if sys.argv[1] == "upgrade" else downgrade)(sys.argv[3], sys.argv[2])
