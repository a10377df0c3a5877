"""Slipstream checkpoints: SB3 export round trips exactly; hostile files fail clearly."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from agents import checkpoint as ckpt
from agents.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    MAX_SPACE_ELEMENTS,
    CheckpointError,
    CheckpointMeta,
    TorchMLPPolicy,
    export_sb3,
    read_checkpoint,
    save_checkpoint,
    space_from_json,
)
from agents.policy import Policy, PolicyError
from arena.version import ENV_VERSION
from tests.agents.models import (
    BOX_ACTIONS,
    DISCRETE_ACTIONS,
    fixed_observations,
    make_ppo,
    members,
    payload,
    with_checksum,
    write_zip,
)

CONFIGS: dict[str, tuple[spaces.Space[Any], dict[str, Any]]] = {
    "continuous": (BOX_ACTIONS, {}),
    "discrete": (DISCRETE_ACTIONS, {}),
    # gSDE + squash_output: the mean goes through tanh and is rescaled, not clipped.
    "sde-squash-relu": (
        BOX_ACTIONS,
        {
            "use_sde": True,
            "policy_kwargs": {
                "squash_output": True,
                "net_arch": {"pi": [32, 16], "vf": [8]},
                "activation_fn": torch.nn.ReLU,
            },
        },
    ),
    "linear-actor": (BOX_ACTIONS, {"policy_kwargs": {"net_arch": {"pi": [], "vf": [16]}}}),
}


@pytest.fixture(scope="module")
def model() -> Any:
    """The default continuous PPO MlpPolicy (tanh, [64, 64])."""
    return make_ppo(BOX_ACTIONS)


@pytest.fixture
def exported(model: Any, tmp_path: Path) -> Path:
    """``model`` exported to a checkpoint in a fresh directory."""
    return export_sb3(model, tmp_path / "policy.zip", name="tester", env_config={"track": "oval"})


# ---- round trips ----------------------------------------------------------------------------


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_export_read_gives_identical_actions(config: str, tmp_path: Path) -> None:
    action_space, kwargs = CONFIGS[config]
    model = make_ppo(action_space, **kwargs)
    path = export_sb3(model, tmp_path / "p.zip", name=config, env_config={})
    policy = TorchMLPPolicy(*read_checkpoint(path))
    assert isinstance(policy, Policy)
    obs = fixed_observations(model.observation_space)
    at_bound = 0
    for o in obs:
        want, _ = model.predict(o, deterministic=True)
        got = policy.act(o)
        if isinstance(action_space, spaces.Discrete):
            assert isinstance(got, int)
            assert got == int(want)
        else:
            assert isinstance(got, np.ndarray)
            assert got.dtype == np.float32
            assert got.shape == (2,)
            np.testing.assert_array_equal(got, want)  # bit for bit, not approximately
            at_bound += int(np.any(np.abs(got) >= 0.999))
    if isinstance(action_space, spaces.Box):
        assert at_bound > 10, "the jittered weights should push many actions to the bounds"
    want_batch, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(policy.act_batch(obs), want_batch)


def test_discrete_actions_are_not_all_the_same(tmp_path: Path) -> None:
    model = make_ppo(DISCRETE_ACTIONS)
    policy = TorchMLPPolicy.from_file(
        export_sb3(model, tmp_path / "d.zip", name="d", env_config={})
    )
    actions = {policy.act(o) for o in fixed_observations(model.observation_space)}
    assert len(actions) > 2


def test_value_head_matches_sb3(model: Any, tmp_path: Path) -> None:
    path = export_sb3(model, tmp_path / "v.zip", name="v", env_config={}, include_value=True)
    policy = TorchMLPPolicy.from_file(path)
    for o in fixed_observations(model.observation_space, n=20):
        want = model.policy.predict_values(torch.as_tensor(o[None])).item()
        assert policy.value(o) == want


def test_value_without_value_head_is_an_error(exported: Path, model: Any) -> None:
    policy = TorchMLPPolicy.from_file(exported)
    with pytest.raises(CheckpointError, match="no value head"):
        policy.value(fixed_observations(model.observation_space, n=1)[0])


def test_meta_records_spaces_architecture_and_provenance(model: Any, tmp_path: Path) -> None:
    path = export_sb3(
        model,
        tmp_path / "m.zip",
        name="fast-one",
        env_config={"track": "oval", "n_cars": 4, "lidar_rays": 64, "out": Path("x")},
        hyperparameters={"learning_rate": 1e-4, "note": "override"},
        training={"wall_time_s": 12.5, "tracks": ["oval"], "command": "slipstream train"},
    )
    meta, tensors = read_checkpoint(path)
    assert (meta.format, meta.version) == (CHECKPOINT_FORMAT, CHECKPOINT_VERSION)
    assert meta.name == "fast-one"
    assert meta.env_version == ENV_VERSION
    assert (meta.obs_mode, meta.action_mode, meta.algorithm) == ("vector", "continuous", "PPO")
    assert space_from_json(meta.observation_space) == model.observation_space
    assert space_from_json(meta.action_space) == model.action_space
    assert meta.policy.net_arch == [64, 64]
    assert meta.policy.activation == "tanh"
    assert meta.policy.output == "gaussian_mean"
    assert meta.policy.clip_actions and not meta.policy.squash_output
    assert meta.hyperparameters["n_steps"] == 64
    assert meta.hyperparameters["learning_rate"] == 1e-4  # the caller's value wins
    assert meta.hyperparameters["note"] == "override"
    assert meta.training["steps"] == model.num_timesteps
    assert meta.training["tracks"] == ["oval"]
    assert meta.env_config["out"] == "x"  # a Path is recorded as text
    assert {"python", "numpy", "torch", "stable-baselines3", "slipstream"} <= set(meta.packages)
    assert meta.packages["torch"] == torch.__version__
    assert datetime.fromisoformat(meta.created).tzinfo is not None
    raw = members(path)
    assert meta.weights_sha256 == hashlib.sha256(raw["weights.safetensors"]).hexdigest()
    assert sorted(raw) == ["meta.json", "weights.safetensors"]
    assert sorted(tensors) == sorted(
        [f"mlp_extractor.policy_net.{i}.{p}" for i in (0, 2) for p in ("weight", "bias")]
        + ["action_net.bias", "action_net.weight"]
    )


def test_save_checkpoint_refuses_tensors_that_do_not_match(exported: Path, tmp_path: Path) -> None:
    meta, tensors = read_checkpoint(exported)
    del tensors["action_net.bias"]
    with pytest.raises(CheckpointError, match=r"lack tensor\(s\) action_net\.bias"):
        save_checkpoint(tensors, meta, tmp_path / "bad.zip")
    assert [p.name for p in tmp_path.iterdir()] == ["policy.zip"]  # nothing written


def test_save_checkpoint_round_trips_torch_tensors(exported: Path, tmp_path: Path) -> None:
    meta, tensors = read_checkpoint(exported)
    as_torch = {k: torch.from_numpy(v) for k, v in tensors.items()}
    meta2, tensors2 = read_checkpoint(save_checkpoint(as_torch, meta, tmp_path / "again.zip"))
    assert meta2.weights_sha256 == meta.weights_sha256
    for name, value in tensors.items():
        np.testing.assert_array_equal(tensors2[name], value)


def test_export_refuses_action_mode_that_contradicts_the_model(model: Any, tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match=r"action_mode 'discrete'.*Box"):
        export_sb3(model, tmp_path / "x.zip", name="x", env_config={"action_mode": "discrete"})


def test_export_refuses_dict_observation_policies(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    from tests.agents.models import SpacesOnlyEnv

    obs = spaces.Dict({"a": spaces.Box(-1, 1, (3,), dtype=np.float32)})
    env = SpacesOnlyEnv(BOX_ACTIONS, obs)  # type: ignore[arg-type]
    model = PPO("MultiInputPolicy", env, n_steps=64, batch_size=32, device="cpu")
    with pytest.raises(CheckpointError, match="MlpPolicy"):
        export_sb3(model, tmp_path / "x.zip", name="x", env_config={})


# ---- the observation-shape check ------------------------------------------------------------


def test_wrong_sized_observation_is_a_clear_error(exported: Path) -> None:
    policy = TorchMLPPolicy.from_file(exported)
    n = policy.observation_shape[0]
    with pytest.raises(CheckpointError, match=rf"expects observation shape \({n},\), got \(90,\)"):
        policy.act(np.zeros(90, dtype=np.float32))
    with pytest.raises(CheckpointError, match="expects"):
        policy.act(np.zeros((1, n), dtype=np.float32))  # a batch is not one observation
    with pytest.raises(CheckpointError, match="batch"):
        policy.act_batch(np.zeros((4, n + 1), dtype=np.float32))
    assert issubclass(CheckpointError, PolicyError)


def test_other_env_version_warns(exported: Path, tmp_path: Path) -> None:
    raw = members(exported)
    doc = json.loads(raw["meta.json"])
    doc["env_version"] = "0.0-old"
    path = write_zip(tmp_path / "old.zip", {**raw, "meta.json": json.dumps(doc).encode()})
    with pytest.warns(UserWarning, match="env version 0.0-old"):
        TorchMLPPolicy.from_file(path)


# ---- tampering and corruption ---------------------------------------------------------------


def _flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1 :]


def test_flipped_weight_byte_fails_the_checksum(exported: Path, tmp_path: Path) -> None:
    raw = members(exported)
    weights = raw["weights.safetensors"]
    bad = write_zip(tmp_path / "t.zip", {**raw, "weights.safetensors": _flip(weights, -5)})
    recorded = json.loads(raw["meta.json"])["weights_sha256"]
    actual = hashlib.sha256(_flip(weights, -5)).hexdigest()
    # The whole message: where, both hashes' first 16 digits, and what it means.
    message = (
        f"{bad}: weights checksum mismatch: meta.json records sha256 {recorded[:16]}…, "
        f"weights.safetensors hashes to {actual[:16]}… (modified or corrupted)"
    )
    with pytest.raises(CheckpointError) as err:
        read_checkpoint(bad)
    assert str(err.value) == message
    # The same bytes given as an upload are labelled "checkpoint".
    with pytest.raises(CheckpointError) as err:
        read_checkpoint(bad.read_bytes())
    assert str(err.value) == message.replace(str(bad), "checkpoint")


def test_every_refusal_names_the_file(exported: Path, tmp_path: Path) -> None:
    """A refused file's message starts with its path: at the archive, meta.json and weights."""
    raw = members(exported)
    cases = {
        "garbage.zip": b"not a zip at all",
        "meta.zip": write_zip(tmp_path / "m", {**raw, "meta.json": b"{"}).read_bytes(),
        "tensors.zip": write_zip(
            tmp_path / "w",
            {
                "meta.json": with_checksum(raw["meta.json"], b"\x00" * 64),
                "weights.safetensors": b"\x00" * 64,
            },
        ).read_bytes(),
    }
    for name, data in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(CheckpointError) as err:
            read_checkpoint(path)
        assert str(err.value).startswith(f"{path}: "), str(err.value)


