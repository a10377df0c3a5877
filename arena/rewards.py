"""Reward functions: pure functions of per-car arrays, each term reported on its own.

``"racing"`` (default), per car and control step::

    progress   + w_progress  · Δs                      metres along the centre line (− backwards)
    off_track  − w_off_track · dt · [all wheels off]    per second off the road
    wall       − w_wall      · dt · [touching a wall]   per second against a wall
    collision  − w_collision · Σ closing speed          only for contacts the car is to blame for
    overtake   + w_overtake  · places gained            (− for places lost: passing back and
                                                        forth earns nothing)

Blame (:func:`collision_blame`) follows the rear-end rule of GT Sophy and DeepRacer: in a
contact between cars i and j, i is at fault when j lies ahead of it (within ±60° of its
heading) and i closes on j (``(v_i − v_j) · r̂_ij > 0``); the penalty scales with that closing
speed. The car that is hit is not at fault. In a head-on contact both are.

``"progress"`` is the progress term alone. A DeepRacer ``reward_function(params)`` gets the
params dict of :mod:`arena.deepracer`.

The functions take arrays with any number of leading batch axes (``(B, n, ...)`` for the
batched backend) and an array namespace ``ops`` (:mod:`arena.batch.xp`, numpy by default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from arena.batch.xp import NUMPY, NumpyOps, count_true

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

RACING_TERMS = ("progress", "off_track", "wall", "collision", "overtake")
BLAME_CONE = math.radians(60.0)  # rad: the other car counts as "ahead" within this angle


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the racing reward terms (see the module docstring for units)."""

    progress: float = 1.0  # per m
    off_track: float = 1.0  # per s
    wall: float = 2.0  # per s
    collision: float = 0.5  # per m/s of closing speed
    overtake: float = 1.0  # per place


def collision_blame(
    poses: FloatArray,
    velocity: FloatArray,
    contact: BoolArray,
    cone: float = BLAME_CONE,
    ops: NumpyOps = NUMPY,
) -> tuple[BoolArray, FloatArray]:
    """Who is to blame in each car–car contact.

    Args:
        poses: (n, 3) [x m, y m, yaw rad].
        velocity: (n, 2+) world velocity [vx, vy] m/s in the first two columns.
        contact: (n, n) symmetric, True where cars touched this step.
        cone: half-angle, rad, within which the other car counts as ahead.
        ops: array namespace.

    Returns:
        at_fault (n, n): True where car i is to blame for its contact with car j;
        closing (n, n): closing speed of i on j, m/s (positive when approaching).
    """
    rel = poses[..., None, :, :2] - poses[..., :, None, :2]  # (..., n, n, 2): j seen from i
    dist = ops.maximum(ops.hypot(rel[..., 0], rel[..., 1]), 1e-9)
    unit = rel / dist[..., None]
    dv = velocity[..., :, None, :2] - velocity[..., None, :, :2]  # v_i − v_j
    closing = dv[..., 0] * unit[..., 0] + dv[..., 1] * unit[..., 1]
    bearing = ops.atan2(rel[..., 1], rel[..., 0]) - poses[..., :, None, 2]
    ahead = ops.cos(bearing) >= math.cos(cone)
    return contact & ahead & (closing > 0), closing


def race_positions(race_progress: FloatArray, ops: NumpyOps = NUMPY) -> NDArray[np.int64]:
    """1-based positions (..., n) from race progress (..., n) m: the furthest car is 1st."""
    return ops.inverse_permutation(ops.argsort(-race_progress, axis=-1)) + 1


def racing_terms(
    progress: FloatArray,
    off_track: BoolArray,
    wall: BoolArray,
    at_fault: BoolArray,
    closing: FloatArray,
    places_gained: NDArray[np.int64],
    dt: float,
    w: RewardWeights,
    ops: NumpyOps = NUMPY,
) -> dict[str, FloatArray]:
    """Each racing reward term (..., n) for one control step of ``dt`` seconds."""
    if (
        isinstance(at_fault, np.ndarray)
        and closing.dtype == ops.float == np.float64
        and not count_true(at_fault)
    ):
        # Nobody to blame (the usual step): each sum is of +0.0 only, so +0.0.
        blamed = ops.zeros(at_fault.shape[:-1])
    else:
        blamed = ops.sum(ops.where(at_fault, closing, 0.0), axis=-1)
    return {
        "progress": w.progress * progress,
        "off_track": -w.off_track * dt * ops.cast(off_track, ops.float),
        "wall": -w.wall * dt * ops.cast(wall, ops.float),
        "collision": -w.collision * blamed,
        "overtake": w.overtake * ops.cast(places_gained, ops.float),
    }
