"""Baseline drivers: ``random``, ``pursuit`` (pure pursuit) and ``gap`` (follow the gap).

All three read only the ``"vector"`` observation (and continuous actions), so they can race
anywhere a submitted policy can, sandbox included. They need the observation layout
(:class:`arena.observations.ObservationLayout`) and the car's parameters to decode it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from agents.policy import PolicyError
from arena.lidar import DEFAULT_FOV, DEFAULT_RANGE
from arena.observations import LOOKAHEAD, ObservationLayout
from arena.sim import GRAVITY, CarParams

FloatArray = NDArray[np.float64]
BASELINES = ("pursuit", "gap", "random")


class RandomPolicy:
    """Uniformly random steering and throttle (seeded): the floor every policy must beat."""

    def __init__(self, name: str = "random", seed: int | None = None) -> None:
        self.name = name
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        """Reseed."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)

    def act(self, obs: NDArray[np.float32]) -> NDArray[np.float32]:
        """A random [steer, throttle] in [-1, 1]²."""
        return self.rng.uniform(-1.0, 1.0, 2).astype(np.float32)


class PursuitPolicy:
    """Pure pursuit along the centre line with a curvature-based speed profile.

    Steering: the look-ahead point at ``ld = 0.8 + 0.3 v`` m (1–4 m) on the centre-line
    preview; steer to the arc through it (``δ = atan(2 L sin α / ld)``). Speed: each
    preview point allows ``sqrt(a_lat / κ)`` (κ from three consecutive points), reachable
    only if the car can brake to it in time (``v² ≤ v_allowed² + 2 a_brake · distance``).
    It lifts for a car close ahead in its path.

    Args:
        layout: observation layout of the env it drives in.
        params: the car's parameters.
        grip: fraction of the friction limit used in corners.
    """

    def __init__(
        self,
        layout: ObservationLayout,
        params: CarParams | None = None,
        *,
        name: str = "pursuit",
        grip: float = 0.75,
        brake: float = 5.0,
        max_range: float = DEFAULT_RANGE,
    ) -> None:
        self.name = name
        self.layout = layout
        self.params = params or CarParams()
        self.a_lat = grip * self.params.friction * GRAVITY
        self.brake = brake
        self.max_range = max_range
        self.dist = np.asarray(LOOKAHEAD)

    def reset(self, seed: int | None = None) -> None:
        """Stateless: nothing to reset."""

    def act(self, obs: NDArray[np.float32]) -> NDArray[np.float32]:
        """[steer, throttle] from one vector observation."""
        p, lay = self.params, self.layout
        ego = obs[lay.ego].astype(np.float64)
        v = float(ego[0]) * p.max_speed
        pts = obs[lay.track_ahead].astype(np.float64).reshape(-1, 2) * self.max_range
        ld = min(max(0.8 + 0.3 * v, self.dist[0]), 4.0)
        target = np.array(
            [np.interp(ld, self.dist, pts[:, 0]), np.interp(ld, self.dist, pts[:, 1])]
        )
        dist = max(float(np.hypot(*target)), 1e-3)
        alpha = math.atan2(target[1], target[0])
        steer = math.atan(2.0 * p.wheelbase * math.sin(alpha) / dist)
        v_target = self._speed_limit(pts, v)
        v_target = min(v_target, self._follow_speed(obs, v))
        throttle = float(np.clip(2.0 * (v_target - v), -1.0, 1.0))
        return np.array([np.clip(steer / p.max_steer, -1, 1), throttle], dtype=np.float32)

    def _speed_limit(self, pts: FloatArray, v: float) -> float:
        """Fastest speed from which every corner in the preview can still be taken, m/s."""
        chain = np.vstack([[0.0, 0.0], pts])
        a, b, c = chain[:-2], chain[1:-1], chain[2:]
        ab, bc, ca = (
            np.linalg.norm(b - a, axis=1),
            np.linalg.norm(c - b, axis=1),
            np.linalg.norm(a - c, axis=1),
        )
        cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
        kappa = 2.0 * cross / np.maximum(ab * bc * ca, 1e-9)  # Menger curvature, 1/m
        allowed = np.sqrt(self.a_lat / np.maximum(kappa, 1e-6))
        reach = np.sqrt(allowed**2 + 2.0 * self.brake * np.maximum(self.dist[:-1] - 1.0, 0.0))
        return float(min(self.params.top_speed, reach.min()))

    def _follow_speed(self, obs: NDArray[np.float32], v: float) -> float:
        """Speed that keeps a gap to the nearest car ahead in the car's path, m/s."""
        lay, p = self.layout, self.params
        opp = obs[lay.opponents].astype(np.float64).reshape(lay.k_opponents, 5)
        dx, dy = opp[:, 1] * self.max_range, opp[:, 2] * self.max_range
        ahead = (opp[:, 0] > 0.5) & (dx > 0.0) & (dx < 3.0) & (np.abs(dy) < 0.45)
        if not ahead.any():
            return math.inf
        k = int(np.argmin(np.where(ahead, dx, np.inf)))
        their_speed = v + opp[k, 3] * p.max_speed
        return max(0.0, their_speed + 1.5 * (dx[k] - 1.0))


