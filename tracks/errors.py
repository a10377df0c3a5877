"""Error types a user can meet.

Every package raises a subclass of :class:`SlipstreamError` for problems in user input (a bad
track file, a wrong checkpoint, a bad configuration). The command line prints such an error as
one line, without a traceback, and exits non-zero. It lives here because ``tracks`` is the
bottom of the import chain (``tracks`` ← ``arena`` ← ``agents`` ← ``submissions`` ←
``leaderboard``), so every package can derive from it.
"""


class SlipstreamError(Exception):
    """Base class for errors caused by user input; the message says what is wrong."""


class TrackError(SlipstreamError):
    """A track is malformed, cannot be read, or cannot be found."""
