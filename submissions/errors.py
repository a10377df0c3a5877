"""Error types of the submissions package.

All derive from :class:`tracks.errors.SlipstreamError`, so the command line prints them as one
line and exits with status 2.
"""

from tracks.errors import SlipstreamError


class SubmissionError(SlipstreamError):
    """Something about a submission is wrong (its bundle, its policy, its evaluation)."""


class BundleError(SubmissionError):
    """A submission bundle is malformed, too large, unsafe, or does not match the env."""


class SandboxError(SubmissionError):
    """The sandbox could not be set up, or a sandboxed policy could not be started."""
