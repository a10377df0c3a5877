"""Submissions and their versions: upload, validate, store, withdraw.

An upload is streamed to disk with a size cap, validated by the submissions package
(:func:`submissions.bundle.open_bundle`: archive safety, manifest, declared spaces), then kept
as ``bundles_dir/<submission id>/v<version>-<random>.zip``. The manifest's ``name`` picks the
submission among the uploader's own: a new name creates a submission, a known one adds a
version. Only the owner can add versions to a submission or withdraw it. Each new version is
queued for a validation race (:func:`leaderboard.matchmaking.schedule_validation`).

Quotas (settings): ``max_uploads_per_day`` uploads per user in any 24 hours (429 with
``Retry-After``), ``max_active_submissions`` pending or active submissions per user and
``max_versions`` versions per submission (409). A bundle byte-identical (same SHA-256) to a
version already stored and not rejected is refused with 409. Concurrent uploads of one new
name get 201 or 409, never a server error: the database part is retried on a lost race.

The web process must not import the simulator: the bundle's manifest is checked against
:meth:`~submissions.bundle.EnvSpec.current`, which reads :mod:`arena.version` (no pybullet).
"""

from __future__ import annotations

import hashlib
import math
import os
import secrets
import shutil
import tempfile
import time
import zipfile
from datetime import timedelta
from pathlib import Path
from typing import BinaryIO

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session

from leaderboard.errors import (
    Conflict,
    Forbidden,
    InvalidBundle,
    NotFound,
    PayloadTooLarge,
    QuotaExceeded,
)
from leaderboard.matchmaking import schedule_validation
from leaderboard.models import Submission, SubmissionVersion, User, utcnow
from leaderboard.settings import Settings
from submissions.bundle import MANIFEST_NAME, BundleLimits, EnvSpec, Manifest, open_bundle
from submissions.errors import BundleError

BASELINES = ("pursuit", "gap", "random")
_CHUNK = 1 << 20
QUOTA_WINDOW = timedelta(days=1)
_DB_RETRIES = 5  # tries of an upload's database part when a concurrent upload wins a race
UPLOAD_NAME = "the uploaded bundle"  # how errors name the file (never the server's temp path)
# Said when a zip without manifest.json comes in: most often a bare checkpoint (issue 13).
NOT_A_BUNDLE_HINT = (
    "; a bundle is a zip with manifest.json next to the policy — for a bare checkpoint, "
    "`slipstream submit CHECKPOINT.zip` wraps it (or run `slipstream bundle wrap CHECKPOINT.zip`)"
)


def save_stream(src: BinaryIO, dest: Path, max_bytes: int) -> tuple[int, str]:
    """Copy an upload to ``dest``, stopping past ``max_bytes``; returns (size, sha256).

    Raises:
        PayloadTooLarge: the stream is longer than ``max_bytes`` (``dest`` is removed).
    """
    digest = hashlib.sha256()
    size = 0
    with dest.open("wb") as out:
        while chunk := src.read(_CHUNK):
            size += len(chunk)
            if size > max_bytes:
                out.close()
                dest.unlink(missing_ok=True)
                raise PayloadTooLarge(f"bundle is larger than {max_bytes / 2**20:.0f} MiB")
            digest.update(chunk)
            out.write(chunk)
    return size, digest.hexdigest()


def validate_bundle(path: Path, settings: Settings) -> Manifest:
    """Check an uploaded bundle with the submissions package's validator; its manifest.

    Raises:
        InvalidBundle: the validator's one-line reason (the server's own file and folder
            names replaced by "the uploaded bundle").
    """
    limits = BundleLimits(max_archive_bytes=settings.max_upload_bytes)
    with tempfile.TemporaryDirectory(prefix="slipstream-check-") as tmp:
        try:
            bundle = open_bundle(path, Path(tmp) / "bundle", limits, env=EnvSpec.current())
        except BundleError as err:
            message = str(err)
            for private in (str(path.resolve()), str(path), str(Path(tmp).resolve()), tmp):
                message = message.replace(private, UPLOAD_NAME)
            message = message.replace(path.name, UPLOAD_NAME)
            if _zip_without_manifest(path):
                message += NOT_A_BUNDLE_HINT
            raise InvalidBundle(f"invalid bundle: {message}") from None
    return bundle.manifest


