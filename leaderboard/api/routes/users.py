"""Users: ``/api/users`` (admin), ``/api/users/me``, ``/api/users/{name}``."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter, Depends, status
from pydantic import BaseModel, Field

from leaderboard import auth, queries
from leaderboard.api.deps import CurrentUser, PageDep, SessionDep, require_admin

router = APIRouter(tags=["users"])


class UserCreate(BaseModel):
    """A new user."""

    name: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    is_admin: bool = False


class UserPublic(queries.UtcModel):
    """A user as others see them."""

    name: str
    created_at: datetime


class UserWithToken(BaseModel):
    """A new user and their first API token (shown only once)."""

    user: UserPublic
    token: str


class UserPage(BaseModel):
    """A user and their submissions."""

    user: UserPublic
    submissions: queries.Page[queries.SubmissionSummary]


@router.post(
    "/users",
    response_model=UserWithToken,
    status_code=status.HTTP_201_CREATED,
    dependencies=[Depends(require_admin)],
)
def create_user(session: SessionDep, body: UserCreate) -> UserWithToken:
    """Create a user (admin only); the answer carries their first API token."""
    user, token = auth.create_user(session, name=body.name, is_admin=body.is_admin)
    session.commit()
    return UserWithToken(user=UserPublic(name=user.name, created_at=user.created_at), token=token)


@router.get("/users/me", response_model=UserPublic)
def me(user: CurrentUser) -> UserPublic:
    """The user of the token."""
    return UserPublic(name=user.name, created_at=user.created_at)


@router.get("/users/{name}", response_model=UserPage)
def get_user(session: SessionDep, name: str, pages: PageDep) -> UserPage:
    """A user and their submissions (any status), newest first."""
    user = auth.get_user(session, name)
    subs = queries.submissions(session, page=pages.page, per_page=pages.per_page, author=name)
    return UserPage(user=UserPublic(name=user.name, created_at=user.created_at), submissions=subs)
