"""``load_policy``: a baseline name or a policy file, as a :class:`agents.Policy`.

=====================  ==================================  ======================================
what                   recognised by                       loaded
=====================  ==================================  ======================================
baseline name          ``pursuit``, ``gap``, ``random``    :func:`agents.baselines.make_baseline`
Slipstream checkpoint  zip with ``meta.json``              always: data only, fully validated
                                                           (:mod:`agents.checkpoint`)
stable-baselines3 zip  zip with ``data``, ``policy.pth``   only with ``trusted=True``: unpickles
TorchScript            zip with ``*/code/…`` or            only with ``trusted=True``: a program
                       ``*/constants.pkl``
=====================  ==================================  ======================================

Telling them apart reads only the zip's list of member names; nothing is unpickled. SB3 zips
and TorchScript files are code: load them only from your own disk (``trusted=True``, with an
:class:`UntrustedCodeWarning`); anything uploaded is opened only inside the sandbox
(:mod:`submissions`). :func:`convert_sb3` turns your own SB3 zip into a Slipstream checkpoint
once, after which it loads anywhere.

A Slipstream checkpoint records the car it was trained with (``meta.env_config["car"]``;
none: the default ``f1tenth``). Loaded for a race with another car (``load_policy(...,
params=)``), it still loads, with a one-line :class:`CarMismatchWarning` naming both cars:
a policy drives the car it learned, and a 1/10-car policy on the 1/18 DeepRacer car (or the
other way round) mostly leaves the road.
"""

from __future__ import annotations

import warnings
import zipfile
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.baselines import BASELINES, TRACK_BASELINES, make_baseline
from agents.checkpoint import (
    META_MEMBER,
    WEIGHTS_MEMBER,
    CheckpointError,
    CheckpointMeta,
    TorchMLPPolicy,
    looks_like_pickle,
)
from agents.policy import Policy
from arena.cars import CAR_PRESETS, car_name
from arena.observations import ObservationLayout
from arena.sim import CarParams
from tracks import Track

DEFAULT_LAYOUT = ObservationLayout(64, 3)  # the env's defaults: 64 lidar rays, 3 opponents
SB3_MEMBERS = ("data", "policy.pth")  # also pytorch_variables.pth, _stable_baselines3_version
EXPORT_HINT = (
    "convert it once, on your own machine, with `slipstream export` "
    "(agents.loading.convert_sb3), or load it with trusted=True if it is your own local file; "
    "uploaded files are opened only inside the sandbox"
)


class UntrustedCodeWarning(UserWarning):
    """A file that runs code when loaded (SB3 zip, TorchScript) is being loaded."""


class CarMismatchWarning(UserWarning):
    """A checkpoint trained with one car is raced with another."""


def car_mismatch(meta: CheckpointMeta, params: CarParams) -> str | None:
    """One line naming both cars when the car ``meta`` was trained with
    (:attr:`agents.checkpoint.CheckpointMeta.car`) is not ``params``; None when it is."""
    trained, raced = meta.car, car_name(params)
    if isinstance(trained, dict):  # a custom car's parameters
        if raced is None and trained == asdict(params):
            return None
        label = "a custom"
    elif trained == raced:
        return None
    else:  # a preset name, or any text a meta.json holds: shown quoted, in one line
        label = "the " + (trained if trained in CAR_PRESETS else repr(trained[:40]))
    return (
        f"policy {meta.name[:60]!r} was trained with {label} car but races the "
        f"{raced or 'custom'} car: expect it to leave the road (train one for this car: "
        f"slipstream train --car {raced or '<car>'})"
    )


def checkpoint_car_mismatch(path: Path, car: str | CarParams) -> str | None:
    """:func:`car_mismatch` for the Slipstream checkpoint at ``path`` raced with ``car`` (a
    preset name or CarParams). Only ``meta.json`` and the tensors are read, with the strict
    code-free reader; a file that is not a readable Slipstream checkpoint gives None (whatever
    loads it says what is wrong).
    """
    from agents.checkpoint import read_checkpoint  # noqa: PLC0415 - only for this check
    from arena.cars import car_params  # noqa: PLC0415 - only for this check

    try:
        meta, _ = read_checkpoint(path)
    except CheckpointError:
        return None
    return car_mismatch(meta, car_params(car))


