"""Dependencies of the API routes, with short aliases: ``SessionDep``, ``SettingsDep``,
``CurrentUser``, ``PageDep``.

The app keeps its settings and session factory on ``app.state`` (set by ``create_app``), so
every app — one per test database — has its own.
"""

from __future__ import annotations

import hmac
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from leaderboard.auth import user_for_token
from leaderboard.errors import Forbidden, NotAuthenticated
from leaderboard.models import User
from leaderboard.settings import Settings

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
    page: Annotated[int, Query(ge=1, description="page number, from 1")] = 1,
    per_page: Annotated[int | None, Query(ge=1, le=200, description="rows per page")] = None,
) -> PageParams:
    """Pagination parameters (``per_page`` defaults to ``settings.page_size``)."""
    return PageParams(page=page, per_page=per_page or settings.page_size)


PageDep = Annotated[PageParams, Depends(page_params)]
