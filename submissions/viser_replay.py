"""3D replays: a race's :class:`~arena.replay.ReplayLog` recorded as a ``.viser`` file.

A ``.viser`` file is viser's scene recording (``viser==1.1.1``): the static scene (track
ribbon, red/white kerbs, start/finish line, ground grid, one box per car with a nose and a
name label) followed by every car's pose, frame by frame, with ``insert_sleep(1 / fps)``
between frames. The site plays it with viser's prebuilt static player
(``/viewer/?playbackPath=/replays/<id>.viser``); nothing runs on the server while people watch.

The replay log stays the source of truth: after a viser upgrade, regenerate the ``.viser``
files from the ``.replay.json.gz`` logs with :func:`write_viser`.

Frames: output frame ``k`` (``k = 0 … K-1``, ``K = ⌊duration × fps⌋ + 1``) shows the race at
``t₀ + k / fps`` seconds, interpolating each car's pose linearly between the two replay frames
around it (yaw along the shorter arc). With ``fps = 1 / replay.dt`` there is exactly one
output frame per replay frame. A car that has left the race is hidden. The recording lasts
``K / fps`` seconds; viser records only what changes, so a car standing still adds nothing.
"""

from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.replay import ReplayLog
from arena.sim import CarParams
from submissions.errors import SubmissionError

FloatArray = NDArray[np.float64]

ROAD_COLOUR = (70, 70, 75)
KERB_COLOURS = ((220, 30, 30), (245, 245, 245))
KERB_RUN = 3  # border segments per kerb stripe
KERB_WIDTH = 0.08  # m, drawn line width
SURFACE_Z = 0.0  # m
LINE_Z = 0.01  # m: lines just above the road, so they are not z-fighting with it
MAX_FRAMES = 200_000  # ~1.8 h at 30 fps: more is a corrupt replay, not a race


