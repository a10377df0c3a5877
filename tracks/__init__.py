"""Track geometry, the built-in track library, importers and a procedural generator.

The bottom of the import chain: ``tracks`` ← ``arena`` ← ``agents`` ← ``submissions`` ←
``leaderboard``. Pure numpy/scipy; no physics.

>>> from tracks import load_track
>>> oval = load_track("oval")
>>> round(oval.length, 1) > 30
True
"""

from tracks.errors import SlipstreamError, TrackError
from tracks.geometry import Projection, Raceline, Track
from tracks.laps import LapCounter
from tracks.library import list_tracks, load_track

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
