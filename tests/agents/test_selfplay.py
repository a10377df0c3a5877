"""Self-play VecEnv step by step: zero-sum natures, slots, episode ends, opponents, seeds.

``tests/agents/test_train.py`` checks the VecEnv's shapes and SB3 conventions on a few
episodes; these compare every slot on every step with what the env itself returned (a spy on
``RacingEnv.step``), so the RARL alternation's contract is pinned exactly: a nature's reward
is minus its car's scaled reward on every step, the DNF penalty included, and it sees the
env's global state with its car's one-hot.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any
from unittest import mock

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy

from agents.baselines import make_baseline
from agents.policy import PolicyError
from agents.selfplay import (
    OpponentPool,
    PolicyDriver,
    Procedural,
    SB3Driver,
    SelfPlayVecEnv,
    parse_mix,
)
from arena import RacingEnv
from arena.uncertainty import default_config
from tracks import TrackError

ADVERSARIAL = default_config("adversarial")
K = len(ADVERSARIAL.free)


class Constant:
    """A driver that gives every car it drives the same action."""

    def __init__(self, action: list[float], name: str = "constant") -> None:
        self.name = name
        self.action = np.array(action, np.float32)

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        return np.tile(self.action, (len(obs), 1))


class PursuitAndStraight:
    """Pursuit for even rows (car_0 of each copy), full left lock at 0.8 for odd rows (car_1),
    which retires off the track: a race with one DNF and one driving car per copy."""

    def __init__(self, env: RacingEnv) -> None:
        self.name = "mixed"
        self.pursuit = make_baseline("pursuit", env.layout, env.params)

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        rows = [
            self.pursuit.act(row) if i % 2 == 0 else np.array([1.0, 0.8])
            for i, row in enumerate(obs)
        ]
        return np.asarray(rows, dtype=np.float32)


@contextmanager
def spying(vec: SelfPlayVecEnv) -> Iterator[list[list[dict[str, Any]]]]:
    """Record, per step, every copy's actions sent and what its env returned (and its state)."""
    log: list[list[dict[str, Any]]] = []
    real = RacingEnv.step

    def spy(env: RacingEnv, actions: dict[str, Any]) -> Any:
        sent = {a: np.array(v, copy=True) for a, v in actions.items()}
        out = real(env, actions)
        k = next(i for i, c in enumerate(vec._copies) if c.env is env)
        if k == 0:
            log.append([])
        log[-1].append({"actions": sent, "out": out, "state": env.state()})
        return out

    with mock.patch.object(RacingEnv, "step", autospec=True, side_effect=spy):
        yield log


def expected_reward(rec: dict[str, Any], car: str, scale: float, penalty: float, sign: float):
    """The slot's reward from the env's own step: scaled, DNF penalty, then the sign."""
    _, rew, term, _, infos = rec["out"]
    r = rew.get(car, 0.0) * scale
    if term.get(car, False) and infos[car].get("dnf_reason") is not None:
        r -= penalty
    r *= sign
    return r


