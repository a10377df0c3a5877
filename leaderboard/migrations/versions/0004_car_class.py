"""Car classes: each version and each race records its car preset (one ladder per car).

* ``submission_versions.car``: the manifest's ``car`` (``f1tenth`` for every earlier version);
* ``races.car``: the car every car of the race drives (``f1tenth`` for every earlier race).

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24 10:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TABLES = ("submission_versions", "races")


def upgrade() -> None:
    """Apply this revision."""
    for table in TABLES:
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.add_column(
                sa.Column("car", sa.String(length=16), server_default="f1tenth", nullable=False)
            )


def downgrade() -> None:
    """Revert this revision."""
    for table in reversed(TABLES):
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.drop_column("car")
