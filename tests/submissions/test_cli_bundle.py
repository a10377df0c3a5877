"""``slipstream bundle init | wrap | check`` and ``submit``'s bare-checkpoint handling.

The inputs are what a new participant has in hand: a template straight from ``bundle init``,
the shipped PPO checkpoint (``agents/data/ppo_racer.zip``), an SB3 zip from
``stable_baselines3.PPO.save`` (as ``slipstream train`` users produce), a pickle someone
renamed to ``.zip``, and a template edited to raise in ``act`` (the most common first bug).
"""

from __future__ import annotations

import json
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest

from arena.observations import ObservationLayout
from leaderboard.cli import main
from leaderboard.settings import Settings
from submissions import cli_bundle
from submissions.bundle import EnvSpec, open_bundle
from submissions.errors import SubmissionError

SHIPPED = Path(__file__).resolve().parents[2] / "agents" / "data" / "ppo_racer.zip"


def _load_template_policy(folder: Path) -> object:
    """Import the template's agent.py in-process (our own file, not an upload)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("template_agent", folder / "agent.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.Policy(env_spec={"lidar_rays": 64, "k_opponents": 3})


def test_init_python_writes_a_bundle_the_server_opens(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "my_bot"
    assert main(["bundle", "init", str(folder), "--author", "ada"]) == 0
    assert "bundle check" in capsys.readouterr().out
    bundle = open_bundle(folder, tmp_path / "opened", env=EnvSpec.current())
    assert bundle.manifest.name == "my_bot"
    assert bundle.manifest.author == "ada"
    assert bundle.manifest.format == "python"
    text = (folder / "agent.py").read_text()
    for documented in ("lidar", "ego (7)", "track ahead", "opponents", "steer", "throttle"):
        assert documented in text
    # the driver answers a real-sized observation with an action inside the box
    policy = _load_template_policy(folder)
    layout = ObservationLayout(64, 3)
    obs = np.zeros(layout.size, dtype=np.float32)
    obs[layout.track_ahead] = np.tile([0.1, 0.05], 7).astype(np.float32)  # road bends left
    action = policy.act(obs)  # type: ignore[attr-defined]
    assert action.shape == (2,) and action.dtype == np.float32
    assert np.all(np.abs(action) <= 1.0)
    assert action[0] > 0  # steers left, towards the road
    assert action[1] > 0  # standing still: drives off


def test_init_checkpoint_ships_the_trained_racer(tmp_path: Path) -> None:
    folder = tmp_path / "ck"
    assert main(["bundle", "init", str(folder), "--template", "checkpoint"]) == 0
    assert (folder / "policy.zip").read_bytes() == SHIPPED.read_bytes()
    manifest = open_bundle(folder, tmp_path / "o", env=EnvSpec.current()).manifest
    assert (manifest.format, manifest.entry) == ("slipstream", "policy.zip")


def test_init_refuses_a_folder_with_files(tmp_path: Path, capsys) -> None:
    (tmp_path / "keep.txt").write_text("mine")
    assert main(["bundle", "init", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not an empty folder" in err
    assert (tmp_path / "keep.txt").read_text() == "mine"
    assert not (tmp_path / "agent.py").exists()


def test_wrap_our_checkpoint(tmp_path: Path, capsys) -> None:
    out = tmp_path / "racer.zip"
    assert main(["bundle", "wrap", str(SHIPPED), "--name", "racer", "--out", str(out)]) == 0
    assert "wrapped" in capsys.readouterr().out
    with zipfile.ZipFile(out) as zf:
        manifest = json.loads(zf.read("manifest.json"))
        assert zf.read("policy.zip") == SHIPPED.read_bytes()
    assert manifest["name"] == "racer"
    assert (manifest["format"], manifest["action_mode"]) == ("slipstream", "continuous")


@pytest.mark.component("stable-baselines3")
def test_wrap_sb3_needs_trust_then_converts(tmp_path: Path, capsys) -> None:
    from tests.agents.models import BOX_ACTIONS, make_ppo

    sb3 = tmp_path / "ppo_model.zip"
    make_ppo(BOX_ACTIONS).save(sb3)
    out = tmp_path / "b.zip"
    assert main(["bundle", "wrap", str(sb3), "--out", str(out)]) == 2
    assert "trusted" in capsys.readouterr().err
    assert not out.exists()
    assert main(["bundle", "wrap", str(sb3), "--out", str(out), "--trusted"]) == 0
    assert "converted the SB3 zip" in capsys.readouterr().out
    with zipfile.ZipFile(out) as zf:
        inner = zf.read("policy.zip")
    with zipfile.ZipFile(__import__("io").BytesIO(inner)) as zf:
        assert "meta.json" in zf.namelist()  # our safe format, no pickle inside the bundle
        assert not any(n.endswith(".pkl") or n == "policy.pth" for n in zf.namelist())


def test_wrap_refuses_a_pickle(tmp_path: Path, capsys) -> None:
    evil = tmp_path / "model.zip"
    evil.write_bytes(pickle.dumps({"a": 1}))
    assert main(["bundle", "wrap", str(evil), "--out", str(tmp_path / "x.zip")]) == 2
    assert "pickle" in capsys.readouterr().err
    assert not (tmp_path / "x.zip").exists()


def test_submit_helper_wraps_a_bare_checkpoint_and_passes_bundles(tmp_path: Path) -> None:
    path, note = cli_bundle.bundle_for_upload(SHIPPED, tmp_path)
    assert note is not None and "wrapped" in note
    with zipfile.ZipFile(path) as zf:
        assert "manifest.json" in zf.namelist()
    folder = cli_bundle.init_bundle(tmp_path / "f", "python")
    assert cli_bundle.bundle_for_upload(folder, tmp_path) == (folder, None)


@pytest.mark.component("stable-baselines3")
def test_submit_helper_explains_how_to_wrap_sb3(tmp_path: Path) -> None:
    from tests.agents.models import BOX_ACTIONS, make_ppo

    sb3 = tmp_path / "ppo_model.zip"
    make_ppo(BOX_ACTIONS).save(sb3)
    with pytest.raises(SubmissionError, match=r"slipstream bundle wrap .* --trusted"):
        cli_bundle.bundle_for_upload(sb3, tmp_path)


def test_check_races_like_the_server() -> None:
    """The local check's race is the server's validation race (its settings' defaults)."""
    settings = Settings.model_fields
    assert settings["validation_track"].default == cli_bundle.VALIDATION_TRACK
    assert settings["validation_opponent"].default == cli_bundle.VALIDATION_OPPONENT
    from leaderboard.results import POLICY_FAILURES

    assert set(cli_bundle.POLICY_FAILURES) == POLICY_FAILURES


@pytest.mark.slow
@pytest.mark.component("bubblewrap")
def test_check_passes_the_template_and_rejects_a_crash(tmp_path: Path, capsys) -> None:
    good = cli_bundle.init_bundle(tmp_path / "good", "python")
    assert main(["bundle", "check", str(good), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] and report["sandbox"] in ("bwrap", "seccomp")
    car = next(c for c in report["result"]["cars"] if c["agent"] == "car_0")
    assert car["status"] == "finished"

    bad = cli_bundle.init_bundle(tmp_path / "bad", "python")
    src = (bad / "agent.py").read_text()
    src = src.replace(
        '        """[steer, throttle] for one observation (see the module docstring)."""\n',
        '        """Crash."""\n        raise RuntimeError("my first bug")\n',
    )
    (bad / "agent.py").write_text(src)
    assert main(["bundle", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "dnf (error)" in err and "would be rejected at the race stage" in err


def test_check_reports_a_bad_manifest_without_racing(tmp_path: Path, capsys) -> None:
    folder = cli_bundle.init_bundle(tmp_path / "b", "python")
    doc = json.loads((folder / "manifest.json").read_text())
    doc["env_version"] = "0.0-old"
    (folder / "manifest.json").write_text(json.dumps(doc))
    assert main(["bundle", "check", str(folder)]) == 2
    err = capsys.readouterr().err
    assert "at the bundle stage" in err and "0.0-old" in err
