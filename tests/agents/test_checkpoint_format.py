"""The checkpoint file itself: exact bytes written, exact boundaries and messages on reading.

Companion to ``test_checkpoint.py`` (SB3 round trips, tampering). These pin what a reader of
the file format can rely on — the ``meta.json`` layout, the zip's members, timestamps,
compression and permissions, the atomic write — and each limit at its boundary (member count,
member and file size caps, the zip-bomb ratio), with the whole refusal message. Hostile
archives are shaped as an attacker who read ``agents/checkpoint.py`` would build them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import pickle
import sys
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from agents import checkpoint as ckpt
from agents.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    PolicyArchitecture,
    read_checkpoint,
    save_checkpoint,
    space_from_json,
    space_to_json,
)
from arena.version import ENV_VERSION
from tests.agents.models import members, with_checksum, write_zip

CREATED = "2026-01-01T00:00:00+00:00"


def _meta(**changes: Any) -> CheckpointMeta:
    """A small discrete policy's metadata: 2 observations, one hidden layer of 2, 3 actions."""
    meta = CheckpointMeta(
        name="golden",
        env_version=ENV_VERSION,
        obs_mode="vector",
        action_mode="discrete",
        observation_space=space_to_json(
            spaces.Box(
                np.array([-1.0, -np.inf], np.float32),
                np.array([1.0, np.inf], np.float32),
                dtype=np.float32,
            )
        ),
        action_space=space_to_json(spaces.Discrete(3)),
        algorithm="PPO",
        policy=PolicyArchitecture(
            net_arch=[2], activation="tanh", output="categorical_argmax", clip_actions=False
        ),
        hyperparameters={"schedule": [[0, 0.001], [1, 0.0001]], "net_arch": [{"pi": [4]}]},
        training={"steps": 10, "none": [], "empty": {}},
        packages={"python": "3.11.0"},
        created=CREATED,
    )
    return dataclasses.replace(meta, **changes)


def _tensors(meta: CheckpointMeta) -> dict[str, np.ndarray]:
    """Distinct float32 values of the shapes ``meta`` declares."""
    out = {}
    for i, (name, shape) in enumerate(sorted(ckpt.expected_tensors(meta).items())):
        out[name] = (np.arange(math.prod(shape), dtype=np.float32) / 7 + i).reshape(shape)
    return out


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    meta = _meta()
    return save_checkpoint(_tensors(meta), meta, tmp_path / "p.zip")


def _message(source: Path | bytes) -> str:
    with pytest.raises(CheckpointError) as err:
        read_checkpoint(source)
    return str(err.value)


# ---- writing ----------------------------------------------------------------------------------


def test_meta_json_layout(saved: Path) -> None:
    """Objects indented by two, lists of numbers on one line, lists of lists or objects one
    item per line, ±inf bounds as strings, strict JSON, a final newline (the module docstring's
    format; golden text written by hand)."""
    raw = members(saved)
    digest = hashlib.sha256(raw["weights.safetensors"]).hexdigest()
    assert raw["meta.json"].decode() == (
        "{\n"
        '  "name": "golden",\n'
        f'  "env_version": "{ENV_VERSION}",\n'
        '  "obs_mode": "vector",\n'
        '  "action_mode": "discrete",\n'
        '  "observation_space": {\n'
        '    "type": "Box",\n'
        '    "shape": [2],\n'
        '    "dtype": "float32",\n'
        '    "low": [-1.0, "-inf"],\n'
        '    "high": [1.0, "inf"]\n'
        "  },\n"
        '  "action_space": {\n'
        '    "type": "Discrete",\n'
        '    "n": 3\n'
        "  },\n"
        '  "algorithm": "PPO",\n'
        '  "policy": {\n'
        '    "net_arch": [2],\n'
        '    "activation": "tanh",\n'
        '    "output": "categorical_argmax",\n'
        '    "squash_output": false,\n'
        '    "clip_actions": false,\n'
        '    "value_net_arch": null,\n'
        '    "kind": "mlp"\n'
        "  },\n"
        '  "hyperparameters": {\n'
        '    "schedule": [\n'
        "      [0, 0.001],\n"
        "      [1, 0.0001]\n"
        "    ],\n"
        '    "net_arch": [\n'
        "      {\n"
        '        "pi": [4]\n'
        "      }\n"
        "    ]\n"
        "  },\n"
        '  "training": {\n'
        '    "steps": 10,\n'
        '    "none": [],\n'
        '    "empty": {}\n'
        "  },\n"
        '  "env_config": {},\n'
        '  "packages": {\n'
        '    "python": "3.11.0"\n'
        "  },\n"
        f'  "created": "{CREATED}",\n'
        f'  "weights_sha256": "{digest}",\n'
        '  "format": "slipstream-policy",\n'
        '  "version": 1\n'
        "}\n"
    )


