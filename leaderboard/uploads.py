"""Submissions and their versions: upload, validate, store, withdraw.

An upload is streamed to disk with a size cap, validated by the submissions package
(:func:`submissions.bundle.open_bundle`: archive safety, manifest, declared spaces), then kept
as ``bundles_dir/<submission id>/v<version>.zip``. The manifest's ``name`` picks the submission
among the uploader's own: a new name creates a submission, a known one adds a version. Only
the owner can add versions to a submission or withdraw it. Each new version is queued for a
validation race (:func:`leaderboard.matchmaking.schedule_validation`).

The web process must not import the simulator: the bundle's manifest is checked against
:meth:`~submissions.bundle.EnvSpec.current`, which reads :mod:`arena.version` (no pybullet).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import BinaryIO

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from leaderboard.errors import Conflict, Forbidden, InvalidBundle, NotFound, PayloadTooLarge
from leaderboard.matchmaking import schedule_validation
from leaderboard.models import Submission, SubmissionVersion, User, utcnow
from leaderboard.settings import Settings
from submissions.bundle import BundleLimits, EnvSpec, Manifest, open_bundle
from submissions.errors import BundleError

BASELINES = ("pursuit", "gap", "random")
_CHUNK = 1 << 20


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
        InvalidBundle: the validator's one-line reason.
    """
    limits = BundleLimits(max_archive_bytes=settings.max_upload_bytes)
    with tempfile.TemporaryDirectory(prefix="slipstream-check-") as tmp:
        try:
            bundle = open_bundle(path, Path(tmp) / "bundle", limits, env=EnvSpec.current())
        except BundleError as err:
            raise InvalidBundle(f"invalid bundle: {err}") from None
    return bundle.manifest


def upload(
    session: Session,
    settings: Settings,
    *,
    user: User,
    stream: BinaryIO,
    submission_id: int | None = None,
) -> SubmissionVersion:
    """Store an uploaded bundle as a new submission or a new version of one.

    Args:
        session: the caller's transaction (flushed, not committed).
        settings: for the size limit and the bundle folder.
        user: the uploader.
        stream: the bundle zip.
        submission_id: add a version to this submission (must be the user's); by default
            the manifest's ``name`` selects or creates one of the user's submissions.

    Raises:
        PayloadTooLarge, InvalidBundle: the upload is refused (nothing is stored).
        NotFound, Forbidden: adding by id to a missing submission or someone else's.
        Conflict: the submission has ``settings.max_versions`` versions already.
    """
    settings.ensure_dirs()
    incoming = settings.bundles_dir / ".incoming"
    incoming.mkdir(exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(suffix=".zip", dir=incoming)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        size, sha = save_stream(stream, tmp, settings.max_upload_bytes)
        manifest = validate_bundle(tmp, settings)
        if submission_id is None:
            sub = _named_submission(session, user, manifest.name)
        else:
            sub = owned_submission(session, user=user, submission_id=submission_id)
        if manifest.description:
            sub.description = manifest.description
        version = _new_version(session, settings, sub, source="", fmt=manifest.format)
        dest = settings.bundles_dir / str(sub.id) / f"v{version.version}.zip"
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(tmp, dest)
        version.source = str(dest.resolve())
        version.manifest = manifest.to_dict()
        version.size_bytes = size
        version.sha256 = sha
        schedule_validation(session, settings, version)
        return version
    finally:
        tmp.unlink(missing_ok=True)


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


def _named_submission(session: Session, user: User, name: str, description: str = "") -> Submission:
    """The user's submission called ``name``, created (with ``description``) if missing."""
    sub = session.scalar(
        select(Submission).where(Submission.user_id == user.id, Submission.name == name)
    )
    if sub is None:
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
