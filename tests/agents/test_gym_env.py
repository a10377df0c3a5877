"""The single-agent Gymnasium env ``slipstream/Race-v0`` (agents/gym_env.py).

The compliance checks are the ecosystem's own (Gymnasium's and stable-baselines3's
``check_env``, as a user runs them before training); the opponent tests assert what the
opponents do on the track, seen through the learner's public ``info``.
"""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest

import agents
from agents.gym_env import RaceEnv, is_bundle, register_bundle_loader
from agents.policy import PolicyError
from arena import SimError

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "agents" / "data" / "ppo_racer.zip"
BRAKE = np.array([0.0, -1.0], dtype=np.float32)


def make(**kwargs: Any) -> Any:
    return gymnasium.make(agents.GYM_ENV_ID, **kwargs)


@pytest.mark.component("stable-baselines3")
@pytest.mark.parametrize("backend", ["pybullet", "batch"])
@pytest.mark.parametrize("opponents", [["pursuit"], []], ids=["pursuit", "time-trial"])
def test_passes_gymnasium_and_sb3_check_env(backend: str, opponents: list[str]) -> None:
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = make(track="oval", opponents=opponents, backend=backend)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a checker warning is a defect too
        check_env(env.unwrapped)
        sb3_check_env(env.unwrapped)
    env.close()


def test_dict_observations_pass_check_env_in_a_time_trial() -> None:
    from gymnasium.utils.env_checker import check_env

    env = make(track="oval", opponents=[], obs_mode="dict")
    check_env(env.unwrapped)
    assert isinstance(env.observation_space, gymnasium.spaces.Dict)
    env.close()


def test_registered_on_import_and_by_module_prefix() -> None:
    """What a user types: the module prefix works with nothing imported before."""
    code = (
        "import gymnasium; "
        "env = gymnasium.make('agents:slipstream/Race-v0', opponents=[], backend='batch'); "
        "obs, info = env.reset(seed=0); "
        "print(obs.shape, 'slipstream/Race-v0' in gymnasium.registry)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        check=False,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["(100,)", "True"]


def test_time_trial_has_one_car() -> None:
    env = make(track="oval", opponents=[])
    assert env.unwrapped.race.possible_agents == ["car_0"]
    _, info = env.reset(seed=0)
    assert info["rank"] == 1  # ranks are 1-based
    env.close()


@pytest.mark.parametrize("backend", ["pybullet", "batch"])
@pytest.mark.parametrize("opponent", ["pursuit", str(SHIPPED)], ids=["baseline", "checkpoint"])
def test_opponent_drives_past_a_braking_learner(backend: str, opponent: str) -> None:
    """The learner brakes on pole; a driven opponent passes it, so its rank drops to 2."""
    env = make(track="oval", opponents=[opponent], backend=backend)
    _, info = env.reset(seed=0)
    assert info["rank"] == 1  # pole
    for _ in range(60):  # 3 s
        _, _, _, truncated, info = env.step(BRAKE)
        assert not truncated
    assert info["rank"] == 2
    env.close()


def test_seed_fixes_the_race_random_opponents_included() -> None:
    def run() -> list[np.ndarray]:
        env = make(track="oval", opponents=["random", "random"])
        obs, _ = env.reset(seed=5)
        out = [obs]
        for _ in range(40):
            obs, *_ = env.step(np.array([0.1, 0.6], dtype=np.float32))
            out.append(obs)
        env.close()
        return out

    first, second = run(), run()
    assert all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))


class Recorder:
    """A user's own Policy object: records what it was given."""

    name = "recorder"

    def __init__(self) -> None:
        self.seeds: list[int | None] = []
        self.shapes: list[tuple[int, ...]] = []
        self.closed = False

    def reset(self, seed: int | None = None) -> None:
        self.seeds.append(seed)

    def act(self, obs: np.ndarray) -> np.ndarray:
        self.shapes.append(np.shape(obs))
        return np.array([0.0, 1.0], dtype=np.float32)

    def close(self) -> None:
        self.closed = True


def test_policy_object_gets_its_own_observations_and_stays_open() -> None:
    rec = Recorder()
    env = make(track="oval", opponents=[rec])
    env.reset(seed=1)
    for _ in range(3):
        env.step(BRAKE)
    env.close()
    assert len(rec.seeds) == 1 and rec.seeds[0] is not None
    assert rec.shapes == [(100,)] * 3
    assert not rec.closed  # objects passed in stay the caller's


class Crashes(Recorder):
    def act(self, obs: np.ndarray) -> np.ndarray:
        err = RuntimeError("policy died")
        err.dnf_reason = "error"  # type: ignore[attr-defined] - as submissions.remote raises
        raise err


@pytest.mark.parametrize("backend", ["pybullet", "batch"])
def test_a_failing_opponent_retires_and_the_race_goes_on(backend: str) -> None:
    env = make(track="oval", opponents=[Crashes(), "pursuit"], backend=backend)
    env.reset(seed=0)
    env.step(np.array([0.0, 1.0], dtype=np.float32))
    race = env.unwrapped.race
    assert "car_1" not in race.agents
    assert "car_2" in race.agents and "car_0" in race.agents
    env.close()


