"""Observation functions: pure functions of per-car arrays, vectorised over cars.

The ``"vector"`` observation of one car is a flat float32 array::

    [ lidar (n_rays) | ego (7) | track ahead (7 × 2) | opponents (k × 5) | perturbation (9)? ]

* lidar: ranges / ``max_range``, in [0, 1] (1 = nothing within range);
* ego: forward speed / v_max, lateral speed / v_max, steering / max_steer,
  yaw rate / 10 rad/s, heading error / π (car heading minus track heading, + = pointing left
  of the track direction), lateral offset relative to the half-width on that side (0 on the
  centre line, ±1 on the road edges, beyond when off the road), progress rate / v_max
  (metres of centre line per second);
* track ahead: the centre line at ``LOOKAHEAD`` metres ahead (along the lap from the car's
  projection), each ``[dx, dy]`` in the car's frame / lidar range — the road's shape ahead,
  which a pure-pursuit driver steers by and a learner can read curvature from;
* opponents: the ``k`` nearest other cars, nearest first, each
  ``[present, dx, dy, dvx, dvy]`` in the car's frame (x forward, y left): positions / lidar
  range, relative velocities / v_max; absent slots (fewer cars, or finished ones) are zeros;
* perturbation (only with ``observe_perturbation=True``, :attr:`ObservationLayout.context`):
  the car's own model-uncertainty values (``arena.uncertainty.CONTEXT_FEATURES``: friction,
  mass, motor and steering-gain multipliers, steering offset, latency, action noise, lidar
  noise and dropout) as ``(value − nominal) / scale`` with fixed scales (the half-widths of
  the widest training set, ``agents.robustness.wide_dynamics``;
  :func:`arena.uncertainty.perturbation_context`), so 0 is the nominal car and ±1 the edge of
  that set whatever set an env draws from — the same meaning in training, in a robustness
  grid and on either backend. A perturbation-aware policy is told its car's conditions (an
  oracle, as a universal policy is in Yu et al.'s "Preparing for the Unknown", 2017), where
  a plain one must race them blind.

Every element is clipped to the bounds of :func:`vector_bounds`, so an observation always lies
inside the observation space.

The functions take arrays with any number of leading batch axes (``(n, ...)`` per car, or
``(B, n, ...)`` for the batched backend) and an array namespace ``ops``
(:mod:`arena.batch.xp`; numpy by default, torch for the batched backend on a GPU).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from arena.batch.xp import NUMPY, NumpyOps

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

EGO_FEATURES = (
    "speed",
    "lateral_speed",
    "steering",
    "yaw_rate",
    "heading_error",
    "lateral_offset",
    "progress_rate",
)
OPPONENT_FEATURES = ("present", "dx", "dy", "dvx", "dvy")
LOOKAHEAD = (1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 10.0)  # m along the centre line
TRACK_LIMIT = 1.5  # bound of the normalised track-ahead coordinates
YAW_RATE_SCALE = 10.0  # rad/s
EGO_LOW = np.array([-1.0, -2.0, -1.0, -2.0, -1.0, -3.0, -2.0])
EGO_HIGH = np.array([2.0, 2.0, 1.0, 2.0, 1.0, 3.0, 2.0])
OPP_LOW = np.array([0.0, -1.0, -1.0, -2.0, -2.0])
OPP_HIGH = np.array([1.0, 1.0, 1.0, 2.0, 2.0])
# The perturbation block: its length (arena.uncertainty.CONTEXT_FEATURES, whose values it
# holds) and the bound it is clipped to (latency 10 steps reads 3.3).
CONTEXT_SIZE = 9
CONTEXT_LIMIT = 4.0
# The ego feature scaled by the road's half-width rather than by a constant.
_IS_OFFSET = np.array([name == "lateral_offset" for name in EGO_FEATURES])
_IS_OFFSET.flags.writeable = False


@dataclass(frozen=True)
class ObservationLayout:
    """Sizes and slices of the flat vector observation."""

    n_rays: int
    k_opponents: int
    context: bool = False  # the perturbation block at the end (observe_perturbation)

    @property
    def size(self) -> int:
        """Length of the flat vector."""
        return self.perturbation.stop

    @property
    def lidar(self) -> slice:
        """Slice of the lidar ranges."""
        return slice(0, self.n_rays)

    @property
    def ego(self) -> slice:
        """Slice of the ego features."""
        return slice(self.n_rays, self.n_rays + len(EGO_FEATURES))

    @property
    def track_ahead(self) -> slice:
        """Slice of the track-ahead block (len(LOOKAHEAD) × 2, row-major)."""
        start = self.ego.stop
        return slice(start, start + 2 * len(LOOKAHEAD))

    @property
    def opponents(self) -> slice:
        """Slice of the opponent block (k × 5, row-major)."""
        start = self.track_ahead.stop
        return slice(start, start + len(OPPONENT_FEATURES) * self.k_opponents)

    @property
    def perturbation(self) -> slice:
        """Slice of the perturbation block (empty without :attr:`context`)."""
        start = self.opponents.stop
        return slice(start, start + (CONTEXT_SIZE if self.context else 0))

    def bounds(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Low and high bounds (size,) of the vector observation (fresh copies)."""
        low, high = _bounds(self.n_rays, self.k_opponents, self.context)
        return low.copy(), high.copy()