def _zip_without_manifest(path: Path) -> bool:
    """Whether ``path`` is a readable zip with no ``manifest.json`` at its root."""
    try:
        with zipfile.ZipFile(path) as zf:
            return MANIFEST_NAME not in zf.namelist()
    except (zipfile.BadZipFile, OSError, ValueError):
        return False


def check_daily_quota(session: Session, settings: Settings, user: User) -> None:
    """Refuse an upload past ``settings.max_uploads_per_day`` in the last 24 hours.

    Raises:
        QuotaExceeded: with ``retry_after`` = seconds until the oldest counted upload ages out.
    """
    since = utcnow() - QUOTA_WINDOW
    count, oldest = session.execute(
        select(func.count(SubmissionVersion.id), func.min(SubmissionVersion.created_at))
        .join(Submission, Submission.id == SubmissionVersion.submission_id)
        .where(Submission.user_id == user.id, SubmissionVersion.created_at > since)
    ).one()
    if count >= settings.max_uploads_per_day:
        wait = (oldest + QUOTA_WINDOW - utcnow()).total_seconds() if oldest else 60.0
        raise QuotaExceeded(
            f"{count} uploads in the last 24 hours; the limit is {settings.max_uploads_per_day}",
            retry_after=max(1, math.ceil(wait)),
        )


def check_duplicate(session: Session, sha256: str) -> None:
    """Refuse a bundle identical to a stored version that was not rejected.

    Raises:
        Conflict: names the submission and version that hold the same bytes.
    """
    row = session.execute(
        select(Submission.id, Submission.name, SubmissionVersion.version)
        .join(Submission, Submission.id == SubmissionVersion.submission_id)
        .where(SubmissionVersion.sha256 == sha256, SubmissionVersion.status != "rejected")
        .limit(1)
    ).first()
    if row is not None:
        raise Conflict(
            f"this bundle is identical (SHA-256 {sha256[:12]}…) to version {row.version} of "
            f"submission {row.id} ({row.name!r}); change something before uploading it again"
        )


