"""Collision blame at its edges: who pays for a contact, and by how much.

The rule (arena/rewards.py, after GT Sophy and DeepRacer's rear-end rule): car i is at fault
for a contact with car j when j lies within ±60° of i's heading AND i closes on j. These cases
pin each half of that rule and the cone's boundary, which a suite of "normal" races does not
exercise (an outside mutation audit found that dropping ``closing > 0`` or widening the cone to
120° went unnoticed).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from arena.rewards import BLAME_CONE, RewardWeights, collision_blame, race_positions, racing_terms

TOUCH = np.array([[False, True], [True, False]])


def pair(bearing_deg: float, v_i: tuple[float, float], v_j: tuple[float, float], dist: float = 0.5):
    """Car i at the origin heading +x; car j at ``dist`` m along ``bearing_deg`` from i's nose."""
    b = math.radians(bearing_deg)
    poses = np.array([[0.0, 0.0, 0.0], [dist * math.cos(b), dist * math.sin(b), 0.0]])
    velocity = np.array([v_i, v_j], dtype=float)
    return poses, velocity


def test_rear_end_blames_the_car_behind_by_its_closing_speed() -> None:
    poses, vel = pair(0.0, (3.0, 0.0), (1.0, 0.0))
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    assert at_fault[0, 1] and not at_fault[1, 0]
    assert closing[0, 1] == pytest.approx(2.0)
    assert closing[1, 0] == pytest.approx(2.0)  # symmetric closing; only the one behind is blamed


def test_contact_with_a_car_pulling_away_blames_nobody() -> None:
    # i is behind j and touching, but j is faster: the gap opens, closing < 0.
    poses, vel = pair(0.0, (1.0, 0.0), (3.0, 0.0))
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    assert closing[0, 1] == pytest.approx(-2.0)
    assert not at_fault.any()


def test_equal_speeds_are_not_a_fault() -> None:
    poses, vel = pair(0.0, (2.0, 0.0), (2.0, 0.0))
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    assert closing[0, 1] == pytest.approx(0.0)
    assert not at_fault.any()


def test_side_contact_at_ninety_degrees_is_not_a_rear_end() -> None:
    # j straight to i's left while i drifts into it: closing > 0 but j is not ahead.
    poses, vel = pair(90.0, (2.0, 1.0), (2.0, 0.0))
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    assert closing[0, 1] == pytest.approx(1.0)
    assert not at_fault[0, 1]


@pytest.mark.parametrize(
    ("bearing", "blamed"), [(59.0, True), (61.0, False), (-59.0, True), (-61.0, False)]
)
def test_the_blame_cone_ends_at_sixty_degrees(bearing: float, blamed: bool) -> None:
    assert math.degrees(BLAME_CONE) == pytest.approx(60.0)
    b = math.radians(bearing)
    # i moves straight at j so it always closes on it.
    poses, vel = pair(bearing, (2.0 * math.cos(b), 2.0 * math.sin(b)), (0.0, 0.0))
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    assert closing[0, 1] == pytest.approx(2.0)
    assert bool(at_fault[0, 1]) is blamed


def test_head_on_blames_both() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, math.pi]])
    vel = np.array([[2.0, 0.0], [-2.0, 0.0]])
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    assert at_fault[0, 1] and at_fault[1, 0]
    assert closing[0, 1] == pytest.approx(4.0)


def test_no_contact_no_blame_even_when_closing() -> None:
    poses, vel = pair(0.0, (3.0, 0.0), (1.0, 0.0))
    at_fault, _ = collision_blame(poses, vel, np.zeros((2, 2), dtype=bool))
    assert not at_fault.any()


def test_batch_axes_give_the_same_answer_per_race() -> None:
    cases = [pair(0.0, (3.0, 0.0), (1.0, 0.0)), pair(0.0, (1.0, 0.0), (3.0, 0.0))]
    poses = np.stack([c[0] for c in cases])
    vel = np.stack([c[1] for c in cases])
    at_fault, closing = collision_blame(poses, vel, np.stack([TOUCH, TOUCH]))
    for b, (p, v) in enumerate(cases):
        one_fault, one_closing = collision_blame(p, v, TOUCH)
        np.testing.assert_array_equal(at_fault[b], one_fault)
        np.testing.assert_allclose(closing[b], one_closing)


