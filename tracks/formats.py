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
      "direction": "ccw" | "cw",        # the driving direction seen from above
      "resampled": true,                # optional: the points are a fitted centre line
                                        # (what we write); read as is, not fitted again
      "waypoints": [[x, y], ...],       # optional: the source file's own centre points
      "raceline": {"points": [[x, y], ...], "speed": [...]}   # optional reference line, m/s
    }

If ``direction`` disagrees with the orientation of the stored points, the points are read in
reverse (and left/right swapped), so a file can store a circuit either way round. F1TENTH CSV
files carry ``x_m, y_m, w_tr_right_m, w_tr_left_m`` per row in driving order; files whose
header names their columns are read by name, so the ForzaETH race stack's waypoint CSVs
(``id; s_m; d_m; x_m; y_m; d_right; d_left; psi_rad; kappa_radpm; vx_mps; ax_mps2``, as
MapZoo publishes its ``*_centerline.csv`` and ``*_racing_line.csv``) are read too. DeepRacer
``.npy`` files are (N, 6) arrays ``[centre_x, centre_y, inner_x, inner_y, outer_x, outer_y]``;
which border column is left is read from the geometry, and the half-widths are measured to the
file's border polylines. F1TENTH race lines (``s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps;
ax_mps2``) are read by :func:`read_raceline`. Importers of outside files drop repeated rows
and fit too-wide half-widths to the bends (:func:`tracks.validation.fit_widths`) instead of
refusing them; ``track.import_notes`` says what they changed.
"""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from tracks.errors import TrackError
from tracks.geometry import FloatArray, Raceline, Track, border_widths, signed_area, tightened_bends
from tracks.validation import fit_widths, validate_track

SCHEMA_VERSION = 1
TrackFormat = Literal["json", "f1tenth", "deepracer"]
FORMATS: tuple[TrackFormat, ...] = ("json", "f1tenth", "deepracer")
MAX_FILE_BYTES = 20 * 1024 * 1024  # a track file larger than this is not a track

_NUMBER = {"type": "number"}
_POINTS = {
    "type": "array",
    "items": {"type": "array", "items": _NUMBER, "minItems": 2, "maxItems": 2},
}
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
        "resampled": {"type": "boolean"},
        "waypoints": _POINTS,
        "raceline": {
            "type": "object",
            "required": ["points", "speed"],
            "properties": {"points": _POINTS, "speed": {"type": "array", "items": _NUMBER}},
            "additionalProperties": False,
        },
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
    import jsonschema  # noqa: PLC0415 - ~0.1 s: loaded by the first track, not every import

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
    waypoints = data.get("waypoints")
    resampled = bool(data.get("resampled", False))
    raceline = None
    try:
        if "raceline" in data:
            raceline = Raceline(
                np.asarray(data["raceline"]["points"], dtype=np.float64).reshape(-1, 2),
                np.asarray(data["raceline"]["speed"], dtype=np.float64),
            )
        if len(pts) >= 3 and np.isfinite(pts).all() and (signed_area(pts) > 0) != ccw:
            # Stored the other way round: drive it reversed, keeping the first point first.
            order = np.roll(np.arange(len(pts))[::-1], 1)
            pts = pts[order]
            same = (len(pts),)
            wl, wr = (
                (wr[order] if wr.shape == same else wr),
                (wl[order] if wl.shape == same else wl),
            )
            start_s = -start_s
            raceline = raceline.reversed() if raceline is not None else None
            waypoints = waypoints[::-1] if waypoints is not None else None
        return Track(
            pts,
            wl,
            wr,
            name=data["name"],
            description=data.get("description", ""),
            start_s=start_s,
            raceline=raceline,
            waypoints=waypoints,
            smooth=not resampled,
            shape_preserving=True,
        )
    except TrackError as err:
        raise TrackError(f"{source}: {err}") from None


def track_to_dict(track: Track) -> dict[str, Any]:
    """Our JSON structure for a track: its resampled centre line in driving order (marked
    ``resampled``, so loading uses it as is and import -> save -> load gives the same road
    rather than a fit of a fit), plus the source file's waypoints and the race line when it
    has them."""
    out: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "name": track.name,
        "description": track.description,
        "units": "m",
        "centre_line": np.round(track.centre, 6).tolist(),
        "width_left": np.round(track.width_left, 6).tolist(),
        "width_right": np.round(track.width_right, 6).tolist(),
        "start": {"s": 0.0},
        "direction": track.orientation,
        "resampled": True,
    }
    if track.waypoints is not None:
        out["waypoints"] = np.round(track.waypoints, 6).tolist()
    if track.raceline is not None:
        out["raceline"] = {
            "points": np.round(track.raceline.points, 6).tolist(),
            "speed": np.round(track.raceline.speed, 6).tolist(),
        }
    return out


def read_json(path: Path) -> Track:
    """Load one of our JSON track files."""
    try:
        data = json.loads(_read_bytes(path).decode("utf-8-sig"))  # a BOM (Windows editors)
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise TrackError(f"{path}: not valid JSON ({err})") from None
    return track_from_dict(data, source=str(path))


def write_json(track: Track, path: Path) -> None:
    """Write a track as our JSON."""
    path.write_text(json.dumps(track_to_dict(track), indent=1) + "\n", encoding="utf-8")


@dataclass(frozen=True)
class ImportOptions:
    """How an imported file is adapted (``slipstream tracks import`` options).

    Attributes:
        scale: multiply every coordinate and width by this (e.g. 0.1 for a 1/10 model of a
            full-size circuit).
        width: replace the file's half-widths by this constant, m (after scaling).
        max_width: cap the half-widths at this many metres (after scaling).
    """

    scale: float = 1.0
    width: float | None = None
    max_width: float | None = None

    def __post_init__(self) -> None:
        for name in ("scale", "width", "max_width"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise TrackError(f"--{name.replace('_', '-')} must be a positive number")


def _drop_repeats(points: FloatArray) -> tuple[NDArray[np.bool_], int]:
    """Mask (K,) of the points to keep and how many repeats it drops: a point equal to the
    one before it is a repeat; a last point equal to the first closes the loop (dropped,
    not counted)."""
    same_as_prev = np.zeros(len(points), dtype=bool)
    same_as_prev[1:] = np.all(np.abs(np.diff(points, axis=0)) <= 1e-9, axis=1)
    keep = ~same_as_prev
    kept = np.flatnonzero(keep)
    if len(kept) > 1 and np.all(np.abs(points[kept[-1]] - points[kept[0]]) <= 1e-9):
        keep[kept[-1]] = False
    return keep, int(same_as_prev.sum())


def _without_repeats(rows: FloatArray, notes: list[str]) -> FloatArray:
    """``rows`` (K, C) without repeated points (the first two columns, see
    :func:`_drop_repeats`); a note says how many were dropped."""
    if not np.isfinite(rows[:, :2]).all():
        return rows  # check_raw_inputs names the bad point
    keep, dropped = _drop_repeats(rows[:, :2])
    if dropped:
        notes.append(f"dropped {dropped} repeated row(s)")
    return rows[keep]


def _build_imported(
    centre: FloatArray,
    width_left: FloatArray,
    width_right: FloatArray,
    *,
    name: str,
    description: str,
    options: ImportOptions,
    notes: list[str],
    waypoints: FloatArray | None = None,
    borders: tuple[FloatArray, FloatArray] | None = None,
) -> Track:
    """Smooth, fit widths to bends, validate: the common end of every importer.

    ``borders`` (left, right polylines (K, 2) m, one point per centre point) make the
    half-widths the distance from the smoothed centre line to the file's own borders.
    """
    track = Track(
        centre,
        width_left,
        width_right,
        name=name,
        description=description,
        validate=False,
        waypoints=waypoints,
        shape_preserving=True,
    )
    if borders is not None and options.width is None:
        left, right = border_widths(track, centre, borders)
        track = track.with_widths(left, right)
    notes += tightened_bends(track, centre)
    fitted, narrowed = fit_widths(track, options.max_width)
    validate_track(fitted)
    fitted.import_notes = (*notes, *narrowed)
    return fitted


# The columns of an F1TENTH centre line in file order, and the names each one goes by in a
# header (f1tenth_racetracks; the ForzaETH race stack / MapZoo waypoint files).
CENTRELINE_COLUMNS = ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m")
CENTRELINE_NAMES = (("x_m",), ("y_m",), ("w_tr_right_m", "d_right"), ("w_tr_left_m", "d_left"))


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _cells(line: str) -> list[str]:
    """The cells of one line, split on ';' when it has one, else on ','."""
    return [c.strip() for c in line.split(";" if ";" in line else ",")]


def read_columns(
    path: Path, layout: tuple[str, ...], names: tuple[tuple[str, ...], ...], what: str
) -> FloatArray:
    """The wanted columns (K, len(names)) of a ';'- or ','-separated text file, as floats.

    ``layout`` is the columns a file without a usable header has, in order; ``names`` lists,
    for every column wanted, the header names it goes by (the first is in ``layout``). The
    header is the last ``#`` line before the data (``# s_m; x_m; ...``) or a first line of
    names without ``#`` (``id; s_m; d_m; x_m; ...``); when it names every wanted column, they
    are picked by name from rows of its width, else every row must match ``layout``.
    Raises TrackError naming the row that does not fit, or the cell that is not a number.
    """
    # utf-8-sig: a CSV saved by Excel ("CSV UTF-8") starts with a byte-order mark, which
    # would make the first cell a name and drop the first point
    text = _read_bytes(path).decode("utf-8-sig", errors="replace")
    header: list[str] = []
    data: list[str] = []
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("#"):
            if not data:
                header = _cells(line[1:])
        elif line:
            data.append(line)
    if data and not any(_is_number(c) for c in _cells(data[0])):
        header = _cells(data.pop(0))
    expected = ", ".join(layout)
    if not data:
        raise TrackError(f"{path}: no data rows (expected {expected})")
    rows = [_cells(line) for line in data]
    lower = [h.lower() for h in header]
    if all(any(n in lower for n in alias) for alias in names):
        width = len(header)
        index = [next(lower.index(n) for n in alias if n in lower) for alias in names]
        fits = f"{what} has {width} by its header ({', '.join(header)})"
    else:
        width = len(layout)
        index = [layout.index(alias[0]) for alias in names]
        fits = f"{what} has {width} ({expected})"
    bad = next((i for i, r in enumerate(rows) if len(r) != width), None)
    if bad is not None:
        raise TrackError(f"{path}: row {bad + 1} has {len(rows[bad])} columns; {fits}")
    try:
        return np.array([[float(r[i]) for i in index] for r in rows], dtype=np.float64)
    except ValueError as err:
        raise TrackError(f"{path}: not a number ({err})") from None


def read_f1tenth(
    path: Path, name: str | None = None, options: ImportOptions | None = None
) -> Track:
    """Load an F1TENTH race-track CSV (``# x_m, y_m, w_tr_right_m, w_tr_left_m``), or a
    waypoint CSV whose header names ``x_m, y_m, d_right, d_left`` (ForzaETH / MapZoo).

    Consecutive repeated points are dropped and half-widths wider than a bend's radius are
    narrowed there (see :func:`tracks.validation.fit_widths`); ``track.import_notes`` says
    what changed.
    """
    opts = options or ImportOptions()
    arr = read_columns(path, CENTRELINE_COLUMNS, CENTRELINE_NAMES, "an F1TENTH track")
    notes: list[str] = []
    arr = _without_repeats(arr, notes)
    arr = arr * opts.scale
    wl, wr = arr[:, 3], arr[:, 2]
    if opts.width is not None:
        wl = wr = np.full(len(arr), opts.width)
    try:
        return _build_imported(
            arr[:, :2],
            wl,
            wr,
            # f1tenth_racetracks names its files <Track>/<Track>_centerline.csv
            name=name or path.stem.removesuffix("_centerline"),
            description=f"imported from F1TENTH CSV {path.name}",
            options=opts,
            notes=notes,
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


def read_deepracer(
    path: Path,
    name: str | None = None,
    direction: str = "ccw",
    options: ImportOptions | None = None,
) -> Track:
    """Load a DeepRacer waypoint ``.npy`` ((N, 6): centre, inner and outer points, m).

    The file's points are driven in their order. The road is what the file says: each
    half-width is the distance from the smoothed centre line to the file's own border
    polyline on that side (which column is left is read from the geometry). Repeated rows
    (DeepRacer files close the loop by repeating the first, and several repeat another) are
    dropped from the geometry; the file's centre points, every row as published (repeats
    included, so indices match DeepRacer's), are kept as ``track.waypoints`` (DeepRacer's
    ``params["waypoints"]``). ``direction`` only breaks the tie for files whose loop
    orientation cannot be read.
    """
    opts = options or ImportOptions()
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
    arr = arr.astype(np.float64) * opts.scale
    # DeepRacer's params["waypoints"] are every centre row of the file, repeats included
    # (deepracer-simapp markov/track_geom/track_data.py: list(LinearRing(rows[:, 0:2]).coords)),
    # so reward functions keyed to waypoint indices see the same indices here.
    file_points = arr[:, 0:2].copy()
    notes: list[str] = []
    arr = _without_repeats(arr, notes)
    centre, first, second = arr[:, 0:2], arr[:, 2:4], arr[:, 4:6]
    area = signed_area(centre) if np.isfinite(arr).all() and len(centre) >= 3 else 0.0
    ccw = area > 0 if area != 0 else direction == "ccw"
    w_first = np.linalg.norm(first - centre, axis=1)
    w_second = np.linalg.norm(second - centre, axis=1)
    if np.isfinite(arr).all() and len(centre) >= 3:
        tangent = np.roll(centre, -1, axis=0) - np.roll(centre, 1, axis=0)
        first_left = float(np.sum(np.sign(_cross2(tangent, first - centre)))) > 0
    else:
        first_left = ccw  # anticlockwise the inner border (column 3-4) is on the left
    left, right = (first, second) if first_left else (second, first)
    wl, wr = (w_first, w_second) if first_left else (w_second, w_first)
    borders: tuple[FloatArray, FloatArray] | None = (left, right)
    if opts.width is not None:
        wl = wr = np.full(len(centre), opts.width)
        borders = None
    try:
        return _build_imported(
            centre,
            wl,
            wr,
            name=name or path.stem,
            description=f"imported from DeepRacer waypoints {path.name}",
            options=opts,
            notes=notes,
            waypoints=file_points,
            borders=borders,
        )
    except TrackError as err:
        raise TrackError(f"{path}: {err}") from None


def _cross2(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.asarray(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], dtype=np.float64)


def write_deepracer(track: Track, path: Path) -> None:
    """Write a track as a DeepRacer waypoint ``.npy`` (closed: the first row is repeated)."""
    ccw = track.orientation == "ccw"
    inner = track.left_border if ccw else track.right_border
    outer = track.right_border if ccw else track.left_border
    arr = np.column_stack([track.centre, inner, outer])
    with path.open("wb") as fh:
        np.save(fh, np.vstack([arr, arr[:1]]), allow_pickle=False)


RACELINE_COLUMNS = ("s_m", "x_m", "y_m", "psi_rad", "kappa_radpm", "vx_mps", "ax_mps2")


def read_raceline(path: Path, scale: float = 1.0) -> Raceline:
    """Load an F1TENTH race-line CSV (``# s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps;
    ax_mps2``, semicolon separated, ``#`` comment lines; the loop closed by repeating the
    first point), or one whose header names ``x_m``, ``y_m`` and ``vx_mps`` among others
    (the ForzaETH race stack / MapZoo ``*_racing_line.csv``). Only x, y and vx are used:
    headings and curvature follow from the points.
    """
    arr = read_columns(
        path, RACELINE_COLUMNS, (("x_m",), ("y_m",), ("vx_mps",)), "an F1TENTH race line"
    )
    pts, speed = arr[:, :2], arr[:, 2]
    if np.isfinite(pts).all():
        keep, _ = _drop_repeats(pts)
        pts, speed = pts[keep], speed[keep]
    try:
        return Raceline(pts, speed).scaled(scale) if scale != 1.0 else Raceline(pts, speed)
    except TrackError as err:
        raise TrackError(f"{path}: {err}") from None


def read_track_file(
    path: Path,
    fmt: TrackFormat | None = None,
    name: str | None = None,
    options: ImportOptions | None = None,
) -> Track:
    """Load a track file in any supported format (guessed from the suffix when not given).

    ``options`` (scale, width, max width) apply to F1TENTH and DeepRacer files; our JSON is
    read as written.
    """
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
        if options is not None and options != ImportOptions():
            raise TrackError(
                "--scale, --width and --max-width apply to F1TENTH and DeepRacer files"
            )
        track = read_json(path)
        if name:
            track.name = name
        return track
    if fmt == "f1tenth":
        return read_f1tenth(path, name, options)
    if fmt == "deepracer":
        return read_deepracer(path, name, options=options)
    raise TrackError(f"unknown track format {fmt!r}; use one of {', '.join(FORMATS)}")


def write_track_file(track: Track, path: Path, fmt: TrackFormat) -> None:
    """Write a track in one of the supported formats."""
    writers = {"json": write_json, "f1tenth": write_f1tenth, "deepracer": write_deepracer}
    if fmt not in writers:
        raise TrackError(f"unknown track format {fmt!r}; use one of {', '.join(FORMATS)}")
    writers[fmt](track, path)