def yaw_to_wxyz(yaw: FloatArray) -> FloatArray:
    """Quaternions (..., 4) [w, x, y, z] of rotations by ``yaw`` rad about +z."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zero = np.zeros_like(half)
    return np.stack([np.cos(half), zero, zero, np.sin(half)], axis=-1)


def sample_poses(replay: ReplayLog, fps: float) -> tuple[FloatArray, FloatArray]:
    """Car poses at ``fps`` frames per second, interpolated from the replay's frames.

    Returns:
        ``(times, poses)``: times (K,) s and poses (K, n, 3) [x m, y m, yaw rad], NaN where
        a car is out of the race.
    """
    if replay.n_frames == 0:
        raise SubmissionError("the replay has no frames to record")
    t = np.asarray(replay.t, dtype=np.float64)
    poses = replay.pose_array().reshape(replay.n_frames, len(replay.cars), 3)
    n_out = math.floor((t[-1] - t[0]) * fps + 1e-6) + 1
    if n_out > MAX_FRAMES:
        raise SubmissionError(f"the replay would record {n_out} frames at {fps} fps; too many")
    times = t[0] + np.arange(n_out) / fps
    i0 = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)
    i1 = np.minimum(i0 + 1, len(t) - 1)
    span = np.maximum(t[i1] - t[i0], 1e-9)
    w = np.clip((times - t[i0]) / span, 0.0, 1.0)[:, None]  # (K, 1)
    a, b = poses[i0], poses[i1]  # (K, n, 3)
    dyaw = (b[..., 2] - a[..., 2] + np.pi) % (2 * np.pi) - np.pi
    mixed = np.stack(
        [
            a[..., 0] + w * (b[..., 0] - a[..., 0]),
            a[..., 1] + w * (b[..., 1] - a[..., 1]),
            a[..., 2] + w * dyaw,
        ],
        axis=-1,
    )
    # Where the next frame has the car out (or it just joined), hold the earlier pose.
    return times, np.where(np.isnan(b), a, mixed)


def track_ribbon(replay: ReplayLog) -> tuple[NDArray[np.float32], NDArray[np.uint32]]:
    """The road surface as a closed triangle strip: vertices (2N, 3) m and faces (2N, 3)."""
    track = replay.track
    n = track.n_points
    verts = np.zeros((2 * n, 3), dtype=np.float32)
    verts[0::2, :2] = track.left_border
    verts[1::2, :2] = track.right_border
    verts[:, 2] = SURFACE_Z
    i = np.arange(n)
    j = (i + 1) % n
    a, b, c, d = 2 * i, 2 * i + 1, 2 * j, 2 * j + 1
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)]).astype(np.uint32)
    return verts, faces


def kerb_segments(border: FloatArray) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """A closed border polyline (N, 2) m as segments (N, 2, 3) and red/white colours (N, 2, 3)."""
    pts = np.concatenate([border, np.full((len(border), 1), LINE_Z)], axis=1)
    seg = np.stack([pts, np.roll(pts, -1, axis=0)], axis=1).astype(np.float32)
    stripe = (np.arange(len(seg)) // KERB_RUN) % 2
    cols = np.asarray(KERB_COLOURS, dtype=np.uint8)[stripe]
    return seg, np.repeat(cols[:, None, :], 2, axis=1)


def _build_scene(server: Any, replay: ReplayLog, car: CarParams) -> list[Any]:
    """Add the static scene and one node per car (hidden); returns the car nodes."""
    scene = server.scene
    track = replay.track
    scene.set_up_direction("+z")
    xmin, ymin, xmax, ymax = track.bounds
    cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    size = max(xmax - xmin, ymax - ymin) + 4.0
    scene.add_grid(
        "/ground",
        width=size,
        height=size,
        cell_size=1.0,
        section_size=5.0,
        plane="xy",
        position=(cx, cy, -0.01),
    )
    verts, faces = track_ribbon(replay)
    scene.add_mesh_simple(
        "/track/surface", verts, faces, color=ROAD_COLOUR, side="double", cast_shadow=False
    )
    for name, border in (("left", track.left_border), ("right", track.right_border)):
        seg, cols = kerb_segments(border)
        scene.add_line_segments(f"/track/kerb_{name}", seg, cols, thickness=KERB_WIDTH)
    gate = track.gates([0.0])[0]
    line = np.concatenate([gate, np.full((2, 1), LINE_Z)], axis=1)[None].astype(np.float32)
    scene.add_line_segments("/track/start_finish", line, (255, 255, 255), thickness=0.1)
    nodes = []
    for i, info in enumerate(replay.cars):
        colour = tuple(int(c) for c in info.get("colour", (200, 200, 200)))
        node = scene.add_frame(f"/cars/car_{i}", show_axes=False, visible=False)
        scene.add_box(
            f"/cars/car_{i}/body",
            color=colour,
            dimensions=(car.length, car.width, car.height),
            position=(0.0, 0.0, 0.5 * car.height),
        )
        scene.add_box(  # a dark nose, so the heading reads at a glance
            f"/cars/car_{i}/nose",
            color=(25, 25, 25),
            dimensions=(0.15 * car.length, 0.8 * car.width, 0.3 * car.height),
            position=(0.45 * car.length, 0.0, car.height),
        )
        scene.add_label(
            f"/cars/car_{i}/label",
            str(info.get("name", info.get("agent", f"car_{i}"))),
            position=(0.0, 0.0, 3.0 * car.height),
        )
        nodes.append(node)
    server.initial_camera.position = (cx, cy - 0.6 * size, 0.7 * size)
    server.initial_camera.look_at = (cx, cy, 0.0)
    return nodes


def write_viser(replay: ReplayLog, out: Path, fps: float = 30) -> Path:
    """Record ``replay`` as a ``.viser`` file at ``fps`` frames per second.

    Args:
        replay: the race's replay log.
        out: the file to write (its folder is created).
        fps: output frame rate; ``1 / replay.dt`` gives one frame per replay frame.

    Returns:
        ``out``.

    Raises:
        SubmissionError: an empty replay, a bad ``fps``, or a replay too long to record.
    """
    if not math.isfinite(fps) or fps <= 0:
        raise SubmissionError(f"fps must be a positive number, not {fps!r}")
    _, poses = sample_poses(replay, fps)
    pos = np.zeros(poses.shape, dtype=np.float64)
    pos[..., :2] = poses[..., :2]
    wxyz = yaw_to_wxyz(poses[..., 2])
    present = ~np.isnan(poses[..., 0])
    import viser  # noqa: PLC0415 - optional `eval` extra, only where replays are recorded

    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):  # viser prints its address table even when quiet
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        nodes = _build_scene(server, replay, CarParams())
        serializer = server.get_scene_serializer()
        shown = [False] * len(nodes)
        for k in range(len(poses)):
            with server.atomic():
                for c, node in enumerate(nodes):
                    if present[k, c]:
                        node.position = pos[k, c]
                        node.wxyz = wxyz[k, c]
                    if present[k, c] != shown[c]:
                        node.visible = bool(present[k, c])
                        shown[c] = bool(present[k, c])
            serializer.insert_sleep(1.0 / fps)
        data = serializer.serialize()
    finally:
        with contextlib.redirect_stdout(quiet):
            server.stop()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    return out


def read_viser(path: Path) -> dict[str, Any]:
    """Decode a ``.viser`` file: ``{"durationSeconds", "messages": [(t, msg), …], …}``.

    The layout (viser 1.1.1): 8-byte little-endian size of the inner blob, then zstd of
    [8-byte msgpack length][msgpack document][binary buffers].
    """
    import msgspec  # noqa: PLC0415 - viser's own dependencies, used only to inspect files
    import zstandard  # noqa: PLC0415

    raw = Path(path).read_bytes()
    if len(raw) < 16:
        raise SubmissionError(f"{path}: not a .viser recording (too short)")
    inner_size = int.from_bytes(raw[:8], "little")
    try:
        inner = zstandard.ZstdDecompressor().decompress(raw[8:], max_output_size=inner_size)
        n = int.from_bytes(inner[:8], "little")
        doc = msgspec.msgpack.decode(inner[8 : 8 + n])
    except (zstandard.ZstdError, msgspec.DecodeError, ValueError) as err:
        raise SubmissionError(f"{path}: not a .viser recording ({err})") from None
    if not isinstance(doc, dict) or "messages" not in doc:
        raise SubmissionError(f"{path}: not a .viser recording (no messages)")
    return doc
