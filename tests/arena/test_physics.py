"""Car physics against its own parameters: speed, turning, braking, contacts, DNF rules."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from arena.env import RacingEnv
from arena.sim import (
    TILT_INERTIA,
    CarParams,
    CarScales,
    SimState,
    Simulator,
    ackermann_angles,
    pb,
)
from arena.walls import DEFAULT_RUNOFF
from tests.arena.conftest import FloatArray, drag_strip, grid_at, pose_at, speed_throttle
from tracks import load_track

CONTROL_DT = 1.0 / 20.0  # s, the default control step


def drive(sim: Simulator, steer: float, throttle: float, steps: int) -> list[SimState]:
    """``steps`` control steps of constant commands for every car."""
    n = sim.n_cars
    return [sim.step(np.full(n, steer), np.full(n, throttle)) for _ in range(steps)]


@pytest.fixture(scope="module")
def strip_sim() -> Iterator[Simulator]:
    """A one-car simulator on the drag strip."""
    sim = Simulator(drag_strip(), 1)
    yield sim
    sim.close()


def test_top_speed_and_acceleration_match_car_params(strip_sim: Simulator) -> None:
    p = CarParams()
    strip_sim.reset(pose_at(drag_strip(), -28.0)[None])
    states = drive(strip_sim, 0.0, 1.0, round(12.0 / CONTROL_DT))
    v = np.array([st.v_long[0] for st in states])
    t = np.array([st.time for st in states])
    assert v[-1] == pytest.approx(p.top_speed, rel=0.02)
    reached = t[np.argmax(v >= 0.95 * p.top_speed)]
    assert reached == pytest.approx(p.time_to_speed(0.95), rel=0.05)
    # Straight line: no lateral drift, no yaw.
    assert abs(states[-1].poses[0, 1] - pose_at(drag_strip(), -28.0)[1]) < 0.05
    assert np.all(np.abs([st.v_lat[0] for st in states]) < 0.05)


def fit_circle(xy: FloatArray) -> tuple[FloatArray, float]:
    """Least-squares circle (Kåsa fit) through points (m, 2): centre (2,) and radius m."""
    a = np.column_stack([2 * xy, np.ones(len(xy))])
    b = (xy**2).sum(axis=1)
    (cx, cy, c), *_ = np.linalg.lstsq(a, b, rcond=None)
    return np.array([cx, cy]), float(math.sqrt(c + cx * cx + cy * cy))


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_full_lock_turn_radius_matches_wheelbase(strip_sim: Simulator, direction: float) -> None:
    p = CarParams()
    expected = p.wheelbase / math.tan(p.max_steer)
    strip_sim.reset(pose_at(drag_strip(), -20.0, -direction)[None])
    path = []
    for _ in range(round(8.0 / CONTROL_DT)):
        v = float(strip_sim.step(np.array([direction]), np.zeros(1)).v_long[0])
        st = strip_sim.step(np.array([direction]), np.array([speed_throttle(v, 1.0)]))
        path.append(st.poses[0, :2])
    xy = np.array(path[len(path) // 4 :])  # after the car settles onto its circle
    centre, radius = fit_circle(xy)
    assert radius == pytest.approx(expected, rel=0.10)
    assert np.std(np.hypot(*(xy - centre).T)) < 0.02  # it really is a circle
    # Full left lock circles anticlockwise (yaw rate > 0), right lock clockwise.
    assert np.sign(st.velocity[0, 2]) == direction


def test_inner_front_wheel_steers_more() -> None:
    p = CarParams()
    for steer in (0.1, 0.3, p.max_steer):
        left, right = ackermann_angles(steer, p.wheelbase, p.track_width)
        assert left > steer > right > 0  # turning left: the left wheel is inside
        # Both wheels point at one turning centre on the rear axle line.
        r_centre = p.wheelbase / math.tan(steer)
        assert p.wheelbase / math.tan(left) == pytest.approx(r_centre - p.track_width / 2)
        assert p.wheelbase / math.tan(right) == pytest.approx(r_centre + p.track_width / 2)
        mirror = ackermann_angles(-steer, p.wheelbase, p.track_width)
        assert mirror == pytest.approx((-right, -left))
    assert ackermann_angles(0.0, p.wheelbase, p.track_width) == (0.0, 0.0)


def test_heavier_car_stays_flat_and_accelerates_less(strip_sim: Simulator) -> None:
    """Mass changes (model uncertainty) keep the roll/pitch lock pybullet would reset; the
    motor keeps its force, so a car 1.5× as heavy accelerates at 1/1.5 of the nominal rate.

    (It used to keep its acceleration: with every force scaled by mass, the mass
    perturbation changed nothing in a solo race.)"""
    scales = CarScales.nominal(1)
    scales.mass[:] = 1.5
    strip_sim.set_scales(scales)
    try:
        mass, _, inertia, *_ = pb.getDynamicsInfo(
            strip_sim.cars[0], -1, physicsClientId=strip_sim.client
        )
        assert mass == pytest.approx(1.5 * CarParams().mass)
        assert inertia[0] == inertia[1] == TILT_INERTIA
        strip_sim.reset(pose_at(drag_strip(), -28.0)[None])  # scales survive the reset
        states = drive(strip_sim, 0.0, 1.0, round(6.0 / CONTROL_DT))
        assert np.all(np.abs([st.poses[0, 2] for st in states]) < 0.01)  # no yaw drift
        assert np.all(np.abs([st.upright[0] for st in states]) > 0.999)  # no rocking
        p = CarParams()
        a = p.drive_accel / 1.5  # dv/dt = a (1 − v / v_max) − rolling resistance
        v_inf = p.max_speed * (1.0 - p.rolling_resistance / a)
        expected = v_inf * (1.0 - math.exp(-6.0 * a / p.max_speed))
        nominal = p.top_speed * (1.0 - math.exp(-6.0 * p.drive_accel / p.max_speed))
        assert expected < 0.97 * nominal
        assert states[-1].v_long[0] == pytest.approx(expected, rel=0.02)
    finally:
        strip_sim.set_scales(CarScales.nominal(1))


def test_braking_from_top_speed_stops_the_car(strip_sim: Simulator) -> None:
    p = CarParams()
    strip_sim.reset(pose_at(drag_strip(), -28.0)[None])
    st = drive(strip_sim, 0.0, 1.0, round(9.0 / CONTROL_DT))[-1]
    v0, x0 = float(st.v_long[0]), float(st.poses[0, 0])
    assert v0 > 0.98 * p.top_speed
    t0, speeds = st.time, [v0]
    while speeds[-1] > 0.3:
        st = strip_sim.step(np.zeros(1), -np.ones(1))
        speeds.append(float(st.v_long[0]))
        assert st.time - t0 < 2.0, "still rolling two seconds after full braking"
    decel = p.brake_accel + p.rolling_resistance
    assert np.all(np.diff(speeds) < 0)
    assert st.time - t0 == pytest.approx((v0 - 0.3) / decel, abs=2 * CONTROL_DT)
    assert st.poses[0, 0] - x0 == pytest.approx((v0**2 - 0.09) / (2 * decel), rel=0.1)
    # Off the brake it rolls to a stop and never reverses.
    coast = drive(strip_sim, 0.0, 0.0, round(5.0 / CONTROL_DT))
    assert abs(coast[-1].v_long[0]) < 0.05
    assert min(c.v_long[0] for c in coast) > -1e-3


def first_contact(env: RacingEnv, actions: dict[str, FloatArray], limit: int = 100) -> dict:
    """Step with constant ``actions`` until some car reports a collision; its infos."""
    for _ in range(limit):
        _, _, _, _, infos = env.step(actions)
        if any(info["collisions"] for info in infos.values()):
            return infos
    raise AssertionError(f"no collision within {limit} steps")


def test_rear_end_collision_blames_the_car_behind() -> None:
    env = RacingEnv(track=drag_strip(), n_cars=2)
    track = env.base_track
    # car_0 waits in the middle of the straight; car_1 comes from 3 m behind, flat out.
    with grid_at(env, np.stack([pose_at(track, -20.0), pose_at(track, -23.5)])):
        env.reset(seed=0)
    infos = first_contact(env, {"car_0": np.zeros(2), "car_1": np.array([0.0, 1.0])})
    front, rear = infos["car_0"], infos["car_1"]
    assert [c["with"] for c in front["collisions"]] == ["car_1"]
    assert [c["with"] for c in rear["collisions"]] == ["car_0"]
    assert rear["collisions"][0]["at_fault"] is True
    assert front["collisions"][0]["at_fault"] is False
    closing = rear["collisions"][0]["closing_speed"]
    assert closing > 2.0
    assert rear["reward_terms"]["collision"] == pytest.approx(-env.weights.collision * closing)
    assert rear["reward_terms"]["collision"] < 0
    assert front["reward_terms"]["collision"] == 0.0
    assert env.at_fault_count.tolist() == [0, 1]
    assert env.collision_count.tolist() == [1, 1]
    # Pushing on is the same incident: reported each step, counted once, no new blame.
    for _ in range(10):
        infos = env.step({"car_0": np.zeros(2), "car_1": np.array([0.0, 1.0])})[4]
        assert [c["with"] for c in infos["car_1"]["collisions"]] == ["car_0"]
    assert env.at_fault_count.tolist() == [0, 1]
    assert env.collision_count.tolist() == [1, 1]
    env.close()


def test_head_on_collision_blames_both_cars() -> None:
    env = RacingEnv(track=drag_strip(), n_cars=2)
    track = env.base_track
    facing = np.stack([pose_at(track, -20.0), pose_at(track, -14.0, yaw_offset=math.pi)])
    with grid_at(env, facing):
        env.reset(seed=0)
    infos = first_contact(env, {"car_0": np.array([0.0, 1.0]), "car_1": np.array([0.0, 1.0])})
    for agent in ("car_0", "car_1"):
        (hit,) = infos[agent]["collisions"]
        assert hit["at_fault"] is True
        assert infos[agent]["reward_terms"]["collision"] < 0
    env.close()


@pytest.mark.parametrize("track_name", ["oval", "monza"])
def test_walls_stop_cars_all_round_the_track(track_name: str) -> None:
    """Every part of both walls is solid: a car driven straight at it touches and stops."""
    track = load_track(track_name)
    sim = Simulator(track, 1)
    for frac in (0.05, 0.3, 0.55, 0.8):
        s = frac * track.length
        left, right = (float(w[0]) for w in track.widths_at([s]))
        for side, width in ((1.0, left), (-1.0, right)):
            sim.reset(pose_at(track, s, yaw_offset=side * math.pi / 2)[None])
            states = drive(sim, 0.0, 1.0, 30)
            assert any(st.wall_contact[0] for st in states), (frac, side)
            d = track.project(np.array([st.poses[0, :2] for st in states])).d
            assert np.all(side * d < width + DEFAULT_RUNOFF), (frac, side)
    sim.close()


def test_wall_contact_reported_in_infos() -> None:
    env = RacingEnv(track=drag_strip(), n_cars=1)
    with grid_at(env, pose_at(env.base_track, -20.0, yaw_offset=0.6)[None]):
        env.reset(seed=0)
    seen = []
    for _ in range(40):
        _, _, _, _, infos = env.step({"car_0": np.array([0.0, 0.6])})
        seen.append((infos["car_0"]["wall_contact"], infos["car_0"]["reward_terms"]["wall"]))
    assert any(touch for touch, _ in seen)
    for touch, term in seen:
        assert term == (-env.weights.wall * env.dt if touch else 0.0)
    env.close()


def test_off_track_car_is_retired_after_the_tolerance() -> None:
    env = RacingEnv(track=drag_strip(), n_cars=1)
    track = env.base_track
    # In the run-off beside the road, parallel to it: all four wheels off the road.
    with grid_at(env, pose_at(track, -28.0, track.width_left[0] + 0.2)[None]):
        env.reset(seed=0)
    limit_steps = env.off_track_limit / env.dt
    v, steps = 0.0, 0
    while "car_0" in env.agents:
        _, _, term, trunc, infos = env.step({"car_0": np.array([0.0, speed_throttle(v, 1.0)])})
        info = infos["car_0"]
        v, steps = info["speed"], steps + 1
        assert info["off_track"] is True
        assert info["reward_terms"]["off_track"] == pytest.approx(-env.weights.off_track * env.dt)
    assert term["car_0"] and not trunc["car_0"]
    assert info["dnf_reason"] == "off_track"
    assert limit_steps <= steps <= limit_steps + 1
    assert env.off_track_count.tolist() == [1]
    env.close()


def test_car_that_does_not_move_is_retired_as_stuck() -> None:
    env = RacingEnv(track="oval", n_cars=2, stuck_time=2.0)
    env.reset(seed=0)
    steps = 0
    while "car_0" in env.agents:
        _, _, term, _, infos = env.step({"car_0": np.zeros(2), "car_1": np.array([0.0, 0.3])})
        steps += 1
    assert term["car_0"]
    assert infos["car_0"]["dnf_reason"] == "stuck"
    assert steps == round(env.stuck_time / env.dt)
    assert env.agents == ["car_1"]  # the car that drives is still racing
    env.close()


def test_a_step_from_the_state_read_last_equals_one_that_queries_pybullet_again() -> None:
    """``Simulator.step`` starts from the state the previous step read; ``sync()`` makes it
    query pybullet again. Both give the same race bit for bit, across a parked car and a
    mass change (which the simulator tracks itself)."""
    track = load_track("technical")
    grid = track.start_grid(3)
    # Steering either way, mostly forward throttle: cars that drive, turn and touch.
    controls = np.random.default_rng(3).uniform([-0.6, -0.2], [0.6, 1.0], (90, 3, 2))
    heavy = CarScales.nominal(3)
    heavy.mass[1] = 1.2
    runs = []
    for fresh in (False, True):
        sim = Simulator(track, 3)
        sim.reset(grid)
        trace = []
        for k, cmd in enumerate(controls):
            if k == 30:
                sim.set_scales(heavy)
            if k == 60:
                sim.park(2)
            if fresh:
                sim.sync()
            state = sim.step(cmd[:, 0], cmd[:, 1])
            trace.append(np.concatenate([state.poses.ravel(), state.velocity.ravel()]))
        sim.close()
        runs.append(np.array(trace))
    assert runs[0].tobytes() == runs[1].tobytes()
    assert float(np.hypot(*(runs[0][-1, :2] - runs[0][0, :2]))) > 2.0  # car 0 drove


def test_sync_makes_a_step_start_from_a_velocity_set_through_pybullet() -> None:
    """A car given 3 m/s with pybullet directly (then ``sync()``) covers about 3 m/s × the
    step in its first step, not the distance from rest."""
    sim = Simulator(drag_strip(), 1)
    try:
        start = pose_at(drag_strip(), 0.0)
        sim.reset(start[None])
        yaw = float(start[2])
        pb.resetBaseVelocity(
            sim.cars[0],
            [3.0 * math.cos(yaw), 3.0 * math.sin(yaw), 0.0],
            [0.0, 0.0, 0.0],
            physicsClientId=sim.client,
        )
        sim.sync()
        state = sim.step(np.zeros(1), np.zeros(1))
    finally:
        sim.close()
    moved = float(np.hypot(*(state.poses[0, :2] - start[:2])))
    assert moved == pytest.approx(3.0 * CONTROL_DT, rel=0.1)
