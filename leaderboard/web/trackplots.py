"""Track plot images for the track pages, drawn once with :mod:`tracks.plot` and cached.

The picture of a track never changes for a given library, so the first request renders it
(matplotlib, ~0.5 s) into ``<data_dir>/cache/tracks/<name>.png`` and every later one is a
file read. Only library names and ``random:<seed>...`` generator specs are accepted (never a
path), and the file name of a generated track is a hash of its spec.

>>> import tempfile
>>> with tempfile.TemporaryDirectory() as tmp:
...     png = track_image("oval", Path(tmp))
...     png.read_bytes()[:4] == b"\\x89PNG"
True
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

from leaderboard.matchmaking import library_tracks
from tracks import load_track
from tracks.errors import TrackError
from tracks.library import RANDOM_PREFIX

IMAGE_SUFFIX = ".png"


def track_image(name: str, data_dir: Path) -> Path:
    """The cached top-down picture of library track ``name``, rendered if missing.

    Args:
        name: a track library name (see ``slipstream tracks list``) or a ``random:`` spec.
        data_dir: the service's data folder; images live under ``cache/tracks/``.

    Returns:
        Path of the PNG file.

    Raises:
        TrackError: ``name`` is neither a library track nor a valid ``random:`` spec.
    """
    if name.startswith(RANDOM_PREFIX):
        stem = "random-" + hashlib.sha256(name.encode()).hexdigest()[:16]
    elif name in library_tracks():
        stem = name
    else:
        raise TrackError(f"unknown track {name!r}")
    out = Path(data_dir) / "cache" / "tracks" / f"{stem}{IMAGE_SUFFIX}"
    if out.is_file():
        return out
    from tracks.plot import plot_track  # noqa: PLC0415 - matplotlib, only to draw a picture

    out.parent.mkdir(parents=True, exist_ok=True)
    # Draw to a temporary file, then rename: concurrent requests never see half a file.
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{stem}-", suffix=IMAGE_SUFFIX)
    os.close(fd)
    try:
        plot_track(load_track(name), Path(tmp))
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out
