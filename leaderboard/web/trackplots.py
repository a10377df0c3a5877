"""Track plot images for the track pages, drawn once with :mod:`tracks.plot` and cached.

The picture of a track never changes for a given library, so the first request renders it
(matplotlib, ~0.5 s) into ``<data_dir>/cache/tracks/<name>.png`` and every later one is a
file read. Only library names and ``random:<seed>...`` generator specs are accepted (never a
path), and the file name of a generated track is a hash of its spec. Anyone can ask for any
generated track, so their seeds must lie in ``0 … 2³¹−1`` and at most ``max_random`` of their
pictures are kept (the least recently drawn are deleted first).

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
from tracks.library import RANDOM_PREFIX, parse_random_spec

IMAGE_SUFFIX = ".png"
MAX_RANDOM_SEED = 2**31 - 1
MAX_RANDOM_IMAGES = 64  # pictures of generated tracks kept (Settings.random_track_images)


def track_image(name: str, data_dir: Path, *, max_random: int = MAX_RANDOM_IMAGES) -> Path:
    """The cached top-down picture of library track ``name``, rendered if missing.

    Args:
        name: a track library name (see ``slipstream tracks list``) or a ``random:`` spec.
        data_dir: the service's data folder; images live under ``cache/tracks/``.
        max_random: pictures of generated tracks kept; older ones are deleted.

    Returns:
        Path of the PNG file.

    Raises:
        TrackError: ``name`` is neither a library track nor a valid ``random:`` spec with a
            seed in ``0 … 2³¹−1``.
    """
    if name.startswith(RANDOM_PREFIX):
        seed, _params = parse_random_spec(name)
        if not 0 <= seed <= MAX_RANDOM_SEED:
            raise TrackError(f"random track seeds lie in 0 … {MAX_RANDOM_SEED}, not {seed}")
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
    if stem.startswith("random-"):
        _evict_random(out.parent, keep=max_random)
    return out


def _evict_random(folder: Path, keep: int) -> None:
    """Delete all but the ``keep`` most recently drawn pictures of generated tracks."""
    pictures = []
    for path in folder.glob(f"random-*{IMAGE_SUFFIX}"):
        try:
            pictures.append((path.stat().st_mtime_ns, path))
        except FileNotFoundError:  # deleted by a concurrent request
            continue
    pictures.sort(reverse=True)
    for _mtime, path in pictures[keep:]:
        path.unlink(missing_ok=True)