def upload(
    session: Session,
    settings: Settings,
    *,
    user: User,
    stream: BinaryIO,
    submission_id: int | None = None,
) -> SubmissionVersion:
    """Store an uploaded bundle as a new submission or a new version of one, and commit.

    Args:
        session: the caller's session, with nothing pending (this commits).
        settings: for the size limit, the quotas and the bundle folder.
        user: the uploader.
        stream: the bundle zip.
        submission_id: add a version to this submission (must be the user's); by default
            the manifest's ``name`` selects or creates one of the user's submissions.

    Raises:
        PayloadTooLarge, InvalidBundle: the upload is refused (nothing is stored).
        NotFound, Forbidden: adding by id to a missing submission or someone else's.
        QuotaExceeded: the user's daily upload quota is spent.
        Conflict: a duplicate bundle, too many versions or active submissions, or concurrent
            uploads that kept colliding.
    """
    check_daily_quota(session, settings, user)
    settings.ensure_dirs()
    incoming = settings.bundles_dir / ".incoming"
    incoming.mkdir(exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(suffix=".zip", dir=incoming)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        size, sha = save_stream(stream, tmp, settings.max_upload_bytes)
        manifest = validate_bundle(tmp, settings)
        session.commit()  # the caller's work, and a fresh snapshot that sees concurrent uploads
        for attempt in range(_DB_RETRIES):
            try:
                return _store(session, settings, user, tmp, manifest, size, sha, submission_id)
            except (IntegrityError, OperationalError):
                session.rollback()  # another upload won a race (same name, same version)
                time.sleep(0.02 * (attempt + 1))
        raise Conflict("concurrent uploads to this submission kept colliding; try again")
    finally:
        tmp.unlink(missing_ok=True)


def _store(
    session: Session,
    settings: Settings,
    user: User,
    tmp: Path,
    manifest: Manifest,
    size: int,
    sha: str,
    submission_id: int | None,
) -> SubmissionVersion:
    """The database part of :func:`upload`: one transaction, committed; the file linked in."""
    check_duplicate(session, sha)
    if submission_id is None:
        sub = _named_submission(session, user, manifest.name, settings=settings)
    else:
        sub = owned_submission(session, user=user, submission_id=submission_id)
    if manifest.description:
        sub.description = manifest.description
    version = _new_version(session, settings, sub, source="", fmt=manifest.format)
    dest = settings.bundles_dir / str(sub.id) / f"v{version.version}-{secrets.token_hex(4)}.zip"
    version.source = str(dest.resolve())
    version.manifest = manifest.to_dict()
    version.size_bytes = size
    version.sha256 = sha
    schedule_validation(session, settings, version)
    session.flush()
    dest.parent.mkdir(parents=True, exist_ok=True)
    try:  # the bundle is in place before a worker can see its validation race
        os.link(tmp, dest)
    except OSError:  # no hard links on this file system
        shutil.copyfile(tmp, dest)
    try:
        session.commit()
    except BaseException:
        dest.unlink(missing_ok=True)
        raise
    return version


def add_baseline(
    session: Session, settings: Settings, *, user: User, baseline: str, name: str | None = None
) -> SubmissionVersion:
    """Enter one of our baselines (``pursuit``, ``gap``, ``random``) as a submission.

    Baselines are our own code, so they race in-process rather than sandboxed; they still
    get a validation race like every version.

    Raises:
        NotFound: not a baseline name.
    """
    if baseline not in BASELINES:
        raise NotFound(f"no baseline {baseline!r} (one of {', '.join(BASELINES)})")
    name = name or baseline
    sub = _named_submission(session, user, name, description=f"the {baseline} baseline")
    version = _new_version(session, settings, sub, source=baseline, fmt="baseline")
    version.manifest = {"name": name, "author": user.name, "format": "baseline"}
    schedule_validation(session, settings, version)
    return version


def _named_submission(
    session: Session,
    user: User,
    name: str,
    description: str = "",
    *,
    settings: Settings | None = None,
) -> Submission:
    """The user's submission called ``name``, created (with ``description``) if missing.

    With ``settings``, a new one counts against ``settings.max_active_submissions``.

    Raises:
        Conflict: the user already has that many pending or active submissions.
    """
    sub = session.scalar(
        select(Submission).where(Submission.user_id == user.id, Submission.name == name)
    )
    if sub is None:
        if settings is not None:
            live = session.scalar(
                select(func.count(Submission.id)).where(
                    Submission.user_id == user.id, Submission.status.in_(("pending", "active"))
                )
            )
            if (live or 0) >= settings.max_active_submissions:
                raise Conflict(
                    f"you have {live} pending or active submissions; the limit is "
                    f"{settings.max_active_submissions} (withdraw one, or upload a new "
                    "version of an existing one)"
                )
        sub = Submission(user_id=user.id, name=name, description=description)
        session.add(sub)
        session.flush()
    return sub


def _new_version(
    session: Session, settings: Settings, sub: Submission, *, source: str, fmt: str
) -> SubmissionVersion:
    if sub.status == "withdrawn":
        sub.status = "active" if sub.active_version_id is not None else "pending"
    latest, count = session.execute(
        select(func.max(SubmissionVersion.version), func.count(SubmissionVersion.id)).where(
            SubmissionVersion.submission_id == sub.id
        )
    ).one()
    if count >= settings.max_versions:
        raise Conflict(f"submission {sub.name!r} has {count} versions; the limit is reached")
    version = SubmissionVersion(
        submission_id=sub.id, version=(latest or 0) + 1, source=source, format=fmt
    )
    session.add(version)
    sub.updated_at = utcnow()
    session.flush()
    return version


def owned_submission(session: Session, *, user: User, submission_id: int) -> Submission:
    """A submission that ``user`` owns.

    Raises:
        NotFound: no such submission.
        Forbidden: it belongs to someone else.
    """
    sub = session.get(Submission, submission_id)
    if sub is None:
        raise NotFound(f"no submission {submission_id}")
    if sub.user_id != user.id:
        raise Forbidden(f"submission {submission_id} belongs to another user")
    return sub


def withdraw(session: Session, *, user: User, submission_id: int) -> Submission:
    """Withdraw one of the user's submissions: it leaves the leaderboard and matchmaking.

    Races already queued still run. Uploading a new version brings it back.
    """
    sub = owned_submission(session, user=user, submission_id=submission_id)
    sub.status = "withdrawn"
    sub.updated_at = utcnow()
    return sub
