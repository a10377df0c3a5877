"""``load_policy``: baselines by name, our checkpoints always, code formats only when trusted."""

from __future__ import annotations

import base64
import io
import json
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from agents import Policy, load_policy
from agents.baselines import GapFollowerPolicy, PursuitPolicy, RandomPolicy
from agents.checkpoint import CheckpointError, TorchMLPPolicy, export_sb3
from agents.loading import (
    DEFAULT_LAYOUT,
    SB3Policy,
    TorchScriptPolicy,
    UntrustedCodeWarning,
    convert_sb3,
    detect_format,
)
from agents.policy import PolicyError
from arena.observations import ObservationLayout
from tests.agents.models import (
    DISCRETE_ACTIONS,
    fixed_observations,
    make_ppo,
    members,
    payload,
    write_zip,
)


@pytest.fixture(scope="module")
def model() -> Any:
    """A continuous PPO MlpPolicy with jittered weights."""
    return make_ppo()


@pytest.fixture
def sb3_zip(model: Any, tmp_path: Path) -> Path:
    """``model`` saved the SB3 way (a zip with pickled parts)."""
    path = tmp_path / "sb3_model.zip"
    model.save(path)
    return path


@pytest.fixture
def ours(model: Any, tmp_path: Path) -> Path:
    """``model`` exported to a Slipstream checkpoint."""
    return export_sb3(model, tmp_path / "ours.zip", name="ours", env_config={})


def _assert_same_actions(policy: Policy, model: Any, n: int = 100) -> None:
    for o in fixed_observations(model.observation_space, n=n):
        want, _ = model.predict(o, deterministic=True)
        np.testing.assert_array_equal(policy.act(o), want)


# ---- baselines ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "cls"),
    [("pursuit", PursuitPolicy), ("gap", GapFollowerPolicy), ("random", RandomPolicy)],
)
def test_baselines_by_name(name: str, cls: type) -> None:
    policy = load_policy(name)
    assert isinstance(policy, cls)
    assert isinstance(policy, Policy)
    policy.reset(0)
    action = policy.act(np.zeros(DEFAULT_LAYOUT.size, dtype=np.float32))
    assert np.asarray(action).shape == (2,)
    assert np.all(np.abs(action) <= 1.0)


def test_baseline_takes_the_given_layout() -> None:
    layout = ObservationLayout(16, 1)
    policy = load_policy("gap", layout=layout)
    assert isinstance(policy, GapFollowerPolicy)
    assert policy.layout == layout
    assert load_policy("pursuit").layout == ObservationLayout(64, 3)


def test_unknown_name_says_what_it_looked_for() -> None:
    with pytest.raises(CheckpointError, match=r"no such file.*pursuit, gap, random") as err:
        load_policy("pursuitt")
    assert isinstance(err.value, PolicyError)


# ---- our checkpoints ------------------------------------------------------------------------


def test_checkpoint_loads_without_trust_and_acts_like_sb3(ours: Path, model: Any) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # loading our format warns about nothing
        policy = load_policy(ours)
    assert isinstance(policy, TorchMLPPolicy)
    assert policy.name == "ours"
    _assert_same_actions(policy, model)
    assert detect_format(ours) == "slipstream"


def test_discrete_checkpoint_returns_ints(tmp_path: Path) -> None:
    model = make_ppo(DISCRETE_ACTIONS)
    policy = load_policy(str(export_sb3(model, tmp_path / "d.zip", name="d", env_config={})))
    for o in fixed_observations(model.observation_space, n=50):
        action = policy.act(o)
        assert isinstance(action, int)
        assert action == int(model.predict(o, deterministic=True)[0])


def test_hostile_zip_through_load_policy_gets_the_strict_message(
    ours: Path, tmp_path: Path
) -> None:
    evil = write_zip(tmp_path / "evil.zip", [*members(ours).items(), ("../../etc/x", b"")])
    with pytest.raises(CheckpointError, match="unsafe path"):
        load_policy(evil)


def test_checkpoint_races_in_the_real_env(tmp_path: Path) -> None:
    from gymnasium import spaces

    from arena.env import RacingEnv
    from arena.race import run_race

    env = RacingEnv(track="oval", n_cars=2)
    obs_space = env.observation_space("car_0")
    env.close()
    assert isinstance(obs_space, spaces.Box)
    model = make_ppo(obs_space=obs_space, jitter=0.05)
    path = export_sb3(model, tmp_path / "racer.zip", name="racer", env_config={"track": "oval"})
    result, _ = run_race(
        [load_policy(path), load_policy("pursuit")],
        track="oval",
        seed=3,
        record=False,
        env_kwargs={"max_cycles": 30},
    )
    racer = next(c for c in result.cars if c.name == "racer")
    assert racer.dnf_reason not in ("error", "invalid")  # it produced valid actions throughout


# ---- stable-baselines3 zips -----------------------------------------------------------------


def test_sb3_zip_is_refused_without_trust(sb3_zip: Path) -> None:
    assert detect_format(sb3_zip) == "sb3"
    with pytest.raises(
        CheckpointError, match=r"stable-baselines3 zip.*unpickles.*slipstream export"
    ):
        load_policy(sb3_zip)


