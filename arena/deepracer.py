"""The AWS DeepRacer reward-function ``params`` dict, so DeepRacer users' functions run as is.

Keys and meanings follow the DeepRacer documentation; units are metres, m/s and degrees
(DeepRacer's convention for ``heading`` and ``steering_angle``, positive to the left).
``waypoints`` are centre-line points about every 0.5 m; ``closest_waypoints`` are the indices
of the waypoints behind and ahead of the car. ``progress`` is the percentage (0–100) of the
race distance (``laps`` laps) completed. The ``objects_*`` keys describe the other cars.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tracks import Track

RewardFunction = Callable[[dict[str, Any]], float]
WAYPOINT_SPACING = 0.5  # m


class DeepRacerParams:
    """Builds DeepRacer params dicts for the cars on one track."""

    def __init__(self, track: Track, race_distance: float) -> None:
        self.track = track
        self.race_distance = race_distance
        self.stride = max(1, round(WAYPOINT_SPACING / float(np.mean(track.segment_lengths))))
        self.waypoint_index = np.arange(0, track.n_points, self.stride)
        self.waypoints = [tuple(map(float, p)) for p in track.centre[self.waypoint_index]]

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
        """The params dict of car ``i``; array arguments are per car (n,) or (n, 3)."""
        t = self.track
        left, right = t.widths_at(s[i : i + 1])
        n_wp = len(self.waypoints)
        prev_wp = int(segment[i] // self.stride) % n_wp
        others = [j for j in range(len(poses)) if j != i and present[j]]
        locations = [(float(poses[j, 0]), float(poses[j, 1])) for j in others]
        gaps = [float(t.delta_s(s[j], s[i])) for j in others]
        ahead = [k for k, g in enumerate(gaps) if g >= 0]
        behind = [k for k, g in enumerate(gaps) if g < 0]
        closest = [
            max(behind, key=lambda k: gaps[k]) if behind else (ahead[-1] if ahead else 0),
            min(ahead, key=lambda k: gaps[k]) if ahead else (behind[0] if behind else 0),
        ]
        in_camera = any(
            0 <= g <= 5.0 and abs(d[others[k]] - d[i]) < 1.0 for k, g in enumerate(gaps)
        )
        return {
            "all_wheels_on_track": bool(all_wheels_on[i]),
            "x": float(poses[i, 0]),
            "y": float(poses[i, 1]),
            "heading": math.degrees(float(poses[i, 2])),
            "distance_from_center": abs(float(d[i])),
            "is_left_of_center": bool(d[i] > 0),
            "projection_distance": float(s[i]),
            "progress": float(np.clip(100.0 * race_progress[i] / self.race_distance, 0, 100)),
            "steps": int(steps),
            "speed": float(speed[i]),
            "steering_angle": math.degrees(float(steering[i])),
            "track_width": float(left[0] + right[0]),
            "track_length": float(t.length),
            "waypoints": self.waypoints,
            "closest_waypoints": [prev_wp, (prev_wp + 1) % n_wp],
            "is_offtrack": bool(off_track[i]),
            "is_crashed": bool(crashed[i]),
            "is_reversed": bool(abs(heading_error[i]) > math.pi / 2),
            "closest_objects": closest if others else [],
            "objects_location": locations,
            "objects_left_of_center": [bool(d[j] > 0) for j in others],
            "objects_speed": [float(speed[j]) for j in others],
            "objects_heading": [math.degrees(float(poses[j, 2])) for j in others],
            "objects_distance": [float(s[j]) for j in others],
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
