"""``slipstream train --car``: the learner, its opponents and its evaluation races drive that
car, on tracks scaled to its size; the checkpoint records the car, and racing it with another
car warns in one line."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from agents.checkpoint import CheckpointError, read_checkpoint, save_checkpoint
from agents.loading import (
    CarMismatchWarning,
    car_mismatch,
    checkpoint_car_mismatch,
    load_policy,
)
from agents.selfplay import SelfPlayVecEnv
from agents.train import (
    TrainArgs,
    _batch_vec_env,
    main,
    parse_args,
    procedural_callback,
    procedural_of,
    training_env_kwargs,
    training_tracks,
)
from arena.cars import DEEPRACER, CarError
from arena.race import run_race
from arena.sim import CarParams
from tracks import load_track

SHIPPED = Path(__file__).parents[2] / "agents" / "data" / "ppo_racer.zip"
SCALE = DEEPRACER.length / CarParams().length  # 0.52: the 1/18 car against the 1/10 one


def test_car_flag_scales_every_track_kind_and_is_checked(tmp_path: Path) -> None:
    args = parse_args(["--car", "deepracer", "--tracks", "oval", "random:7", "--procedural", "1"])
    assert args.car == "deepracer"
    # Built-in and generated names get the car's scale; a name with its own scale keeps it
    # (DeepRacer's own tracks, imported at their real size, are named FILE@1).
    assert training_tracks(args, ["oval", "random:7", "carrera.json@1"]) == [
        "oval@0.52",
        "random:7@0.52",
        "carrera.json@1",
    ]
    assert training_tracks(TrainArgs(tracks=["oval"])) == ["oval"]
    assert load_track("oval@0.52").length == pytest.approx(SCALE * load_track("oval").length)
    # Generated tracks: drawn with the 1/10-car ranges (hairpins 0.5-0.9 m), then scaled.
    draw = procedural_of(
        TrainArgs(car="deepracer", procedural_hairpin=[0.5, 0.9], procedural_length=[60, 80])
    ).draw
    small = draw(np.random.default_rng(4))
    spec, _, factor = small.name.rpartition("@")
    assert factor == "0.52" and ",hairpin=" in spec
    assert small.length == pytest.approx(SCALE * load_track(spec).length)
    np.testing.assert_allclose(small.width_left, SCALE * load_track(spec).width_left)
    with pytest.raises(CarError, match="deepracer"):
        main(TrainArgs(car="tamiya", out=tmp_path))


def test_both_backends_put_the_car_on_scaled_tracks() -> None:
    from stable_baselines3 import PPO

    args = TrainArgs(
        backend="batch", car="deepracer", tracks=["bean"], procedural=0.5, n_cars=2, n_envs=2,
        procedural_length=[60.0, 80.0], procedural_hairpin=[0.5, 0.9], off_track_limit=0.4,
        runoff=0.1,
    )  # fmt: skip
    vec = _batch_vec_env(args)
    assert all(sim.off_track_limit == sim.rules.off_track_limit == 0.4 for sim in vec.sims)
    assert all(sim.runoff == 0.1 for sim in vec.sims)
    bean = load_track("bean")
    assert [sim.track.name for sim in vec.sims][::2] == ["bean@0.52", "bean@0.52-reversed"]
    assert vec.sims[0].track.length == pytest.approx(SCALE * bean.length)
    assert all(sim.params == DEEPRACER for sim in vec.sims)
    # A generated group redrawn during training is rebuilt with the same car.
    model = PPO("MlpPolicy", vec, n_steps=2048, batch_size=256, device="cpu", seed=0)
    redraw = procedural_callback(args, vec)
    redraw.init_callback(model)
    model._last_obs = vec.reset()
    model._last_episode_starts = np.ones(vec.num_envs, dtype=bool)
    before = vec.sims[1].track.name
    redraw.on_rollout_end()
    assert redraw.drawn and vec.sims[1].track.name == redraw.drawn[0] != before
    assert redraw.drawn[0].endswith("@0.52")
    assert vec.sims[1].params == vec.sims[3].params == DEEPRACER
    assert vec.sims[1].rules.off_track_limit == 0.4  # and its training rules
    assert vec.sims[1].runoff == 0.1
    vec.close()
    # pybullet: the learner and the baseline opponents drive the DeepRacer car, by the
    # training rules (and evaluation races by the env's own).
    kwargs = training_env_kwargs(args, {"car": "deepracer"})
    assert kwargs == {"car": "deepracer", "off_track_limit": 0.4, "runoff": 0.1}
    bullet = SelfPlayVecEnv(training_tracks(args), n_envs=1, n_cars=2, seed=0, env_kwargs=kwargs)
    try:
        bullet.reset()
        env = bullet._copies[0].env
        assert env is not None and env.params == DEEPRACER and env.off_track_limit == 0.4
        assert env.runoff == 0.1
        assert env.base_track.name == "bean@0.52"
        opponent: Any = bullet._copies[0].opponents["car_1"]
        assert opponent.policy.params == DEEPRACER
    finally:
        bullet.close()


@pytest.fixture(scope="module")
def deepracer_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The summary of a tiny ``--car deepracer --backend batch`` run (2,048 steps)."""
    return main(
        TrainArgs(
            backend="batch", car="deepracer", tracks=["oval"], n_cars=2, n_envs=8,
            total_timesteps=2048, n_steps=64, batch_size=1024, n_epochs=2, net_arch=[16, 16],
            wall_ends_episode=True, eval_every=0, out=tmp_path_factory.mktemp("runs"),
            run_name="dr", progress_bar=False, seed=3,
        )
    )  # fmt: skip