def detect_format(path: Path) -> str:
    """``"slipstream"``, ``"sb3"`` or ``"torchscript"``, from the zip's member names only.

    Raises:
        CheckpointError: not a file, not a zip, a bare pickle, or an unknown zip.
    """
    if not path.exists():
        raise CheckpointError(
            f"{path}: no such file (and not a baseline name: {', '.join(BASELINES)})"
        )
    if not path.is_file():
        raise CheckpointError(f"{path}: is a directory, not a policy file")
    try:
        with zipfile.ZipFile(path) as zf:
            names = zf.namelist()
    except (zipfile.BadZipFile, OSError, ValueError) as err:
        with path.open("rb") as fh:
            head = fh.read(2)
        if looks_like_pickle(head):
            raise CheckpointError(
                f"{path}: a pickle file; pickles can run code and are never loaded"
            ) from err
        raise CheckpointError(
            f"{path}: not a policy file (expected a Slipstream checkpoint, an SB3 zip or "
            "TorchScript, all zip archives)"
        ) from err
    if META_MEMBER in names or WEIGHTS_MEMBER in names:
        return "slipstream"
    if all(member in names for member in SB3_MEMBERS):
        return "sb3"
    parts = [n.split("/") for n in names]
    if any("code" in p[:-1] for p in parts) or any(p[-1] == "constants.pkl" for p in parts):
        return "torchscript"
    if any(p[-1] == "data.pkl" for p in parts):
        raise CheckpointError(
            f"{path}: a torch.save archive (a pickle): never loaded; export the weights to a "
            "Slipstream checkpoint"
        )
    return "slipstream"  # let the strict reader say precisely what is wrong with it


def load_policy(
    path_or_name: str | Path,
    *,
    layout: ObservationLayout | None = None,
    params: CarParams | None = None,
    trusted: bool = False,
    track: Track | None = None,
    observe_perturbation: bool | None = False,
) -> Policy:
    """A policy from a baseline name or a file.

    Args:
        path_or_name: ``pursuit``, ``gap``, ``random``, or a path to a Slipstream checkpoint,
            an SB3 zip or a TorchScript file.
        layout: observation layout for the baselines (default: 64 rays, 3 opponents).
        params: the race's car: the baselines drive it (default: ``CarParams()``), and a
            Slipstream checkpoint trained with another car loads with a
            :class:`CarMismatchWarning` (:func:`car_mismatch`).
        trusted: allow files that run code when loaded (SB3 zips, TorchScript). Only for
            your own local files; an :class:`UntrustedCodeWarning` is still emitted.
        track: the race's track, for baselines that follow it (``raceline`` needs one with
            a race line).
        observe_perturbation: whether the races it will drive observe the perturbation
            block (:attr:`arena.observations.ObservationLayout.context`): False (a plain
            race) refuses a Slipstream checkpoint trained on perturbation-aware observations
            and True one trained without, naming the option; None: the caller builds its env
            for the policy (``slipstream robustness``:
            :func:`agents.robustness.observation_kwargs`).

    Returns:
        An object with ``name``, ``reset(seed)`` and ``act(obs)``.

    Raises:
        CheckpointError: the file is missing, corrupt, unsafe, or code while ``trusted`` is
            False (one-line message).
        PolicyError: a name that is neither a baseline nor a file.
    """
    if isinstance(path_or_name, str) and path_or_name in BASELINES + TRACK_BASELINES:
        return make_baseline(path_or_name, layout or DEFAULT_LAYOUT, params, track=track)
    path = Path(path_or_name)
    kind = detect_format(path)
    if kind == "slipstream":
        policy = TorchMLPPolicy.from_file(path)
        aware = policy.meta.observes_perturbation
        if observe_perturbation is not None and aware != observe_perturbation:
            raise CheckpointError(
                f"{path}: trained on perturbation-aware observations (observe_perturbation: "
                "its car is told its own grip, latency …), and these races observe without "
                "them: score it with `slipstream robustness`"
                if aware
                else f"{path}: trained without perturbation-aware observations, and these "
                "races add them (observe_perturbation)"
            )
        mismatch = None if params is None else car_mismatch(policy.meta, params)
        if mismatch is not None:
            warnings.warn(mismatch, CarMismatchWarning, stacklevel=2)
        return policy
    if kind == "sb3":
        if not trusted:
            raise CheckpointError(
                f"{path}: a stable-baselines3 zip; loading one unpickles arbitrary code, so it "
                f"is refused: {EXPORT_HINT}"
            )
        return SB3Policy.from_file(path)
    if not trusted:
        raise CheckpointError(
            f"{path}: a TorchScript file; TorchScript is a program and is refused: run it in "
            "the sandbox, or pass trusted=True if it is your own local file"
        )
    return TorchScriptPolicy.from_file(path)


def _warn_code(path: Path, what: str) -> None:
    warnings.warn(
        f"loading {path} ({what}) executes code from the file; do this only for files you "
        "made yourself",
        UntrustedCodeWarning,
        stacklevel=3,
    )


def _check_shape(name: str, obs: NDArray[Any], shape: tuple[int, ...] | None) -> None:
    if shape is not None and obs.shape != shape:
        raise CheckpointError(f"policy {name!r} expects observation shape {shape}, got {obs.shape}")