@pytest.mark.parametrize("role", ["nature", "racer"])
def test_every_slot_reward_is_its_cars_scaled_reward_with_the_sign_of_its_role(role: str) -> None:
    """On every step, DNF steps included: racer slots get ``scale·r − penalty``, nature slots
    exactly minus that (RARL's zero-sum alternation, the audit's survivor in issue 18)."""
    scale, penalty = 0.5, 7.0
    vec = SelfPlayVecEnv(
        ["oval"],
        n_envs=2,
        n_cars=2,
        n_learners=2,
        seed=3,
        env_kwargs={"uncertainty": ADVERSARIAL, "off_track_limit": 0.5},  # quick DNFs
        reward_scale=scale,
        dnf_penalty=penalty,
        role=role,
    )
    sign = -1.0 if role == "nature" else 1.0
    learners = ["nature_car_0", "nature_car_1"] if role == "nature" else ["car_0", "car_1"]
    assert vec.learners == learners and vec.cars == ["car_0", "car_1"]
    driver = PursuitAndStraight(vec._copies[0].envs["oval"])
    if role == "nature":
        vec.racer = driver
        actions = np.array([[-1.0] * K, [1.0] * K, [0.5] * K, [-0.5] * K], np.float32)
    else:
        vec.nature = Constant([0.25] * K, name="nature")
        vec.pool = OpponentPool(mix={"pursuit": 1.0})
        actions = np.array([[0.0, 0.5], [1.0, 0.8], [0.1, 0.5], [-1.0, 0.8]], np.float32)
    try:
        vec.reset()
        returns = np.zeros(4)
        lengths = np.zeros(4, dtype=int)
        dnf_steps = live_steps = 0
        with spying(vec) as log:
            for _ in range(120):
                obs_out, rewards, dones, infos = vec.step(actions)
                assert obs_out.dtype == np.float32 and dones.dtype == bool
                for k, rec in enumerate(log[-1]):
                    sent = rec["actions"]
                    for j, (learner, car) in enumerate(zip(learners, vec.cars, strict=True)):
                        slot = 2 * k + j
                        # Each slot: its agent's observation (the new episode's after an end).
                        np.testing.assert_array_equal(obs_out[slot], vec._copies[k].obs[learner])
                        np.testing.assert_array_equal(sent[learner], actions[slot])
                        r = expected_reward(rec, car, scale, penalty, sign)
                        assert rewards[slot] == np.float32(r)
                        returns[slot] += r
                        lengths[slot] += 1
                        if rec["out"][2].get(car) and rec["out"][4][car].get("dnf_reason"):
                            dnf_steps += 1
                        else:
                            live_steps += 1
                    if role == "nature":  # the racer drives both cars, natures get nothing else
                        assert set(sent) == {"car_0", "car_1", "nature_car_0", "nature_car_1"}
                        assert sent["car_1"].tolist() == [1.0, pytest.approx(0.8)]
                    else:
                        np.testing.assert_array_equal(sent["nature_car_0"], [0.25] * K)
                        np.testing.assert_array_equal(sent["nature_car_1"], [0.25] * K)
                    if dones[2 * k]:
                        for j in range(2):
                            ep = infos[2 * k + j]["episode"]
                            assert ep["r"] == returns[2 * k + j]
                            assert ep["l"] == lengths[2 * k + j]
                        returns[2 * k : 2 * k + 2] = 0.0
                        lengths[2 * k : 2 * k + 2] = 0
        assert dnf_steps >= 2 and live_steps > 100
    finally:
        vec.close()


def test_nature_slots_see_the_global_state_and_their_cars_one_hot() -> None:
    """A nature slot's observation is ``state()`` then a one-hot of its car; at an episode
    end the terminal observation is the env's last one, and the slot restarts fresh."""
    vec = SelfPlayVecEnv(
        ["oval"],
        n_envs=1,
        n_cars=2,
        n_learners=2,
        seed=5,
        env_kwargs={"uncertainty": ADVERSARIAL},
        role="nature",
    )
    vec.racer = PursuitAndStraight(vec._copies[0].envs["oval"])
    state_size = 2 * (10 + K)
    assert vec.observation_space.shape == (state_size + 2,)
    try:
        first = vec.reset()
        env = vec._copies[0].env
        assert env is not None
        np.testing.assert_array_equal(first[:, :state_size], np.tile(env.state(), (2, 1)))
        np.testing.assert_array_equal(first[:, state_size:], np.eye(2))
        ended = False
        with spying(vec) as log:
            for _ in range(200):
                obs_out, _, dones, infos = vec.step(np.zeros((2, K), np.float32))
                rec = log[-1][0]
                env_obs = rec["out"][0]
                for j, nat in enumerate(["nature_car_0", "nature_car_1"]):
                    np.testing.assert_array_equal(env_obs[nat][:state_size], rec["state"])
                    np.testing.assert_array_equal(env_obs[nat][state_size:], np.eye(2)[j])
                    if not dones[j]:
                        np.testing.assert_array_equal(obs_out[j], env_obs[nat])
                        continue
                    np.testing.assert_array_equal(infos[j]["terminal_observation"], env_obs[nat])
                    env = vec._copies[0].env
                    assert env is not None
                    fresh = np.concatenate([env.state(), np.eye(2, dtype=np.float32)[j]])
                    np.testing.assert_array_equal(obs_out[j], fresh)
                    ended = True
                if ended:
                    break
        assert ended
    finally:
        vec.close()