def test_tiny_deepracer_batch_run_records_the_car_and_races_it(
    deepracer_run: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    from leaderboard.cli import main as slipstream

    summary = deepracer_run
    meta, _ = read_checkpoint(summary["policy"])
    assert meta.env_config["car"] == "deepracer" and meta.car == "deepracer"
    assert meta.hyperparameters["track_scale"] == pytest.approx(SCALE)
    # The evaluation after the reload raced the scaled track, pursuit with the same car: it
    # laps a 49 m oval at DeepRacer speeds (about 14 s; the 1/10 car needs about 10 s on 94 m).
    (key,) = summary["reloaded_eval"]["tracks"]
    assert key == "oval@0.52"
    pursuit = summary["reloaded_eval"]["tracks"][key]["pursuit"][0]
    assert pursuit["status"] == "finished" and 10.0 < pursuit["best_lap"] < 25.0
    # The checkpoint loads and races with its own car, without a word.
    with warnings.catch_warnings():
        warnings.simplefilter("error", CarMismatchWarning)
        policy = load_policy(summary["policy"], params=DEEPRACER)
    result, _ = run_race(
        [policy], track="oval@0.52", laps=1, record=False, env_kwargs={"car": "deepracer"}
    )
    assert result.cars[0].agent == "car_0"
    # With the 1/10 car it still races, after one line that names both cars.
    code = slipstream(["race", "--agents", summary["policy"], "--car", "f1tenth", "--laps", "1"])
    err = capsys.readouterr().err
    assert code == 0
    (line,) = [ln for ln in err.splitlines() if "warning" in ln]
    assert line.startswith("slipstream: warning: policy 'dr' was trained with the deepracer car")
    assert "races the f1tenth car" in line
    recorded = json.loads((Path(summary["run_dir"]) / "summary.json").read_text())
    assert recorded["args"]["car"] == "deepracer"


def test_a_wrapped_deepracer_checkpoint_declares_its_car(
    deepracer_run: dict[str, Any], tmp_path: Path
) -> None:
    from submissions.bundle import EnvSpec, open_bundle
    from submissions.cli_bundle import wrap_checkpoint

    policy = Path(deepracer_run["policy"])
    out, _ = wrap_checkpoint(policy, tmp_path / "dr.zip")
    bundle = open_bundle(out, tmp_path / "open", env=EnvSpec.current())
    assert bundle.manifest.car == "deepracer"  # so its ranked races run the DeepRacer car
    # What `slipstream evaluate` says of a bundle whose manifest names another car.
    assert checkpoint_car_mismatch(bundle.entry_path, "deepracer") is None
    message = checkpoint_car_mismatch(bundle.entry_path, "f1tenth")
    assert message is not None and "deepracer car but races the f1tenth car" in message
    assert checkpoint_car_mismatch(tmp_path / "dr.zip", "f1tenth") is None  # not a checkpoint


def test_a_checkpoint_without_a_car_is_the_default_car(tmp_path: Path) -> None:
    # Checkpoints exported before car presets (the first shipped racer among them) have an
    # env_config of {}: they drove the default car.
    meta, tensors = read_checkpoint(SHIPPED)
    assert meta.car == "f1tenth"
    meta.env_config.pop("car", None)
    legacy = save_checkpoint(tensors, meta, tmp_path / "legacy.zip")
    meta, _ = read_checkpoint(legacy)
    assert "car" not in meta.env_config and meta.car == "f1tenth"
    with warnings.catch_warnings():
        warnings.simplefilter("error", CarMismatchWarning)
        load_policy(legacy, params=CarParams())
        load_policy(legacy)  # no race car given: nothing to compare
    with pytest.warns(CarMismatchWarning, match="the f1tenth car but races the deepracer car"):
        load_policy(legacy, params=DEEPRACER)
    # Hostile text in a meta.json's car stays on one line.
    meta.env_config["car"] = "x\nslipstream: error: fake"
    message = car_mismatch(meta, DEEPRACER)
    assert message is not None and "\n" not in message and "'x\\nslipstream" in message
    meta.env_config["car"] = {"length": 0.26}  # a custom car's parameters
    assert "a custom car" in (car_mismatch(meta, DEEPRACER) or "")


def test_export_records_preset_names_and_refuses_unknown_cars(tmp_path: Path) -> None:
    from agents.checkpoint import export_sb3
    from tests.agents.models import make_ppo

    model = make_ppo()
    path = export_sb3(model, tmp_path / "a.zip", name="a", env_config={"car": DEEPRACER})
    assert read_checkpoint(path)[0].env_config["car"] == "deepracer"  # CarParams -> its name
    custom = CarParams(length=0.4)
    path = export_sb3(model, tmp_path / "b.zip", name="b", env_config={"car": custom})
    meta = read_checkpoint(path)[0]
    assert isinstance(meta.car, dict) and meta.car["length"] == 0.4
    assert car_mismatch(meta, custom) is None
    with pytest.raises(CheckpointError, match="unknown car 'tamiya'"):
        export_sb3(model, tmp_path / "c.zip", name="c", env_config={"car": "tamiya"})


SHIPPED_DEEPRACER = SHIPPED.with_name("ppo_deepracer.zip")


def test_the_shipped_deepracer_policy_declares_its_car_and_laps_a_scaled_hairpin_track() -> None:
    """``ppo_deepracer.zip`` records the DeepRacer car (a race with the 1/10 car warns) and,
    with its car, finishes a lap of the hairpins track at DeepRacer scale on pybullet — the
    tight bends that stopped the 1/10 policy with the small car."""
    meta, _ = read_checkpoint(SHIPPED_DEEPRACER)
    assert meta.car == "deepracer"
    with pytest.warns(CarMismatchWarning, match="the deepracer car but races the f1tenth car"):
        load_policy(SHIPPED_DEEPRACER, params=CarParams())
    policy = load_policy(SHIPPED_DEEPRACER, params=DEEPRACER)
    result, _ = run_race(
        [policy], track=load_track("hairpins@0.52"), laps=1, seed=0, env_kwargs={"car": "deepracer"}
    )
    (car,) = result.cars
    assert car.status == "finished", (car.status, car.dnf_reason)