class GapFollowerPolicy:
    """Follow the gap, as the F1TENTH "disparity extender": a purely reactive lidar driver.

    Where neighbouring beams jump in range (an edge of a wall or a car), the nearer range is
    extended over the beams a car-width-plus-margin would need to pass, so gaps too narrow
    to fit through close up; the car then steers toward the farthest remaining beam in the
    front half (ties: the one nearest straight ahead) and sets its speed from the free space
    straight ahead. It knows nothing of the track but what the lidar sees.
    """

    def __init__(
        self,
        layout: ObservationLayout,
        params: CarParams | None = None,
        *,
        name: str = "gap",
        fov: float = DEFAULT_FOV,
        max_range: float = DEFAULT_RANGE,
        margin: float = 0.45,
        disparity: float = 0.3,
    ) -> None:
        self.name = name
        self.layout = layout
        self.params = params or CarParams()
        n = layout.n_rays
        self.step = fov / max(n - 1, 1)
        self.angles = -0.5 * fov + self.step * np.arange(n)
        self.front = np.abs(self.angles) <= math.pi / 2
        self.max_range = max_range
        self.half = 0.5 * self.params.width + margin
        self.disparity = disparity

    def reset(self, seed: int | None = None) -> None:
        """Stateless: nothing to reset."""

    def act(self, obs: NDArray[np.float32]) -> NDArray[np.float32]:
        """[steer, throttle] from one vector observation."""
        p = self.params
        ranges = obs[self.layout.lidar].astype(np.float64) * self.max_range
        safe = ranges.copy()
        jumps = np.flatnonzero(np.abs(np.diff(ranges)) > self.disparity)
        for k in jumps.tolist():  # a handful per scan
            near_i, far_dir = (k, 1) if ranges[k] < ranges[k + 1] else (k + 1, -1)
            near = max(ranges[near_i], 0.05)
            width = math.ceil(math.atan2(self.half, near) / self.step)
            lo, hi = sorted((near_i, near_i + far_dir * width))
            lo, hi = max(lo, 0), min(hi, len(safe) - 1)
            safe[lo : hi + 1] = np.minimum(safe[lo : hi + 1], near)
        score = np.where(self.front, safe, -1.0) - 1e-3 * np.abs(self.angles)
        best = int(np.argmax(score))
        aim = self.angles[best]
        dist = min(max(safe[best], 0.5), 3.0)
        steer = math.atan(2.0 * p.wheelbase * math.sin(aim) / dist)
        ahead = float(np.min(np.where(np.abs(self.angles) < 0.2, safe, np.inf)))
        v = float(obs[self.layout.ego][0]) * p.max_speed
        v_target = float(np.clip(1.2 * ahead - 0.6, 2.0, 6.5))
        throttle = float(np.clip(1.5 * (v_target - v), -1.0, 1.0))
        return np.array([np.clip(steer / p.max_steer, -1.0, 1.0), throttle], dtype=np.float32)


def make_baseline(
    name: str,
    layout: ObservationLayout,
    params: CarParams | None = None,
    seed: int | None = None,
) -> RandomPolicy | PursuitPolicy | GapFollowerPolicy:
    """A baseline policy by name: ``pursuit``, ``gap`` or ``random``."""
    if name == "pursuit":
        return PursuitPolicy(layout, params)
    if name == "gap":
        return GapFollowerPolicy(layout, params)
    if name == "random":
        return RandomPolicy(seed=seed)
    raise PolicyError(f"unknown baseline {name!r}; choose from {', '.join(BASELINES)}")