def test_episode_end_infos_for_a_retirement_and_its_cut_short_team_mate() -> None:
    """The retired car's slot: terminal, its DNF reason and laps; the other slot: cut short,
    bootstrapped as a time limit; both carry the track and the summed episode return."""
    vec = SelfPlayVecEnv(
        ["oval"], n_envs=1, n_cars=2, n_learners=2, seed=2, randomise=False, dnf_penalty=3.0
    )
    try:
        vec.reset()
        with spying(vec) as log:
            for _ in range(300):
                _, _, dones, infos = vec.step(np.array([[0.0, 0.5], [0.0, 0.0]], np.float32))
                if dones.any():
                    break
        _, _, term, trunc, env_infos = log[-1][0]["out"]
        assert dones.tolist() == [True, True]
        assert (term["car_1"], trunc["car_1"]) == (True, False)
        assert (term["car_0"], trunc["car_0"]) == (False, False)
        moving, parked = infos
        assert parked["dnf_reason"] == "stuck" == env_infos["car_1"]["dnf_reason"]
        assert parked["TimeLimit.truncated"] is False and parked["cut_short"] is False
        assert moving["dnf_reason"] is None and moving["cut_short"] is True
        assert moving["TimeLimit.truncated"] is True
        for info, car in zip(infos, ["car_0", "car_1"], strict=True):
            assert info["track"] == "oval"
            assert info["laps_completed"] == env_infos[car]["laps_completed"] == 0
            assert info["episode"]["l"] == len(log)
            t = info["episode"]["t"]
            assert isinstance(t, float) and 0.0 <= t < 60.0  # wall seconds since the reset
            assert info["episode"]["t"] == round(info["episode"]["t"], 3)
        assert parked["episode"]["r"] < -2.0  # the penalty (3) on the retiring step
        assert moving["episode"]["r"] > 0.5  # the moving car made progress
    finally:
        vec.close()


def test_a_time_limit_is_a_truncation_without_the_dnf_penalty() -> None:
    """Truncated by ``max_cycles``: no penalty, ``TimeLimit.truncated``, not cut short."""
    vec = SelfPlayVecEnv(
        ["oval"],
        n_envs=1,
        n_cars=1,
        seed=0,
        randomise=False,
        dnf_penalty=100.0,
        reward_scale=2.0,
        env_kwargs={"max_cycles": 12},
    )
    try:
        vec.reset()
        with spying(vec) as log:
            for t in range(12):
                _, rew, dones, infos = vec.step(np.array([[0.0, 0.8]], np.float32))
                assert rew[0] == np.float32(2.0 * log[-1][0]["out"][1]["car_0"])
                assert dones[0] == (t == 11)
        assert rew[0] > 0.0
        info = infos[0]
        assert info["TimeLimit.truncated"] is True and info["cut_short"] is False
        assert info["episode"]["l"] == 12
        # The next episode's counters start again from zero.
        _, _, _, infos = vec.step(np.array([[0.0, 0.8]], np.float32))
        assert infos[0] == {} and vec._copies[0].length == 1
    finally:
        vec.close()


