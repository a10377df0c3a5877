"""PPO self-play training: the VecEnv's conventions, the typed arguments, a tiny real run."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from agents.policy import PolicyError
from agents.selfplay import OpponentPool, Procedural, SelfPlayVecEnv, parse_mix
from agents.train import TrainArgs, _to_argv, add_train_arguments, main, parse_args


def _drive(vec: SelfPlayVecEnv, steps: int, throttle: float = 0.6) -> list[tuple]:
    """Step with a fixed [0, throttle] action; returns (obs, rew, dones, infos) per step."""
    out = []
    action = np.tile([0.0, throttle], (vec.num_envs, 1)).astype(np.float32)
    for _ in range(steps):
        out.append(vec.step(action))
    return out


def test_vec_env_shapes_and_slots() -> None:
    pool = OpponentPool(mix=parse_mix("pursuit=1,gap=1"))
    vec = SelfPlayVecEnv(["oval"], n_envs=2, n_cars=3, n_learners=2, pool=pool, seed=0)
    try:
        assert vec.num_envs == 4
        obs = vec.reset()
        assert obs.shape == (4, *vec.observation_space.shape)
        assert obs.dtype == np.float32
        obs, rew, dones, infos = vec.step(np.zeros((4, 2), dtype=np.float32))
        assert obs.shape == (4, *vec.observation_space.shape)
        assert rew.shape == dones.shape == (4,)
        assert len(infos) == 4
        assert vec.get_attr("n_cars") == [3, 3, 3, 3]
        assert vec.env_is_wrapped(object) == [False] * 4
    finally:
        vec.close()


def test_vec_env_episode_end_follows_sb3_conventions() -> None:
    """Standing still gets a learner retired as stuck: a terminal, non-truncated end."""
    vec = SelfPlayVecEnv(
        ["oval"], n_envs=2, n_cars=2, n_learners=2, seed=1, randomise=False, dnf_penalty=5.0
    )
    try:
        vec.reset()
        steps = _drive(vec, 100, throttle=0.0)
        ends = [(t, i) for t, (_, _, d, _) in enumerate(steps) for i in np.flatnonzero(d)]
        assert ends, "parked cars must be retired as stuck"
        t, slot = ends[0]
        info = steps[t][3][slot]
        assert info["dnf_reason"] == "stuck"
        assert info["TimeLimit.truncated"] is False
        assert info["terminal_observation"].shape == vec.observation_space.shape
        assert info["episode"]["l"] == t + 1
        assert info["track"] == "oval"
        assert info["cut_short"] is False
        assert steps[t][1][slot] == pytest.approx(-5.0, abs=0.05)  # the DNF penalty
        # Both learners of a copy end together (a copy resets when its first learner is done).
        copy_slots = {slot - slot % 2, slot - slot % 2 + 1}
        assert copy_slots <= set(np.flatnonzero(steps[t][2]))
    finally:
        vec.close()


def test_vec_env_team_mate_end_is_a_truncation() -> None:
    """A learner whose team-mate ends the episode is cut short: bootstrapped, not terminal."""
    vec = SelfPlayVecEnv(["oval"], n_envs=1, n_cars=2, n_learners=2, seed=2, randomise=False)
    try:
        vec.reset()
        moving = np.array([[0.0, 0.0], [0.0, 0.5]], dtype=np.float32)  # car_0 parks
        for _ in range(200):
            _, _, dones, infos = vec.step(moving)
            if dones.any():
                break
        assert dones.all()
        assert infos[0]["dnf_reason"] == "stuck" and not infos[0]["TimeLimit.truncated"]
        assert infos[1]["TimeLimit.truncated"] is True
    finally:
        vec.close()


def test_vec_env_procedural_tracks() -> None:
    vec = SelfPlayVecEnv(["oval"], n_envs=1, n_cars=1, seed=4, procedural=Procedural(share=1.0))
    try:
        vec.reset()
        tracks = set()
        for _, _, dones, infos in _drive(vec, 300, throttle=0.0):
            tracks |= {info["track"] for info, done in zip(infos, dones, strict=True) if done}
        assert len(tracks) >= 2
        assert all(name.startswith("random:") for name in tracks)
    finally:
        vec.close()


def test_vec_env_is_deterministic_over_many_steps() -> None:
    def run() -> np.ndarray:
        pool = OpponentPool(mix=parse_mix("pursuit=1,gap=1"))
        vec = SelfPlayVecEnv(["oval", "bean"], n_envs=2, n_cars=2, pool=pool, seed=7)
        try:
            vec.seed(7)
            first = vec.reset()
            rest = [step[0] for step in _drive(vec, 300)]
            return np.stack([first, *rest])
        finally:
            vec.close()

    np.testing.assert_array_equal(run(), run())


def test_parse_mix() -> None:
    assert parse_mix("snapshot=1, pursuit=3") == {"snapshot": 0.25, "pursuit": 0.75}
    for bad in ("nobody=1", "pursuit=x", "pursuit=-1", "pursuit=0", ""):
        with pytest.raises(PolicyError):
            parse_mix(bad)


def test_arguments_have_types_and_help() -> None:
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    text = parser.format_help()
    assert "training tracks, one drawn per episode" in text
    assert "--stop-at-first-clean-lap" in text and "--no-randomise" in text
    assert "starts at 30 % of its width" in " ".join(text.split())  # "%" is text, not a format
    args = parse_args(
        [
            "--tracks",
            "oval",
            "bean",
            "--net-arch",
            "32",
            "32",
            "--n-envs",
            "3",
            "--max-minutes",
            "1.5",
            "--no-randomise",
        ]
    )
    assert args.tracks == ["oval", "bean"]
    assert args.net_arch == [32, 32]
    assert args.n_envs == 3
    assert args.max_minutes == 1.5
    assert args.randomise is False
    assert parse_args(_to_argv(args)) == args


def test_bad_settings_are_user_errors(tmp_path: Path) -> None:
    with pytest.raises(PolicyError, match="n_learners"):
        main(TrainArgs(n_cars=1, n_learners=2, out=tmp_path))
    with pytest.raises(PolicyError, match="opponent"):
        main(TrainArgs(n_cars=2, n_learners=1, opponent_mix="aliens=1", out=tmp_path))


def test_tiny_training_run_produces_a_loadable_checkpoint(tmp_path: Path) -> None:
    from agents.loading import load_policy
    from arena.env import RacingEnv

    args = TrainArgs(
        tracks=["oval"],
        n_cars=2,
        n_learners=1,
        n_envs=2,
        total_timesteps=1024,
        n_steps=256,
        batch_size=256,
        n_epochs=2,
        net_arch=[16, 16],
        snapshot_every=512,
        eval_every=1024,
        out=tmp_path,
        run_name="tiny",
        progress_bar=False,
        seed=3,
    )
    summary = main(args)
    run_dir = tmp_path / "tiny"
    zip_path = run_dir / "policy.zip"
    assert Path(summary["policy"]) == zip_path and zip_path.is_file()
    assert zip_path.stat().st_size < 100_000
    assert summary["training"]["steps"] >= 1024
    assert any((run_dir / "tb").rglob("events.out.tfevents.*"))
    rows = [json.loads(line) for line in (run_dir / "curve.jsonl").read_text().splitlines()]
    assert rows and rows[0]["timesteps"] >= 1024
    assert {"wall_s", "completed_laps", "best_lap", "clean_lap"} <= set(rows[0])
    assert json.loads((run_dir / "summary.json").read_text())["run"] == "tiny"

    policy = load_policy(str(zip_path))
    env = RacingEnv(track="hairpins", n_cars=2)
    try:
        obs, _ = env.reset(seed=0)
        policy.reset(0)
        action = np.asarray(policy.act(obs["car_0"]))
    finally:
        env.close()
    assert action.shape == (2,)
    assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)


def test_procedural_draws_hairpin_tracks_from_its_range() -> None:
    """`--procedural-hairpin 0.6 0.9`: every generated training track has real-track hairpins."""
    rng = np.random.default_rng(4)
    plain = Procedural(share=1.0, length=(150.0, 200.0), difficulty=(0.7, 0.9))
    tight = Procedural(share=1.0, length=(150.0, 200.0), difficulty=(0.7, 0.9), hairpin=(0.6, 0.9))
    for _ in range(2):
        assert (1.0 / np.abs(plain.draw(rng).curvature)).min() > 1.0
        track = tight.draw(rng)
        assert "hairpin=" in track.name
        assert (1.0 / np.abs(track.curvature)).min() < 1.0


def test_procedural_width_range_sets_the_generated_roads() -> None:
    rng = np.random.default_rng(5)
    narrow = Procedural(share=1.0, length=(100.0, 120.0), width=(1.3, 1.4), scale=0.52)
    track = narrow.draw(rng)
    assert "width=1.3" in track.name and track.name.endswith("@0.52")
    assert 0.52 * 1.3 <= (track.width_left + track.width_right).max() <= 0.52 * 1.4 + 1e-9


def test_procedural_hairpin_range_is_checked() -> None:
    from agents.train import _check

    with pytest.raises(PolicyError, match="procedural_hairpin"):
        _check(TrainArgs(procedural_hairpin=[0.9]))


def test_wall_ends_episode_is_refused_on_pybullet() -> None:
    from agents.train import _check

    with pytest.raises(PolicyError, match="wall_ends_episode"):
        _check(TrainArgs(wall_ends_episode=True, backend="bullet"))
    _check(TrainArgs(wall_ends_episode=True, backend="batch"))


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf")])
def test_off_track_limit_and_runoff_must_be_sizes(bad: float) -> None:
    from agents.train import _check

    with pytest.raises(PolicyError, match="off_track_limit"):
        _check(TrainArgs(off_track_limit=bad))
    with pytest.raises(PolicyError, match="runoff"):
        _check(TrainArgs(runoff=bad))
    _check(TrainArgs(off_track_limit=0.0, runoff=0.0))  # DeepRacer's rule; walls at the edge
