"""Baseline drivers: ``random``, ``pursuit`` (pure pursuit), ``gap`` (follow the gap) and
``raceline`` (pure pursuit on a track's race line, with its speed profile).

All read only the ``"vector"`` observation (and continuous actions), so they can race
anywhere a submitted policy can, sandbox included. They need the observation layout
(:class:`arena.observations.ObservationLayout`) and the car's parameters to decode it;
``raceline`` also needs the track (with a :class:`tracks.geometry.Raceline`), on which it
finds itself from the observation.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from agents.policy import PolicyError
from arena.lidar import DEFAULT_FOV, DEFAULT_RANGE
from arena.observations import LOOKAHEAD, ObservationLayout
from arena.sim import GRAVITY, CarParams
from tracks import Track
from tracks.geometry import three_point_curvature

FloatArray = NDArray[np.float64]
REFERENCE_WHEELBASE = CarParams().wheelbase  # m: the F1TENTH car, for which look-aheads are tuned
BASELINES = ("pursuit", "gap", "random")  # need only the observation (and the car)
TRACK_BASELINES = ("raceline",)  # also need the track: make_baseline(..., track=)


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

    Steering: the look-ahead point at ``ld = (0.8 + 0.3 v) k`` m (``k`` to ``4 k``) on the
    centre-line preview, where ``k = L / 0.33 m`` scales the look-ahead to the car's wheelbase
    ``L`` (1 for the F1TENTH car; 0.5 for the DeepRacer car, whose tracks are 0.6-1.1 m wide
    and bend at 0.6 m radii, where a 1.6 m look-ahead cuts an S-bend into the wall: AWS
    DeepRacer "Carrera" track); below the first preview point (1 m) it aims along the chord
    from the car to that point. Steer to the arc through it (``δ = atan(2 L sin α / ld)``).
    Speed: each preview point allows ``sqrt(a_lat / κ)`` (κ from three consecutive points),
    reachable only if the car can brake to it in time (``v² ≤ v_allowed² + 2 a_brake · distance``).
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
        # look-ahead scale: the F1TENTH car's wheelbase is the reference (k = 1)
        self.k_look = self.params.wheelbase / REFERENCE_WHEELBASE

    def reset(self, seed: int | None = None) -> None:
        """Stateless: nothing to reset."""

    def act(self, obs: NDArray[np.float32]) -> NDArray[np.float32]:
        """[steer, throttle] from one vector observation."""
        p, lay = self.params, self.layout
        ego = obs[lay.ego].astype(np.float64)
        v = float(ego[0]) * p.max_speed
        pts = obs[lay.track_ahead].astype(np.float64).reshape(-1, 2) * self.max_range
        ld = self.lookahead(v)
        # the car itself (0, 0) is the point 0 m ahead, for look-aheads under the first preview
        ahead, chain = np.concatenate([[0.0], self.dist]), np.vstack([[0.0, 0.0], pts])
        target = np.array([np.interp(ld, ahead, chain[:, 0]), np.interp(ld, ahead, chain[:, 1])])
        dist = max(float(np.hypot(*target)), 1e-3)
        alpha = math.atan2(target[1], target[0])
        steer = math.atan(2.0 * p.wheelbase * math.sin(alpha) / dist)
        v_target = self._speed_limit(pts, v)
        v_target = min(v_target, self._follow_speed(obs, v))
        throttle = float(np.clip(2.0 * (v_target - v), -1.0, 1.0))
        return np.array([np.clip(steer / p.max_steer, -1, 1), throttle], dtype=np.float32)

    def lookahead(self, v: float) -> float:
        """Look-ahead distance at speed ``v`` m/s: ``(0.8 + 0.3 v) k`` m within ``[k, 4 k]``."""
        k = self.k_look
        return min(max((0.8 + 0.3 * v) * k, k), 4.0 * k)

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


class RacelinePolicy(PursuitPolicy):
    """Pure pursuit on the track's race line, at the race line's speeds.

    Localisation: the vector observation holds the centre line ahead (points at
    ``LOOKAHEAD`` m, in the car's frame), the heading error and the lateral offset. For every
    centre-line point ``s`` of the track (both directions, so reversed races work) the car's
    pose that those two imply is built and the centre line ahead of it is compared with the
    observed one; the best match (searched within 3 m of the last one once found) gives the
    pose. Steering: the look-ahead point ``ld`` of :meth:`PursuitPolicy.lookahead` along the
    race line,
    ``δ = atan(2 L sin α / ld)``. Speed: the race line's speed times ``speed_scale``, capped
    by the car's top speed and ``sqrt(a_lat / κ)`` of the race line, with a braking pass
    (``v² ≤ v_next² + 2 a_brake ds``) so it slows before bends; it lifts for a car close ahead
    like pursuit.

    Args:
        layout: observation layout of the env it drives in.
        params: the car's parameters.
        track: the track, with a race line.
        speed_scale: multiplies the race line's speed profile.

    Raises:
        PolicyError: the track has no race line.
    """

    WINDOW = 3.0  # m of progress searched around the last position

    def __init__(
        self,
        layout: ObservationLayout,
        params: CarParams | None,
        track: Track,
        *,
        name: str = "raceline",
        speed_scale: float = 1.0,
        grip: float = 0.75,
        brake: float = 5.0,
        max_range: float = DEFAULT_RANGE,
    ) -> None:
        super().__init__(layout, params, name=name, grip=grip, brake=brake, max_range=max_range)
        if track.raceline is None:
            raise PolicyError(f"track {track.name!r} has no race line for the raceline baseline")
        self.speed_scale = speed_scale
        self._views = [self._prepare(track), self._prepare(track.reversed())]
        self.direction: int | None = None  # index into _views once localised
        self._k: int | None = None  # last centre-line index
        self._r: int | None = None  # last race-line index

    def _prepare(self, track: Track) -> dict[str, FloatArray]:
        """Per-direction tables: centre points ahead (N, L, 2), race line and its speeds."""
        assert track.raceline is not None
        ahead_s = (track.s[:, None] + np.asarray(LOOKAHEAD)[None, :]).ravel()
        ahead = track.to_cartesian(np.column_stack([ahead_s, np.zeros_like(ahead_s)]))
        pts = track.raceline.points
        seg = np.linalg.norm(np.roll(pts, -1, axis=0) - pts, axis=1)
        kappa = np.abs(three_point_curvature(pts))
        v = np.minimum(track.raceline.speed * self.speed_scale, self.params.top_speed)
        v = np.minimum(v, np.sqrt(self.a_lat / np.maximum(kappa, 1e-6)))
        for _ in range(2):  # braking pass round the loop (twice: the seam)
            for i in range(len(v) - 1, -1, -1):
                j = (i + 1) % len(v)
                v[i] = min(v[i], math.sqrt(v[j] ** 2 + 2.0 * self.brake * seg[i]))
        return {
            "centre": track.centre,
            "normals": track.normals,
            "headings": track.headings,
            "left": track.width_left,
            "right": track.width_right,
            "s": track.s,
            "length": np.array([track.length]),
            "ahead": ahead.reshape(track.n_points, -1, 2),
            "line": pts,
            "seg": seg,
            "speed": v,
        }

    def reset(self, seed: int | None = None) -> None:
        """Forget where the car was (the next observation is localised from scratch)."""
        self.direction, self._k, self._r = None, None, None

    def _match(
        self, view: dict[str, FloatArray], obs: NDArray[np.float32], cand: NDArray[np.int64]
    ) -> tuple[int, float, FloatArray]:
        """Best candidate centre-line index, its cost and the pose (3,) it implies."""
        lay = self.layout
        ego = obs[lay.ego].astype(np.float64)
        seen = obs[lay.track_ahead].astype(np.float64).reshape(-1, 2)
        half = np.where(ego[5] >= 0, view["left"][cand], view["right"][cand])
        pos = view["centre"][cand] + (ego[5] * half)[:, None] * view["normals"][cand]
        yaw = view["headings"][cand] + ego[4] * math.pi
        rel = view["ahead"][cand] - pos[:, None, :]
        cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        local = np.stack(
            [cos * rel[..., 0] + sin * rel[..., 1], cos * rel[..., 1] - sin * rel[..., 0]], -1
        )
        cost = np.sum((local / self.max_range - seen) ** 2, axis=(1, 2))
        best = int(np.argmin(cost))
        return int(cand[best]), float(cost[best]), np.array([*pos[best], yaw[best]])

    def locate(self, obs: NDArray[np.float32]) -> FloatArray:
        """The car's pose (3,) [x m, y m, yaw rad] found from one vector observation."""
        if self.direction is None or self._k is None:
            found = [self._match(v, obs, np.arange(len(v["s"]))) for v in self._views]
            self.direction = int(np.argmin([f[1] for f in found]))
            self._k, _, pose = found[self.direction]
            return pose
        view = self._views[self.direction]
        n = len(view["s"])
        step = float(view["length"][0]) / n
        reach = int(self.WINDOW / step) + 1
        cand = (self._k + np.arange(-reach, reach + 1)) % n
        self._k, _, pose = self._match(view, obs, cand)
        return pose

    def act(self, obs: NDArray[np.float32]) -> NDArray[np.float32]:
        """[steer, throttle] from one vector observation."""
        p = self.params
        pose = self.locate(obs)
        assert self.direction is not None
        view = self._views[self.direction]
        line, seg = view["line"], view["seg"]
        m = len(line)
        cand = np.arange(m) if self._r is None else (self._r + np.arange(-20, 60)) % m
        r = int(cand[np.argmin(np.linalg.norm(line[cand] - pose[:2], axis=1))])
        self._r = r
        v = float(obs[self.layout.ego][0]) * p.max_speed
        ld = self.lookahead(v)
        k, run = r, 0.0
        while run < ld:
            run += float(seg[k])
            k = (k + 1) % m
        rel = line[k] - pose[:2]
        c, s_ = math.cos(pose[2]), math.sin(pose[2])
        x, y = c * rel[0] + s_ * rel[1], c * rel[1] - s_ * rel[0]
        dist = max(math.hypot(x, y), 1e-3)
        steer = math.atan(2.0 * p.wheelbase * math.sin(math.atan2(y, x)) / dist)
        v_target = min(float(view["speed"][r]), self._follow_speed(obs, v))
        throttle = float(np.clip(2.0 * (v_target - v), -1.0, 1.0))
        return np.array([np.clip(steer / p.max_steer, -1, 1), throttle], dtype=np.float32)


def make_baseline(
    name: str,
    layout: ObservationLayout,
    params: CarParams | None = None,
    seed: int | None = None,
    track: Track | None = None,
) -> RandomPolicy | PursuitPolicy | GapFollowerPolicy:
    """A baseline policy by name: ``pursuit``, ``gap``, ``random`` or ``raceline`` (which
    needs ``track``, with a race line)."""
    if name == "raceline":
        if track is None:
            raise PolicyError("the raceline baseline needs the track (with a race line)")
        return RacelinePolicy(layout, params, track)
    if name == "pursuit":
        return PursuitPolicy(layout, params)
    if name == "gap":
        return GapFollowerPolicy(layout, params)
    if name == "random":
        return RandomPolicy(seed=seed)
    raise PolicyError(
        f"unknown baseline {name!r}; choose from {', '.join(BASELINES + TRACK_BASELINES)}"
    )