def test_who_drives_which_agent_in_each_role() -> None:
    """Racer role without a nature policy: natures get no action (the nominal point stays);
    nature role: its own slot drives its nature, ``nature`` the other cars' natures,
    ``racer`` every learner car, the pool the rest."""
    lone = SelfPlayVecEnv(
        ["oval"],
        n_envs=1,
        n_cars=2,
        seed=1,
        pool=OpponentPool(mix={"gap": 1.0}),
        env_kwargs={"uncertainty": ADVERSARIAL},
    )
    try:
        lone.reset()
        assert set(lone._copies[0].opponents) == {"car_1"}
        with spying(lone) as log:
            lone.step(np.array([[0.0, 0.5]], np.float32))
        sent = log[0][0]["actions"]
        assert set(sent) == {"car_0", "car_1"}
        infos = log[0][0]["out"][4]
        assert infos["car_0"]["perturbation"]["friction"] == 1.0
    finally:
        lone.close()
    vec = SelfPlayVecEnv(
        ["oval"],
        n_envs=1,
        n_cars=3,
        n_learners=2,
        seed=1,
        pool=OpponentPool(mix={"gap": 1.0}),
        env_kwargs={"uncertainty": ADVERSARIAL},
        role="nature",
    )
    vec.racer = Constant([0.0, 0.3], name="racer")
    vec.nature = Constant([-1.0] * K, name="nature")
    try:
        vec.reset()
        opponents = {a: d.name for a, d in vec._copies[0].opponents.items()}
        assert opponents == {
            "car_0": "racer",
            "car_1": "racer",
            "car_2": "gap",
            "nature_car_2": "nature",
        }
        mine = np.array([[1.0] * K, [0.5] * K], np.float32)
        with spying(vec) as log:
            vec.step(mine)
        sent = log[0][0]["actions"]
        np.testing.assert_array_equal(sent["nature_car_0"], mine[0])
        np.testing.assert_array_equal(sent["nature_car_1"], mine[1])
        np.testing.assert_array_equal(sent["nature_car_2"], [-1.0] * K)
        np.testing.assert_array_equal(sent["car_0"], np.float32([0.0, 0.3]))
        np.testing.assert_array_equal(sent["car_1"], np.float32([0.0, 0.3]))
        assert sent["car_2"].shape == (2,)
    finally:
        vec.close()


def test_the_constructor_seed_makes_runs_repeat() -> None:
    """Copies seeded by ``seed`` (without ``seed()``): the same seed, the same episodes;
    another seed, others; ``laps`` reaches every env."""

    def run(seed: int) -> tuple[np.ndarray, list[str]]:
        vec = SelfPlayVecEnv(["oval", "bean", "hairpins"], n_envs=2, n_cars=2, seed=seed, laps=2)
        try:
            assert vec.get_attr("laps") == [2, 2]
            rows = [vec.reset()]
            rows += [vec.step(np.zeros((2, 2), np.float32))[0] for _ in range(3)]
            return np.concatenate(rows), [c.track for c in vec._copies]
        finally:
            vec.close()

    a, b, c = run(21), run(21), run(22)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]
    assert not np.array_equal(a[0], c[0])


def test_a_flat_action_array_is_one_row_per_slot() -> None:
    """``step_async`` takes (num_envs·2,) as well as (num_envs, 2)."""
    vec = SelfPlayVecEnv(["oval"], n_envs=1, n_cars=2, n_learners=2, seed=1, randomise=False)
    try:
        vec.reset()
        vec.step_async(np.array([0.1, 0.2, 0.3, 0.4]))
        assert vec._actions.dtype == np.float32
        np.testing.assert_array_equal(vec._actions, np.array([[0.1, 0.2], [0.3, 0.4]], np.float32))
    finally:
        vec.close()


# ---- construction -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"role": "referee"}, "role must be racer or nature, got 'referee'"),
        ({"tracks": []}, "at least one training track is needed"),
        ({"n_learners": 0}, "n_learners must be in 1..n_cars (2), got 0"),
        ({"n_learners": 3}, "n_learners must be in 1..n_cars (2), got 3"),
        ({"n_envs": 0}, "n_envs must be at least 1, got 0"),
        ({"role": "nature"}, "role='nature' needs an adversarial uncertainty config"),
        (
            {"env_kwargs": {"action_mode": "discrete"}},
            "self-play needs obs_mode='vector' and action_mode='continuous'",
        ),
    ],
)
def test_bad_vec_env_settings_are_user_errors(kwargs: dict[str, Any], message: str) -> None:
    """Each refusal is a PolicyError with its own message (the CLI prints it on one line)."""
    args: dict[str, Any] = {"tracks": ["oval"], "n_envs": 1, "n_cars": 2, **kwargs}
    tracks = args.pop("tracks")
    with pytest.raises(PolicyError, match=f"^{re.escape(message)}$"):
        SelfPlayVecEnv(tracks, **args)


def test_the_edges_of_the_settings_are_accepted() -> None:
    """One copy, every car a learner, and one learner among several cars are all valid."""
    every = SelfPlayVecEnv(["oval"], n_envs=1, n_cars=2, n_learners=2, seed=0)
    one = SelfPlayVecEnv(["oval"], n_envs=1, n_cars=2, n_learners=1, seed=0)
    try:
        assert (every.num_envs, one.num_envs) == (2, 1)
        assert one.observation_space.shape == every.observation_space.shape
        assert one.action_space.shape == (2,)
    finally:
        every.close()
        one.close()


