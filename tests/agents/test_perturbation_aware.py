"""A perturbation-aware checkpoint (``slipstream train --observe-perturbation``) end to end:
training records the option, robustness scoring races it with the block on both backends,
and where the block is missing (a plain race, a ranked submission) the error says why."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.checkpoint import CheckpointError, export_sb3
from agents.loading import load_policy
from agents.robustness import evaluate_robustness, observation_kwargs
from arena import RacingEnv
from arena.observations import ObservationLayout
from leaderboard.cli import main as cli_main
from tests.agents.models import make_ppo, vector_space

pytestmark = pytest.mark.component("stable-baselines3")

AWARE = ObservationLayout(64, 3, context=True)
SMALL_GRID = {"friction": (0.6, 1.0), "latency": (0, 2)}


def _aware_checkpoint(path: Path) -> Path:
    model = make_ppo(obs_space=vector_space(AWARE), jitter=0.1)
    return export_sb3(
        model, path, name="aware", env_config={"car": "f1tenth", "observe_perturbation": True}
    )


def test_the_checkpoint_says_it_observes_its_perturbation(tmp_path: Path) -> None:
    policy = load_policy(str(_aware_checkpoint(tmp_path / "aware.zip")), observe_perturbation=None)
    assert policy.observation_shape == (AWARE.size,)
    assert getattr(policy, "observes_perturbation", False) is True
    assert observation_kwargs(policy) == {"observe_perturbation": True}
    plain = load_policy("agents/data/ppo_racer.zip", observe_perturbation=None)
    assert observation_kwargs(plain) == {}
    # Loaded for a race that adds the block, a plain checkpoint is refused by name too.
    with pytest.raises(CheckpointError, match="trained without perturbation-aware"):
        load_policy("agents/data/ppo_racer.zip", observe_perturbation=True)


@pytest.mark.parametrize("backend", ["pybullet", "batch"])
def test_robustness_races_an_aware_policy_with_the_block(tmp_path: Path, backend: str) -> None:
    policy = load_policy(str(_aware_checkpoint(tmp_path / "aware.zip")), observe_perturbation=None)
    report = evaluate_robustness(
        policy, "oval", n_random=2, nature_steps=0, scales=(1.0,), grid=SMALL_GRID,
        backend=backend, confirm=1,
    )  # fmt: skip
    assert report.grid["n"] == 4
    assert all(np.isfinite(r["score"]) for r in report.grid_races)
    if backend == "batch":
        assert report.confirmed is not None and len(report.confirmed) == 1


def test_a_race_without_the_block_names_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``slipstream race`` observes the standard layout: an aware checkpoint stops at load,
    with the reason and where to score it (it used to race as ``dnf (error)``, no reason);
    and a policy that gets the wrong observations anyway names the option in its error."""
    ckpt = _aware_checkpoint(tmp_path / "aware.zip")
    code = cli_main(["race", "--track", "oval", "--agents", f"{ckpt},pursuit"])
    assert code == 2
    err = capsys.readouterr().err
    assert "perturbation-aware" in err and "slipstream robustness" in err
    with pytest.raises(CheckpointError, match="perturbation-aware"):
        load_policy(str(ckpt))
    policy = load_policy(str(ckpt), observe_perturbation=None)
    env = RacingEnv(track="oval", n_cars=1)
    obs, _ = env.reset(seed=0)
    with pytest.raises(CheckpointError, match="observe_perturbation"):
        policy.act(obs["car_0"])
    env.close()


def test_a_ranked_bundle_refuses_an_aware_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ranked races observe the standard layout, blind to the conditions: wrapping an aware
    checkpoint for the leaderboard stops with the reason and writes nothing."""
    ckpt = _aware_checkpoint(tmp_path / "aware.zip")
    out = tmp_path / "bundle.zip"
    assert cli_main(["bundle", "wrap", str(ckpt), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "perturbation-aware" in err and "--observe-perturbation" in err
    assert not out.exists()


def _tiny_run(tmp_path: Path, name: str, **changes: Any) -> Any:
    """``slipstream train --backend batch --uncertainty sample --observe-perturbation`` on
    the oval, a few hundred steps (``changes``: other TrainArgs fields)."""
    from agents.train import TrainArgs

    return TrainArgs(
        backend="batch", tracks=["oval"], n_cars=2, n_envs=2, total_timesteps=512, n_steps=64,
        batch_size=128, n_epochs=1, eval_every=0, uncertainty="sample",
        observe_perturbation=True, out=tmp_path, run_name=name, progress_bar=False,
        **changes,
    )  # fmt: skip


def test_training_with_the_option_records_it_and_scores_it(tmp_path: Path) -> None:
    from agents.train import main

    summary = main(_tiny_run(tmp_path, "aware", procedural=0.5))
    assert summary["training"]["steps"] >= 512
    policy = load_policy(str(tmp_path / "aware" / "policy.zip"), observe_perturbation=True)
    assert policy.observation_shape == (AWARE.size,)
    assert policy.meta.env_config["observe_perturbation"] is True
    report = evaluate_robustness(
        policy, "oval", n_random=0, nature_steps=0, scales=(1.0,), grid=SMALL_GRID,
        backend="batch", confirm=0,
    )  # fmt: skip
    assert report.grid["n"] == 4


def test_training_refuses_the_option_without_uncertainty_and_a_plain_start(
    tmp_path: Path,
) -> None:
    """Nominal training would observe zeros throughout, and a plain checkpoint's weights do
    not fit a network with 9 more inputs: both stop before training, with the reason."""
    from agents.policy import PolicyError
    from agents.train import TrainArgs, main

    with pytest.raises(PolicyError, match="nominal"):
        main(TrainArgs(observe_perturbation=True, out=tmp_path))
    plain = Path("agents/data/ppo_racer.zip")
    with pytest.raises(PolicyError, match=r"\(64, 100\) does not fit .*\(64, 109\)"):
        main(_tiny_run(tmp_path, "plain-start", init_from=plain))


def test_a_redrawn_generated_track_keeps_the_block() -> None:
    """``--procedural`` rebuilds a group's simulator on a new track mid-training: the new one
    observes the perturbation too (it once did not, and PPO's next rollout broke on the
    narrower observations)."""
    from stable_baselines3 import PPO

    from agents.train import TrainArgs, _batch_vec_env, procedural_callback
    from arena.uncertainty import default_config

    args = TrainArgs(
        backend="batch", tracks=["oval"], procedural=0.5, n_cars=2, n_envs=2,
        uncertainty="sample", observe_perturbation=True,
    )  # fmt: skip
    vec = _batch_vec_env(args, default_config("sample"))
    assert vec.observation_space.shape == (AWARE.size,)
    model = PPO("MlpPolicy", vec, n_steps=2048, batch_size=256, device="cpu", seed=0)
    redraw = procedural_callback(args, vec)
    redraw.init_callback(model)
    model._last_obs = vec.reset()
    model._last_episode_starts = np.ones(vec.num_envs, dtype=bool)
    redraw.on_rollout_end()
    assert redraw.drawn
    assert all(sim.layout.context for sim in vec.sims)
    generated = vec.sims[1]
    first = np.asarray(model._last_obs)[int(vec._bounds[1]) : int(vec._bounds[2])]
    block = first[:, AWARE.perturbation]
    np.testing.assert_allclose(
        block.reshape(generated.n_envs, generated.n_cars, -1),
        generated.ops.to_numpy(generated._context),
        rtol=1e-6,
    )
    assert np.abs(block).max() > 0  # drawn cars, not the nominal one
    vec.close()