def test_weights_come_back_as_float32(exported: Path) -> None:
    _, tensors = read_checkpoint(exported)
    assert tensors and all(t.dtype == np.float32 and t.flags.c_contiguous for t in tensors.values())


def test_flipped_byte_in_the_archive_is_reported_corrupt(exported: Path, tmp_path: Path) -> None:
    data = exported.read_bytes()
    with zipfile.ZipFile(exported) as zf:
        info = zf.getinfo("weights.safetensors")
    at = info.header_offset + 30 + len(info.filename) + info.compress_size // 2  # mid-member
    bad = tmp_path / "flipped.zip"
    bad.write_bytes(_flip(data, at))
    with pytest.raises(CheckpointError, match=r"weights\.safetensors is corrupt.*CRC"):
        read_checkpoint(bad)


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def edit(doc: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        for key in parents:
            doc = doc[key]
        doc[last] = value

    return edit


def _both(
    first: Callable[[dict[str, Any]], None], second: Callable[[dict[str, Any]], None]
) -> Callable[[dict[str, Any]], None]:
    def edit(doc: dict[str, Any]) -> None:
        first(doc)
        second(doc)

    return edit


def _obs_shape_90(doc: dict[str, Any]) -> None:
    space = doc["observation_space"]
    space["shape"] = [90]
    space["low"], space["high"] = space["low"][:90], space["high"][:90]


def _only_format(doc: dict[str, Any]) -> None:
    doc.clear()
    doc["format"] = CHECKPOINT_FORMAT


META_TAMPERING: dict[str, tuple[Callable[[dict[str, Any]], None], str]] = {
    "unknown format": (_set("format", "sb3"), "not a Slipstream policy checkpoint.*'sb3'"),
    "newer version": (_set("version", 2), "version 2 is newer.*up to 1"),
    "wrong observation shape": (
        _obs_shape_90,
        r"tensor mlp_extractor\.policy_net\.0\.weight has shape \(64, \d+\).*needs \(64, 90\)",
    ),
    "bounds do not fit the shape": (_set("observation_space.shape", [7]), "low/high need 7"),
    "action width": (_set("action_space.shape", [3]), "low/high need 3"),
    "negative layer width": (_set("policy.net_arch", [-3]), "at policy/net_arch/0"),
    "unknown activation": (_set("policy.activation", "swish9"), "at policy/activation"),
    "missing field": (lambda d: d.pop("name"), "'name' is a required property"),
    "extra field": (_set("evil", 1), "'evil' was unexpected"),
    "bad checksum text": (_set("weights_sha256", "xyz"), "at weights_sha256"),
    "mode contradicts space": (_set("action_mode", "discrete"), "needs a Discrete action_space"),
    "only a format": (_only_format, r"at top level: '\w+' is a required property"),
    # Cross-field rules (_check_consistency): each refusal's whole message, so a changed or
    # lost message is a failure too.
    "2-D action space": (
        _set("action_space.shape", [1, 2]),
        r"meta\.json: a Box action_space must be one-dimensional$",
    ),
    "squashed infinite actions": (
        _both(_set("policy.squash_output", True), _set("action_space.low", ["-inf", -1.0])),
        r"meta\.json: squash_output needs finite action bounds$",
    ),
    "space over the cap": (  # each axis within the schema's limit, their product not
        _set("observation_space.shape", [257, MAX_SPACE_ELEMENTS // 256]),
        rf"meta\.json observation_space has {257 * (MAX_SPACE_ELEMENTS // 256)} elements, "
        "over the cap$",
    ),
    "space at the cap is only short of bounds": (
        _set("observation_space.shape", [MAX_SPACE_ELEMENTS]),
        rf"low/high need {MAX_SPACE_ELEMENTS} values",
    ),
    "one bound list short": (
        lambda d: d["action_space"]["high"].pop(),
        r"meta\.json action_space: low/high need 2 values for shape \(2,\), got 2/1$",
    ),
    "low above high": (
        _set("action_space.low", [-1.0, 1.5]),
        r"meta\.json action_space: a low bound exceeds its high bound$",
    ),
    "discrete observations": (
        _set("observation_space", {"type": "Discrete", "n": 4}),
        r"meta\.json observation_space must be a Box for an MLP policy$",
    ),
    "continuous mode, categorical output": (
        _set("policy.output", "categorical_argmax"),
        r"meta\.json: action_mode 'continuous' needs a Box action_space and output "
        r"'gaussian_mean', got Box and 'categorical_argmax'$",
    ),
    "discrete mode, gaussian output": (
        _both(
            _set("action_mode", "discrete"),
            _set("action_space", {"type": "Discrete", "n": 5}),
        ),
        r"meta\.json: action_mode 'discrete' needs a Discrete action_space and output "
        r"'categorical_argmax', got Discrete and 'gaussian_mean'$",
    ),
}


def test_equal_bounds_are_allowed(exported: Path, tmp_path: Path) -> None:
    # A low bound equal to its high bound is a fixed value, not an error.
    raw = members(exported)
    doc = json.loads(raw["meta.json"])
    doc["action_space"]["low"][0] = doc["action_space"]["high"][0]
    path = write_zip(tmp_path / "t.zip", {**raw, "meta.json": json.dumps(doc).encode()})
    meta, _ = read_checkpoint(path)
    assert meta.action_space["low"][0] == meta.action_space["high"][0]


@pytest.mark.parametrize("case", sorted(META_TAMPERING))
def test_tampered_meta_is_a_clear_error(case: str, exported: Path, tmp_path: Path) -> None:
    edit, message = META_TAMPERING[case]
    raw = members(exported)
    doc = json.loads(raw["meta.json"])
    edit(doc)
    path = write_zip(tmp_path / "t.zip", {**raw, "meta.json": json.dumps(doc).encode()})
    with pytest.raises(CheckpointError, match=message) as err:
        read_checkpoint(path)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (b"{not json", "meta.json is not valid JSON"),
        (b'{"format": NaN}', "meta.json is not valid JSON.*NaN"),
        (b"\xff\xfe", "meta.json is not valid JSON"),
        (b"[1, 2]", "must be a JSON object"),
        (b"[" * 100_000, "meta.json is not valid JSON.*recursion"),
    ],
)
def test_meta_that_is_not_json_is_a_clear_error(
    text: bytes, message: str, exported: Path, tmp_path: Path
) -> None:
    path = write_zip(tmp_path / "t.zip", {**members(exported), "meta.json": text})
    with pytest.raises(CheckpointError, match=message):
        read_checkpoint(path)


def test_zip_with_path_traversal_member_is_refused(exported: Path, tmp_path: Path) -> None:
    raw = members(exported)
    for name in ("../meta.json", "/etc/meta.json", "a/../../x", "C:\\x", "dir/"):
        path = write_zip(tmp_path / "t.zip", [*raw.items(), (name, b"x")])
        with pytest.raises(CheckpointError, match="unsafe path"):
            read_checkpoint(path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("extra", r"unexpected member\(s\) notes\.txt"),
        ("missing", r"missing weights\.safetensors"),
        ("duplicate", r"duplicate member\(s\) meta\.json"),
        ("many", "zip has 40 members"),
    ],
)
def test_zip_members_must_be_exactly_ours(
    change: str, message: str, exported: Path, tmp_path: Path
) -> None:
    raw = members(exported)
    items = list(raw.items())
    if change == "extra":
        items.append(("notes.txt", b"hello"))
    elif change == "missing":
        items = [("meta.json", raw["meta.json"])]
    elif change == "duplicate":
        items.append(("meta.json", raw["meta.json"]))
    else:
        items += [(f"f{i}", b"") for i in range(38)]
    path = tmp_path / "t.zip"
    with pytest.warns(UserWarning, match="Duplicate") if change == "duplicate" else _nothing():
        write_zip(path, items)
    with pytest.raises(CheckpointError, match=message):
        read_checkpoint(path)


