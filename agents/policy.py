"""The Policy protocol every racer implements: baselines, trained checkpoints, submissions.

The protocol itself lives in :mod:`arena.race` (the race runner is what calls it); it is
re-exported here so users write ``from agents import Policy``.
"""

from __future__ import annotations

from arena.race import Policy
from tracks.errors import SlipstreamError


class PolicyError(SlipstreamError):
    """A policy could not be built or loaded (unknown name, bad checkpoint)."""


__all__ = ["Policy", "PolicyError"]