class SB3Policy:
    """A trusted stable-baselines3 model as a Policy (``predict(obs, deterministic=True)``)."""

    def __init__(self, model: Any, name: str) -> None:
        from gymnasium import spaces  # noqa: PLC0415 - only needed with SB3 models

        self.model = model
        self.name = name
        self.observation_shape: tuple[int, ...] | None = model.observation_space.shape
        self.discrete = isinstance(model.action_space, spaces.Discrete)

    @classmethod
    def from_file(cls, path: Path, name: str | None = None) -> SB3Policy:
        """Load an SB3 PPO zip (unpickles code: trusted local files only; warns)."""
        _warn_code(path, "a stable-baselines3 zip is unpickled")
        try:
            from stable_baselines3 import PPO  # noqa: PLC0415 - optional `train` extra
        except ImportError as err:
            raise CheckpointError(
                "loading SB3 zips needs stable-baselines3: pip install 'slipstream[train]'"
            ) from err
        try:
            model = PPO.load(path, device="cpu")
        except Exception as err:  # SB3 raises anything from pickle to KeyError on a bad zip
            raise CheckpointError(
                f"{path}: stable-baselines3 could not load it: {type(err).__name__}: {err}"
            ) from err
        return cls(model, name or path.stem)

    def reset(self, seed: int | None = None) -> None:
        """Deterministic: nothing to reset."""

    def act(self, obs: NDArray[np.floating[Any]]) -> NDArray[np.float32] | int:
        """``model.predict(obs, deterministic=True)``: float32 action, or int (Discrete)."""
        arr = np.asarray(obs, dtype=np.float32)
        _check_shape(self.name, arr, self.observation_shape)
        action, _ = self.model.predict(arr, deterministic=True)
        if self.discrete:
            return int(action)
        return np.asarray(action, dtype=np.float32)


class TorchScriptPolicy:
    """A trusted TorchScript module as a Policy.

    Convention: the module maps a float32 batch (B, *obs_shape) to actions (B, action_dim)
    (float) or (B,) (integer: a Discrete action); a tuple output uses its first element.
    """

    def __init__(self, module: Any, name: str) -> None:
        self.module = module
        self.name = name

    @classmethod
    def from_file(cls, path: Path, name: str | None = None) -> TorchScriptPolicy:
        """``torch.jit.load`` a TorchScript file (code: trusted local files only; warns)."""
        _warn_code(path, "TorchScript is a program")
        try:
            import torch  # noqa: PLC0415 - optional `train` extra, imported on use
        except ImportError as err:
            raise CheckpointError(
                "loading TorchScript needs torch: pip install 'slipstream[train]'"
            ) from err
        try:
            with warnings.catch_warnings():  # torch.jit is deprecated; our warning was enough
                warnings.simplefilter("ignore", DeprecationWarning)
                module = torch.jit.load(str(path), map_location="cpu")
        except Exception as err:  # torch raises RuntimeError and friends on a bad file
            raise CheckpointError(
                f"{path}: not a loadable TorchScript file: {type(err).__name__}: {err}"
            ) from err
        module.eval()
        return cls(module, name or path.stem)

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset (a stateful module keeps its own state)."""

    def act(self, obs: NDArray[np.floating[Any]]) -> NDArray[np.float32] | int:
        """Run the module on one observation (batch of one); see the class docstring."""
        import torch  # noqa: PLC0415 - optional `train` extra, imported on use

        batch = torch.from_numpy(np.asarray(obs, dtype=np.float32)[None])
        try:
            with torch.no_grad():
                out = self.module(batch)
        except Exception as err:  # the module's own failure, e.g. a shape mismatch
            raise CheckpointError(
                f"TorchScript policy {self.name!r} failed on an observation of shape "
                f"{tuple(batch.shape[1:])}: {type(err).__name__}: {str(err).splitlines()[0]}"
            ) from err
        if isinstance(out, tuple | list):
            out = out[0]
        arr = out.detach().cpu().numpy()
        if np.issubdtype(arr.dtype, np.integer):
            return int(arr.reshape(-1)[0])
        return arr[0].astype(np.float32)


def convert_sb3(
    src: str | Path,
    dst: str | Path,
    *,
    env_config: dict[str, Any] | None = None,
    name: str | None = None,
    trusted: bool = False,
) -> Path:
    """Convert your own SB3 PPO zip into a Slipstream checkpoint (what ``slipstream export`` does).

    Args:
        src: the SB3 zip (unpickled: only with ``trusted=True``).
        dst: the checkpoint to write.
        env_config: the env keyword arguments it was trained with (recorded).
        name: display name (default: the file's stem).
        trusted: must be True; loading an SB3 zip runs code from it.

    Raises:
        CheckpointError: not trusted, not an SB3 zip, or not an exportable MLP policy.
    """
    from agents.checkpoint import export_sb3  # noqa: PLC0415 - keeps the top imports small

    src = Path(src)
    if detect_format(src) != "sb3":
        raise CheckpointError(f"{src}: not a stable-baselines3 zip")
    if not trusted:
        raise CheckpointError(
            f"{src}: converting unpickles the SB3 zip (arbitrary code); pass trusted=True for "
            "your own local file"
        )
    policy = SB3Policy.from_file(src)
    return export_sb3(
        policy.model,
        dst,
        name=name or src.stem,
        env_config=env_config or {},
        training={"source": src.name},
    )