class _nothing:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *args: object) -> None:
        return None


def test_zip_bomb_member_is_refused_by_its_ratio(exported: Path, tmp_path: Path) -> None:
    raw = members(exported)
    bomb = b"\0" * (8 << 20)  # 8 MiB of zeros deflate ~1000:1
    path = write_zip(tmp_path / "bomb.zip", {**raw, "weights.safetensors": bomb})
    with pytest.raises(CheckpointError, match=r"compresses \d+:1 \(a zip bomb\?\)"):
        read_checkpoint(path)


def test_member_over_its_size_cap_is_refused(
    exported: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ckpt, "MAX_WEIGHTS_BYTES", 1000)
    with pytest.raises(CheckpointError, match=r"weights\.safetensors is \d+ bytes .*over the 1000"):
        read_checkpoint(exported)
    monkeypatch.setattr(ckpt, "MAX_FILE_BYTES", 100)
    with pytest.raises(CheckpointError, match="over the 100-byte cap"):
        read_checkpoint(exported)


def test_member_whose_header_understates_its_size_is_caught(
    exported: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The per-member read is bounded whatever the header says: lie about the size.
    data = bytearray(exported.read_bytes())
    with zipfile.ZipFile(exported) as zf:
        info = zf.getinfo("meta.json")
        cd_offset = zf.start_dir
    central = data.find(b"PK\x01\x02meta.json"[:4], cd_offset)
    data[central + 24 : central + 28] = (10).to_bytes(4, "little")  # uncompressed size: 10
    path = tmp_path / "liar.zip"
    path.write_bytes(bytes(data))
    assert info.file_size > 10
    with pytest.raises(CheckpointError, match=r"member meta.json is corrupt"):
        read_checkpoint(path)


@pytest.mark.parametrize("kind", ["garbage", "empty", "truncated", "cut tail"])
def test_not_a_zip_or_truncated_is_a_clear_error(kind: str, exported: Path, tmp_path: Path) -> None:
    data = exported.read_bytes()
    content = {
        "garbage": bytes(range(256)) * 10,
        "empty": b"",
        "truncated": data[: len(data) // 2],
        "cut tail": data[:-10],
    }[kind]
    path = tmp_path / "bad.zip"
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match="not a valid zip archive"):
        read_checkpoint(path)
    with pytest.raises(CheckpointError, match="not a valid zip archive"):
        read_checkpoint(content)  # the same check on bytes (an upload)


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="no such file"):
        read_checkpoint(tmp_path / "nope.zip")
    with pytest.raises(CheckpointError, match="not a file"):
        read_checkpoint(tmp_path)


