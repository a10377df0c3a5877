"""Reading and writing track files: our JSON, F1TENTH race-track CSV, DeepRacer waypoint .npy.

Our JSON (``schema_version`` 1)::

    {
      "schema_version": 1,
      "name": "oval",
      "description": "...",
      "units": "m",
      "centre_line": [[x, y], ...],     # control points, in the order they are stored
      "width_left": 1.5 | [...],        # half-widths relative to the stored order, m
      "width_right": 1.5 | [...],
      "start": {"s": 0.0},              # start line, m along the curve from the first point
      "direction": "ccw" | "cw"         # the driving direction seen from above
    }

If ``direction`` disagrees with the orientation of the stored points, the points are read in
reverse (and left/right swapped), so a file can store a circuit either way round. F1TENTH CSV
files carry ``x_m, y_m, w_tr_right_m, w_tr_left_m`` per row in driving order. DeepRacer
``.npy`` files are (N, 6) arrays ``[centre_x, centre_y, inner_x, inner_y, outer_x, outer_y]``;
inner/outer become left/right according to the driving direction (anticlockwise: inner is left).
"""

from __future__ import annotations

import csv
import io
import json
import zipfile
from pathlib import Path
from typing import Any, Literal

import jsonschema
import numpy as np

from tracks.errors import TrackError
from tracks.geometry import Track, signed_area

SCHEMA_VERSION = 1
TrackFormat = Literal["json", "f1tenth", "deepracer"]
FORMATS: tuple[TrackFormat, ...] = ("json", "f1tenth", "deepracer")
MAX_FILE_BYTES = 20 * 1024 * 1024  # a track file larger than this is not a track

_WIDTH = {"oneOf": [{"type": "number"}, {"type": "array", "items": {"type": "number"}}]}
TRACK_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "Slipstream track",
    "type": "object",
    "required": ["schema_version", "name", "centre_line", "width_left", "width_right"],
    "properties": {
        "schema_version": {"const": SCHEMA_VERSION},
        "name": {"type": "string", "minLength": 1, "maxLength": 64},
        "description": {"type": "string", "maxLength": 2000},
        "units": {"const": "m"},
        "centre_line": {
            "type": "array",
            "items": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2},
        },
        "width_left": _WIDTH,
        "width_right": _WIDTH,
        "start": {
            "type": "object",
            "properties": {"s": {"type": "number"}},
            "additionalProperties": False,
        },
        "direction": {"enum": ["ccw", "cw"]},
    },
    "additionalProperties": False,
}


def _read_bytes(path: Path) -> bytes:
    if not path.is_file():
        raise TrackError(f"track file not found: {path}")
    if path.stat().st_size > MAX_FILE_BYTES:
        raise TrackError(f"{path} is {path.stat().st_size} bytes; a track file is at most 20 MB")
    return path.read_bytes()


def track_from_dict(data: Any, *, source: str = "track") -> Track:
    """Build a :class:`Track` from our JSON structure, validating it against the schema."""
    try:
        jsonschema.validate(data, TRACK_SCHEMA)
    except jsonschema.ValidationError as err:
        where = "/".join(str(p) for p in err.absolute_path) or "top level"
        raise TrackError(f"{source}: invalid track JSON at {where}: {err.message}") from None
    pts = np.asarray(data["centre_line"], dtype=np.float64).reshape(-1, 2)
    wl = np.asarray(data["width_left"], dtype=np.float64)
    wr = np.asarray(data["width_right"], dtype=np.float64)
    start_s = float(data.get("start", {}).get("s", 0.0))
    ccw = data.get("direction", "ccw") == "ccw"
    if len(pts) >= 3 and np.isfinite(pts).all() and (signed_area(pts) > 0) != ccw:
        # Stored the other way round: drive it reversed, keeping the first point first.
        order = np.roll(np.arange(len(pts))[::-1], 1)
        pts = pts[order]
        same = (len(pts),)
        wl, wr = (wr[order] if wr.shape == same else wr), (wl[order] if wl.shape == same else wl)
        start_s = -start_s
    try:
        return Track(
            pts,
            wl,
            wr,
            name=data["name"],
            description=data.get("description", ""),
            start_s=start_s,
        )
    except TrackError as err:
        raise TrackError(f"{source}: {err}") from None


def track_to_dict(track: Track) -> dict[str, Any]:
    """Our JSON structure for a track: its resampled centre line in driving order."""
    return {
        "schema_version": SCHEMA_VERSION,
        "name": track.name,
        "description": track.description,
        "units": "m",
        "centre_line": np.round(track.centre, 6).tolist(),
        "width_left": np.round(track.width_left, 6).tolist(),
        "width_right": np.round(track.width_right, 6).tolist(),
        "start": {"s": 0.0},
        "direction": track.orientation,
    }


