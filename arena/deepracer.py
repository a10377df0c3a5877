"""AWS DeepRacer compatibility: the reward-function ``params`` dict, the ``deepracer`` preset's
settings and action spaces read from a DeepRacer ``model_metadata.json``.

Params keys and meanings follow the AWS DeepRacer Developer Guide ("Input parameters of the
AWS DeepRacer reward function",
https://docs.aws.amazon.com/deepracer/latest/developerguide/deepracer-reward-function-input.html)
and the DeepRacer simulation (aws-deepracer-community/deepracer-simapp,
``markov/track_geom/track_data.py``). Units are metres, m/s and degrees (``heading`` and
``steering_angle``, positive to the left).

=========================== =============================================================
key                         here
=========================== =============================================================
``waypoints``               the track file's own centre points for tracks imported from a
                            DeepRacer ``.npy`` (``Track.waypoints``: every row, a repeated
                            row included, as the simulator's ``LinearRing`` keeps it, so
                            indices match DeepRacer's), closed (first == last), in driving
                            order (reversed when the episode runs reversed, as DeepRacer
                            reverses its centre line); other tracks:
                            centre-line points about every 0.5 m, closed the same way
``closest_waypoints``       ``[prev, next]`` indices into ``waypoints`` of the points behind
                            and ahead of the car along the lap (``next`` may be the closing
                            duplicate's index)
``is_reversed``             True when the episode runs against the track file's direction
                            (reset option ``direction="reverse"``; DeepRacer's "reverse"
                            training), whatever the car's heading
``closest_objects``         ``[prev, next]`` indices into the ``objects_*`` lists of the
                            objects just behind and ahead along the lap (DeepRacer's
                            ``find_prev_next``, cyclic); ``[0, 0]`` with one object or none
``objects_*``               every other car of the race, in car order, also after it
                            finished or retired (then reported where the simulator holds it,
                            off the track), as DeepRacer keeps parked cars in its object list
``progress``                percentage (0-100) of the race distance (all laps) completed
=========================== =============================================================

What cannot match: ``objects_speed`` is the other car's actual speed (DeepRacer reports a bot
car's set speed and 0 for static boxes); ``track_width`` is the road width at the car's
progress (DeepRacer measures between the nearest border points); there are no static boxes.
With a single car the ``objects_*`` lists are empty, so AWS example 4 (which indexes
``objects_location``) needs at least two cars, as in DeepRacer where it needs objects.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.actions import SPEED_GAIN
from tracks import Track
from tracks.errors import SlipstreamError

RewardFunction = Callable[[dict[str, Any]], float]
WAYPOINT_SPACING = 0.5  # m between waypoints of tracks that do not carry their file's points
CAMERA_RANGE = 5.0  # m ahead within which another car counts as ``object_in_camera``

FloatArray = NDArray[np.float64]


class DeepRacerError(SlipstreamError):
    """A DeepRacer file (``model_metadata.json``) or setting is malformed."""


def find_prev_next(ordered: FloatArray, x: float) -> tuple[int, int]:
    """DeepRacer's ``find_prev_next``: indices around ``x`` in ascending ``ordered``, cyclic."""
    nxt = int(np.searchsorted(ordered, x, side="right"))
    prev = nxt - 1
    if prev == -1:
        prev = len(ordered) - 1
    if nxt == len(ordered):
        nxt = 0
    return prev, nxt