def _retensor(exported: Path, tmp_path: Path, edit: Callable[[dict[str, Any]], None]) -> Path:
    """A checkpoint whose tensors were edited and whose checksum was re-signed to match."""
    from safetensors.numpy import save

    raw = members(exported)
    _, tensors = read_checkpoint(exported)
    edit(tensors)
    weights = save(tensors)
    meta = with_checksum(raw["meta.json"], weights)
    return write_zip(tmp_path / "t.zip", {"meta.json": meta, "weights.safetensors": weights})


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", r"lack tensor\(s\) action_net\.weight"),
        ("wrong shape", r"tensor action_net\.weight has shape \(3, 64\).*needs \(2, 64\)"),
        # Same number of elements, other shape: a size check alone would let it through.
        ("transposed", r"tensor action_net\.weight has shape \(64, 2\).*needs \(2, 64\)"),
        ("extra", r"unexpected tensor\(s\) log_std"),
        ("float64", r"tensor action_net\.bias is float64, expected float32"),
        ("nan", r"tensor action_net\.bias holds NaN"),
    ],
)
def test_wrong_tensors_are_a_clear_error(
    case: str, message: str, exported: Path, tmp_path: Path
) -> None:
    def edit(t: dict[str, Any]) -> None:
        if case == "missing":
            del t["action_net.weight"]
        elif case == "wrong shape":
            t["action_net.weight"] = np.zeros((3, 64), dtype=np.float32)
        elif case == "transposed":
            t["action_net.weight"] = np.ascontiguousarray(t["action_net.weight"].T)
        elif case == "extra":
            t["log_std"] = np.zeros(2, dtype=np.float32)
        elif case == "float64":
            t["action_net.bias"] = t["action_net.bias"].astype(np.float64)
        else:
            t["action_net.bias"] = np.array([np.nan, 0.0], dtype=np.float32)

    with pytest.raises(CheckpointError, match=message):
        read_checkpoint(_retensor(exported, tmp_path, edit))