def test_slot_indices_map_to_their_copies() -> None:
    """get/set_attr and env_method address the copy behind each slot (slot // n_learners)."""
    vec = SelfPlayVecEnv(["oval", "bean"], n_envs=2, n_cars=2, n_learners=2, seed=4)
    try:
        assert vec.get_attr("render_mode") == [None] * 4
        assert vec.get_attr("render_mode", [1, 2]) == [None, None]
        # Before any reset the copies answer with their first track's env.
        assert [t.name for t in vec.get_attr("base_track", [0, 3])] == ["oval", "oval"]
        vec.reset()
        vec.set_attr("marker", "b", indices=[2, 3])
        vec.set_attr("marker", "a", indices=0)
        assert vec.get_attr("marker") == ["a", "a", "b", "b"]
        tracks = [c.track for c in vec._copies]
        names = vec.env_method("__getattribute__", "base_track")
        assert [t.name for t in names] == [tracks[0], tracks[0], tracks[1], tracks[1]]
        spaces_of = vec.env_method("observation_space", agent="car_1", indices=[3])
        assert len(spaces_of) == 1 and spaces_of[0].shape == vec.observation_space.shape
        assert len(vec.env_method("__getattribute__", "laps", indices=2)) == 1
        assert vec.env_is_wrapped(object, indices=[0, 1]) == [False, False]
    finally:
        vec.close()
    assert all(not c.envs for c in vec._copies)


def test_seeded_copies_take_consecutive_slot_seeds() -> None:
    """``seed(s)`` then ``reset()``: copy k starts from seed ``s + k·n_learners`` (SB3 gives
    each slot its own seed); the next reset continues the stream instead of repeating it."""
    two = SelfPlayVecEnv(["oval", "bean"], n_envs=2, n_cars=2, n_learners=2, seed=0)
    alone = SelfPlayVecEnv(["oval", "bean"], n_envs=1, n_cars=2, n_learners=2, seed=99)
    try:
        two.seed(11)
        alone.seed(13)
        first, solo = two.reset(), alone.reset()
        np.testing.assert_array_equal(first[2:], solo)
        assert two._copies[1].track == alone._copies[0].track
        again = two.reset()
        assert not np.array_equal(again, first)
        two.seed(11)
        np.testing.assert_array_equal(two.reset(), first)
    finally:
        two.close()
        alone.close()


@pytest.mark.parametrize(
    ("randomise", "options"),
    [
        (True, {"start_offset": "random", "direction": "random", "grid_order": "random"}),
        (False, {}),
    ],
)
def test_randomise_sets_the_reset_options(randomise: bool, options: dict[str, str]) -> None:
    """``randomise=True`` asks for a random start, direction and grid; False asks nothing."""
    vec = SelfPlayVecEnv(["oval"], n_envs=1, n_cars=2, seed=0, randomise=randomise)
    seen: list[dict[str, Any]] = []
    real = RacingEnv.reset

    def spy(env: RacingEnv, **kwargs: Any) -> Any:
        seen.append(kwargs)
        return real(env, **kwargs)

    try:
        with mock.patch.object(RacingEnv, "reset", autospec=True, side_effect=spy):
            vec.reset()
        assert [kw["options"] for kw in seen] == [options]
        assert isinstance(seen[0]["seed"], int)
    finally:
        vec.close()


def test_generated_tracks_are_closed_when_the_next_episode_starts() -> None:
    """With ``procedural.share=1`` every episode has a fresh generated env; the old one closes."""
    vec = SelfPlayVecEnv(
        ["oval"], n_envs=1, n_cars=1, seed=4, procedural=Procedural(share=1.0, length=(60, 80))
    )
    try:
        vec.reset()
        first = vec._copies[0].generated
        assert first is not None and vec._copies[0].env is first
        assert vec._copies[0].track == first.base_track.name
        assert vec._copies[0].track.startswith("random:")
        with mock.patch.object(first, "close", wraps=first.close) as closed:
            vec.reset()
        closed.assert_called_once_with()
        assert vec._copies[0].generated is not first
    finally:
        vec.close()
    assert vec._copies[0].generated is None


