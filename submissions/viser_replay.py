"""3D replays: a race's :class:`~arena.replay.ReplayLog` recorded as a ``.viser`` file.

A ``.viser`` file is viser's scene recording (``viser==1.1.1``): the static scene of
:func:`arena.viser_scene.build_scene` (track ribbon, red/white kerbs, start/finish line,
ground grid, one box per car with a nose, a track-sized marker arrow and a pole in the car's
colour topped by a ``P<position> <name>`` label, a standings board with the lap counter, and a
camera that frames the whole track) followed by every car's pose, frame by frame, with
``insert_sleep(1 / fps)`` between frames; labels and board change when the standings do
(:func:`replay_standings`). The site plays it with viser's prebuilt static player
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
from arena.standings import Standing, StandingsTracker, race_laps
from arena.viser_scene import build_scene, replay_car, yaw_to_wxyz  # noqa: F401 - re-exported
from submissions.errors import SubmissionError

FloatArray = NDArray[np.float64]

MAX_FRAMES = 200_000  # ~1.8 h at 30 fps: more is a corrupt replay, not a race


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


def replay_standings(replay: ReplayLog) -> list[Standing]:
    """The standings at each of the replay's frames (F,), events applied at their times."""
    tracker = StandingsTracker(replay.track, [str(c.get("agent", "")) for c in replay.cars])
    events = sorted(replay.events, key=lambda e: float(e.get("t", 0.0)))
    poses = replay.pose_array().reshape(replay.n_frames, len(replay.cars), 3)
    out, k = [], 0
    for f, t in enumerate(replay.t):
        while k < len(events) and float(events[k].get("t", 0.0)) <= t:
            tracker.event(events[k])
            k += 1
        out.append(tracker.frame(float(t), poses[f]))
    return out


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
    times, poses = sample_poses(replay, fps)
    standings = replay_standings(replay)
    t = np.asarray(replay.t, dtype=np.float64)
    frame_of = np.clip(np.searchsorted(t, times + 1e-9, side="right") - 1, 0, len(t) - 1)
    laps = race_laps(replay.events, replay.laps)
    import viser  # noqa: PLC0415 - optional `eval` extra, only where replays are recorded

    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):  # viser prints its address table even when quiet
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        car = replay_car(replay.car)
        cars = build_scene(server, replay.track, replay.cars, car=car, start=poses[0])
        cars.rank(standings[0], laps)
        serializer = server.get_scene_serializer()
        for k in range(len(poses)):
            with server.atomic():
                cars.move(poses[k])
                cars.rank(standings[frame_of[k]], laps)
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