def test_garbage_weights_with_a_valid_checksum_are_refused(exported: Path, tmp_path: Path) -> None:
    raw = members(exported)
    for garbage in (b"\x08\x00\x00\x00\x00\x00\x00\x00{garbage", b"", b"\xff" * 64):
        meta = with_checksum(raw["meta.json"], garbage)
        path = write_zip(tmp_path / "g.zip", {"meta.json": meta, "weights.safetensors": garbage})
        with pytest.raises(CheckpointError, match="not a valid safetensors file"):
            read_checkpoint(path)


def test_pickle_named_weights_is_refused_without_unpickling(exported: Path, tmp_path: Path) -> None:
    sentinel = tmp_path / "pwned"
    evil = payload(sentinel)
    raw = members(exported)
    meta = with_checksum(raw["meta.json"], evil)
    path = write_zip(tmp_path / "evil.zip", {"meta.json": meta, "weights.safetensors": evil})
    with pytest.raises(CheckpointError, match="holds a pickle, not safetensors"):
        read_checkpoint(path)
    with pytest.raises(CheckpointError, match="holds a pickle"):
        TorchMLPPolicy.from_file(path)
    # a torch.save archive under the same name is named and refused as well
    buf = io.BytesIO()
    torch.save({"action_net.weight": torch.zeros(2, 64)}, buf)
    meta = with_checksum(raw["meta.json"], buf.getvalue())
    path = write_zip(
        tmp_path / "ts.zip", {"meta.json": meta, "weights.safetensors": buf.getvalue()}
    )
    with pytest.raises(CheckpointError, match=r"torch.save"):
        read_checkpoint(path)
    assert not sentinel.exists()


