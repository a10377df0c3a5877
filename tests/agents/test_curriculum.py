"""A curriculum on the bounds (``--curriculum``): domain randomisation that starts narrow
about the nominal car and widens to the full training set as training goes."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.curriculum import CURRICULUM_START, curriculum_callback, curriculum_scale
from agents.policy import PolicyError
from agents.robustness import training_uncertainty
from agents.train import TrainArgs, main
from arena.uncertainty import INDEX, UncertaintyError, default_config


def _tiny_run(out: Path, name: str, **settings: Any) -> dict[str, Any]:
    """A 512-step batched training run with ``settings``; its summary."""
    return main(
        TrainArgs(
            backend="batch", tracks=["oval"], n_cars=2, n_envs=2, total_timesteps=512,
            n_steps=32, batch_size=128, n_epochs=1, net_arch=[16, 16], eval_every=0,
            out=out, run_name=name, progress_bar=False, seed=2, **settings,
        )
    )  # fmt: skip


def test_the_scale_grows_linearly_from_the_start_to_the_full_set_then_stays() -> None:
    assert curriculum_scale(0, 1000, 0.5) == CURRICULUM_START
    assert curriculum_scale(250, 1000, 0.5) == pytest.approx((CURRICULUM_START + 1) / 2)
    assert curriculum_scale(500, 1000, 0.5) == 1.0
    assert curriculum_scale(900, 1000, 0.5) == 1.0
    assert curriculum_scale(0, 1000, 0.0) == 1.0  # off: the full set from the start
    steps = [curriculum_scale(t, 1000, 0.8) for t in range(0, 1001, 50)]
    assert steps == sorted(steps)


def test_the_narrowest_bounds_keep_every_parameter_of_the_set_free() -> None:
    # Latency is whole steps: a start of 0.25 rounds the default set's 0-2 to 0-0 (and below
    # 1/6 the wide set's 0-3), and the global state (and any nature's action) would change
    # width mid-training.
    for arm in ("sample", "wide", "cvar"):
        full = training_uncertainty(arm)
        assert full.scaled(CURRICULUM_START).free_names == full.free_names


def test_a_simulator_takes_new_bounds_for_its_next_draws_and_refuses_other_shapes() -> None:
    from arena.batch.sim import BatchSim

    full = training_uncertainty("wide")
    narrow = full.scaled(CURRICULUM_START)
    sim = BatchSim("oval", 256, 2, 1, seed=0, uncertainty=full)
    friction = INDEX["friction"]
    sim.reset()  # episodes draw their perturbations as they start
    spread = np.ptp(sim.unc.values[..., friction])
    assert spread > 0.7  # of the wide set's 0.4-1.3
    sim.set_uncertainty(narrow)
    sim.reset()  # new episodes: fresh draws from the narrow bounds
    lo, hi = narrow.dynamics.friction
    drawn = sim.unc.values[..., friction]
    assert lo <= drawn.min() and drawn.max() <= hi
    assert np.ptp(drawn) < 0.5 * spread  # the full set's draws spread wider
    sim.set_uncertainty(full)
    sim.reset()
    assert np.ptp(sim.unc.values[..., friction]) > hi - lo

    with pytest.raises(UncertaintyError, match="mode"):
        sim.set_uncertainty(default_config("adversarial"))
    with pytest.raises(UncertaintyError, match="free parameters"):
        sim.set_uncertainty(full.scaled(0.1))  # latency 0-3 rounds to 0-0: no longer free
    with pytest.raises(UncertaintyError, match="uncertainty="):
        BatchSim("oval", 2, 2, 1, seed=0).set_uncertainty(full)


def test_the_callback_widens_every_simulator_during_ppo_training() -> None:
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList

    from arena.batch.vec_env import BatchVecEnv

    full = training_uncertainty("wide")
    env = BatchVecEnv(
        ["oval", "bean"], n_envs=2, n_cars=2, seed=0,
        sim_kwargs={"uncertainty": full.scaled(CURRICULUM_START)},
    )  # fmt: skip
    seen: list[list[tuple[float, float]]] = []

    class Watch(BaseCallback):
        def _on_step(self) -> bool:
            return True

        def _on_rollout_start(self) -> None:  # what the coming rollout draws from
            seen.append([sim.unc.cfg.dynamics.friction for sim in env.sims])

    widen = curriculum_callback(full, env, total=1024, ramp=0.5)
    model = PPO("MlpPolicy", env, n_steps=16, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=1024, callback=CallbackList([widen, Watch()]))
    env.close()
    narrow = full.scaled(CURRICULUM_START).dynamics.friction
    assert seen[0] == [narrow] * len(env.sims)  # every simulator, the same bounds
    assert seen[-1] == [full.dynamics.friction] * len(env.sims)  # the full set from half-way
    lows = [s[0][0] for s in seen]
    assert lows == sorted(lows, reverse=True) and len(set(lows)) > 3  # widening, step by step
    scales = [s for _, s in widen.scales]
    assert scales[0] == CURRICULUM_START and scales[-1] == 1.0
    assert max(t for t, s in widen.scales if s < 1.0) < 512


def test_train_records_the_curriculum_and_refuses_it_where_it_cannot_apply(
    tmp_path: Path,
) -> None:
    summary = _tiny_run(tmp_path, "cur", uncertainty="cvar", curriculum=0.5)
    assert summary["args"]["curriculum"] == 0.5
    assert "--curriculum 0.5" in summary["training"]["command"]
    bad_settings: list[tuple[dict[str, Any], str]] = [
        ({"uncertainty": "nominal", "curriculum": 0.5}, "curriculum"),
        ({"uncertainty": "adversarial", "curriculum": 0.5}, "curriculum"),
        ({"backend": "bullet", "uncertainty": "sample", "curriculum": 0.5}, "curriculum"),
        ({"uncertainty": "sample", "curriculum": 1.5}, "curriculum"),
    ]
    for bad, match in bad_settings:
        args = dataclasses.replace(TrainArgs(backend="batch", out=tmp_path), **bad)
        with pytest.raises(PolicyError, match=match):
            main(args)


def test_train_draws_corner_weighted_when_asked_and_refuses_it_without_randomisation(
    tmp_path: Path,
) -> None:
    """``--edge-share``: the training envs' draws are corner-weighted (the config the
    simulators get carries it), the run records it, and it needs a randomising arm."""
    from agents.train import training_env_kwargs

    args = TrainArgs(backend="batch", uncertainty="cvar", edge_share=0.5, out=tmp_path)
    cfg = training_env_kwargs(args, {})["uncertainty"]
    assert cfg.edge_share == 0.5 and cfg.dynamics == training_uncertainty("cvar").dynamics
    plain = training_env_kwargs(dataclasses.replace(args, edge_share=0.0), {})["uncertainty"]
    assert plain == training_uncertainty("cvar")
    summary = _tiny_run(tmp_path, "edges", uncertainty="sample", edge_share=1.0)
    assert summary["args"]["edge_share"] == 1.0
    assert "--edge-share 1.0" in summary["training"]["command"]
    for bad in ({"uncertainty": "nominal"}, {"uncertainty": "adversarial"}, {"edge_share": 1.5}):
        settings = {"uncertainty": "sample", "edge_share": 0.5, **bad}
        with pytest.raises(PolicyError, match="edge_share"):
            main(dataclasses.replace(TrainArgs(backend="batch", out=tmp_path), **settings))
