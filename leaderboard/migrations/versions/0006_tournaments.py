"""Tournaments: an operator's event beside the ladder (leaderboard.tournaments).

* ``tournaments``: format, car class, tracks, seeds, laps, heat and final sizes, status;
* ``tournament_entrants``: its submissions, the version each races, their seeding;
* ``races.tournament_id`` / ``races.stage``: a tournament's heats, trials and final (races of
  kind ``tournament``).

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24 14:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    op.create_table(
        "tournaments",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=64), nullable=False),
        sa.Column("format", sa.String(length=16), nullable=False),
        sa.Column("car", sa.String(length=16), nullable=False),
        sa.Column("tracks", sa.JSON(), nullable=False),
        sa.Column("seeds", sa.JSON(), nullable=False),
        sa.Column("laps", sa.Integer(), nullable=False),
        sa.Column("heat_size", sa.Integer(), nullable=False),
        sa.Column("final_size", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("created_by", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("finished_at", sa.DateTime(), nullable=True),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_table(
        "tournament_entrants",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("tournament_id", sa.Integer(), nullable=False),
        sa.Column("submission_id", sa.Integer(), nullable=False),
        sa.Column("version_id", sa.Integer(), nullable=True),
        sa.Column("seed_rank", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=128), nullable=False),
        sa.Column("source", sa.String(length=1024), nullable=False),
        sa.ForeignKeyConstraint(["tournament_id"], ["tournaments.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["submission_id"], ["submissions.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["version_id"], ["submission_versions.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("tournament_id", "submission_id", name="uq_tournament_entrants"),
    )
    with op.batch_alter_table("tournament_entrants", schema=None) as batch_op:
        batch_op.create_index(
            "ix_tournament_entrants_tournament_id", ["tournament_id"], unique=False
        )
    with op.batch_alter_table("races", schema=None) as batch_op:
        batch_op.add_column(sa.Column("tournament_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("stage", sa.String(length=16), nullable=True))
        batch_op.create_foreign_key(
            "fk_races_tournament", "tournaments", ["tournament_id"], ["id"], ondelete="CASCADE"
        )
        batch_op.create_index("ix_races_tournament_id", ["tournament_id", "id"], unique=False)


def downgrade() -> None:
    """Revert this revision."""
    with op.batch_alter_table("races", schema=None) as batch_op:
        batch_op.drop_index("ix_races_tournament_id")
        batch_op.drop_constraint("fk_races_tournament", type_="foreignkey")
        batch_op.drop_column("stage")
        batch_op.drop_column("tournament_id")
    op.drop_table("tournament_entrants")
    op.drop_table("tournaments")
