"""Users and API tokens. Tokens are random, shown once, and stored as SHA-256 hashes.

A token is ``slp_`` + 43 URL-safe characters (256 random bits), so a plain unsalted hash is
enough: there is nothing to brute-force. Look-ups go by the hash (a unique index).
"""

from __future__ import annotations

import hashlib
import re
import secrets
from datetime import timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session

from leaderboard.errors import Conflict, LeaderboardError, NotFound
from leaderboard.models import ApiToken, User, utcnow

TOKEN_PREFIX = "slp_"
USER_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_TOUCH_EVERY = timedelta(minutes=1)  # last_used_at is refreshed at most this often


def new_token() -> str:
    """A fresh random API token (``slp_`` + 43 characters)."""
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def hash_token(token: str) -> str:
    """The stored form of a token: SHA-256, hex."""
    return hashlib.sha256(token.encode()).hexdigest()


def create_user(session: Session, *, name: str, is_admin: bool = False) -> tuple[User, str]:
    """Add a user with one API token; returns the user and the token (shown only now).

    Raises:
        LeaderboardError: the name is not ``[A-Za-z0-9_.-]{1,64}``.
        Conflict: a user of that name exists.
    """
    if not USER_NAME.match(name):
        raise LeaderboardError(f"user name {name!r} must match [A-Za-z0-9_.-]{{1,64}}")
    if session.scalar(select(User.id).where(User.name == name)) is not None:
        raise Conflict(f"user {name!r} already exists")
    user = User(name=name, is_admin=is_admin)
    session.add(user)
    session.flush()
    return user, issue_token(session, user=user, label="created with the user")


def issue_token(session: Session, *, user: User, label: str = "") -> str:
    """A new API token for ``user``; returns the token (only its hash is stored)."""
    return create_token(session, user=user, label=label)[1]


def create_token(session: Session, *, user: User, label: str = "") -> tuple[ApiToken, str]:
    """A new API token for ``user``: its stored row (id, label, ...) and the token itself."""
    token = new_token()
    row = ApiToken(
        user_id=user.id,
        token_hash=hash_token(token),
        prefix=token[: len(TOKEN_PREFIX) + 6],
        label=label[:64],
    )
    session.add(row)
    session.flush()
    return row, token


def list_tokens(session: Session, *, user: User) -> list[ApiToken]:
    """``user``'s tokens, revoked ones included, oldest first."""
    return list(
        session.scalars(select(ApiToken).where(ApiToken.user_id == user.id).order_by(ApiToken.id))
    )


def user_for_token(session: Session, token: str) -> User | None:
    """The user a token belongs to (None if unknown or revoked); refreshes ``last_used_at``."""
    row = session.scalar(select(ApiToken).where(ApiToken.token_hash == hash_token(token)))
    if row is None or row.revoked_at is not None:
        return None
    now = utcnow()
    if row.last_used_at is None or now - row.last_used_at > _TOUCH_EVERY:
        row.last_used_at = now
    return row.user


def revoke_token(session: Session, *, user: User, token_id: int) -> None:
    """Revoke one of ``user``'s tokens.

    Raises:
        NotFound: no such token of this user.
    """
    row = session.get(ApiToken, token_id)
    if row is None or row.user_id != user.id:
        raise NotFound(f"no token {token_id} of user {user.name!r}")
    row.revoked_at = row.revoked_at or utcnow()


def get_user(session: Session, name: str) -> User:
    """The user called ``name``.

    Raises:
        NotFound: no such user.
    """
    user = session.scalar(select(User).where(User.name == name))
    if user is None:
        raise NotFound(f"no user {name!r}")
    return user