def test_zip_layout_is_reproducible(saved: Path, tmp_path: Path) -> None:
    """meta.json deflated then the weights stored, both dated 1980-01-01, readable by all;
    saving the same policy again gives the same bytes (only ``created`` would differ)."""
    with zipfile.ZipFile(saved) as zf:
        infos = [(i.filename, i.date_time, i.compress_type) for i in zf.infolist()]
    assert infos == [
        ("meta.json", (1980, 1, 1, 0, 0, 0), zipfile.ZIP_DEFLATED),
        ("weights.safetensors", (1980, 1, 1, 0, 0, 0), zipfile.ZIP_STORED),
    ]
    assert saved.stat().st_mode & 0o777 == 0o644
    meta = _meta()
    again = save_checkpoint(_tensors(meta), meta, tmp_path / "again.zip")
    assert again.read_bytes() == saved.read_bytes()


def test_parent_directories_are_created(tmp_path: Path) -> None:
    meta = _meta()
    path = save_checkpoint(_tensors(meta), meta, tmp_path / "runs" / "a" / "p.zip")
    assert read_checkpoint(path)[0] == dataclasses.replace(
        meta, weights_sha256=read_checkpoint(path)[0].weights_sha256
    )


def test_write_is_atomic_beside_the_destination(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The zip is written to a hidden temporary file in the destination's directory (so the
    rename is atomic and a ``*.zip`` glob never sees half a file), then renamed; a failed
    rename leaves nothing behind and raises its own error."""
    meta, seen = _meta(), []
    real = os.replace

    def spy(src: str, dst: str) -> None:
        seen.append((Path(src), sorted(p.name for p in tmp_path.iterdir())))
        real(src, dst)

    monkeypatch.setattr(os, "replace", spy)
    save_checkpoint(_tensors(meta), meta, tmp_path / "p.zip")
    [(tmp, listed)] = seen
    assert tmp.parent == tmp_path and tmp.name.startswith(".p.zip.")
    assert listed == [tmp.name]
    assert not list(tmp_path.glob("*.zip.*")) and not tmp.exists()

    def broken(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(_tensors(meta), meta, tmp_path / "q.zip")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.zip"]


def test_weights_cap_on_writing_is_inclusive(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    meta = _meta()
    size = len(
        members(save_checkpoint(_tensors(meta), meta, tmp_path / "p.zip"))[ckpt.WEIGHTS_MEMBER]
    )
    monkeypatch.setattr(ckpt, "MAX_WEIGHTS_BYTES", size)
    read_checkpoint(save_checkpoint(_tensors(meta), meta, tmp_path / "at.zip"))  # at the cap
    monkeypatch.setattr(ckpt, "MAX_WEIGHTS_BYTES", size - 1)
    with pytest.raises(CheckpointError) as err:
        save_checkpoint(_tensors(meta), meta, tmp_path / "over.zip")
    assert str(err.value) == f"weights are {size} bytes, over the {size - 1}-byte cap"
    assert not (tmp_path / "over.zip").exists()


def test_parameters_that_require_grad_are_saved(tmp_path: Path) -> None:
    """``dict(module.named_parameters())`` (tensors that require grad) saves like a state_dict."""
    meta = _meta()
    params = {k: torch.nn.Parameter(torch.from_numpy(v)) for k, v in _tensors(meta).items()}
    assert all(p.requires_grad for p in params.values())
    _, tensors = read_checkpoint(save_checkpoint(params, meta, tmp_path / "p.zip"))
    for name, value in _tensors(meta).items():
        np.testing.assert_array_equal(tensors[name], value)


def test_metadata_that_is_not_plain_json_is_refused(tmp_path: Path) -> None:
    """A NaN in the hyperparameters would make meta.json unreadable by strict JSON parsers."""
    meta = _meta(hyperparameters={"lr": float("nan")})
    with pytest.raises(CheckpointError) as err:
        save_checkpoint(_tensors(meta), meta, tmp_path / "p.zip")
    assert str(err.value) == (
        "checkpoint metadata is not plain JSON: Out of range float values are not JSON compliant"
    )
    assert not list(tmp_path.iterdir())


def test_missing_safetensors_is_named_with_the_extra(
    saved: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "safetensors.numpy", None)  # as if not installed
    message = "reading or writing checkpoints needs safetensors: pip install 'slipstream[train]'"
    meta = _meta()
    with pytest.raises(CheckpointError) as err:
        save_checkpoint(_tensors(meta), meta, tmp_path / "q.zip")
    assert str(err.value) == message
    assert _message(saved) == message


def test_tensor_refusals_list_every_name(saved: Path) -> None:
    meta, tensors = read_checkpoint(saved)
    fewer = {k: v for k, v in tensors.items() if not k.startswith("action_net.")}
    with pytest.raises(CheckpointError) as err:
        ckpt.check_tensors(meta, fewer)
    assert str(err.value) == "weights lack tensor(s) action_net.bias, action_net.weight"
    more = {
        **tensors,
        "log_std": np.zeros(3, np.float32),
        "value_net.bias": np.zeros(1, np.float32),
    }
    with pytest.raises(CheckpointError) as err:
        ckpt.check_tensors(meta, more)
    assert str(err.value) == (
        "weights hold unexpected tensor(s) log_std, value_net.bias for the declared architecture"
    )


# ---- spaces -----------------------------------------------------------------------------------


def test_spaces_round_trip_exactly() -> None:
    """A 2-D float64 Box (the schema allows up to 4 axes) keeps its shape, dtype and bounds."""
    box = spaces.Box(
        np.array([[-1.5, -np.inf, 0.0], [2.0, 3.0, -4.0]]),
        np.array([[1.5, 0.0, np.inf], [2.5, 3.25, 4.0]]),
        dtype=np.float64,
    )
    doc = space_to_json(box)
    assert doc == {
        "type": "Box",
        "shape": [2, 3],
        "dtype": "float64",
        "low": [-1.5, "-inf", 0.0, 2.0, 3.0, -4.0],
        "high": [1.5, 0.0, "inf", 2.5, 3.25, 4.0],
    }
    back = space_from_json(json.loads(json.dumps(doc)))
    assert back == box
    assert isinstance(back, spaces.Box) and back.dtype == np.float64
    assert space_from_json(space_to_json(spaces.Discrete(7))) == spaces.Discrete(7)


def test_float32_spaces_read_back_without_precision_warnings() -> None:
    """Bounds are built in the space's dtype (gymnasium warns when float64 bounds are cast)."""
    box = spaces.Box(np.float32(-0.1), np.float32(0.3), (3,), dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = space_from_json(space_to_json(box))
    assert back == box


def test_spaces_checkpoints_cannot_hold_are_refused() -> None:
    with pytest.raises(CheckpointError) as err:
        space_to_json(spaces.Discrete(3, start=1))
    assert str(err.value) == "Discrete spaces must start at 0, got start=1"
    with pytest.raises(CheckpointError) as err:
        space_to_json(spaces.MultiDiscrete([3, 3]))
    assert str(err.value) == "checkpoints support Box and Discrete spaces, not MultiDiscrete"


# ---- reading: the archive -------------------------------------------------------------------


def test_file_and_member_caps_are_inclusive(saved: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A file or member exactly at its cap is read; one byte over is refused by name."""
    raw = members(saved)
    meta_size, weights_size = len(raw["meta.json"]), len(raw["weights.safetensors"])
    file_size = saved.stat().st_size
    monkeypatch.setattr(ckpt, "MAX_META_BYTES", meta_size)
    monkeypatch.setattr(ckpt, "MAX_WEIGHTS_BYTES", weights_size)
    monkeypatch.setattr(ckpt, "MAX_FILE_BYTES", file_size)
    assert read_checkpoint(saved)[0].name == "golden"
    monkeypatch.setattr(ckpt, "MAX_META_BYTES", meta_size - 1)
    assert _message(saved) == (
        f"{saved}: member meta.json is {meta_size} bytes uncompressed, over the "
        f"{meta_size - 1}-byte cap"
    )
    monkeypatch.setattr(ckpt, "MAX_FILE_BYTES", file_size - 1)
    assert _message(saved) == f"{saved}: {file_size} bytes, over the {file_size - 1}-byte cap"


def test_member_reads_stop_at_the_cap(saved: Path) -> None:
    """However large the member, at most cap + 1 bytes are read and then it is refused."""
    with zipfile.ZipFile(saved) as zf:
        info = zf.getinfo("meta.json")
        with pytest.raises(CheckpointError) as err:
            ckpt._read_member(zf, info, 10, "upload")
        assert str(err.value) == "upload: member meta.json exceeds the 10-byte cap"
        assert ckpt._read_member(zf, info, info.file_size, "upload") == zf.read("meta.json")


def test_member_count_boundary(saved: Path, tmp_path: Path) -> None:
    """Up to 16 members are looked at by name; 17 are refused by count alone."""
    raw = members(saved)
    extra = [(f"f{i:02d}", b"") for i in range(15)]
    path = write_zip(tmp_path / "t.zip", [*raw.items(), *extra[:14]])
    assert _message(path) == (
        f"{path}: unexpected member(s) {', '.join(n for n, _ in extra[:14])}; a checkpoint "
        "holds only meta.json and weights.safetensors"
    )
    path = write_zip(tmp_path / "t.zip", [*raw.items(), *extra])
    assert _message(path) == f"{path}: zip has 17 members; a checkpoint has 2"


def test_duplicate_and_missing_members_are_all_named(saved: Path, tmp_path: Path) -> None:
    raw = members(saved)
    path = tmp_path / "t.zip"
    with pytest.warns(UserWarning, match="Duplicate name"):
        write_zip(path, [*raw.items(), *raw.items()])
    assert _message(path) == f"{path}: duplicate member(s) meta.json, weights.safetensors"
    write_zip(path, [])
    assert _message(path) == f"{path}: missing meta.json, weights.safetensors"


@pytest.mark.parametrize("name", ["C:meta.json", "dir\\meta.json", "a//meta.json", "../x"])
def test_unsafe_member_names_are_refused(name: str, saved: Path, tmp_path: Path) -> None:
    """Drive letters, backslashes (Windows separators) and empty path parts, as in a
    zip-slip archive (Snyk's "Zip Slip" write-up): each refused before anything is read."""
    path = write_zip(tmp_path / "t.zip", [*members(saved).items(), (name, b"x")])
    assert _message(path) == (
        f"{path}: member {name!r} has an unsafe path (absolute, '..' or a directory); "
        "refusing the archive"
    )


def _set_central_field(data: bytes, name: bytes, offset: int, value: int, size: int) -> bytes:
    """``data`` with a field of ``name``'s central-directory entry set (APPNOTE 4.3.12)."""
    at = data.rfind(b"PK\x01\x02", 0, data.rfind(name))
    out = bytearray(data)
    out[at + offset : at + offset + size] = value.to_bytes(size, "little")
    return bytes(out)


def test_encrypted_member_is_refused(saved: Path, tmp_path: Path) -> None:
    """General-purpose flag bit 0 set (traditional PKWARE encryption)."""
    data = _set_central_field(saved.read_bytes(), b"meta.json", 8, 0x1, 2)
    path = tmp_path / "enc.zip"
    path.write_bytes(data)
    assert _message(path) == f"{path}: member meta.json is encrypted"


def test_other_compression_methods_are_refused(saved: Path, tmp_path: Path) -> None:
    path = tmp_path / "bz.zip"
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members(saved).items():
            zf.writestr(name, data, compress_type=zipfile.ZIP_BZIP2)
    assert _message(path) == (
        f"{path}: member meta.json uses compression method 12; only stored or deflated "
        "members are read"
    )


def _zeros_zip(path: Path, saved: Path, n: int) -> Path:
    """``saved``'s meta.json re-signed for ``n`` zero bytes of weights (deflate ~1000:1)."""
    zeros = b"\0" * n
    meta = with_checksum(members(saved)["meta.json"], zeros)
    return write_zip(path, {"meta.json": meta, "weights.safetensors": zeros})


def test_zip_bomb_ratio_applies_only_above_one_mebibyte(saved: Path, tmp_path: Path) -> None:
    """1 MiB of zeros is only bad safetensors; one byte more is refused as a bomb."""
    at = _zeros_zip(tmp_path / "at.zip", saved, ckpt.RATIO_MIN_BYTES)
    assert "is not a valid safetensors file" in _message(at)
    over = _zeros_zip(tmp_path / "over.zip", saved, ckpt.RATIO_MIN_BYTES + 1)
    with zipfile.ZipFile(over) as zf:
        info = zf.getinfo("weights.safetensors")
    ratio = info.file_size / info.compress_size
    assert _message(over) == (
        f"{over}: member weights.safetensors compresses {ratio:.0f}:1 (a zip bomb?); refusing"
    )


def test_zip_bomb_ratio_of_exactly_100_is_allowed(saved: Path, tmp_path: Path) -> None:
    """The central directory's compressed size set so the ratio is exactly 100, then 100.005."""
    n = 2_000_000
    data = _zeros_zip(tmp_path / "z.zip", saved, n).read_bytes()
    exact = tmp_path / "exact.zip"
    exact.write_bytes(_set_central_field(data, b"weights.safetensors", 20, n // 100, 4))
    assert "is not a valid safetensors file" in _message(exact)
    over = tmp_path / "over.zip"
    over.write_bytes(_set_central_field(data, b"weights.safetensors", 20, n // 100 - 1, 4))
    assert _message(over) == (
        f"{over}: member weights.safetensors compresses 100:1 (a zip bomb?); refusing"
    )
    # A header claiming 0 or 1 compressed bytes: the ratio is taken against 1 byte.
    for claimed in (0, 1):
        over.write_bytes(_set_central_field(data, b"weights.safetensors", 20, claimed, 4))
        assert _message(over) == (
            f"{over}: member weights.safetensors compresses {n}:1 (a zip bomb?); refusing"
        )


def test_real_weights_over_one_mebibyte_are_read(tmp_path: Path) -> None:
    """A [512, 512] actor on a 95-float observation (1.2 MB, barely compressible) reads back."""
    obs = spaces.Box(-1.0, 1.0, (95,), dtype=np.float32)
    meta = _meta(
        observation_space=space_to_json(obs),
        policy=PolicyArchitecture(
            net_arch=[512, 512], activation="relu", output="categorical_argmax", clip_actions=False
        ),
    )
    rng = np.random.default_rng(0)
    tensors = {
        name: rng.standard_normal(shape).astype(np.float32)
        for name, shape in ckpt.expected_tensors(meta).items()
    }
    path = save_checkpoint(tensors, meta, tmp_path / "big.zip")
    assert len(members(path)["weights.safetensors"]) > ckpt.RATIO_MIN_BYTES
    _, back = read_checkpoint(path)
    for name, value in tensors.items():
        np.testing.assert_array_equal(back[name], value)


def test_archive_and_member_errors_carry_the_label(saved: Path, tmp_path: Path) -> None:
    """Whole messages for a file that is no zip and for corrupt members, path first."""
    path = tmp_path / "garbage.zip"
    path.write_bytes(b"not a zip at all")
    assert _message(path) == (
        f"{path}: not a valid zip archive (corrupt or truncated): File is not a zip file"
    )
    data = bytearray(saved.read_bytes())
    with zipfile.ZipFile(saved) as zf:
        info = zf.getinfo("weights.safetensors")
    at = info.header_offset + 30 + len(info.filename) + 3
    data[at] ^= 0xFF
    path.write_bytes(bytes(data))
    assert _message(path) == (
        f"{path}: member weights.safetensors is corrupt: Bad CRC-32 for file 'weights.safetensors'"
    )
    data = bytearray(saved.read_bytes())
    with zipfile.ZipFile(saved) as zf:
        info = zf.getinfo("meta.json")
    data[info.header_offset + 30 + len(info.filename) + 3] ^= 0xFF
    path.write_bytes(bytes(data))
    assert _message(path).startswith(f"{path}: member meta.json is corrupt: ")


# ---- reading: the members' content ------------------------------------------------------------


def _with_meta(saved: Path, tmp_path: Path, text: bytes) -> Path:
    return write_zip(tmp_path / "t.zip", {**members(saved), "meta.json": text})


def test_meta_json_errors_are_whole_one_line_messages(saved: Path, tmp_path: Path) -> None:
    path = _with_meta(saved, tmp_path, b"{not json")
    assert _message(path) == (
        f"{path}: meta.json is not valid JSON: Expecting property name enclosed in double "
        "quotes: line 1 column 2 (char 1)"
    )
    path = _with_meta(saved, tmp_path, b"[1, 2]")
    assert _message(path) == f"{path}: meta.json must be a JSON object, got list"


def _doc(saved: Path) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(members(saved)["meta.json"])
    return doc


def test_long_schema_messages_are_cut_at_160_characters(saved: Path, tmp_path: Path) -> None:
    """A schema message of 160 characters is kept whole; 161 are cut to 159 and an ellipsis."""
    prefix = f"{tmp_path / 't.zip'}: meta.json is invalid at top level: "
    for length in (160, 161):
        key = "k" * (length - 57)  # the message around the key is 57 characters
        message = f"Additional properties are not allowed ('{key}' was unexpected)"
        assert len(message) == length
        doc = {**_doc(saved), key: 1}
        got = _message(_with_meta(saved, tmp_path, json.dumps(doc).encode()))
        assert got == prefix + (message if length == 160 else message[:159] + "…")


def test_long_values_in_schema_messages_are_cut_at_40_characters(
    saved: Path, tmp_path: Path
) -> None:
    """A rejected value whose repr is 40 characters is quoted whole; at 41 its first 36 are."""
    path = tmp_path / "t.zip"
    for length in (40, 41):
        value = "v" * (length - 2)  # repr adds the quotes
        doc = {**_doc(saved), "obs_mode": value}
        shown = repr(value) if length == 40 else repr(value)[:36] + " …"
        assert _message(_with_meta(saved, tmp_path, json.dumps(doc).encode())) == (
            f"{path}: meta.json is invalid at obs_mode: {shown} is not one of "
            "['vector', 'dict', 'image']"
        )


def test_meta_nested_just_below_the_parsers_limit(saved: Path, tmp_path: Path) -> None:
    """Nesting the JSON parser accepts but validation cannot walk is refused in one line.

    On CPython 3.11 the JSON parser and the validator share Python's recursion limit, so
    the window is a few levels just under the parser's own limit; scan down to it.
    """
    doc = _doc(saved)
    outcomes = []
    for depth in range(sys.getrecursionlimit() + 10, sys.getrecursionlimit() - 150, -1):
        text = json.dumps({**doc, "name": "@"}).replace('"@"', "[" * depth + "]" * depth)
        with pytest.raises(CheckpointError) as err:
            read_checkpoint(_with_meta(saved, tmp_path, text.encode()).read_bytes())
        outcomes.append(str(err.value))
        if "is invalid at name" in outcomes[-1]:
            break
    assert all("\n" not in o for o in outcomes)
    if sys.version_info < (3, 12):  # where json's C parser counts Python's recursion limit
        deepest_parsed = next(o for o in outcomes if "not valid JSON" not in o)
        assert deepest_parsed == "checkpoint: meta.json is nested too deeply"


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_pickles_of_every_binary_protocol_are_named(protocol: int) -> None:
    """torch.save's legacy format and plain pickle.dump write protocols 2 to 5 (PEP 3154, 574)."""
    assert ckpt.looks_like_pickle(pickle.dumps({"w": [1.0]}, protocol=protocol))
    assert not ckpt.looks_like_pickle(pickle.dumps({"w": [1.0]}, protocol=1))  # no 0x80 header


def test_weights_refusals_are_whole_messages(saved: Path, tmp_path: Path) -> None:
    raw = members(saved)
    pickle_head = b"\x80\x04\x95" + b"\0" * 20
    path = write_zip(
        tmp_path / "t.zip",
        {
            "meta.json": with_checksum(raw["meta.json"], pickle_head),
            "weights.safetensors": pickle_head,
        },
    )
    assert _message(path) == (
        f"{path}: weights.safetensors holds a pickle, not safetensors; pickles can run code and "
        "are never loaded"
    )
    path = write_zip(
        tmp_path / "t.zip",
        {"meta.json": with_checksum(raw["meta.json"], b""), "weights.safetensors": b""},
    )
    assert _message(path) == (
        f"{path}: weights.safetensors is not a valid safetensors file: Error while "
        "deserializing: header too small"
    )
