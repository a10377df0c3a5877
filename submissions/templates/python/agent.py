"""A Slipstream racer: edit ``Policy.act`` and check it with ``slipstream bundle check .``.

The server builds ``Policy(env_spec=...)`` once, in a sandbox (no network, no files outside
this folder, numpy and torch available), calls ``reset(seed)`` before each race and
``act(obs)`` every control step (20 Hz; answer within the step deadline, about 50 ms).

Observation: ``obs`` is a flat float32 vector (``env_spec["obs_shape"]``, 95 values with the
default 64 lidar rays and 3 opponents), in this order::

    [ lidar (n_rays) | ego (7) | track ahead (7 x 2) | opponents (k x 5) ]

* lidar: ``n_rays`` ranges over 270 degrees (right to left), 10 m, as fractions of 10 m
  (1.0 = nothing within range); walls and other cars both show.
* ego (7): forward speed / v_max, lateral speed / v_max, steering / max steer,
  yaw rate / 10 rad/s, heading error / pi (+ = pointing left of the track), lateral offset
  (0 on the centre line, +-1 on the road edges), progress rate / v_max.
* track ahead (7 x 2): the centre line 1, 2, 3, 4, 6, 8 and 10 m ahead, each ``[dx, dy]``
  in the car's frame (x forward, y left) / 10 m. Steering towards these points follows the
  road.
* opponents (k x 5): the nearest cars, nearest first: ``[present, dx, dy, dvx, dvy]`` in
  the car's frame (positions / 10 m, velocities / v_max); absent slots are all zeros.

Action: ``[steer, throttle]``, two floats in [-1, 1]. ``steer`` is the fraction of full
lock (0.42 rad on the F1TENTH car, 30 degrees on the DeepRacer: ``env_spec["car"]`` says
which you drive), + turns left. ``throttle`` > 0 drives, < 0 brakes (then reverses). An
action outside the box, NaN, or of the wrong shape retires the car (``dnf``, ``invalid``).

Race rules in short: laps count only through every checkpoint in order; ranked races add
+2 s per off-track excursion and +5 s per collision you caused.
"""

from __future__ import annotations

import math

import numpy as np

LOOKAHEAD = (1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 10.0)  # m: where the track-ahead points are
CARS = {"f1tenth": (0.33, 0.42), "deepracer": (0.164, math.radians(30.0))}  # wheelbase m, lock rad
MAX_RANGE = 10.0  # m: lidar range, the scale of the track-ahead points
N_EGO = 7


class Policy:
    """Follow the centre line; slow down before corners and when a car is close ahead.

    Args:
        env_spec: what the server races you in (``lidar_rays``, ``k_opponents``,
            ``obs_shape``, ``action_mode``, ``car``: the car you drive, ``"f1tenth"`` or
            ``"deepracer"``, ...); the defaults match the ranked races.
    """

    def __init__(self, env_spec: dict | None = None) -> None:
        spec = env_spec or {}
        self.n_rays = int(spec.get("lidar_rays", 64))
        self.k_opponents = int(spec.get("k_opponents", 3))
        self.wheelbase, self.max_steer = CARS.get(spec.get("car") or "f1tenth", CARS["f1tenth"])
        self.top_speed = 0.55  # fraction of v_max on straights
        self.corner_speed = 0.25  # fraction of v_max in tight corners

    def reset(self, seed: int | None = None) -> None:
        """A new race starts (nothing to forget here)."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        """[steer, throttle] for one observation (see the module docstring)."""
        ego = obs[self.n_rays : self.n_rays + N_EGO]
        start = self.n_rays + N_EGO
        ahead = obs[start : start + 2 * len(LOOKAHEAD)].reshape(-1, 2) * MAX_RANGE
        speed = float(ego[0])

        # Steer at the centre-line point 3 m ahead (pure pursuit for this car's wheelbase).
        x, y = float(ahead[2, 0]), float(ahead[2, 1])
        dist = max(math.hypot(x, y), 1e-3)
        steer = math.atan(2.0 * self.wheelbase * (y / dist) / dist) / self.max_steer

        # How sharply the road bends 10 m ahead sets the target speed.
        far = ahead[-1]
        bend = abs(math.atan2(float(far[1]), float(far[0])))  # rad
        target = self.top_speed - (self.top_speed - self.corner_speed) * min(bend / 1.0, 1.0)

        # Lift off for a car close ahead in our lane.
        opp = obs[start + 2 * len(LOOKAHEAD) :].reshape(-1, 5)
        for present, dx, dy, _dvx, _dvy in opp:
            if present > 0.5 and 0.0 < dx * MAX_RANGE < 2.0 and abs(dy * MAX_RANGE) < 0.5:
                target = min(target, 0.8 * speed)

        throttle = float(np.clip(4.0 * (target - speed), -1.0, 1.0))
        return np.array([np.clip(steer, -1.0, 1.0), throttle], dtype=np.float32)