def test_a_plain_exception_from_an_opponent_is_not_swallowed() -> None:
    class Buggy(Recorder):
        def act(self, obs: np.ndarray) -> np.ndarray:
            raise ZeroDivisionError

    env = make(track="oval", opponents=[Buggy()])
    env.reset(seed=0)
    with pytest.raises(ZeroDivisionError):
        env.step(BRAKE)
    env.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"opponents": "pursuit"}, "must be a list"),
        ({"opponents": ["nobody"]}, "nobody"),
        ({"opponents": [42]}, "neither a baseline name"),
        ({"opponents": ["pursuit"], "obs_mode": "image"}, "vector observations"),
        ({"opponents": ["gap"], "action_mode": "discrete"}, "continuous actions"),
    ],
)
def test_bad_opponents_are_refused_with_a_clear_error(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(PolicyError, match=message):
        RaceEnv(track="oval", **kwargs)


def test_adversarial_uncertainty_is_refused() -> None:
    from arena.uncertainty import default_config

    with pytest.raises(PolicyError, match="nature agents"):
        RaceEnv(track="oval", opponents=[], uncertainty=default_config("adversarial"))


def test_sampled_uncertainty_reaches_the_learner() -> None:
    from arena.uncertainty import default_config

    env = make(track="oval", opponents=["pursuit"], uncertainty=default_config("sample"))
    _, info = env.reset(seed=0)
    assert set(info["perturbation"]) >= {"friction", "mass"}
    env.close()


def test_step_after_the_end_is_refused() -> None:
    env = RaceEnv(track="oval", opponents=[], max_cycles=2)
    env.reset(seed=0)
    env.step(BRAKE)
    *_, truncated, _ = env.step(BRAKE)
    assert truncated
    with pytest.raises(SimError, match="reset"):
        env.step(BRAKE)
    env.close()


def _bundle(tmp_path: Path) -> Path:
    """A bundle folder shaped like submissions' (manifest.json + entry), never run here."""
    root = tmp_path / "bundle"
    root.mkdir()
    (root / "manifest.json").write_text('{"schema": 1, "name": "x", "format": "python"}')
    (root / "policy.py").write_text("raise SystemExit('must never be imported in-process')\n")
    return root


def test_bundle_path_without_the_sandbox_loader_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without ``submissions`` imported (no loader registered; another test in this process
    may have imported it, so the registry is emptied here), a bundle path is refused."""
    from agents import gym_env

    monkeypatch.setattr(gym_env, "_bundle_loader", [])
    root = _bundle(tmp_path)
    assert is_bundle(root)
    with pytest.raises(PolicyError, match="sandbox"):
        RaceEnv(track="oval", opponents=[str(root)])


def test_bundle_path_goes_through_the_registered_loader(tmp_path: Path) -> None:
    root = _bundle(tmp_path)
    calls: list[tuple[Path, Any]] = []
    rec = Recorder()

    def loader(path: Path, env: Any) -> Recorder:
        calls.append((path, env))
        return rec

    register_bundle_loader(loader)
    try:
        env = RaceEnv(track="oval", opponents=[str(root)])
        env.reset(seed=0)
        env.step(BRAKE)
        env.close()
    finally:
        from agents import gym_env

        gym_env._bundle_loader.clear()
    assert calls == [(root, env.race)]
    assert rec.shapes == [(100,)]
    assert rec.closed  # loaded by the env, so closed by it (a sandbox must not outlive it)


def test_renders_on_pybullet_and_refuses_only_render_on_batch() -> None:
    """SB3's make_vec_env passes render_mode="rgb_array" to every env it makes."""
    env = RaceEnv(track="oval", opponents=["pursuit"], render_mode="rgb_array")
    env.reset(seed=0)
    image = env.render()
    assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8
    env.close()
    batch = RaceEnv(track="oval", opponents=[], backend="batch", render_mode="rgb_array")
    batch.reset(seed=0)
    batch.step(BRAKE)
    with pytest.raises(SimError, match="does not render"):
        batch.render()
    batch.close()


SANDBOXED_PURSUIT = b"""
from agents.baselines import make_baseline
from arena.observations import ObservationLayout


class Policy:
    def __init__(self, env_spec):
        layout = ObservationLayout(env_spec["lidar_rays"], env_spec["k_opponents"])
        self.pursuit = make_baseline("pursuit", layout)

    def reset(self, seed):
        self.pursuit.reset(seed)

    def act(self, obs):
        return self.pursuit.act(obs)
"""


@pytest.mark.component("bubblewrap")
def test_a_sandboxed_bundle_races_as_an_opponent(tmp_path: Path) -> None:
    """The documented way to race a submission bundle: a SandboxedPolicy object (the bundle
    is a python-format one, as `slipstream bundle init` writes; it runs only in its sandbox)."""
    from arena.version import ENV_VERSION
    from submissions.bundle import Manifest, make_bundle, open_bundle
    from submissions.remote import SandboxedPolicy

    manifest = Manifest(
        name="sandboxed-pursuit", author="tests", format="python", entry="agent.py",
        env_version=ENV_VERSION,
    )  # fmt: skip
    zipped = make_bundle(tmp_path / "b.zip", manifest, {"agent.py": SANDBOXED_PURSUIT})
    opponent = SandboxedPolicy(open_bundle(zipped, tmp_path / "b"))
    try:
        env = make(track="oval", opponents=[opponent])
        _, info = env.reset(seed=0)
        for _ in range(60):
            _, _, _, _, info = env.step(BRAKE)
        env.close()
        assert info["rank"] == 2  # the sandboxed pursuit car passed the braking learner
        assert opponent.failure is None
    finally:
        opponent.close()