@lru_cache(maxsize=64)
def _bounds(
    n_rays: int, k_opponents: int, context: bool
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Read-only bounds of :meth:`ObservationLayout.bounds`, built once per layout."""
    ahead = np.full(2 * len(LOOKAHEAD), TRACK_LIMIT)
    ctx = np.full(CONTEXT_SIZE if context else 0, CONTEXT_LIMIT)
    low_parts = [np.zeros(n_rays), EGO_LOW, -ahead, np.tile(OPP_LOW, k_opponents), -ctx]
    high_parts = [np.ones(n_rays), EGO_HIGH, ahead, np.tile(OPP_HIGH, k_opponents), ctx]
    low = np.concatenate(low_parts).astype(np.float32)
    high = np.concatenate(high_parts).astype(np.float32)
    low.flags.writeable = False
    high.flags.writeable = False
    return low, high


def wrap_angle(angle: FloatArray, ops: NumpyOps = NUMPY) -> FloatArray:
    """Angles folded into [-π, π)."""
    return ops.mod(angle + np.pi, 2 * np.pi) - np.pi


def ego_features(
    v_long: FloatArray,
    v_lat: FloatArray,
    steering: FloatArray,
    yaw_rate: FloatArray,
    heading_error: FloatArray,
    d: FloatArray,
    width_left: FloatArray,
    width_right: FloatArray,
    progress_rate: FloatArray,
    v_max: float,
    max_steer: float,
    ops: NumpyOps = NUMPY,
) -> FloatArray:
    """Ego block (..., n, 7), unclipped; inputs are (..., n) in m, m/s, rad, rad/s."""
    half = ops.where(d >= 0, width_left, width_right)
    raw = ops.stack([v_long, v_lat, steering, yaw_rate, heading_error, d, progress_rate], axis=-1)
    # One division by each feature's scale (the road half-width on the car's side for the
    # offset): the same quotients as one division per feature, in fewer array operations.
    scales = ops.floats((v_max, v_max, max_steer, YAW_RATE_SCALE, np.pi, 1.0, v_max))
    return raw / ops.where(ops.const(_IS_OFFSET), half[..., None], scales)


def track_ahead_features(
    poses: FloatArray, points_ahead: FloatArray, max_range: float, ops: NumpyOps = NUMPY
) -> FloatArray:
    """Track-ahead block (..., n, L, 2): centre-line points (..., n, L, 2) m in each car's
    frame / range."""
    rel = points_ahead - poses[..., None, :2]  # [dx, dy]
    return _to_car_frame(rel, poses[..., 2], ops) / max_range


def _to_car_frame(rel: FloatArray, yaw: FloatArray, ops: NumpyOps) -> FloatArray:
    """World vectors (..., n, M, 2K) as K pairs [x, y] → [cos·x + sin·y, cos·y − sin·x] in
    the frames of cars heading ``yaw`` (..., n) rad.

    Both components at once: ``rel · cos`` plus the swapped pairs times ``[sin, −sin]`` (a
    sign flip is exact, and ``a + (−b)`` is ``a − b``), so the same bits as the two formulas.
    """
    cos = ops.cos(yaw)[..., None, None]
    sin = ops.sin(yaw)[..., None, None]
    signs = ops.floats((1.0, -1.0) * (rel.shape[-1] // 2))
    return rel * cos + ops.swap_pairs(rel) * (sin * signs)


def opponent_features(
    poses: FloatArray,
    velocity: FloatArray,
    visible: BoolArray,
    k: int,
    max_range: float,
    v_max: float,
    ops: NumpyOps = NUMPY,
) -> FloatArray:
    """Nearest-``k`` opponent block (..., n, k, 5) in each car's frame.

    Args:
        poses: (..., n, 3) [x m, y m, yaw rad].
        velocity: (..., n, 2+) world velocities [vx, vy] m/s in the first two columns.
        visible: (..., n) False for cars that have left the race (never reported as opponents).
        k: opponent slots per car.
        max_range: distance scale, m (the lidar range).
        v_max: speed scale, m/s.
        ops: array namespace.
    """
    n = poses.shape[-2]
    lead = tuple(poses.shape[:-2])
    if n < 2 or k == 0:
        return ops.zeros((*lead, n, k, len(OPPONENT_FEATURES)))
    state = ops.concat([poses[..., :2], velocity[..., :2]], axis=-1)  # (..., n, 4)
    rel = state[..., None, :, :] - state[..., :, None, :]  # (..., n, n, 4): j relative to i
    dist = ops.hypot(rel[..., 0], rel[..., 1])
    valid = visible[..., None, :] & ~ops.eye(n)
    dist = ops.where(valid, dist, np.inf)
    order = ops.argsort(dist, axis=-1)[..., :k]  # (..., n, min(k, n))
    m = order.shape[-1]
    picked = ops.gather_rows(rel, order)  # (..., n, m, 4) [dx, dy, dvx, dvy]
    # Position and velocity turned into the car's frame at once: [dx, dy, dvx, dvy] forward
    # and to the left, the order of the block's last four features.
    turned = _to_car_frame(picked, poses[..., 2], ops)
    # The visible cars sort first: slot q is filled when more than q of them exist. Absent
    # slots are zeroed by the same factor that scales the present ones.
    others = ops.sum(valid, axis=-1)  # (..., n) visible other cars
    flag = ops.cast(ops.arange(m) < others[..., None], dist.dtype)[..., None]  # (..., n, m, 1)
    inv_range, inv_speed = 1.0 / max_range, 1.0 / v_max
    scale = flag * ops.floats((inv_range, inv_range, inv_speed, inv_speed))
    block = ops.concat([flag, turned * scale], axis=-1)  # [present, dx, dy, dvx, dvy]
    if m == k:
        return block
    # Fewer other cars than slots: the slots beyond m stay zero.
    out = ops.zeros((*lead, n, k, len(OPPONENT_FEATURES)), dtype=dist.dtype)
    out[..., :m, :] = block
    return out


def vector_observation(
    lidar: FloatArray,
    ego: FloatArray,
    ahead: FloatArray,
    opponents: FloatArray,
    layout: ObservationLayout,
    ops: NumpyOps = NUMPY,
) -> NDArray[np.float32]:
    """Flat observations (..., n, size) float32 without the perturbation block, clipped into
    the observation bounds (:func:`with_context` appends the block with ``layout.context``).

    Args:
        lidar: (..., n, n_rays) normalised ranges in [0, 1].
        ego: (..., n, 7) from :func:`ego_features`.
        ahead: (..., n, L, 2) from :func:`track_ahead_features`.
        opponents: (..., n, k, 5) from :func:`opponent_features`.
        layout: sizes of the blocks.
        ops: array namespace.
    """
    low, high = _bounds(layout.n_rays, layout.k_opponents, False)  # built once: a hot path
    rows = tuple(ego.shape[:-1])
    flat = ops.concat([lidar, ego, ahead.reshape(*rows, -1), opponents.reshape(*rows, -1)], axis=-1)
    return ops.cast(ops.clip(flat, ops.const(low), ops.const(high)), ops.float32)


def with_context(obs: NDArray[np.float32], context: FloatArray, ops: NumpyOps = NUMPY) -> Any:
    """Observations without the perturbation block (..., n, D) float32 with it appended
    (..., n, D + 9), clipped to ±:data:`CONTEXT_LIMIT` (context (..., n, 9) from
    :func:`arena.uncertainty.perturbation_context`)."""
    block = ops.cast(ops.clip(context, -CONTEXT_LIMIT, CONTEXT_LIMIT), ops.float32)
    return ops.concat([obs, block], axis=-1)
