"""Track geometry, the built-in track library, importers and a procedural generator.

The bottom of the import chain: ``tracks`` ← ``arena`` ← ``agents`` ← ``submissions`` ←
``leaderboard``. Pure numpy/scipy; no physics.

``import tracks`` (and so ``from tracks.errors import ...``) stays light: the names below load
their module on first use, so a process that needs only the error types (the sandboxed policy
worker) never imports scipy.

>>> from tracks import load_track
>>> oval = load_track("oval")
>>> round(oval.length, 1) > 30
True
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the type checker sees the names eagerly; at run time they load on use
    from tracks.errors import SlipstreamError, TrackError
    from tracks.geometry import Projection, Raceline, Track
    from tracks.laps import LapCounter
    from tracks.library import list_tracks, load_track

_LAZY = {
    "LapCounter": "tracks.laps",
    "Projection": "tracks.geometry",
    "Raceline": "tracks.geometry",
    "SlipstreamError": "tracks.errors",
    "Track": "tracks.geometry",
    "TrackError": "tracks.errors",
    "list_tracks": "tracks.library",
    "load_track": "tracks.library",
}

__all__ = [
    "LapCounter",
    "Projection",
    "Raceline",
    "SlipstreamError",
    "Track",
    "TrackError",
    "list_tracks",
    "load_track",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'tracks' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