class DeepRacerParams:
    """Builds DeepRacer params dicts for the cars on one track (one driving direction).

    Args:
        track: the track as driven (a :meth:`Track.reversed` one for reversed episodes).
        race_distance: metres of the whole race, for ``progress``.
    """

    def __init__(self, track: Track, race_distance: float) -> None:
        self.track = track
        self.race_distance = race_distance
        if track.waypoints is not None:
            points = np.asarray(track.waypoints, dtype=np.float64)  # closed already
        else:
            n = max(4, round(track.length / WAYPOINT_SPACING))
            s_wp = np.arange(n) * (track.length / n)
            open_pts = track.to_cartesian(np.column_stack([s_wp, np.zeros(n)]))
            points = np.vstack([open_pts, open_pts[:1]])
        self.waypoints = [(float(x), float(y)) for x, y in points]
        # Progress of each waypoint from the first, along the lap: closest_waypoints looks the
        # car's progress up in it (the last, closing point is at one full lap).
        s_wp = track.project(points[:-1]).s
        rel = np.maximum.accumulate(np.mod(s_wp - s_wp[0], track.length))
        self._wp_s0 = float(s_wp[0])
        self._wp_rel = rel

    def closest_waypoints(self, s: float) -> list[int]:
        """``[prev, next]`` waypoint indices around progress ``s`` m."""
        rel = float(np.mod(s - self._wp_s0, self.track.length))
        prev = int(np.searchsorted(self._wp_rel, rel, side="right")) - 1
        prev = min(max(prev, 0), len(self._wp_rel) - 1)
        return [prev, prev + 1]

    def build(
        self,
        i: int,
        *,
        poses: NDArray[np.float64],
        speed: NDArray[np.float64],
        steering: NDArray[np.float64],
        s: NDArray[np.float64],
        d: NDArray[np.float64],
        segment: NDArray[np.int64],
        heading_error: NDArray[np.float64],
        race_progress: NDArray[np.float64],
        all_wheels_on: NDArray[np.bool_],
        off_track: NDArray[np.bool_],
        crashed: NDArray[np.bool_],
        present: NDArray[np.bool_],
        steps: int,
    ) -> dict[str, Any]:
        """The params dict of car ``i``; array arguments are per car (n,) or (n, 3).

        ``present`` marks cars still racing; the others stay in the ``objects_*`` lists (see
        the module docstring). ``segment`` and ``heading_error`` are accepted for the env's
        call but not needed.
        """
        t = self.track
        left, right = t.widths_at(s[i : i + 1])
        others = [j for j in range(len(poses)) if j != i]
        obj_s = np.array([float(t.wrap_s(s[j])) for j in others])
        if others:
            order = np.argsort(obj_s, kind="stable")
            prev, nxt = find_prev_next(obj_s[order], float(t.wrap_s(s[i])))
            closest = [int(order[prev]), int(order[nxt])]
        else:
            closest = [0, 0]
        in_camera = any(
            present[j]
            and 0.0 <= float(t.delta_s(s[j], s[i])) <= CAMERA_RANGE
            and abs(float(d[j] - d[i])) < 1.0
            for j in others
        )
        return {
            "all_wheels_on_track": bool(all_wheels_on[i]),
            "x": float(poses[i, 0]),
            "y": float(poses[i, 1]),
            "heading": math.degrees(float(math.remainder(float(poses[i, 2]), 2 * math.pi))),
            "distance_from_center": abs(float(d[i])),
            "is_left_of_center": bool(d[i] > 0),
            "projection_distance": float(t.wrap_s(s[i])),
            "progress": float(np.clip(100.0 * race_progress[i] / self.race_distance, 0, 100)),
            "steps": int(steps),
            "speed": float(speed[i]),
            "steering_angle": math.degrees(float(steering[i])),
            "track_width": float(left[0] + right[0]),
            "track_length": float(t.length),
            "waypoints": self.waypoints,
            "closest_waypoints": self.closest_waypoints(float(s[i])),
            "is_offtrack": bool(off_track[i]),
            "is_crashed": bool(crashed[i]),
            "is_reversed": bool(t.is_reversed),
            "closest_objects": closest,
            "objects_location": [(float(poses[j, 0]), float(poses[j, 1])) for j in others],
            "objects_left_of_center": [bool(d[j] > 0) for j in others],
            "objects_speed": [float(speed[j]) for j in others],
            "objects_heading": [
                math.degrees(math.remainder(float(poses[j, 2]), 2 * math.pi)) for j in others
            ],
            "objects_distance": [float(v) for v in obj_s],
            "objects_distance_from_center": [abs(float(d[j])) for j in others],
            "object_in_camera": bool(in_camera),
        }


def follow_centre_line(params: dict[str, Any]) -> float:
    """The DeepRacer documentation's first example: reward staying near the centre line."""
    track_width = params["track_width"]
    distance_from_center = params["distance_from_center"]
    marker_1 = 0.1 * track_width
    marker_2 = 0.25 * track_width
    marker_3 = 0.5 * track_width
    if distance_from_center <= marker_1:
        reward = 1.0
    elif distance_from_center <= marker_2:
        reward = 0.5
    elif distance_from_center <= marker_3:
        reward = 0.1
    else:
        reward = 1e-3  # likely crashed / close to off track
    return float(reward)


# ---- the deepracer preset ------------------------------------------------------------------------


@dataclass(frozen=True)
class DeepRacerPreset:
    """Settings of the ``preset="deepracer"`` env: DeepRacer's training and race rules.

    Attributes:
        car: car preset name (:mod:`arena.cars`): the 1/18 DeepRacer car.
        control_hz: decisions per second; DeepRacer's camera and policy run at 15 Hz.
        laps: laps per episode (a DeepRacer training episode is one lap).
        end_on_off_track: a car's episode ends as soon as all four wheels leave the road
            (DeepRacer's ``is_offtrack`` ends the episode), not after a grace period.
        end_on_crash: a car's episode ends when it hits a wall or another car (``is_crashed``).
        off_track_penalty: seconds added per off-track excursion in ranked races (DeepRacer
            races reset the car onto the track with this penalty).
        collision_penalty: seconds added per at-fault collision in ranked races.
        max_steering_angle: degrees, the action-space limit (the car's full lock).
        speed_range: (low, high) m/s allowed in an action space.
    """

    car: str = "deepracer"
    control_hz: float = 15.0
    laps: int = 1
    end_on_off_track: bool = True
    end_on_crash: bool = True
    off_track_penalty: float = 2.0
    collision_penalty: float = 5.0
    max_steering_angle: float = 30.0
    speed_range: tuple[float, float] = (0.5, 4.0)


