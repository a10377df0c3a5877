"""A user's API tokens: ``GET/POST /api/tokens``, ``DELETE /api/tokens/{token_id}``.

Tokens are listed and revoked by their owner only; another user's token id answers 404, as
if it did not exist. The secret is shown once, in the answer to ``POST``; only its SHA-256 hash
is stored (see :mod:`leaderboard.auth`).
"""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter, status
from pydantic import BaseModel, Field

from leaderboard import auth, queries
from leaderboard.api.deps import CurrentUser, IdPath, SessionDep

router = APIRouter(tags=["tokens"])


class TokenCreate(BaseModel):
    """A new API token's label."""

    label: str = Field(default="", max_length=64)


class TokenIssued(BaseModel):
    """A new API token (shown only once; only its hash is stored)."""

    id: int
    token: str


class TokenInfo(queries.UtcModel):
    """One of your tokens, without its secret (``prefix``: its first characters)."""

    id: int
    label: str
    prefix: str
    created_at: datetime
    last_used_at: datetime | None
    revoked: bool


@router.get("/tokens", response_model=list[TokenInfo])
def list_tokens(session: SessionDep, user: CurrentUser) -> list[TokenInfo]:
    """Your API tokens, revoked ones included, oldest first."""
    return [
        TokenInfo(
            id=t.id,
            label=t.label,
            prefix=t.prefix,
            created_at=t.created_at,
            last_used_at=t.last_used_at,
            revoked=t.revoked_at is not None,
        )
        for t in auth.list_tokens(session, user=user)
    ]


@router.post("/tokens", response_model=TokenIssued, status_code=status.HTTP_201_CREATED)
def create_token(session: SessionDep, user: CurrentUser, body: TokenCreate) -> TokenIssued:
    """Issue another API token for yourself (its secret is in this answer only)."""
    row, token = auth.create_token(session, user=user, label=body.label)
    session.commit()
    return TokenIssued(id=row.id, token=token)


@router.delete("/tokens/{token_id}", status_code=status.HTTP_204_NO_CONTENT)
def revoke_token(session: SessionDep, user: CurrentUser, token_id: IdPath) -> None:
    """Revoke one of your tokens (404 if it is not yours). Revoking is final."""
    auth.revoke_token(session, user=user, token_id=token_id)
    session.commit()
