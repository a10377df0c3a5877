"""The batched simulator on its own: one code path for numpy and torch, the same
observation as the pybullet env, contacts, episode ends, automatic resets, the APIs."""

from __future__ import annotations

import subprocess
import sys
from typing import Any

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import arena
from arena.batch.contact import corners
from arena.batch.lidar import wall_ranges
from arena.batch.parallel import BatchParallelEnv
from arena.batch.sim import BatchSim
from arena.batch.vec_env import BatchVecEnv
from arena.batch.xp import DeviceError, get_ops
from arena.env import RacingEnv
from arena.lidar import Lidar
from arena.rewards import RACING_TERMS
from arena.sim import SimError
from arena.uncertainty import (
    INDEX,
    DynamicsBounds,
    RewardBounds,
    UncertaintyConfig,
    nominal_values,
)
from tests.arena.conftest import drag_strip, grid_at, pose_at
from tracks import load_track


def _random_actions(seed: int, shape: tuple[int, ...], steps: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.clip(rng.normal(0.3, 0.6, shape), -1, 1) for _ in range(steps)]


def test_numpy_and_torch_follow_one_code_path() -> None:
    a = BatchSim("bean", 8, 4, device="numpy", random_starts=True, seed=5)
    b = BatchSim("bean", 8, 4, device="torch:cpu", dtype="float64", random_starts=True, seed=5)
    start = np.arange(8) * 3 % a.n_starts
    slots = np.tile(np.arange(4), (8, 1))
    obs_a = a.reset(start=start, slot_of_car=slots)
    obs_b = b.ops.to_numpy(b.reset(start=start, slot_of_car=slots))
    np.testing.assert_allclose(obs_a, obs_b, atol=1e-5)
    b.auto_reset = a.auto_reset = False  # the two RNGs draw different restarts
    for act in _random_actions(0, (8, 4, 2), 60):
        ra, rb = a.step(act), b.step(b.ops.asarray(act))
    np.testing.assert_allclose(ra.obs, b.ops.to_numpy(rb.obs), atol=1e-4)
    np.testing.assert_allclose(ra.reward, b.ops.to_numpy(rb.reward), atol=1e-6)
    np.testing.assert_allclose(a.state.car.x, b.ops.to_numpy(b.state.car.x), atol=1e-6)


def test_same_seed_same_actions_same_trajectory_over_hundreds_of_steps() -> None:
    runs = []
    for _ in range(2):
        sim = BatchSim("hairpins", 6, 3, random_starts=True, seed=11)
        sim.reset(seed=11)
        total = np.zeros((6, 3))
        for act in _random_actions(1, (6, 3, 2), 300):
            total += sim.step(act).reward
        runs.append((total, sim.state.car.x.copy()))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def test_observation_matches_the_pybullet_env_from_the_same_poses() -> None:
    track = load_track("oval")
    poses = track.start_grid(3)
    poses[1, 2] += 0.3  # one car turned, so headings and frames differ
    env = RacingEnv(track=track, n_cars=3)
    try:
        with grid_at(env, poses):
            ref, _ = env.reset(seed=0)
    finally:
        env.close()
    sim = BatchSim(track, 1, 3, auto_reset=False)
    obs = sim.set_poses(poses[None])[0]
    lay = sim.layout
    for i in range(3):
        want, got = ref[f"car_{i}"], obs[i]
        assert got.shape == want.shape and got.dtype == np.float32
        np.testing.assert_allclose(got[lay.ego], want[lay.ego], atol=1e-3)
        np.testing.assert_allclose(got[lay.track_ahead], want[lay.track_ahead], atol=1e-3)
        np.testing.assert_allclose(got[lay.opponents], want[lay.opponents], atol=1e-4)
        # The lidar reads a range table: close to the exact caster, not equal.
        assert np.median(np.abs(got[lay.lidar] - want[lay.lidar])) < 0.01  # 10 cm of 10 m


