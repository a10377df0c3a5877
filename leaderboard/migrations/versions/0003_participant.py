"""The participant's view: race time and penalties per car, race events, owner-only logs.

* ``race_entries.race_time`` / ``penalties``: the result's race time (s, before penalties)
  and the penalty seconds added, so pages can show race time + penalties = total.
* ``races.events``: the replay log's events (laps, collisions, off-tracks, DNFs) for the race
  page's timeline.
* ``race_logs``: per race and car, the DNF detail (traceback), the policy's kept
  stdout/stderr and the sandbox mode; only the car's owner is shown them.
* ``web_sessions``: browsers signed in with an API token (:mod:`leaderboard.web.session`).

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23 22:20:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table("race_entries", schema=None) as batch_op:
        batch_op.add_column(sa.Column("race_time", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("penalties", sa.Float(), nullable=True))
    with op.batch_alter_table("races", schema=None) as batch_op:
        batch_op.add_column(sa.Column("events", sa.JSON(), nullable=True))
    op.create_table(
        "race_logs",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("race_id", sa.Integer(), nullable=False),
        sa.Column("car", sa.Integer(), nullable=False),
        sa.Column("dnf_detail", sa.Text(), nullable=True),
        sa.Column("output", sa.Text(), nullable=True),
        sa.Column("sandbox_mode", sa.String(length=16), nullable=True),
        sa.ForeignKeyConstraint(["race_id"], ["races.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("race_id", "car", name="uq_logs_race_car"),
    )
    op.create_table(
        "web_sessions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("session_hash", sa.String(length=64), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=False),
        sa.Column("token_id", sa.Integer(), nullable=False),
        sa.Column("csrf", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("expires_at", sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["token_id"], ["api_tokens.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("session_hash"),
    )
    with op.batch_alter_table("web_sessions", schema=None) as batch_op:
        batch_op.create_index("ix_web_sessions_user_id", ["user_id"], unique=False)


def downgrade() -> None:
    """Revert this revision."""
    op.drop_table("web_sessions")
    op.drop_table("race_logs")
    with op.batch_alter_table("races", schema=None) as batch_op:
        batch_op.drop_column("events")
    with op.batch_alter_table("race_entries", schema=None) as batch_op:
        batch_op.drop_column("penalties")
        batch_op.drop_column("race_time")
