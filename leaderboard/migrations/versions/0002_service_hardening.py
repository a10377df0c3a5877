"""Service hardening: indexes behind duplicate-bundle checks, ranked race counts and caches.

* ``ix_versions_sha256``: an upload identical to a stored version is refused (409).
* ``ix_races_kind_status_track``: ``/tracks`` counts finished ranked races per track.
* ``ix_submissions_updated_at``, ``ix_races_finished_at``, ``ix_records_set_at``: the
  fingerprints of the cached leaderboard and track snapshots are single index look-ups.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-23 22:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# (table, index, columns)
INDEXES = (
    ("submission_versions", "ix_versions_sha256", ["sha256"]),
    ("races", "ix_races_kind_status_track", ["kind", "status", "track"]),
    ("races", "ix_races_finished_at", ["finished_at"]),
    ("submissions", "ix_submissions_updated_at", ["updated_at"]),
    ("track_records", "ix_records_set_at", ["set_at"]),
)


def upgrade() -> None:
    """Apply this revision."""
    for table, name, columns in INDEXES:
        op.create_index(name, table, columns, unique=False)


def downgrade() -> None:
    """Revert this revision."""
    for table, name, _columns in reversed(INDEXES):
        op.drop_index(name, table_name=table)
