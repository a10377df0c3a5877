"""Robustness on the leaderboard: each ranked version's robustness score and its run.

* ``submission_versions.robust_score``: worst-10 % mean effective speed over the fixed
  perturbation grid, m/s (null until its robustness run has finished);
* ``submission_versions.robust_race_id``: that run (a race of kind ``robustness``).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24 12:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("submission_versions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("robust_score", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("robust_race_id", sa.Integer(), nullable=True))
        batch_op.create_foreign_key(
            "fk_versions_robust_race", "races", ["robust_race_id"], ["id"], ondelete="SET NULL"
        )


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("submission_versions", schema=None) as batch_op:
        batch_op.drop_constraint("fk_versions_robust_race", type_="foreignkey")
        batch_op.drop_column("robust_race_id")
        batch_op.drop_column("robust_score")
