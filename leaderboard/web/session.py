"""Signing in to the website with an API token: a server-side session behind a cookie.

* ``GET /signin`` shows a form; ``POST /signin`` takes an API token (the one ``slipstream
  users add`` or ``slipstream tokens create`` printed), checks it with
  :func:`leaderboard.auth.user_for_token` and opens a session: a random cookie value whose
  SHA-256 hash is stored (``web_sessions``) with the user, the token it was opened with and a
  CSRF token. Revoking that API token ends the session; so does ``POST /signout``.
* The cookie (:data:`COOKIE`) is ``HttpOnly`` (no script reads it), ``SameSite=Strict`` (no
  other site's request carries it), ``Secure`` when the site is served over TLS, and lasts
  :data:`SESSION_DAYS` days.
* Every state-changing form carries a CSRF token: the session's own once signed in, and for
  the sign-in form itself a double-submit cookie (:data:`CSRF_COOKIE`) whose value the form
  must repeat. A POST whose token does not match is refused (403) and changes nothing.

Pages read the signed-in user with :func:`signed_in` (None for visitors).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from datetime import timedelta
from typing import Annotated

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from leaderboard import auth
from leaderboard.api.deps import SessionDep
from leaderboard.models import ApiToken, User, WebSession, utcnow

COOKIE = "slipstream_session"
CSRF_COOKIE = "slipstream_csrf"
SESSION_DAYS = 14
MAX_TOKEN_CHARS = 256


@dataclass(frozen=True)
class SignedIn:
    """The signed-in user of a request and the CSRF token its forms must carry."""

    user_id: int
    name: str
    csrf: str


def _hash(value: str) -> str:
    return hashlib.sha256(value.encode("utf-8")).hexdigest()


def _secure(request: Request) -> bool:
    return request.url.scheme == "https"


def signed_in(request: Request, session: Session) -> SignedIn | None:
    """The request's signed-in user, or None (no cookie, unknown, expired, token revoked)."""
    value = request.cookies.get(COOKIE)
    if not value or len(value) > MAX_TOKEN_CHARS:
        return None
    row = session.execute(
        select(WebSession, User, ApiToken)
        .join(User, User.id == WebSession.user_id)
        .join(ApiToken, ApiToken.id == WebSession.token_id)
        .where(WebSession.session_hash == _hash(value))
    ).first()
    if row is None:
        return None
    web, user, token = row
    if web.expires_at <= utcnow() or token.revoked_at is not None:
        return None
    return SignedIn(user_id=user.id, name=user.name, csrf=web.csrf)


def current_viewer(request: Request, session: SessionDep) -> SignedIn | None:
    """FastAPI dependency: the signed-in user or None."""
    return signed_in(request, session)


ViewerDep = Annotated[SignedIn | None, Depends(current_viewer)]


def csrf_ok(expected: str | None, given: str | None) -> bool:
    """Constant-time comparison of CSRF tokens (both present and equal).

    >>> csrf_ok("abc", "abc"), csrf_ok("abc", "abd"), csrf_ok(None, None), csrf_ok("", "")
    (True, False, False, False)
    """
    if not expected or not given:
        return False
    return hmac.compare_digest(expected.encode(), given.encode())


session_router = APIRouter(include_in_schema=False)


def _forbidden(message: str) -> HTMLResponse:
    from leaderboard.web.pages import templates  # noqa: PLC0415 - pages imports this module

    return HTMLResponse(
        templates.get_template("error.html").render(status_code=403, message=message, nav=None),
        status_code=403,
    )


@session_router.get("/signin", response_class=HTMLResponse)
def signin_form(request: Request, session: SessionDep) -> Response:
    """The sign-in form (with a fresh double-submit CSRF cookie)."""
    from leaderboard.web.pages import templates  # noqa: PLC0415 - pages imports this module

    token = secrets.token_urlsafe(24)
    context = {"nav": "signin", "csrf": token, "viewer": signed_in(request, session), "error": None}
    response = templates.TemplateResponse(request, "signin.html", context)
    response.set_cookie(
        CSRF_COOKIE, token, httponly=True, samesite="strict", secure=_secure(request), path="/"
    )
    return response


@session_router.post("/signin")
def signin(
    request: Request,
    session: SessionDep,
    token: Annotated[str, Form(max_length=MAX_TOKEN_CHARS)],
    csrf: Annotated[str, Form(max_length=128)],
) -> Response:
    """Open a session for a valid API token; back to the form with an error otherwise."""
    from leaderboard.web.pages import templates  # noqa: PLC0415 - pages imports this module

    if not csrf_ok(request.cookies.get(CSRF_COOKIE), csrf):
        return _forbidden("The sign-in form expired or did not come from this site; try again.")
    token = token.strip()
    user = auth.user_for_token(session, token) if token else None
    row = session.scalar(select(ApiToken).where(ApiToken.token_hash == auth.hash_token(token)))
    if user is None or row is None:
        session.rollback()
        context = {
            "nav": "signin",
            "csrf": csrf,
            "viewer": None,
            "error": "Unknown or revoked token.",
        }
        return templates.TemplateResponse(request, "signin.html", context, status_code=401)
    value = secrets.token_urlsafe(32)
    now = utcnow()
    session.execute(delete(WebSession).where(WebSession.expires_at <= now))  # tidy up
    session.add(
        WebSession(
            session_hash=_hash(value),
            user_id=user.id,
            token_id=row.id,
            csrf=secrets.token_urlsafe(24),
            created_at=now,
            expires_at=now + timedelta(days=SESSION_DAYS),
        )
    )
    session.commit()
    response = RedirectResponse(f"/users/{user.name}", status_code=303)
    response.set_cookie(
        COOKIE,
        value,
        max_age=SESSION_DAYS * 86400,
        httponly=True,
        samesite="strict",
        secure=_secure(request),
        path="/",
    )
    response.delete_cookie(CSRF_COOKIE, path="/")
    return response


@session_router.post("/signout")
def signout(
    request: Request, session: SessionDep, csrf: Annotated[str, Form(max_length=128)]
) -> Response:
    """End the session (its row is deleted, so the cookie is useless even if kept)."""
    viewer = signed_in(request, session)
    if viewer is not None:
        if not csrf_ok(viewer.csrf, csrf):
            return _forbidden("The sign-out form did not come from this site.")
        value = request.cookies.get(COOKIE, "")
        session.execute(delete(WebSession).where(WebSession.session_hash == _hash(value)))
        session.commit()
    response = RedirectResponse("/", status_code=303)
    response.delete_cookie(
        COOKIE, path="/", httponly=True, samesite="strict", secure=_secure(request)
    )
    return response


__all__ = [
    "COOKIE",
    "CSRF_COOKIE",
    "SignedIn",
    "ViewerDep",
    "csrf_ok",
    "current_viewer",
    "session_router",
    "signed_in",
]
