"""The built-in track library and name resolution.

A track can be named three ways wherever the project takes a track: a built-in name
(``tracks/data/<name>.json``), a path to a track file (JSON, F1TENTH ``.csv``, DeepRacer
``.npy``), or ``random:<seed>[:length=<m>,difficulty=<0..1>,hairpin=<m>]`` for a procedurally
generated circuit (the same one for the same seed and parameters).

Any of them may end in ``@<factor>``: the track scaled by that factor
(:meth:`tracks.Track.scaled`, whose name it is), e.g. ``oval@0.52`` or
``random:7:length=80,hairpin=0.6@0.52`` for the 1/18 DeepRacer car on roads drawn for the
1/10 F1TENTH car. A file whose own name ends that way is found first.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from tracks.errors import TrackError
from tracks.formats import read_json, read_track_file
from tracks.geometry import Track

DATA_DIR = Path(__file__).parent / "data"
RANDOM_PREFIX = "random:"
SCALE_MARK = "@"


def list_tracks() -> list[str]:
    """Names of the built-in tracks, sorted."""
    return sorted(p.stem for p in DATA_DIR.glob("*.json"))


@lru_cache(maxsize=64)
def _load_builtin(name: str) -> Track:
    return read_json(DATA_DIR / f"{name}.json")


def parse_random_spec(spec: str) -> tuple[int, dict[str, float]]:
    """Split ``random:<seed>[:key=value,...]`` into the seed and generator keyword arguments."""
    body = spec[len(RANDOM_PREFIX) :]
    seed_text, _, opts = body.partition(":")
    try:
        seed = int(seed_text)
    except ValueError:
        raise TrackError(f"bad random track {spec!r}: the seed must be an integer") from None
    params: dict[str, float] = {}
    for item in filter(None, opts.split(",")):
        key, eq, value = item.partition("=")
        if not eq or key not in ("length", "difficulty", "hairpin", "width"):
            raise TrackError(
                f"bad random track option {item!r}; use length=<m>, difficulty=<0..1>, "
                "hairpin=<m> and/or width=<m>"
            )
        try:
            params[key] = float(value)
        except ValueError:
            raise TrackError(f"bad random track option {item!r}: not a number") from None
    return seed, params


@lru_cache(maxsize=64)
def _load_random(spec: str) -> Track:
    from tracks.generator import generate_track  # noqa: PLC0415 (only for random: tracks)

    seed, params = parse_random_spec(spec)
    return generate_track(seed, **params)


def split_scale(name: str) -> tuple[str, float | None]:
    """``("oval", 0.52)`` for ``"oval@0.52"``; ``(name, None)`` when ``name`` names no scale
    (no ``@<number>`` at the end, or it is an existing file's own name).

    >>> split_scale("random:7:length=80@0.52")
    ('random:7:length=80', 0.52)
    >>> split_scale("oval")
    ('oval', None)
    """
    base, mark, factor = name.rpartition(SCALE_MARK)
    if not mark or not base or Path(name).exists():
        return name, None
    try:
        return base, float(factor)
    except ValueError:  # an "@" that is part of a name or path
        return name, None


def load_track(track: str | Path | Track) -> Track:
    """Resolve a built-in name, a file path, ``random:<seed>`` or a :class:`Track` to a Track;
    any name may end in ``@<factor>`` (the track scaled, see the module docstring).

    Raises:
        TrackError: the name is unknown, the file is missing or malformed, or the scale is
            not a positive number or leaves an invalid track.
    """
    if isinstance(track, Track):
        return track
    text = str(track)
    base, factor = split_scale(text)
    if factor is not None:
        return load_track(base).scaled(factor)  # a few ms: not cached
    if text.startswith(RANDOM_PREFIX):
        return _load_random(text)
    if isinstance(track, str) and text in list_tracks():
        return _load_builtin(text)
    path = Path(text)
    if path.suffix or path.exists():
        return read_track_file(path)
    known = ", ".join(list_tracks()) or "none installed"
    raise TrackError(
        f"unknown track {text!r}; built-in tracks: {known}; or a file path, or random:<seed>; "
        "any of them scaled with @<factor>"
    )
