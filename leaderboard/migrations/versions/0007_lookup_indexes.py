"""Indexes for the submission page's look-ups (issue 13).

* ``race_entries.version_id``: a version's races (its validation races, its robustness run),
  and the ``ON DELETE SET NULL`` of a deleted version, no longer scan every entry;
* ``track_records.submission_id``: a submission's best lap per track in one look-up (the
  unique index leads with the track).

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-25 07:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    op.create_index("ix_entries_version_id", "race_entries", ["version_id"], unique=False)
    op.create_index("ix_records_submission_id", "track_records", ["submission_id"], unique=False)


def downgrade() -> None:
    """Revert this revision."""
    op.drop_index("ix_records_submission_id", table_name="track_records")
    op.drop_index("ix_entries_version_id", table_name="race_entries")