# ---- opponents ---------------------------------------------------------------------------------


def test_parse_mix_normalises_and_names_each_bad_part() -> None:
    """Weights normalised to sum 1 (blank parts and spaces ignored); exact refusals."""
    assert parse_mix(" snapshot = 1 ,, gap=3 ") == {"snapshot": 0.25, "gap": 0.75}
    assert parse_mix("pursuit=0,gap=2") == {"pursuit": 0.0, "gap": 1.0}
    for bad, message in (
        ("nobody=1", "unknown opponent kind 'nobody'; choose from ('snapshot', 'pursuit', 'gap')"),
        ("pursuit=x", "bad opponent weight in 'pursuit=x'"),
        ("gap", "bad opponent weight in 'gap'"),
        ("pursuit=-1", "opponent weight must be >= 0 in 'pursuit=-1'"),
        ("pursuit=nan", "opponent weight must be >= 0 in 'pursuit=nan'"),
        ("pursuit=0", "opponent mix 'pursuit=0' has no positive weight"),
        ("", "opponent mix '' has no positive weight"),
    ):
        with pytest.raises(PolicyError, match=f"^{re.escape(message)}$"):
            parse_mix(bad)


def tiny_policy(obs_size: int) -> ActorCriticPolicy:
    """A small SB3 actor-critic policy for a (obs_size,) Box observation, 2 actions."""
    return ActorCriticPolicy(
        spaces.Box(-np.inf, np.inf, (obs_size,), np.float32),
        spaces.Box(-1.0, 1.0, (2,), np.float32),
        lr_schedule=lambda _: 3e-4,
        net_arch=[8],
    )


def test_frozen_snapshots_are_detached_deterministic_copies() -> None:
    """A snapshot: its own weights (later training does not move it), eval mode, no
    gradients, no optimizer; actions are the mean clipped to [-1, 1]."""
    torch = pytest.importorskip("torch")
    live = tiny_policy(4)
    with torch.no_grad():
        live.action_net.bias.fill_(3.0)  # a mean far outside [-1, 1]
    # As straight after learn(): the last minibatch's distribution holds graph tensors,
    # which deepcopy refuses unless the snapshot drops them first.
    live.evaluate_actions(torch.zeros(3, 4), torch.zeros(3, 2))
    snap = SB3Driver.frozen(live, "snap-1")
    assert snap.name == "snap-1" and snap.policy is not live
    assert not snap.policy.training and snap.policy.optimizer is None
    assert all(not p.requires_grad for p in snap.policy.parameters())
    assert all(p.requires_grad for p in live.parameters()) and live.optimizer is not None
    obs = np.random.default_rng(0).normal(size=(5, 4)).astype(np.float32)
    acts = snap.act_batch(obs)
    assert acts.shape == (5, 2) and acts.dtype == np.float32
    np.testing.assert_array_equal(acts, np.ones((5, 2), np.float32))
    with torch.no_grad():
        live.action_net.bias.fill_(-3.0)
    np.testing.assert_array_equal(snap.act_batch(obs), np.ones((5, 2), np.float32))
    np.testing.assert_array_equal(SB3Driver(live).act(obs[0]), [-1.0, -1.0])
    assert SB3Driver(live).name == "learner"
    snap.reset(seed=3)  # stateless
    with torch.no_grad():
        live.action_net.bias.zero_()
        live.action_net.weight.zero_()
    np.testing.assert_array_equal(SB3Driver(live).act_batch(obs), np.zeros((5, 2)))


