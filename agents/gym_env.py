"""``slipstream/Race-v0``: one learning car racing opponents, as a single-agent Gymnasium env.

====================  =============================================================
Make                  ``import agents; gymnasium.make("slipstream/Race-v0", ...)``
                      or, with no import, ``gymnasium.make("agents:slipstream/Race-v0")``
Agent                 ``car_0`` of :func:`arena.parallel_env` (pole position)
Opponents             ``car_1 …``, driven by baselines, checkpoints, bundles or Policies
Action space          the env's: ``Box(-1, 1, (2,))`` [steer, throttle] or ``Discrete``
Observation space     the env's: ``Box((n_rays + 21 + 5k,), float32)``, ``Dict`` or image
====================  =============================================================

The most common case in the field (f1tenth_gym's ``f110-v0``, DeepRacer's time trial and
head-to-head): the learner drives ``car_0`` of the PettingZoo env and every other car is
driven by a fixed opponent inside the env, so any single-agent library (stable-baselines3,
CleanRL, …) trains on it unchanged. ``opponents=[]`` is a solo time trial.

**Registration.** Gymnasium ≥ 1.0 dropped plugin entry points (the ``gymnasium.envs``
entry-point group of 0.26–0.29 is no longer read), so no installed package can make a bare
``gymnasium.make("slipstream/Race-v0")`` work before something of ours is imported.
Supported: ``import agents`` (registers the id; costs Gymnasium's own import, no simulator,
no torch), ``import agents.gym_env``, or Gymnasium's module prefix
``gymnasium.make("agents:slipstream/Race-v0", ...)``, which imports ``agents`` first.

**Opponents**, one car each (``car_1``, ``car_2``, … in the order given):

* a baseline name: ``"pursuit"``, ``"gap"``, ``"random"`` (:mod:`agents.baselines`);
* a checkpoint path: our safe format, read by :func:`agents.load_policy` (never unpickled;
  SB3 zips and TorchScript are refused: convert them once with ``slipstream export``);
* a submission bundle: bundles are untrusted code and run only in the sandbox, which lives
  in :mod:`submissions` (a package above this one, which this module may not import). Pass
  the sandboxed policy as the opponent object:
  ``SandboxedPolicy(open_bundle(path, dest))`` from :mod:`submissions.remote` /
  :mod:`submissions.bundle` (``env_spec=`` for a non-default ``lidar_rays`` /
  ``k_opponents``; close it when done). A bundle *path* (zip or folder with
  ``manifest.json``) works once a sandboxed loader is registered with
  :func:`register_bundle_loader` (the hook for :mod:`submissions`); without one it is
  refused with an error saying this. Nothing from a bundle is ever imported in-process;
* any object with ``reset(seed)`` and ``act(obs)`` (:class:`agents.Policy`): it receives
  its car's observation in the env's ``obs_mode`` and returns an action of the env's
  ``action_mode``. Objects passed in stay yours: :meth:`RaceEnv.close` does not close them.

Names and paths need ``obs_mode="vector"`` (baselines and checkpoints read the vector
observation); baselines also need ``action_mode="continuous"``. An opponent that fails the
way a sandboxed policy does (an exception with a ``dnf_reason``) retires its car and the
race goes on.

**Rewards, termination, infos**: those of ``car_0`` in the PettingZoo env (see
:class:`arena.env.RacingEnv`): *terminated* when it finishes its laps or retires (stuck,
off the track, flipped), *truncated* at ``max_cycles``. The episode ends with ``car_0``
even if opponents are still racing. ``info`` is ``car_0``'s info dict.

**Arguments.** ``track`` (name, path, ``random:<seed>`` or a ``Track``), ``opponents``
(default ``("pursuit",)``), ``laps`` (1), ``obs_mode`` (``"vector"``, ``"dict"``,
``"image"``), ``action_mode`` (``"continuous"``, ``"discrete"``), ``reward`` (``"racing"``,
``"progress"`` or a DeepRacer ``reward_function(params)``), ``uncertainty`` (an
:class:`arena.uncertainty.UncertaintyConfig`; ``adversarial`` mode needs the nature agents
of the PettingZoo env and is refused here), ``control_hz`` (20), ``max_cycles`` (None: the
env's default), ``backend`` (``"pybullet"``, the reference, or ``"batch"``, the vectorised
simulator with B = 1; vector observations only), ``render_mode`` (None or ``"rgb_array"``;
the batch backend accepts it, as SB3's ``make_vec_env`` always passes it, but its
``render()`` raises), and any other :func:`arena.parallel_env` keyword (``lidar_rays``,
``k_opponents``, ``car``, …).

**Version History.** v0: first release.

>>> import gymnasium, agents
>>> env = gymnasium.make("slipstream/Race-v0", track="oval", opponents=[])
>>> obs, info = env.reset(seed=0)
>>> obs.shape, info["laps_completed"]
((100,), 0)
>>> env.close()
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, SupportsFloat

import gymnasium

import arena
from agents import GYM_ENV_ID as ENV_ID
from agents.baselines import BASELINES
from agents.policy import Policy, PolicyError

EGO = "car_0"
BUNDLE_MANIFEST = "manifest.json"

Opponent = str | Path | Policy
BundleLoader = Callable[[Path, Any], Policy]
"""``(bundle path, the PettingZoo env it races in) -> a sandboxed Policy``."""

_bundle_loader: list[BundleLoader] = []  # at most one: the sandbox's (from submissions)


def register_bundle_loader(loader: BundleLoader) -> None:
    """Let opponent paths that are submission bundles load through ``loader``.

    :mod:`submissions` calls this (it owns the sandbox; this package may not import it).
    ``loader(path, env)`` must return a Policy that runs the bundle in the sandbox; a second
    call replaces the first loader.
    """
    _bundle_loader[:] = [loader]


def is_bundle(path: Path) -> bool:
    """Whether ``path`` is a submission bundle (a folder or zip holding ``manifest.json``).

    Reads only the zip's member names; nothing is extracted or run.
    """
    if path.is_dir():
        return (path / BUNDLE_MANIFEST).is_file()
    if not zipfile.is_zipfile(path):
        return False
    try:
        with zipfile.ZipFile(path) as zf:
            return BUNDLE_MANIFEST in zf.namelist()
    except (zipfile.BadZipFile, OSError):
        return False


class RaceEnv(gymnasium.Env[Any, Any]):
    """One learning car (``car_0``) against fixed opponents; see the module docstring."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}  # noqa: RUF012 - gymnasium's

    def __init__(
        self,
        track: Any = "oval",
        opponents: Sequence[Opponent] = ("pursuit",),
        *,
        laps: int = 1,
        obs_mode: str = "vector",
        action_mode: str = "continuous",
        reward: Any = "racing",
        uncertainty: Any = None,
        control_hz: int = 20,
        max_cycles: int | None = None,
        backend: str = "pybullet",
        render_mode: str | None = None,
        **env_kwargs: Any,
    ) -> None:
        if isinstance(opponents, str | Path):
            raise PolicyError("opponents must be a list (e.g. ['pursuit']), not one name")
        if uncertainty is not None and getattr(uncertainty, "mode", None) == "adversarial":
            raise PolicyError(
                "uncertainty mode 'adversarial' adds nature agents: use arena.parallel_env"
            )
        kwargs: dict[str, Any] = {
            "backend": backend,
            "track": track,
            "n_cars": 1 + len(opponents),
            "laps": laps,
            "obs_mode": obs_mode,
            "action_mode": action_mode,
            "reward": reward,
            "control_hz": control_hz,
            "max_cycles": max_cycles,
            **env_kwargs,
        }
        # Optional features are passed only when used, so a backend without them still builds.
        if uncertainty is not None:
            kwargs["uncertainty"] = uncertainty
        # SB3's make_vec_env asks every env for render_mode="rgb_array" and never renders
        # unless told: the batch backend accepts it and refuses only an actual render().
        if render_mode is not None and backend != "batch":
            kwargs["render_mode"] = render_mode
        self.race = arena.parallel_env(**kwargs)
        self.backend = backend
        self.render_mode = render_mode
        if backend == "batch":  # an instance attribute: what env checkers read
            self.metadata = {"render_modes": [], "render_fps": control_hz}
        else:
            self.metadata = {"render_modes": ["rgb_array"], "render_fps": control_hz}
        self.observation_space = self.race.observation_space(EGO)
        self.action_space = self.race.action_space(EGO)
        self.opponent_agents = list(self.race.possible_agents[1 : 1 + len(opponents)])
        self._owned: list[Policy] = []
        try:
            self.opponents = [self._opponent(o, obs_mode, action_mode) for o in opponents]
        except BaseException:
            self.close()
            raise
        self._obs: dict[str, Any] = {}
        self._done = True

    def _opponent(self, spec: Opponent, obs_mode: str, action_mode: str) -> Policy:
        """A Policy for one opponent spec (see the module docstring)."""
        if not isinstance(spec, str | Path):
            if not (
                callable(getattr(spec, "act", None)) and callable(getattr(spec, "reset", None))
            ):
                raise PolicyError(
                    f"opponent {spec!r} is neither a baseline name, a path nor a Policy "
                    "(an object with reset(seed) and act(obs))"
                )
            return spec
        if obs_mode != "vector":
            raise PolicyError(
                f"opponent {str(spec)!r} reads vector observations; with obs_mode={obs_mode!r} "
                "pass Policy objects that read that mode, or opponents=[]"
            )
        if str(spec) in BASELINES and action_mode != "continuous":
            raise PolicyError(
                f"baseline {str(spec)!r} drives with continuous actions; "
                "use action_mode='continuous' or pass a Policy object"
            )
        path = Path(spec)
        if str(spec) not in BASELINES and path.exists() and is_bundle(path):
            if not _bundle_loader:
                raise PolicyError(
                    f"{path}: a submission bundle; bundles run only in the sandbox: pass "
                    "submissions.remote.SandboxedPolicy(open_bundle(path, dest)) as the "
                    "opponent, or register a sandboxed loader with "
                    "agents.gym_env.register_bundle_loader"
                )
            policy = _bundle_loader[0](path, self.race)
        else:
            from agents.loading import load_policy  # noqa: PLC0415 - pulls in torch for files

            policy = load_policy(spec, layout=self.race.layout, params=self.race.params)
        self._owned.append(policy)
        return policy

    # ---- gymnasium.Env ----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Start a race; ``options`` as :meth:`arena.env.RacingEnv.reset` (grid, start, direction).

        The opponents are reseeded from this env's generator, so a seed fixes the whole race.
        """
        super().reset(seed=seed)
        obs, infos = self.race.reset(seed=seed, options=options)
        for policy in self.opponents:
            policy.reset(int(self.np_random.integers(2**31)))
        self._obs = obs
        self._done = False
        return obs[EGO], infos[EGO]

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        """Drive ``car_0`` with ``action`` and every opponent still racing with its policy."""
        if self._done:
            raise arena.SimError("step() after the episode ended; call reset() first")
        actions: dict[str, Any] = {EGO: action}
        for agent, policy in zip(self.opponent_agents, self.opponents, strict=True):
            if agent in self.race.agents:
                try:
                    actions[agent] = policy.act(self._obs[agent])
                except Exception as err:
                    reason = getattr(err, "dnf_reason", None)
                    if reason is None:
                        raise
                    self._retire(agent, str(reason))
        obs, rewards, terms, truncs, infos = self.race.step(actions)
        self._obs.update(obs)
        terminated, truncated = bool(terms[EGO]), bool(truncs[EGO])
        self._done = terminated or truncated
        return obs[EGO], float(rewards[EGO]), terminated, truncated, infos[EGO]

    def _retire(self, agent: str, reason: str) -> None:
        """Take a failed opponent's car out of the race (where the backend can)."""
        retire = getattr(self.race, "retire", None)
        if retire is None:  # no retire on this backend: the car coasts (zero action)
            return
        retire(agent, reason)

    def render(self) -> Any:
        """The pybullet backend's top-down ``rgb_array`` image (``render_mode="rgb_array"``).

        Raises:
            SimError: on the batch backend, which does not render.
        """
        if self.backend == "batch" and self.render_mode is not None:
            raise arena.SimError("backend='batch' does not render; use backend='pybullet'")
        return self.race.render()

    def close(self) -> None:
        """Release the simulator and the opponents this env loaded (not ones passed in)."""
        for policy in getattr(self, "_owned", []):
            close = getattr(policy, "close", None)
            if callable(close):
                close()
        self._owned = []
        race = getattr(self, "race", None)
        if race is not None:
            race.close()


__all__ = [
    "ENV_ID",
    "BundleLoader",
    "RaceEnv",
    "is_bundle",
    "register_bundle_loader",
]