def test_table_lidar_is_close_to_the_exact_lidar_everywhere_on_the_road() -> None:
    track = load_track("technical")
    sim = BatchSim(track, 1, 1)
    rng = np.random.default_rng(0)
    s = rng.uniform(0, track.length, 400)
    d = rng.uniform(-0.8, 0.8, 400) * track.widths_at(s)[0]
    xy = track.to_cartesian(np.stack([s, d], axis=1))
    yaw = track.heading_at(s) + rng.uniform(-0.6, 0.6, 400)
    exact = Lidar(sim.maps.walls, 64).scan(np.column_stack([xy, yaw]), track.project(xy).segment)
    g = sim.maps.lidar_grid
    got = wall_ranges(
        xy[:, 0], xy[:, 1], yaw, sim._ray_bins, sim._ux, sim._uy, sim.dev.ranges,
        sim.dev.lidar_rows, g.origin, g.cell, g.shape, sim.max_range, sim.ops,
    )  # fmt: skip
    err = np.abs(got - exact)
    assert np.median(err) < 0.04 and np.percentile(err, 90) < 0.2  # m


def test_cars_in_front_show_in_the_lidar() -> None:
    track = drag_strip()
    sim = BatchSim(track, 1, 2, auto_reset=False)
    poses = np.stack([pose_at(track, -30.0), pose_at(track, -27.0)])  # car 1 3 m ahead
    obs = sim.set_poses(poses[None])[0]
    ahead = obs[0, sim.layout.lidar][sim.layout.n_rays // 2]
    assert ahead * sim.max_range == pytest.approx(3.0 - 0.25, abs=0.03)  # its rear face
    alone = BatchSim(track, 1, 1, auto_reset=False).set_poses(poses[None, :1])[0]
    assert alone[0, sim.layout.lidar][sim.layout.n_rays // 2] == 1.0  # 10 m of nothing


def test_rear_end_contact_pushes_blames_and_does_not_interpenetrate() -> None:
    track = drag_strip()
    sim = BatchSim(track, 1, 2, auto_reset=False)
    poses = np.stack([pose_at(track, -25.0), pose_at(track, -26.0)])
    sim.set_poses(poses[None], np.array([[[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]]]))
    touched = fault = False
    worst = 0.0
    for _ in range(20):
        res = sim.step(np.array([[[0.0, 0.0], [0.0, 0.0]]]))
        touched |= bool(res.contact[0, 0, 1] and res.contact[0, 1, 0])
        fault |= bool(res.at_fault[0, 1, 0])
        assert not res.at_fault[0, 0, 1]  # the car hit from behind is never to blame
        gap = sim.state.car.x[0, 0] - sim.state.car.x[0, 1]
        worst = max(worst, 0.5 - gap)  # overlap of the two 0.5 m cars
    assert touched and fault
    assert worst < 0.08  # m: the soft contact lets the bumpers sink a few centimetres
    assert sim.state.car.vx[0, 0] > 1.0  # the front car was pushed forward


def test_a_car_driven_into_a_wall_stays_out_of_it() -> None:
    track = drag_strip()
    sim = BatchSim(track, 1, 1, auto_reset=False)
    sim.set_poses(pose_at(track, -20.0, 0.0, yaw_offset=1.2)[None, None])
    deepest, touched = 0.0, False
    for _ in range(60):
        res = sim.step(np.array([[[0.0, 1.0]]]))
        touched |= bool(res.wall[0, 0])
        cx, cy, _, _ = corners(sim.state.car, sim._lx, sim._ly, sim.ops)
        deepest = max(deepest, float(-sim.dev.clearance(cx, cy)[0].min()))
    assert touched
    assert deepest < 0.15  # m into the wall at worst, never through it


@pytest.mark.parametrize("end_on_wall", [False, True])
def test_end_on_wall_retires_a_car_the_step_it_touches_a_wall(end_on_wall: bool) -> None:
    """Training option (``--wall-ends-episode``): soft walls let a car slide on, so a car
    that touches one may be retired at once, as a pybullet car hitting one at speed stops."""
    track = drag_strip()
    sim = BatchSim(track, 1, 1, auto_reset=False, end_on_wall=end_on_wall)
    sim.set_poses(pose_at(track, -20.0, 0.0, yaw_offset=1.2)[None, None])
    for _ in range(60):
        res = sim.step(np.array([[[0.0, 1.0]]]))
        if res.wall[0, 0]:
            break
    assert res.wall[0, 0], "never reached the wall"
    # Terminated the very step it touched (the stuck test would need 4 s, off-track 3 s).
    assert bool(res.terminated[0, 0]) is end_on_wall
    if not end_on_wall:  # the car goes on against the wall
        res = sim.step(np.array([[[0.0, 1.0]]]))
        assert not res.terminated[0, 0]


def test_end_on_wall_leaves_car_contacts_alone() -> None:
    """Unlike DeepRacer's end_on_crash, a rear-end between two cars retires neither."""
    track = drag_strip()
    sim = BatchSim(track, 1, 2, auto_reset=False, end_on_wall=True)
    poses = np.stack([pose_at(track, -25.0), pose_at(track, -26.0)])
    sim.set_poses(poses[None], np.array([[[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]]]))
    touched = False
    for _ in range(20):
        res = sim.step(np.array([[[0.0, 0.0], [0.0, 0.0]]]))
        touched |= bool(res.contact[0, 0, 1])
        assert not res.terminated.any()
    assert touched


def test_pursuit_cars_finish_and_environments_restart_by_themselves() -> None:
    from agents.baselines import PursuitPolicy

    sim = BatchSim("oval", 3, 2, laps=1)
    policy = PursuitPolicy(sim.layout, sim.params)
    obs = sim.reset(seed=0)
    finished_at = None
    for step in range(1, 600):
        act = np.array([[policy.act(o) for o in env_obs] for env_obs in obs])
        res = sim.step(act)
        obs = res.obs
        if res.env_done.any():
            finished_at = step
            assert res.lap_done.any() and res.terminated.any()
            assert res.lap_time[res.lap_done].min() > 10.0  # s: a real lap of the oval
            done_envs = np.flatnonzero(res.env_done)
            assert (sim.state.steps[done_envs] == 0).all()  # restarted
            assert not np.array_equal(res.final_obs[done_envs], res.obs[done_envs])
            break
    assert finished_at is not None


def test_parallel_env_passes_the_pettingzoo_api_test() -> None:
    env = arena.parallel_env(backend="batch", track="oval", n_cars=3)
    assert isinstance(env, BatchParallelEnv)
    parallel_api_test(env, num_cycles=300)


def test_vec_env_slots_and_episode_infos() -> None:
    venv = BatchVecEnv(["oval"], n_envs=3, n_cars=2, seed=0, sim_kwargs={"max_cycles": 30})
    venv.seed(0)
    obs = venv.reset()
    assert obs.shape == (6, venv.observation_space.shape[0])
    assert venv.observation_space.contains(obs[0])
    for _ in range(30):
        venv.step_async(np.zeros((6, 2), dtype=np.float32))
        obs, _, dones, infos = venv.step_wait()
    assert dones.all()  # max_cycles: every race timed out on the last step
    info = infos[0]
    assert info["TimeLimit.truncated"] and not info["cut_short"]
    assert info["episode"]["l"] == 30 and info["terminal_observation"].shape == obs[0].shape
    assert info["dnf_reason"] == "time_limit"


def test_unknown_devices_are_user_errors_and_numpy_never_imports_torch() -> None:
    with pytest.raises(DeviceError):
        get_ops("tpu")
    code = (
        "import sys; from arena.batch.sim import BatchSim; "
        "BatchSim('oval', 2, 2).step([[[0, 1]] * 2] * 2); print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# ---- model uncertainty on the batched simulator ----------------------------------------------


def _values(b: int, n: int, **given: Any) -> np.ndarray:
    """(b, n, P) perturbation values: nominal, with ``given`` per env (lists) or for all."""
    out = np.tile(nominal_values(), (b, n, 1))
    for name, value in given.items():
        out[..., INDEX[name]] = np.asarray(value, dtype=np.float64).reshape(-1, 1)
    return out


@pytest.mark.parametrize("device", ["numpy", "torch:cpu"])
def test_latency_delays_each_car_by_exactly_its_steps(device: str) -> None:
    sim = BatchSim("oval", 3, 1, auto_reset=False, device=device, dtype="float64")
    sim.set_perturbation(_values(3, 1, latency=[0, 1, 3]))
    sim.reset()
    assert sim.perturbed
    xs = []
    for act in _random_actions(4, (1, 1, 2), 40):
        sim.step(np.repeat(act, 3, axis=0))  # the same commands in every env
        xs.append(sim.ops.to_numpy(sim.state.car.x)[:, 0].copy())
    x = np.array(xs)
    np.testing.assert_allclose(x[1:, 1], x[:-1, 0], atol=1e-9)
    np.testing.assert_allclose(x[3:, 2], x[:-3, 0], atol=1e-9)
    assert np.all(x[:3, 2] == x[0, 2])  # no input during the first 3 steps: parked


def test_dynamics_parameters_are_per_car_and_per_env_and_envs_can_be_updated_alone() -> None:
    sim = BatchSim("oval", 2, 2, auto_reset=False)
    assert not sim.perturbed  # nominal: no uncertainty work at all
    sim.set_perturbation(_values(2, 2, motor=[1.0, 1.2]))
    sim.set_perturbation(_values(2, 2, friction=0.5, steer_offset=0.1), envs=[True, False])
    np.testing.assert_array_equal(sim.scales.motor, [[1.0, 1.0], [1.2, 1.2]])
    np.testing.assert_array_equal(sim.scales.friction, [[0.5, 0.5], [1.0, 1.0]])
    np.testing.assert_array_equal(sim.scales.steer_offset, [[0.1, 0.1], [0.0, 0.0]])
    sim.reset()
    for _ in range(30):
        sim.step(np.tile([0.0, 1.0], (2, 2, 1)))
    speed = np.hypot(sim.state.car.vx, sim.state.car.vy)
    assert speed[1, 0] > speed[0, 0]  # more motor (and full grip) is faster
    assert np.all(np.abs(sim.state.car.steering[0]) > 0.05)  # the trim steers env 0 only
    assert np.all(np.abs(sim.state.car.steering[1]) < 1e-9)
    with pytest.raises(SimError, match="shape"):
        sim.set_perturbation(np.zeros((2, 3, 4)))


def test_lidar_noise_and_dropout_and_action_noise() -> None:
    sim = BatchSim("oval", 3, 1, auto_reset=False, seed=0)
    rays = sim.layout.n_rays
    clean = sim.reset()[..., :rays]
    sim.set_perturbation(
        _values(3, 1, lidar_dropout=[0.0, 1.0, 0.0], lidar_noise=[0.05, 0.0, 0.0],
                action_noise=[0.0, 0.0, 0.2])
    )  # fmt: skip
    noisy = sim.reset()[..., :rays]
    assert np.all(noisy[1] == 1.0)  # every ray dropped reads max range
    np.testing.assert_array_equal(noisy[2], clean[2])
    err = (noisy[0] - clean[0]).ravel()
    assert 0.03 < err.std() < 0.07 and np.all((noisy[0] >= 0) & (noisy[0] <= 1))
    steer = []
    for _ in range(20):
        sim.step(np.tile([0.0, 0.5], (3, 1, 1)))
        steer.append(sim.state.car.steering[:, 0].copy())
    s = np.abs(np.array(steer))
    p = sim.params
    assert np.all(s[:, :2] == 0.0)  # no noise: straight on
    assert 0.0 < s[:, 2].max() <= 0.2 * p.max_steer + 1e-9  # noise within its amplitude


def test_uncertainty_config_drives_the_simulator_through_automatic_resets() -> None:
    cfg = UncertaintyConfig(
        "sample", dynamics=DynamicsBounds(friction=(0.6, 1.2)),
        reward=RewardBounds(noise=0.05, progress=(0.5, 1.5)),
    )  # fmt: skip
    sim = BatchSim("oval", 4, 2, seed=0, uncertainty=cfg, stuck_time=1.0)
    sim.reset(seed=0)
    fric = sim.unc.values[..., INDEX["friction"]].copy()
    assert np.all(sim.scales.friction == fric)  # the simulator acts on what was drawn
    ended = np.zeros(4, dtype=bool)
    # Races 0-1 drive, races 2-3 stay parked: their cars retire as stuck after 1 s and
    # those races restart (with new draws); the driving races keep theirs.
    actions = np.zeros((4, 2, 2))
    actions[:2, :, 1] = 0.8
    for _ in range(40):
        values = sim.unc.values.copy()  # this step's values (the reward noise is redrawn)
        res = sim.step(actions)
        values[..., INDEX["reward_noise"]] = sim.unc.values[..., INDEX["reward_noise"]]
        want = values[..., INDEX["w_progress"]] * res.terms["progress"]
        want = want + values[..., INDEX["reward_noise"]]
        for name in RACING_TERMS[1:]:
            want = want + res.terms[name]
        if not res.env_done.any():  # every car racing: each gets its perturbed reward
            np.testing.assert_allclose(res.reward, want, atol=1e-12)
            assert not np.allclose(res.reward, res.reward_nominal)
        ended |= res.env_done
    assert ended[2:].all() and not ended[:2].any()
    new = sim.unc.values[..., INDEX["friction"]]
    assert np.array_equal(new[:2], fric[:2]) and not np.array_equal(new[2:], fric[2:])
    assert np.array_equal(sim.scales.friction, new)