def test_pool_shares_snapshot_weight_with_baselines_until_one_exists() -> None:
    """No snapshot yet: only baselines (pursuit if the mix names none); then the mix holds,
    snapshots drawn uniformly among the newest ``max_snapshots``, baselines built once."""
    env = RacingEnv(track="oval", n_cars=2)
    try:
        rng = np.random.default_rng(0)
        pool = OpponentPool(mix={"snapshot": 0.5, "gap": 0.5}, max_snapshots=2)
        names = {pool.sample(rng, env).name for _ in range(20)}
        assert names == {"gap"}
        gap = pool.sample(rng, env)
        assert isinstance(gap, PolicyDriver) and pool.sample(rng, env) is gap
        only = OpponentPool(mix={"snapshot": 1.0})
        assert only.sample(rng, env).name == "pursuit"
        zero = OpponentPool(mix={"snapshot": 1.0, "gap": 0.0})
        assert zero.sample(rng, env).name == "pursuit"
        obs_size = env.observation_space("car_0").shape[0]
        for name in ("s1", "s2", "s3"):
            pool.add_snapshot(tiny_policy(obs_size), name)
        assert [s.name for s in pool.snapshots] == ["s2", "s3"]
        drawn = [pool.sample(rng, env).name for _ in range(400)]
        counts = {n: drawn.count(n) for n in ("gap", "s2", "s3")}
        assert sum(counts.values()) == 400
        assert 160 < counts["gap"] < 240 and 70 < counts["s2"] < 130 and 70 < counts["s3"] < 130
    finally:
        env.close()


def test_policy_driver_acts_row_by_row() -> None:
    """A stateless policy applied to each row; its name, or "policy" when it has none."""

    class Echo:
        def act(self, obs: np.ndarray) -> list[float]:
            return [float(obs[0]), -float(obs[1])]

    drv = PolicyDriver(Echo())  # type: ignore[arg-type]
    assert drv.name == "policy"
    out = drv.act_batch(np.array([[0.5, 0.25, 9.0], [1.0, -1.0, 9.0]], np.float32))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, [[0.5, -0.25], [1.0, 1.0]])


# ---- generated tracks --------------------------------------------------------------------------


def test_procedural_draw_gives_up_after_its_attempts() -> None:
    """Every draw refused by the generator: a PolicyError naming the number of draws."""
    refusal = r"^no valid generated track in 3 draws; widen the procedural ranges$"
    with (
        mock.patch("agents.selfplay.generate_track", side_effect=TrackError("no")) as gen,
        pytest.raises(PolicyError, match=refusal),
    ):
        Procedural(share=1.0).draw(np.random.default_rng(0), attempts=3)
    assert gen.call_count == 3


def test_procedural_draw_takes_its_ranges_and_retries_a_refused_seed() -> None:
    """Seed, length, difficulty, hairpin and width come from the ranges; a refused draw is
    followed by a new one; ``scale`` scales the result."""
    calls: list[tuple[Any, ...]] = []
    scaled_by: list[float] = []

    def fake(seed: int, length: float, difficulty: float, hairpin: Any, width: Any) -> Any:
        calls.append((seed, length, difficulty, hairpin, width))
        if len(calls) == 1:
            raise TrackError("no circuit")
        track = mock.Mock()
        track.scaled.side_effect = lambda s: scaled_by.append(s) or "scaled"
        return track

    proc = Procedural(length=(60, 61), difficulty=(0.3, 0.31), hairpin=(1.0, 1.1), width=(2, 2.1))
    with mock.patch("agents.selfplay.generate_track", side_effect=fake):
        plain = proc.draw(np.random.default_rng(0))
        assert len(calls) == 2 and calls[0][0] != calls[1][0]
        for seed, length, difficulty, hairpin, width in calls:
            assert 0 <= seed < 2**31 - 1 and 60 <= length <= 61
            assert 0.3 <= difficulty <= 0.31 and 1.0 <= hairpin <= 1.1 and 2 <= width <= 2.1
        assert plain.scaled.call_count == 0
        calls.clear()
        ordinary = Procedural(scale=0.52).draw(np.random.default_rng(1), attempts=2)
    assert ordinary == "scaled"
    assert scaled_by == [0.52]
    assert calls[-1][3:] == (None, None)