def test_malicious_sb3_zip_is_refused_without_running_it(sb3_zip: Path, tmp_path: Path) -> None:
    sentinel = tmp_path / "pwned"
    raw = members(sb3_zip)
    data = json.loads(raw["data"])
    # What SB3's json_to_data would cloudpickle.loads on PPO.load:
    data["evil"] = {":type:": "x", ":serialized:": base64.b64encode(payload(sentinel)).decode()}
    evil = write_zip(tmp_path / "evil_sb3.zip", {**raw, "data": json.dumps(data).encode()})
    with pytest.raises(CheckpointError, match="refused"):
        load_policy(evil)
    with pytest.raises(CheckpointError, match="trusted=True"):
        convert_sb3(evil, tmp_path / "out.zip")
    assert not sentinel.exists()
    assert not (tmp_path / "out.zip").exists()


def test_trusted_sb3_zip_warns_and_acts_like_the_model(sb3_zip: Path, model: Any) -> None:
    with pytest.warns(UntrustedCodeWarning, match="executes code"):
        policy = load_policy(sb3_zip, trusted=True)
    assert isinstance(policy, SB3Policy)
    assert policy.name == "sb3_model"
    _assert_same_actions(policy, model, n=20)
    with pytest.raises(CheckpointError, match="expects observation shape"):
        policy.act(np.zeros(7, dtype=np.float32))


def test_convert_sb3_makes_a_checkpoint_that_loads_untrusted(
    sb3_zip: Path, model: Any, tmp_path: Path
) -> None:
    with pytest.warns(UntrustedCodeWarning):
        out = convert_sb3(sb3_zip, tmp_path / "converted.zip", trusted=True)
    policy = load_policy(out)
    assert isinstance(policy, TorchMLPPolicy)
    assert policy.name == "sb3_model"
    _assert_same_actions(policy, model)


# ---- TorchScript ----------------------------------------------------------------------------


class _ClippedActor(torch.nn.Module):
    def __init__(self, body: torch.nn.Module, head: torch.nn.Module) -> None:
        super().__init__()
        self.body, self.head = body, head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.clamp(self.head(self.body(x)), -1.0, 1.0)


@pytest.fixture
def torchscript(ours: Path, tmp_path: Path) -> Path:
    """The checkpoint's actor as a TorchScript file (what a user might export themselves)."""
    net = TorchMLPPolicy.from_file(ours).net
    actor = _ClippedActor(net["mlp_extractor"]["policy_net"], net["action_net"])  # type: ignore[index]
    path = tmp_path / "actor.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit is deprecated
        torch.jit.script(actor).save(str(path))
    return path


def test_torchscript_is_refused_without_trust(torchscript: Path) -> None:
    assert detect_format(torchscript) == "torchscript"
    with pytest.raises(CheckpointError, match="TorchScript is a program"):
        load_policy(torchscript)


def test_trusted_torchscript_warns_and_acts_like_the_checkpoint(
    torchscript: Path, ours: Path, model: Any
) -> None:
    with pytest.warns(UntrustedCodeWarning, match="TorchScript"):
        policy = load_policy(torchscript, trusted=True)
    assert isinstance(policy, TorchScriptPolicy)
    reference = TorchMLPPolicy.from_file(ours)
    for o in fixed_observations(model.observation_space, n=20):
        got = policy.act(o)
        assert isinstance(got, np.ndarray) and got.dtype == np.float32
        np.testing.assert_array_equal(got, reference.act(o))
    with pytest.raises(CheckpointError, match="failed on an observation of shape"):
        policy.act(np.zeros(7, dtype=np.float32))


# ---- files that are nothing of ours ---------------------------------------------------------


def test_missing_directory_and_garbage_are_one_line_errors(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.zip"
    garbage.write_bytes(b"\x00\x01 not a policy" * 10)
    cases = {
        tmp_path / "missing.zip": "no such file",
        tmp_path: "is a directory",
        garbage: "not a policy file",
    }
    for path, message in cases.items():
        with pytest.raises(CheckpointError, match=message) as err:
            load_policy(path)
        assert "\n" not in str(err.value)


def test_bare_pickle_and_torch_save_files_are_never_unpickled(tmp_path: Path) -> None:
    sentinel = tmp_path / "pwned"
    bare = tmp_path / "policy.pkl"
    bare.write_bytes(payload(sentinel))
    with pytest.raises(CheckpointError, match="a pickle file"):
        load_policy(bare, trusted=True)
    saved = tmp_path / "policy.pt"
    buf = io.BytesIO()
    torch.save({"w": torch.zeros(2)}, buf)
    saved.write_bytes(buf.getvalue())
    with pytest.raises(CheckpointError, match=r"torch\.save archive"):
        load_policy(saved, trusted=True)
    assert not sentinel.exists()


def test_unknown_zip_goes_to_the_strict_reader(tmp_path: Path) -> None:
    path = tmp_path / "other.zip"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("readme.txt", "hi")
    with pytest.raises(CheckpointError, match=r"unexpected member\(s\) readme\.txt"):
        load_policy(path)


def test_import_agents_does_not_import_torch() -> None:
    code = (
        "import sys, agents; "
        "heavy = [m for m in ('torch', 'stable_baselines3', 'safetensors') if m in sys.modules]; "
        "print(heavy)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "[]"
