"""Dependencies of the API routes, with short aliases: ``SessionDep``, ``SettingsDep``,
``CurrentUser``, ``PageDep``, ``IdPath``.

Numbers from the URL are bounded where they are declared: an id (``IdPath``) fits the
database's integer column (1 … 2³¹−1, PostgreSQL's ``integer``), a page number stays below
:data:`MAX_PAGE`; anything larger is a 422, not a database overflow.

The app keeps its settings and session factory on ``app.state`` (set by ``create_app``), so
every app — one per test database — has its own.
"""

from __future__ import annotations

import hmac
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Path, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel
from sqlalchemy.orm import Session

from leaderboard.auth import user_for_token
from leaderboard.errors import Forbidden, NotAuthenticated
from leaderboard.models import User
from leaderboard.settings import Settings

MAX_ID = 2**31 - 1  # the largest value of an id column (PostgreSQL integer)
MAX_PAGE = 1_000_000  # page numbers past this are refused (offsets stay far below 2^63)


class ErrorBody(BaseModel):
    """An error answer: what went wrong, in one line."""

    detail: str


class ValidationErrorBody(BaseModel):
    """A 422 answer: the request's fields that failed validation (a list, FastAPI's form), or
    a bundle the validator refused (one line)."""

    detail: str | list[dict[str, Any]]


ERROR_RESPONSES: dict[int | str, dict[str, object]] = {
    code: {"model": ErrorBody, "description": text}
    for code, text in {
        400: "bad request",
        401: "missing, unknown or revoked API token",
        403: "not allowed for this user",
        404: "no such object",
        409: "conflict (name taken, duplicate bundle, quota of submissions or versions)",
        413: "request body too large",
        429: "rate limit or upload quota reached (see Retry-After)",
    }.items()
}
ERROR_RESPONSES[422] = {
    "model": ValidationErrorBody,
    "description": "invalid parameters, or an invalid bundle",
}
IdPath = Annotated[int, Path(ge=1, le=MAX_ID, description="an id (1 … 2^31 − 1)")]

bearer = HTTPBearer(auto_error=False, description="an API token: `slipstream users add NAME`")


def get_settings(request: Request) -> Settings:
    """The settings of the app serving this request."""
    settings: Settings = request.app.state.settings
    return settings


def get_session(request: Request) -> Iterator[Session]:
    """A database session for one request (routes that write commit it themselves)."""
    session: Session = request.app.state.sessionmaker()
    try:
        yield session
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


SessionDep = Annotated[Session, Depends(get_session)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]


def _token(credentials: HTTPAuthorizationCredentials | None) -> str:
    if credentials is None:
        raise NotAuthenticated("missing API token: send 'Authorization: Bearer <token>'")
    return credentials.credentials


def _user(session: Session, token: str) -> User:
    user = user_for_token(session, token)
    if user is None:
        raise NotAuthenticated("invalid or revoked API token")
    return user


def current_user(session: SessionDep, credentials: Credentials) -> User:
    """The user of the request's bearer token.

    Raises:
        NotAuthenticated: no token, or an unknown or revoked one.
    """
    user = _user(session, _token(credentials))
    session.commit()  # last_used_at
    return user


CurrentUser = Annotated[User, Depends(current_user)]


def require_admin(session: SessionDep, settings: SettingsDep, credentials: Credentials) -> None:
    """Allow the request if it carries ``settings.admin_token`` or an admin user's token.

    Raises:
        NotAuthenticated: no token, or an unknown one.
        Forbidden: a valid token of a user who is not an admin.
    """
    token = _token(credentials)
    admin = settings.admin_token
    if admin is not None and hmac.compare_digest(token.encode(), admin.get_secret_value().encode()):
        return
    if not _user(session, token).is_admin:
        raise Forbidden("only an admin can do this")


@dataclass(frozen=True)
class PageParams:
    """``?page=`` (from 1) and ``?per_page=`` of a list request."""

    page: int
    per_page: int


def page_params(
    settings: SettingsDep,
    page: Annotated[int, Query(ge=1, le=MAX_PAGE, description="page number, from 1")] = 1,
    per_page: Annotated[int | None, Query(ge=1, le=200, description="rows per page")] = None,
) -> PageParams:
    """Pagination parameters (``per_page`` defaults to ``settings.page_size``)."""
    return PageParams(page=page, per_page=per_page or settings.page_size)


PageDep = Annotated[PageParams, Depends(page_params)]
