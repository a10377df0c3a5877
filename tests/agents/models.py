"""Small stable-baselines3 models and hostile-file builders for the agents tests.

The models are untrained: identical-action tests need fixed weights, not good ones. Their
parameters are jittered so that the continuous actions often leave [-1, 1] and the clipping
(or squashing) path is exercised, not just the middle of the range.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import zipfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from arena.observations import ObservationLayout

LAYOUT = ObservationLayout(64, 3)
BOX_ACTIONS = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
DISCRETE_ACTIONS = spaces.Discrete(10)


def vector_space(layout: ObservationLayout = LAYOUT) -> spaces.Box:
    """The env's ``"vector"`` observation space for ``layout``."""
    low, high = layout.bounds()
    return spaces.Box(low, high, dtype=np.float32)


class SpacesOnlyEnv(gym.Env[Any, Any]):
    """A single-agent env with the racing env's spaces and random observations (no physics)."""

    def __init__(self, action_space: spaces.Space[Any], obs_space: spaces.Box | None = None):
        self.observation_space = obs_space or vector_space()
        self.action_space = action_space

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: Any) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        return self.observation_space.sample(), 0.0, False, False, {}


def make_ppo(
    action_space: spaces.Space[Any] = BOX_ACTIONS,
    obs_space: spaces.Box | None = None,
    *,
    jitter: float = 0.5,
    **kwargs: Any,
) -> Any:
    """An untrained SB3 PPO (seeded) with jittered weights."""
    import torch
    from stable_baselines3 import PPO

    env = SpacesOnlyEnv(action_space, obs_space)
    model = PPO("MlpPolicy", env, n_steps=64, batch_size=32, seed=0, device="cpu", **kwargs)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in model.policy.parameters():
            p.add_(torch.randn(p.shape, generator=gen) * jitter)
    return model


def fixed_observations(space: spaces.Box, n: int = 100, seed: int = 7) -> NDArray[np.float32]:
    """``n`` observations (n, *shape) drawn uniformly inside the space's bounds, seeded."""
    rng = np.random.default_rng(seed)
    low, high = space.low, space.high
    return rng.uniform(low, high, (n, *space.shape)).astype(np.float32)


def members(path: Path) -> dict[str, bytes]:
    """Name → bytes of every member of a zip."""
    with zipfile.ZipFile(path) as zf:
        return {name: zf.read(name) for name in zf.namelist()}


def write_zip(
    path: Path, content: dict[str, bytes] | list[tuple[str, bytes]], *, deflate: bool = True
) -> Path:
    """Write members as given (a list allows duplicate or hostile names)."""
    items = list(content.items()) if isinstance(content, dict) else content
    method = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=method) as zf:
        for name, data in items:
            zf.writestr(name, data)
    return path


def with_checksum(meta_bytes: bytes, weights: bytes) -> bytes:
    """``meta.json`` re-signed with the SHA-256 of ``weights`` (a tamperer's best effort)."""
    doc = json.loads(meta_bytes)
    doc["weights_sha256"] = hashlib.sha256(weights).hexdigest()
    return json.dumps(doc).encode()


class CreatesFile:
    """Pickling payload: unpickling it creates ``path`` (a sentinel that code ran)."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        return (open, (self.path, "w"))


def payload(sentinel: Path) -> bytes:
    """A pickle whose loading would create ``sentinel``."""
    return pickle.dumps(CreatesFile(sentinel))
