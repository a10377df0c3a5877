"""Replay logs: everything needed to watch a race again, independent of the simulator.

A replay is one JSON document (gzip-compressed on disk, ``.replay.json.gz``)::

    {
      "format": "slipstream-replay", "version": 1, "env_version": "0.1",
      "track": {... our track JSON, see tracks.formats ...},
      "dt": 0.05,                                 # seconds between frames
      "cars": [{"agent": "car_0", "name": "pursuit", "colour": [230, 57, 70]}, ...],
      "laps": 3,                                  # optional: the race's lap count
      "frames": {
        "t": [...],                               # (F,) s
        "poses": [[[x, y, yaw], ...], ...],       # (F, n, 3) m, m, rad; null once a car is out
        "steering": [[...], ...],                 # (F, n) rad
        "speed": [[...], ...]                     # (F, n) m/s
      },
      "events": [{"t": 12.3, "type": "lap", "car": "car_0", "lap": 1, "lap_time": 12.3}, ...]
    }

Event types: ``lap``, ``collision`` (with ``other``, ``at_fault``, ``closing_speed``),
``off_track``, ``finish``, ``dnf`` (with ``reason``). Keeping the raw log lets the 3D
``.viser`` replays be regenerated after an upgrade.
"""

from __future__ import annotations

import gzip
import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tracks import Track
from tracks.errors import SlipstreamError, TrackError
from tracks.formats import track_from_dict, track_to_dict

REPLAY_FORMAT = "slipstream-replay"
REPLAY_VERSION = 1


FrameObserver = Callable[["ReplayLog"], None]
_observers: list[FrameObserver] = []


@contextmanager
def observe(callback: FrameObserver) -> Iterator[None]:
    """Call ``callback(log)`` after every frame any replay log records, while in the block.

    How ``slipstream race --watch`` shows a race live: :func:`arena.race.run_race` records
    its replay log frame by frame, and the watcher draws each new frame.
    """
    _observers.append(callback)
    try:
        yield
    finally:
        _observers.remove(callback)


class ReplayError(SlipstreamError):
    """A replay file is missing, corrupt or of an unknown version."""


@dataclass
class ReplayLog:
    """A race as frames and events; built incrementally by :func:`arena.race.run_race`."""

    track: Track
    dt: float
    cars: list[dict[str, Any]]
    env_version: str
    laps: int = 0  # the race's lap count; 0 = not recorded (older logs)
    # The cars' size: {"name": preset or None, "length", "width", "height": m}; {} = not
    # recorded (older logs: the default F1TENTH car).
    car: dict[str, Any] = field(default_factory=dict)
    t: list[float] = field(default_factory=list)
    poses: list[list[list[float] | None]] = field(default_factory=list)
    steering: list[list[float]] = field(default_factory=list)
    speed: list[list[float]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)

    def add_frame(
        self,
        t: float,
        poses: NDArray[np.float64],
        steering: NDArray[np.float64],
        speed: NDArray[np.float64],
        present: NDArray[np.bool_],
    ) -> None:
        """Record one frame: poses (n, 3), steering (n,) rad, speed (n,) m/s."""
        self.t.append(round(float(t), 4))
        self.poses.append(
            [
                [round(float(x), 4), round(float(y), 4), round(float(a), 4)] if on else None
                for (x, y, a), on in zip(poses, present, strict=True)
            ]
        )
        self.steering.append([round(float(v), 4) for v in steering])
        self.speed.append([round(float(v), 3) for v in speed])
        for callback in _observers:
            callback(self)

    def add_event(self, t: float, kind: str, car: str, **fields: Any) -> None:
        """Record an event at time ``t`` s."""
        self.events.append({"t": round(float(t), 4), "type": kind, "car": car, **fields})

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return len(self.t)

    def pose_array(self) -> NDArray[np.float64]:
        """(F, n, 3) poses with NaN where a car was out of the race."""
        nan = [float("nan")] * 3
        return np.array([[p if p is not None else nan for p in row] for row in self.poses])

    def to_dict(self) -> dict[str, Any]:
        """The JSON document."""
        return {
            "format": REPLAY_FORMAT,
            "version": REPLAY_VERSION,
            "env_version": self.env_version,
            "track": track_to_dict(self.track),
            "dt": self.dt,
            "cars": self.cars,
            **({"laps": self.laps} if self.laps > 0 else {}),
            **({"car": self.car} if self.car else {}),
            "frames": {
                "t": self.t,
                "poses": self.poses,
                "steering": self.steering,
                "speed": self.speed,
            },
            "events": self.events,
        }

    def save(self, path: Path) -> Path:
        """Write gzip-compressed JSON to ``path``."""
        data = json.dumps(self.to_dict(), separators=(",", ":")).encode("utf-8")
        with gzip.open(path, "wb", compresslevel=6) as fh:
            fh.write(data)
        return path

    @classmethod
    def from_dict(cls, data: Any) -> ReplayLog:
        """Rebuild a replay from its JSON document."""
        if not isinstance(data, dict) or data.get("format") != REPLAY_FORMAT:
            raise ReplayError("not a Slipstream replay")
        if data.get("version") != REPLAY_VERSION:
            raise ReplayError(f"unsupported replay version {data.get('version')!r}")
        try:
            frames = data["frames"]
            return cls(
                track=track_from_dict(data["track"], source="replay track"),
                dt=float(data["dt"]),
                cars=list(data["cars"]),
                env_version=str(data["env_version"]),
                laps=int(data.get("laps", 0)),
                car=_car_size(data.get("car", {})),
                t=list(frames["t"]),
                poses=list(frames["poses"]),
                steering=list(frames["steering"]),
                speed=list(frames["speed"]),
                events=list(data["events"]),
            )
        except (KeyError, TypeError, ValueError, TrackError) as err:
            raise ReplayError(f"corrupt replay: {err}") from None

    @classmethod
    def load(cls, path: Path) -> ReplayLog:
        """Read a replay written by :meth:`save`."""
        try:
            with gzip.open(path, "rb") as fh:
                data = json.loads(fh.read().decode("utf-8"))
        except FileNotFoundError:
            raise ReplayError(f"replay not found: {path}") from None
        except (OSError, EOFError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ReplayError(f"{path}: corrupt replay ({err})") from None
        return cls.from_dict(data)


def _car_size(data: Any) -> dict[str, Any]:
    """A replay's ``car`` entry, checked: a preset name and positive sizes in metres."""
    if not isinstance(data, dict):
        raise ValueError("car must be an object")
    out: dict[str, Any] = {}
    if data.get("name") is not None:
        out["name"] = str(data["name"])[:32]
    for key in ("length", "width", "height"):
        if key in data:
            value = float(data[key])
            if not 0.0 < value < 10.0:
                raise ValueError(f"car {key} must be between 0 and 10 m, got {value}")
            out[key] = value
    return out