def read_json(path: Path) -> Track:
    """Load one of our JSON track files."""
    try:
        data = json.loads(_read_bytes(path).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise TrackError(f"{path}: not valid JSON ({err})") from None
    return track_from_dict(data, source=str(path))


def write_json(track: Track, path: Path) -> None:
    """Write a track as our JSON."""
    path.write_text(json.dumps(track_to_dict(track), indent=1) + "\n", encoding="utf-8")


def read_f1tenth(path: Path, name: str | None = None) -> Track:
    """Load an F1TENTH race-track CSV (``# x_m, y_m, w_tr_right_m, w_tr_left_m``)."""
    text = _read_bytes(path).decode("utf-8", errors="replace")
    rows = [r for r in csv.reader(io.StringIO(text)) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise TrackError(f"{path}: no data rows (expected x_m, y_m, w_tr_right_m, w_tr_left_m)")
    if any(len(r) != 4 for r in rows):
        bad = next(i for i, r in enumerate(rows) if len(r) != 4)
        raise TrackError(
            f"{path}: row {bad + 1} has {len(rows[bad])} columns; an F1TENTH track has 4 "
            "(x_m, y_m, w_tr_right_m, w_tr_left_m)"
        )
    try:
        arr = np.array([[float(v) for v in r] for r in rows])
    except ValueError as err:
        raise TrackError(f"{path}: not a number ({err})") from None
    try:
        return Track(
            arr[:, :2],
            arr[:, 3],
            arr[:, 2],
            name=name or path.stem,
            description=f"imported from F1TENTH CSV {path.name}",
        )
    except TrackError as err:
        raise TrackError(f"{path}: {err}") from None


def write_f1tenth(track: Track, path: Path) -> None:
    """Write a track as an F1TENTH race-track CSV, in driving order from the start line."""
    rows = np.column_stack([track.centre, track.width_right, track.width_left])
    with path.open("w", encoding="utf-8") as fh:
        fh.write("# x_m, y_m, w_tr_right_m, w_tr_left_m\n")
        for r in rows:
            fh.write(",".join(f"{v:.6f}" for v in r) + "\n")


def read_deepracer(path: Path, name: str | None = None, direction: str = "ccw") -> Track:
    """Load a DeepRacer waypoint ``.npy`` ((N, 6): centre, inner, outer points).

    DeepRacer route files store the points in the direction they are driven; ``direction``
    only breaks the tie for files whose loop orientation cannot be read (it is otherwise
    taken from the points).
    """
    raw = _read_bytes(path)
    try:
        arr = np.load(io.BytesIO(raw), allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as err:  # empty, truncated, junk
        raise TrackError(f"{path}: not a numpy .npy array ({err})") from None
    if not isinstance(arr, np.ndarray):  # np.load opens an .npz archive instead
        raise TrackError(f"{path}: not a numpy .npy array (an .npz archive of several arrays)")
    if arr.ndim != 2 or arr.shape[1] != 6 or not np.issubdtype(arr.dtype, np.number):
        raise TrackError(
            f"{path}: expected an (N, 6) numeric array of centre, inner and outer points, "
            f"got shape {arr.shape} dtype {arr.dtype}"
        )
    arr = arr.astype(np.float64)
    if len(arr) > 1 and np.allclose(arr[0], arr[-1]):
        arr = arr[:-1]
    centre, inner, outer = arr[:, 0:2], arr[:, 2:4], arr[:, 4:6]
    area = signed_area(centre) if np.isfinite(centre).all() else 0.0
    ccw = area > 0 if area != 0 else direction == "ccw"
    w_inner = np.linalg.norm(inner - centre, axis=1)
    w_outer = np.linalg.norm(outer - centre, axis=1)
    left, right = (w_inner, w_outer) if ccw else (w_outer, w_inner)
    try:
        return Track(
            centre,
            left,
            right,
            name=name or path.stem,
            description=f"imported from DeepRacer waypoints {path.name}",
        )
    except TrackError as err:
        raise TrackError(f"{path}: {err}") from None


def write_deepracer(track: Track, path: Path) -> None:
    """Write a track as a DeepRacer waypoint ``.npy`` (closed: the first row is repeated)."""
    ccw = track.orientation == "ccw"
    inner = track.left_border if ccw else track.right_border
    outer = track.right_border if ccw else track.left_border
    arr = np.column_stack([track.centre, inner, outer])
    with path.open("wb") as fh:
        np.save(fh, np.vstack([arr, arr[:1]]), allow_pickle=False)


def read_track_file(path: Path, fmt: TrackFormat | None = None, name: str | None = None) -> Track:
    """Load a track file in any supported format (guessed from the suffix when not given)."""
    if fmt is None:
        by_suffix: dict[str, TrackFormat] = {
            ".json": "json",
            ".csv": "f1tenth",
            ".npy": "deepracer",
        }
        fmt = by_suffix.get(path.suffix.lower())
        if fmt is None:
            raise TrackError(f"{path}: unknown track format; use --format json|f1tenth|deepracer")
    if fmt == "json":
        track = read_json(path)
        if name:
            track.name = name
        return track
    if fmt == "f1tenth":
        return read_f1tenth(path, name)
    if fmt == "deepracer":
        return read_deepracer(path, name)
    raise TrackError(f"unknown track format {fmt!r}; use one of {', '.join(FORMATS)}")


def write_track_file(track: Track, path: Path, fmt: TrackFormat) -> None:
    """Write a track in one of the supported formats."""
    writers = {"json": write_json, "f1tenth": write_f1tenth, "deepracer": write_deepracer}
    if fmt not in writers:
        raise TrackError(f"unknown track format {fmt!r}; use one of {', '.join(FORMATS)}")
    writers[fmt](track, path)
