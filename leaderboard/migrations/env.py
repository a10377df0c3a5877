"""Alembic environment: runs migrations on the engine given in the config (or from its URL).

Alembic executes this file; imported any other way (``pytest --doctest-modules``) it does
nothing.
"""

from __future__ import annotations

from alembic import context

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


def run_migrations_online() -> None:
    """Migrate through a connection of the configured engine."""
    engine = context.config.attributes.get("engine")
    url = context.config.get_main_option("sqlalchemy.url") or ""
    owned = engine is None
    if engine is None:
        engine = make_engine(url)
    try:
        with engine.connect() as connection:
            context.configure(
                connection=connection,
                target_metadata=target_metadata,
                render_as_batch=connection.dialect.name == "sqlite",  # SQLite cannot ALTER much
                compare_type=True,
            )
            with context.begin_transaction():
                context.run_migrations()
    finally:
        if owned:
            engine.dispose()


if not hasattr(context, "config"):  # not run by Alembic
    pass
elif context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