def test_snapshot_actions_are_float32_in_the_envs_box_whatever_the_policys_box() -> None:
    """A policy over a wider float64 box (another project's recipe: ``Box(-3, 3)``) still
    drives the env's cars with float32 actions in [-1, 1]; an SB3 policy without an
    ``action_dist`` (SAC's) can be frozen too."""
    torch = pytest.importorskip("torch")
    from stable_baselines3.sac.policies import SACPolicy

    wide = ActorCriticPolicy(
        spaces.Box(-np.inf, np.inf, (4,), np.float32),
        spaces.Box(-3.0, 3.0, (2,), np.float64),
        lr_schedule=lambda _: 3e-4,
        net_arch=[8],
    )
    with torch.no_grad():
        wide.action_net.weight.zero_()
        wide.action_net.bias.copy_(torch.tensor([2.5, -2.5]))
    obs = np.zeros((3, 4), np.float32)
    acts = SB3Driver.frozen(wide, "wide").act_batch(obs)
    assert acts.dtype == np.float32
    np.testing.assert_array_equal(acts, np.tile([1.0, -1.0], (3, 1)))
    sac = SACPolicy(
        spaces.Box(-np.inf, np.inf, (4,), np.float32),
        spaces.Box(-1.0, 1.0, (2,), np.float32),
        lr_schedule=lambda _: 3e-4,
        net_arch=[8],
    )
    assert not hasattr(sac, "action_dist")
    snap = SB3Driver.frozen(sac, "sac")
    assert snap.act_batch(obs).shape == (3, 2)
    assert np.all(np.abs(snap.act_batch(obs)) <= 1.0)


def test_pool_draws_kinds_by_their_weights_with_the_envs_car() -> None:
    """An 80/20 mix gives about 80/20 draws; baselines are built for the env's car."""
    env = RacingEnv(track="oval", n_cars=2, car="deepracer")
    try:
        pool = OpponentPool(mix=parse_mix("pursuit=4,gap=1"))
        rng = np.random.default_rng(1)
        drawn = [pool.sample(rng, env).name for _ in range(500)]
        assert 360 < drawn.count("pursuit") < 440 and drawn.count("gap") == 500 - drawn.count(
            "pursuit"
        )
        for driver in {id(d): d for d in (pool.sample(rng, env) for _ in range(20))}.values():
            assert isinstance(driver, PolicyDriver)
            assert driver.policy.params == env.params  # type: ignore[attr-defined]
    finally:
        env.close()


def test_procedural_draw_tries_twenty_times_by_default_over_many_seeds() -> None:
    """Twenty refused draws by default; the seeds spread over 0..2³¹−2 (not a handful)."""
    seeds: list[int] = []

    def refuse(seed: int, *args: Any) -> Any:
        seeds.append(seed)
        raise TrackError("no")

    with (
        mock.patch("agents.selfplay.generate_track", side_effect=refuse),
        pytest.raises(PolicyError, match=r"^no valid generated track in 20 draws;"),
    ):
        Procedural().draw(np.random.default_rng(0))
    assert len(seeds) == 20
    with (
        mock.patch("agents.selfplay.generate_track", side_effect=refuse),
        pytest.raises(PolicyError),
    ):
        Procedural().draw(np.random.default_rng(1), attempts=300)
    assert len(set(seeds[20:])) == 300 and max(seeds) > 2**30


def test_generated_envs_take_the_vec_envs_settings() -> None:
    """A generated track's env has the VecEnv's car count, laps and env arguments."""
    vec = SelfPlayVecEnv(
        ["oval"],
        n_envs=1,
        n_cars=2,
        seed=6,
        laps=2,
        procedural=Procedural(share=1.0, length=(60, 80)),
        env_kwargs={"lidar_rays": 16},
    )
    try:
        vec.reset()
        env = vec._copies[0].generated
        assert env is not None
        assert (env.n_cars, env.laps, env.layout.n_rays) == (2, 2, 16)
        assert vec.get_attr("laps") == [2]
    finally:
        vec.close()


def test_defaults_and_a_mix_of_listed_and_generated_tracks() -> None:
    """The documented defaults (4 copies, 2 cars, 1 lap, scale 1, no penalty, no frozen
    drivers); with ``share=0.5`` episodes alternate between listed and generated tracks
    without tripping over the closed generated env."""
    vec = SelfPlayVecEnv(["oval"], seed=0, procedural=Procedural(share=0.5, length=(60, 80)))
    try:
        assert (vec.n_copies, vec.n_cars, vec.n_learners, vec.laps) == (4, 2, 1, 1)
        assert (vec.reward_scale, vec.dnf_penalty, vec.role) == (1.0, 0.0, "racer")
        assert vec.racer is None and vec.nature is None and vec.render_mode is None
        seen = set()
        for _ in range(4):
            vec.reset()
            seen |= {c.track.startswith("random:") for c in vec._copies}
        assert seen == {True, False}
    finally:
        vec.close()