def test_collision_term_charges_only_the_car_at_fault_exactly() -> None:
    poses, vel = pair(0.0, (3.0, 0.0), (1.0, 0.0))
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    w = RewardWeights(collision=0.5)
    terms = racing_terms(
        np.array([0.1, 0.05]), np.array([False, True]), np.array([True, False]),
        at_fault, closing, np.array([1, -1]), 0.05, w,
    )  # fmt: skip
    assert terms["collision"].tolist() == [-0.5 * 2.0, 0.0]
    assert terms["progress"].tolist() == [0.1, 0.05]
    assert terms["off_track"].tolist() == [0.0, -1.0 * 0.05]
    assert terms["wall"].tolist() == [-2.0 * 0.05, 0.0]
    assert terms["overtake"].tolist() == [1.0, -1.0]


def test_blame_follows_the_car_heading_not_the_world_axes() -> None:
    # The rear-end case rotated by 90°: i heads +y with j ahead of it along +y.
    poses = np.array([[0.0, 0.0, math.pi / 2], [0.0, 0.5, math.pi / 2]])
    vel = np.array([[0.0, 3.0], [0.0, 1.0]])
    at_fault, _ = collision_blame(poses, vel, TOUCH)
    assert at_fault[0, 1] and not at_fault[1, 0]
    # And j to i's world +x side (its right, once i heads +y) is not ahead.
    poses = np.array([[0.0, 0.0, math.pi / 2], [0.5, 0.0, math.pi / 2]])
    vel = np.array([[3.0, 3.0], [0.0, 1.0]])
    at_fault, _ = collision_blame(poses, vel, TOUCH)
    assert not at_fault[0, 1]


def test_a_slow_rear_end_is_still_blamed() -> None:
    poses, vel = pair(0.0, (1.5, 0.0), (1.0, 0.0))
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    assert closing[0, 1] == pytest.approx(0.5)
    assert at_fault[0, 1]


def test_race_positions_rank_each_race_of_a_batch_separately() -> None:
    progress = np.array([[5.0, 9.0, 1.0], [0.0, 2.0, 3.0]])
    assert race_positions(progress).tolist() == [[2, 1, 3], [3, 2, 1]]


def test_collision_term_sums_over_the_other_cars_in_a_batch() -> None:
    # Two races of three cars; in race 1 car 0 rear-ends cars 1 and 2 at once.
    at_fault = np.zeros((2, 3, 3), dtype=bool)
    closing = np.zeros((2, 3, 3))
    at_fault[1, 0, 1] = at_fault[1, 0, 2] = True
    closing[1, 0, 1], closing[1, 0, 2] = 1.0, 2.0
    closing[1, 1, 0], closing[1, 2, 0] = 1.0, 2.0  # symmetric, but 1 and 2 are not at fault
    zeros = np.zeros((2, 3))
    terms = racing_terms(
        zeros, zeros.astype(bool), zeros.astype(bool), at_fault, closing,
        np.zeros((2, 3), dtype=np.int64), 0.05, RewardWeights(collision=0.5),
    )  # fmt: skip
    assert terms["collision"].tolist() == [[0.0, 0.0, 0.0], [-1.5, 0.0, 0.0]]


def test_columns_after_vx_vy_are_ignored() -> None:
    # The contract is (n, 2+) velocities [vx, vy, ...] (the pybullet sim's rows carry more
    # columns; arena/env.py slices them today): blame reads the first two only.
    poses, vel = pair(30.0, (3.0, 0.5), (1.0, -0.2))
    with_yaw_rate = np.concatenate([vel, np.array([[2.5], [-4.0]])], axis=1)
    at_fault, closing = collision_blame(poses, vel, TOUCH)
    wide_fault, wide_closing = collision_blame(poses, with_yaw_rate, TOUCH)
    np.testing.assert_array_equal(wide_fault, at_fault)
    np.testing.assert_array_equal(wide_closing, closing)
    assert at_fault[0, 1]


def test_a_car_exactly_on_the_cone_edge_is_ahead() -> None:
    # j at 45° from i's heading, the cone's half-angle set to exactly that bearing: the edge
    # belongs to the cone (atan2(1, 1) is the same float on both sides of the comparison).
    poses = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0]])
    vel = np.array([[2.0, 2.0], [0.0, 0.0]])
    at_fault, closing = collision_blame(poses, vel, TOUCH, cone=math.atan2(1.0, 1.0))
    assert closing[0, 1] > 0
    assert at_fault[0, 1]
    at_fault, _ = collision_blame(poses, vel, TOUCH, cone=math.atan2(1.0, 1.0) - 1e-9)
    assert not at_fault[0, 1]