DEEPRACER_PRESET = DeepRacerPreset()


@dataclass(frozen=True)
class ActionTable:
    """A discrete DeepRacer action space: one (steering angle, speed) pair per action.

    Attributes:
        steering_angle: (n,) degrees, positive turns left.
        speed: (n,) m/s target speeds.
        max_steering_angle: degrees of full lock (steering fraction = angle / this).
    """

    steering_angle: tuple[float, ...]
    speed: tuple[float, ...]
    max_steering_angle: float = DEEPRACER_PRESET.max_steering_angle

    @property
    def n(self) -> int:
        """Number of actions."""
        return len(self.speed)

    def menu(self) -> FloatArray:
        """(n, 2) [steer fraction of full lock in [-1, 1], target speed m/s], like
        :meth:`arena.actions.DiscreteActions.menu`."""
        steer = np.asarray(self.steering_angle, dtype=np.float64) / self.max_steering_angle
        return np.column_stack([steer, np.asarray(self.speed, dtype=np.float64)])

    def to_controls(
        self, actions: NDArray[np.int64], v_long: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Steering commands and throttles (n,) for action indices (n,) at speeds (n,) m/s:
        the same proportional speed controller as :class:`arena.actions.DiscreteActions`."""
        chosen = self.menu()[np.clip(actions, 0, self.n - 1)]
        throttle = np.clip(SPEED_GAIN * (chosen[:, 1] - v_long), -1.0, 1.0)
        return chosen[:, 0], throttle


MAX_ACTIONS = 128  # DeepRacer's console allows far fewer; more is not an action space


def action_table(
    metadata: Mapping[str, Any] | list[Any], preset: DeepRacerPreset = DEEPRACER_PRESET
) -> ActionTable:
    """The discrete action space of a DeepRacer ``model_metadata.json`` (parsed JSON).

    Accepts the whole document (``{"action_space": [...], "action_space_type": "discrete",
    ...}``) or just its ``action_space`` list of ``{"steering_angle": deg, "speed": m/s,
    "index": k}`` entries (``index`` optional; when given it must be the entry's position).

    Raises:
        DeepRacerError: naming the first problem: not a list, a continuous action space,
            a missing or non-numeric key, an angle beyond ±``max_steering_angle``, a speed
            outside ``speed_range``, a wrong index, or too many actions.
    """
    space: Any = metadata
    if isinstance(metadata, Mapping):
        kind = metadata.get("action_space_type", "discrete")
        if kind != "discrete":
            raise DeepRacerError(
                f"action_space_type {kind!r}: only discrete DeepRacer action spaces are "
                "supported (a continuous one is the env's continuous action mode)"
            )
        if "action_space" not in metadata:
            raise DeepRacerError("model_metadata has no 'action_space' list")
        space = metadata["action_space"]
    if not isinstance(space, list) or not space:
        raise DeepRacerError("action_space must be a non-empty list of {steering_angle, speed}")
    if len(space) > MAX_ACTIONS:
        raise DeepRacerError(f"action_space has {len(space)} actions (at most {MAX_ACTIONS})")
    angles: list[float] = []
    speeds: list[float] = []
    lo, hi = preset.speed_range
    limit = preset.max_steering_angle
    for k, entry in enumerate(space):
        if not isinstance(entry, Mapping):
            raise DeepRacerError(f"action {k}: expected an object, got {type(entry).__name__}")
        values = {}
        for key in ("steering_angle", "speed"):
            v = entry.get(key)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise DeepRacerError(f"action {k}: {key!r} must be a finite number, got {v!r}")
            values[key] = float(v)
        if "index" in entry and entry["index"] != k:
            raise DeepRacerError(f"action {k}: index {entry['index']!r} is not its position {k}")
        if abs(values["steering_angle"]) > limit + 1e-9:
            raise DeepRacerError(
                f"action {k}: steering_angle {values['steering_angle']:g}° is beyond the "
                f"car's ±{limit:g}°"
            )
        if not lo - 1e-9 <= values["speed"] <= hi + 1e-9:
            raise DeepRacerError(
                f"action {k}: speed {values['speed']:g} m/s is outside {lo:g}-{hi:g} m/s"
            )
        angles.append(values["steering_angle"])
        speeds.append(values["speed"])
    return ActionTable(tuple(angles), tuple(speeds), limit)


def read_model_metadata(path: Path, preset: DeepRacerPreset = DEEPRACER_PRESET) -> ActionTable:
    """The action table of a ``model_metadata.json`` file (at most 1 MB)."""
    if not path.is_file():
        raise DeepRacerError(f"model metadata not found: {path}")
    if path.stat().st_size > 1_000_000:
        raise DeepRacerError(f"{path}: {path.stat().st_size} bytes; model_metadata.json is small")
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # a BOM: Windows editors
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DeepRacerError(f"{path}: not valid JSON ({err})") from None
    try:
        return action_table(data, preset)
    except DeepRacerError as err:
        raise DeepRacerError(f"{path}: {err}") from None