def test_meta_dict_round_trip_and_schema_errors_are_one_line() -> None:
    meta = CheckpointMeta(
        name="n",
        env_version=ENV_VERSION,
        obs_mode="vector",
        action_mode="discrete",
        observation_space=ckpt.space_to_json(spaces.Box(-1, 1, (3,), dtype=np.float32)),
        action_space=ckpt.space_to_json(spaces.Discrete(4)),
        algorithm="PPO",
        policy=ckpt.PolicyArchitecture(
            net_arch=[5], activation="relu", output="categorical_argmax", clip_actions=False
        ),
    )
    doc = json.loads(json.dumps(meta.to_dict()))
    assert CheckpointMeta.from_dict(doc) == meta
    assert ckpt.expected_tensors(meta) == {
        "mlp_extractor.policy_net.0.weight": (5, 3),
        "mlp_extractor.policy_net.0.bias": (5,),
        "action_net.weight": (4, 5),
        "action_net.bias": (4,),
    }
    doc["observation_space"]["low"] = ["-inf"] * 3
    assert np.all(np.isinf(space_from_json(doc["observation_space"]).low))  # type: ignore[union-attr]
    doc["policy"]["net_arch"] = [5] * 100
    with pytest.raises(CheckpointError, match=r"policy/net_arch: .* is too long") as err:
        CheckpointMeta.from_dict(doc)
    assert "\n" not in str(err.value) and len(str(err.value)) < 250
