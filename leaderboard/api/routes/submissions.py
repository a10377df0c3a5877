"""Submissions: upload (multipart), new versions, withdraw (owner only), and reading them."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Query, UploadFile, status
from fastapi.responses import Response
from pydantic import BaseModel
from sqlalchemy import select
from sqlalchemy.orm import Session

from leaderboard import queries, uploads
from leaderboard.api.deps import CurrentUser, IdPath, PageDep, SessionDep, SettingsDep
from leaderboard.cache import cache_for
from leaderboard.errors import NotFound
from leaderboard.models import Race, RaceEntry, Submission, SubmissionVersion

router = APIRouter(tags=["submissions"])

BundleFile = Annotated[UploadFile, File(description="the bundle zip (manifest.json + policy)")]


class Uploaded(BaseModel):
    """An accepted upload: the version stored and its validation race."""

    submission_id: int
    name: str
    version: int
    status: str
    validation_race_id: int | None
    url: str


def _uploaded(session: Session, version: SubmissionVersion) -> Uploaded:
    race_id = session.scalar(
        select(RaceEntry.race_id)
        .join(Race, Race.id == RaceEntry.race_id)
        .where(RaceEntry.version_id == version.id, Race.kind == "validation")
    )
    return Uploaded(
        submission_id=version.submission_id,
        name=version.submission.name,
        version=version.version,
        status=version.status,
        validation_race_id=race_id,
        url=f"/api/submissions/{version.submission_id}",
    )


@router.post("/submissions", response_model=Uploaded, status_code=status.HTTP_201_CREATED)
def upload_submission(
    session: SessionDep, settings: SettingsDep, user: CurrentUser, file: BundleFile
) -> Uploaded:
    """Upload a bundle. Its manifest's ``name`` picks one of your submissions (a new name
    creates one, a known one adds a version). The bundle is validated now (422 with the
    reason if not) and raced in a validation race before it is ranked."""
    version = uploads.upload(session, settings, user=user, stream=file.file)
    session.commit()
    return _uploaded(session, version)


@router.post(
    "/submissions/{submission_id}/versions",
    response_model=Uploaded,
    status_code=status.HTTP_201_CREATED,
)
def upload_version(
    session: SessionDep,
    settings: SettingsDep,
    user: CurrentUser,
    submission_id: IdPath,
    file: BundleFile,
) -> Uploaded:
    """Add a version to one of your submissions (403 if it is someone else's)."""
    uploads.owned_submission(session, user=user, submission_id=submission_id)
    version = uploads.upload(
        session, settings, user=user, stream=file.file, submission_id=submission_id
    )
    session.commit()
    return _uploaded(session, version)


@router.delete("/submissions/{submission_id}", response_model=queries.SubmissionDetail)
def withdraw_submission(
    session: SessionDep, settings: SettingsDep, user: CurrentUser, submission_id: IdPath
) -> queries.SubmissionDetail:
    """Withdraw one of your submissions from the leaderboard (403 if someone else's)."""
    uploads.withdraw(session, user=user, submission_id=submission_id)
    session.commit()
    return queries.submission_detail(
        session, submission_id, provisional_races=settings.provisional_races
    )


@router.get("/submissions", response_model=queries.Page[queries.SubmissionSummary])
def list_submissions(
    session: SessionDep,
    pages: PageDep,
    author: Annotated[str | None, Query(description="only this user's")] = None,
) -> queries.Page[queries.SubmissionSummary]:
    """All submissions, newest first."""
    return queries.submissions(session, page=pages.page, per_page=pages.per_page, author=author)


@router.get("/submissions/{submission_id}", response_model=queries.SubmissionDetail)
def get_submission(
    session: SessionDep,
    settings: SettingsDep,
    submission_id: IdPath,
    races: Annotated[int, Query(ge=0, le=200, description="recent races included")] = 20,
) -> Response:
    """A submission: rating, rank, versions, recent races, rating history."""
    # The JSON itself is cached with the detail: FastAPI would dump the model, validate the
    # dump against it again and encode it on every request (~2 ms for a veteran's history).
    fingerprint = queries.submission_fingerprint(session, submission_id)

    def encode() -> bytes:
        detail = queries.submission_detail(
            session,
            submission_id,
            races=races,
            provisional_races=settings.provisional_races,
            max_age_s=settings.cache_max_age_s,
            fingerprint=fingerprint,
            cache=False,  # its JSON is what is kept
        )
        return detail.model_dump_json(by_alias=True).encode()  # as FastAPI writes it

    body = cache_for(session).get(
        ("submission-json", submission_id, races, settings.provisional_races),
        fingerprint,
        encode,
        settings.cache_max_age_s,
    )
    return Response(body, media_type="application/json")


@router.get("/submissions/{submission_id}/races", response_model=queries.Page[queries.RaceSummary])
def submission_races(
    session: SessionDep, submission_id: IdPath, pages: PageDep
) -> queries.Page[queries.RaceSummary]:
    """The races a submission took part in, newest first."""
    if session.get(Submission, submission_id) is None:
        raise NotFound(f"no submission {submission_id}")
    return queries.submission_races(
        session, submission_id, page=pages.page, per_page=pages.per_page
    )
