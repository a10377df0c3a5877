"""Errors of the leaderboard service; each carries the HTTP status the API answers with.

They derive from :class:`tracks.errors.SlipstreamError`, so the command line prints them as one
line and exits 2, and the API turns them into ``{"detail": message}`` with ``status_code``.
"""

from tracks.errors import SlipstreamError


class LeaderboardError(SlipstreamError):
    """A request the leaderboard cannot carry out (the message says why)."""

    status_code = 400


class NotAuthenticated(LeaderboardError):
    """No API token, or one that is unknown or revoked."""

    status_code = 401


class Forbidden(LeaderboardError):
    """The token is valid but its user may not do this (someone else's submission)."""

    status_code = 403


class NotFound(LeaderboardError):
    """No such user, submission, race or track."""

    status_code = 404


class Conflict(LeaderboardError):
    """The name is taken, or the object is in a state that does not allow this."""

    status_code = 409


class PayloadTooLarge(LeaderboardError):
    """An upload over the size limit."""

    status_code = 413


class InvalidBundle(LeaderboardError):
    """An upload that is not a valid submission bundle (the validator's message)."""

    status_code = 422


class QuotaExceeded(LeaderboardError):
    """A per-user quota is spent (``retry_after``: seconds until it frees, for ``Retry-After``)."""

    status_code = 429

    def __init__(self, message: str, *, retry_after: int = 60) -> None:
        super().__init__(message)
        self.retry_after = retry_after
