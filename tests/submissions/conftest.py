"""Fixtures for the submissions tests: bundles built on the fly, sandbox capability probes."""

from __future__ import annotations

import base64
import io
import json
import os
import pickle
import textwrap
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from agents.baselines import make_baseline
from agents.loading import DEFAULT_LAYOUT
from arena.race import RaceResult, run_race
from arena.version import ENV_VERSION
from submissions.bundle import Bundle, Manifest, make_bundle, open_bundle
from submissions.remote import SandboxedPolicy
from submissions.sandbox import WEAK_ENV, SandboxLimits, bwrap_works, landlock_abi

# A python-format policy that drives like the pursuit baseline (imported inside the sandbox)
# and calls ``self.attack(obs)`` on its third step; hostile policies override ``attack``.
DRIVER = """
import os, sys, time, socket
import numpy as np
from agents.baselines import make_baseline
from arena.observations import ObservationLayout


class Driver:
    attack_step = 3

    def __init__(self, env_spec):
        layout = ObservationLayout(env_spec["lidar_rays"], env_spec["k_opponents"])
        self.pursuit = make_baseline("pursuit", layout)
        self.steps = 0

    def reset(self, seed):
        self.pursuit.reset(seed)

    def act(self, obs):
        self.steps += 1
        if self.steps == self.attack_step:
            out = self.attack(obs)
            if out is not None:
                return out
        return self.pursuit.act(obs)

    def attack(self, obs):
        return None
"""

MakeBundle = Callable[..., Bundle]


def python_source(body: str, driver: bool = True) -> str:
    """Policy source: ``body`` (dedented) after the :data:`DRIVER` preamble."""
    return (DRIVER if driver else "") + "\n" + textwrap.dedent(body)


def manifest_for(name: str, fmt: str = "python", entry: str = "agent.py") -> Manifest:
    """A valid manifest for the current env."""
    return Manifest(name=name, author="tests", format=fmt, entry=entry, env_version=ENV_VERSION)


@pytest.fixture
def make_python_bundle(tmp_path: Path) -> MakeBundle:
    """``make_python_bundle(body, name=..., driver=True)``: a python bundle, opened."""
    count = iter(range(1000))

    def make(body: str, name: str = "hostile", driver: bool = True) -> Bundle:
        n = next(count)
        source = python_source(body, driver).encode()
        zipped = make_bundle(tmp_path / f"{name}{n}.zip", manifest_for(name), {"agent.py": source})
        return open_bundle(zipped, tmp_path / f"{name}{n}")

    return make


def malicious_sb3_zip(path: Path, sentinel: Path) -> Path:
    """An SB3-looking zip whose ``data`` unpickles a payload that touches ``sentinel``.

    The payload also prints ``PAYLOAD-RAN`` to stderr, so a test can tell that it did run
    (inside the sandbox) and was contained, rather than never reached.
    """

    class Payload:
        def __reduce__(self) -> tuple[Any, tuple[str]]:
            return (os.system, (f"echo PAYLOAD-RAN >&2; touch {sentinel}",))

    class OpenPayload:
        def __reduce__(self) -> tuple[Any, tuple[str, str]]:
            return (open, (str(sentinel), "w"))

    def serialized(obj: Any) -> dict[str, str]:
        return {
            ":type:": "<class 'x'>",
            ":serialized:": base64.b64encode(pickle.dumps(obj)).decode(),
        }

    data = {
        "policy_class": serialized(Payload()),
        "observation_space": serialized(OpenPayload()),
        "zz_extra_key": serialized(Payload()),
    }
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("data", json.dumps(data))
        zf.writestr("policy.pth", b"not a torch file")
        zf.writestr("pytorch_variables.pth", b"")
        zf.writestr("_stable_baselines3_version", "2.9.2")
    path.write_bytes(buf.getvalue())
    return path


@pytest.fixture
def sb3_bundle(tmp_path: Path) -> Callable[[Path], Bundle]:
    """``sb3_bundle(sentinel)``: a bundle of :func:`malicious_sb3_zip`, opened."""

    def make(sentinel: Path) -> Bundle:
        policy = malicious_sb3_zip(tmp_path / "policy.zip", sentinel)
        manifest = manifest_for("pickled", fmt="sb3", entry="policy.zip")
        zipped = make_bundle(tmp_path / "sb3.zip", manifest, {"policy.zip": policy})
        return open_bundle(zipped, tmp_path / "sb3")

    return make


@pytest.fixture(params=["bwrap", "seccomp"])
def mode(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Each sandbox mode in turn (``SANDBOX`` set); skipped where it cannot run here."""
    wanted = str(request.param)
    if wanted == "bwrap" and not bwrap_works():
        pytest.skip("bubblewrap cannot create namespaces here")
    if wanted == "seccomp" and landlock_abi() == 0:
        pytest.skip("no Landlock in this kernel: the fallback cannot confine files")
    monkeypatch.setenv("SANDBOX", wanted)
    if wanted == "seccomp":  # the operator's --allow-weak-sandbox (fail closed without it)
        monkeypatch.setenv(WEAK_ENV, "1")
    return wanted


def race_against_pursuit(
    policy: SandboxedPolicy, *, laps: int = 1, record: bool = True
) -> RaceResult:
    """A short race: ``policy`` (car 0) against one in-process pursuit car on the oval."""
    other = make_baseline("pursuit", DEFAULT_LAYOUT)
    result, _ = run_race([policy, other], track="oval", laps=laps, seed=0, record=record)
    return result


def sandbox_processes(sandbox_id: str) -> list[int]:
    """Host pids whose command line carries ``sandbox_id`` (a worker or its forks)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if sandbox_id.encode() in cmdline:
            found.append(int(entry.name))
    return found


FAST = SandboxLimits(step_deadline_s=0.25, overage_s=10.0, startup_s=60.0)


@pytest.fixture
def home_secret() -> Iterator[tuple[Path, str]]:
    """A fake key file under the real home folder (removed afterwards): (path, content)."""
    token = os.urandom(8).hex()
    path = Path.home() / f".slipstream-test-key-{token}"
    path.write_text(f"FAKE-SECRET-{token}\n")
    path.chmod(0o600)
    try:
        yield path, f"FAKE-SECRET-{token}"
    finally:
        path.unlink(missing_ok=True)
