"""``SandboxedPolicy``: a submitted policy in its sandbox, driven over the worker protocol.

It implements the :class:`agents.Policy` protocol (``name``, ``reset(seed)``, ``act(obs)``)
plus ``start()`` (spawn the sandbox; the policy loads inside while the host does other
work), two-phase ``send(obs)`` / ``receive()`` (so a race steps all sandboxed cars in
parallel) and ``close()`` (kill the whole process tree).

Observations and actions travel through a shared-memory channel (:mod:`submissions.channel`):
the host writes the observation's frame into the request slot and rings the worker's pipe;
the worker answers in the reply slot and rings the host's. No frame ever crosses a pipe, so
a step costs two one-byte wake-ups and a few copies.

Deadlines, Kaggle style: each action must arrive within ``step_deadline_s`` of its
observation being sent; time beyond that is drawn from an overage bank of ``overage_s``
seconds for the whole race, and the policy times out when the bank is spent. Loading and
the first reset share a separate start-up allowance (``startup_s``). Replies are taken by
the thread that waits for one, which polls the bells of every car with a request
outstanding at once and timestamps each reply as it comes, so one slow car never eats into
another's deadline (a thread drains the workers' stdout/stderr, off the step's path). A
race may also set :attr:`SandboxedPolicy.race_deadline` (the job's wall-clock limit,
:mod:`submissions.jobs`): no wait outlasts it.

Nothing the policy does can wedge the host:

* the host never blocks on it: a request is a copy into the slot and one byte on a
  non-blocking pipe end of the host's own; every wait is a ``poll`` with a deadline;
* requests are numbered and only the reply to the current one counts: the host reads the
  reply slot only after a wake-up rung since its request; the slot must then carry the
  request's number (a stale or forged one is ``invalid``), and the host decodes it from its
  own copy (a worker scribbling in the slot at any time gets an ``invalid`` frame or a wrong
  action, which is validated like any other); a reply already in the slot when its request
  is posted (answers sent ahead) is ``invalid``; a reply never rung in does not count;
* wake-ups are counted: more than one per request (a policy waking the host unasked, or
  flooding it) is ``invalid``, so a ringing policy cannot keep the host busy;
* the region's size is fixed and sealed by the host, so no ``ftruncate`` can make the
  host's mapping fault; a reply longer than its slot or malformed is ``invalid``;
* a worker whose end of the channel closes has exited (``error``) or, still running after
  :data:`EXIT_WAIT_S`, closed it on purpose (``invalid``);
* every failure's text is capped at :data:`~submissions.protocol.MAX_TEXT` bytes.

Failures raise a :class:`PolicyFailure` whose ``dnf_reason`` the race records:

==================  ==============  ===================================================
exception           ``dnf_reason``  when
==================  ==============  ===================================================
``PolicyCrash``     ``"error"``     load failed, the policy raised, the worker died
``PolicyTimeout``   ``"timeout"``   deadline and overage bank exhausted (no answer, or
                                    one never rung in), start-up took longer than
                                    ``startup_s``, or the race's wall-clock limit was
                                    reached
``PolicyInvalid``   ``"invalid"``   wrong shape or dtype, NaN/inf, out of the action
                                    space; broke the protocol (malformed or oversized
                                    frame, reply sent ahead, wake-ups unasked for,
                                    its channel closed while it runs)
==================  ==============  ===================================================

After any failure the sandbox is killed at once. A :class:`SandboxPool` keeps healthy
sandboxes between the races of one batch (same bundle, env spec and limits), so a batch pays
each sandbox's start-up once; see its docstring for what that trades.

The worker's stdout/stderr are drained continuously and only the first 4 KiB and last
16 KiB are kept (:attr:`output`), so a policy printing megabytes costs the host nothing but
the reading.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import select
import shutil
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from agents.gym_env import register_bundle_loader
from arena.actions import DiscreteActions
from arena.cars import DEFAULT_CAR, car_name
from arena.env import RacingEnv
from arena.observations import ObservationLayout
from arena.race import ACTION_TOLERANCE, action_problem
from arena.version import ENV_VERSION
from submissions.bundle import Bundle, Manifest, open_bundle
from submissions.channel import Channel, request_bytes_for
from submissions.errors import SubmissionError
from submissions.protocol import (
    MAX_TEXT,
    SEQ_MODULO,
    Frame,
    Kind,
    ProtocolError,
    cap_text,
    encode,
)
from submissions.sandbox import SandboxLimits, SandboxProcess, sandbox_mode
from submissions.scheduling import CONTENTION, PLACEMENT, WAKEUPS, spin_limit_s

log = logging.getLogger(__name__)
OUTPUT_HEAD = 4 << 10  # bytes of the worker's output kept from the start
OUTPUT_TAIL = 16 << 10  # … and from the end
EXIT_WAIT_S = 3.0  # how long a closed channel waits to tell an exit from a hostile close, s
MAX_DETAIL = MAX_TEXT - 96  # a failure's text, leaving room for "PolicyInvalid: " etc.


class PolicyFailure(SubmissionError):
    """A sandboxed policy failed; ``dnf_reason`` says how (the race's DNF reason)."""

    dnf_reason = "error"


class PolicyCrash(PolicyFailure):
    """It failed to load, raised, died, or broke the protocol."""

    dnf_reason = "error"


class PolicyTimeout(PolicyFailure):
    """It missed its deadline with the overage bank spent, or started too slowly."""

    dnf_reason = "timeout"


class PolicyInvalid(PolicyFailure):
    """It returned an action outside the action space (shape, dtype, NaN/inf, range)."""

    dnf_reason = "invalid"


# ---- env spec ----------------------------------------------------------------------------


def make_env_spec(
    *,
    lidar_rays: int = 64,
    k_opponents: int = 3,
    action_mode: str = "continuous",
    car: str | None = DEFAULT_CAR,
) -> dict[str, Any]:
    """The env spec a sandboxed policy is given (and its actions are checked against).

    Keys: ``obs_mode``, ``obs_shape``, ``action_mode``, ``action_shape`` (``[2]`` or
    ``[]``), ``action_low``/``action_high`` (continuous), ``n_actions`` (discrete),
    ``lidar_rays``, ``k_opponents``, ``env_version``, and ``car``: the car preset it drives
    (``"f1tenth"`` or ``"deepracer"``, :data:`arena.cars.CAR_PRESETS`; None for a car
    that is no preset). Matches :class:`arena.env.RacingEnv` with the same arguments,
    without building one.
    """
    spec: dict[str, Any] = {
        "obs_mode": "vector",
        "obs_shape": [ObservationLayout(lidar_rays, k_opponents).size],
        "action_mode": action_mode,
        "lidar_rays": lidar_rays,
        "k_opponents": k_opponents,
        "env_version": ENV_VERSION,
        "car": car,
    }
    if action_mode == "discrete":
        return spec | {"action_shape": [], "n_actions": DiscreteActions().n}
    return spec | {"action_shape": [2], "action_low": [-1.0, -1.0], "action_high": [1.0, 1.0]}


def env_spec_of(env: RacingEnv) -> dict[str, Any]:
    """The env spec of a built env (its first car's spaces, its car preset)."""
    agent = env.possible_agents[0]
    obs_space = env.observation_space(agent)
    act_space = env.action_space(agent)
    spec: dict[str, Any] = {
        "obs_mode": env.obs_mode,
        "obs_shape": list(obs_space.shape or ()),
        "action_mode": env.action_mode,
        "lidar_rays": env.layout.n_rays,
        "k_opponents": env.layout.k_opponents,
        "env_version": ENV_VERSION,
        "car": car_name(env.params),
    }
    if isinstance(act_space, spaces.Discrete):
        return spec | {"action_shape": [], "n_actions": int(act_space.n)}
    assert isinstance(act_space, spaces.Box)
    return spec | {
        "action_shape": list(act_space.shape),
        "action_low": act_space.low.tolist(),
        "action_high": act_space.high.tolist(),
    }


def spec_for_manifest(manifest: Manifest) -> dict[str, Any]:
    """The default env spec for a bundle's manifest (its declared ``env``, action mode and
    car)."""
    return make_env_spec(
        lidar_rays=int(manifest.env.get("lidar_rays", 64)),
        k_opponents=int(manifest.env.get("k_opponents", 3)),
        action_mode=manifest.action_mode,
        car=manifest.car,
    )


def action_space_of(spec: dict[str, Any]) -> spaces.Space[Any]:
    """The gymnasium action space an env spec describes."""
    if spec.get("action_mode") == "discrete":
        return spaces.Discrete(int(spec["n_actions"]))
    low = np.asarray(spec["action_low"], dtype=np.float32)
    high = np.asarray(spec["action_high"], dtype=np.float32)
    return spaces.Box(low, high, dtype=np.float32)


# ---- output and waiting ------------------------------------------------------------------


class _Output:
    """The worker's stdout/stderr, capped: the first and last bytes and a count."""

    def __init__(self) -> None:
        self.head = bytearray()
        self.tail = bytearray()
        self.total = 0

    def add(self, data: bytes) -> None:
        self.total += len(data)
        room = OUTPUT_HEAD - len(self.head)
        if room > 0:
            self.head += data[:room]
            data = data[room:]
        self.tail += data
        if len(self.tail) > OUTPUT_TAIL:
            del self.tail[: len(self.tail) - OUTPUT_TAIL]

    def clear(self) -> None:
        self.head.clear()
        self.tail.clear()
        self.total = 0

    def text(self) -> str:
        skipped = self.total - len(self.head) - len(self.tail)
        gap = f"\n[… {skipped} bytes not kept …]\n".encode() if skipped > 0 else b""
        return bytes(self.head + gap + self.tail).decode("utf-8", "replace")


def _drain_output(output_fd: int, output: _Output) -> None:
    """Until the pipe ends: read the worker's stdout/stderr into ``output`` (a thread)."""
    while True:
        try:
            data = os.read(output_fd, 1 << 16)
        except InterruptedError:
            continue
        except OSError:
            return
        if not data:
            return
        output.add(data)


# Policies of this process with a request outstanding. Whichever thread waits for a reply
# polls the bells of all of them at once, so each reply is timestamped when it arrives even
# while the host waits for another car (one slow car never eats into another's deadline).
_WAITING: set[SandboxedPolicy] = set()
_WAITING_LOCK = threading.Lock()


def _pump(me: SandboxedPolicy, timeout: float) -> None:
    """Wait up to ``timeout`` s for a wake-up on ``me``'s bell or any waiting policy's;
    take and timestamp every reply that came."""
    if me._bell >= 0 and len(_WAITING) == 1 and me in _WAITING:  # alone: no snapshot needed
        if me._spin_s > 0 and CONTENTION.spin_allowed() and me._spin(timeout):
            return
        if me._poller.poll(max(0, math.ceil(timeout * 1000))):
            me._pull(time.monotonic())
        return
    with _WAITING_LOCK:
        others = [p for p in _WAITING if p is not me and p._bell >= 0]
    if others or me._bell < 0:
        members = {p._bell: p for p in others}
        if me._bell >= 0:
            members[me._bell] = me
        poller = select.poll()
        for fd in members:
            poller.register(fd, select.POLLIN)
    else:  # one car waiting (a lone policy, or the last of a step): its own poller
        members, poller = {me._bell: me}, me._poller
    ready = poller.poll(max(0, math.ceil(timeout * 1000)))
    now = time.monotonic()
    for fd, _ in ready:
        members[fd]._pull(now)


def _box_bounds(
    space: spaces.Space[Any],
) -> tuple[tuple[int, ...], list[float], list[float]] | None:
    """A Box's shape and its bounds widened by ``ACTION_TOLERANCE`` exactly as
    :func:`arena.race.action_problem` computes them (in the space's dtype), flattened to
    Python floats; None for other spaces."""
    if not isinstance(space, spaces.Box):
        return None
    low = (space.low - ACTION_TOLERANCE).astype(np.float64).ravel().tolist()
    high = (space.high + ACTION_TOLERANCE).astype(np.float64).ravel().tolist()
    return tuple(space.shape), low, high


def _surely_within(
    arr: NDArray[Any], bounds: tuple[tuple[int, ...], list[float], list[float]]
) -> bool:
    """Whether ``arr`` is, quickly seen, an action of the Box that ``bounds`` describes:
    numeric, of its shape, every value within the widened bounds (NaN fails every
    comparison). A shortcut on every step's path (a few µs less than
    :func:`arena.race.action_problem`): it accepts only what ``action_problem`` accepts,
    and anything it does not accept is ``action_problem``'s call."""
    if arr.shape != bounds[0] or arr.dtype.kind not in "fiu":
        return False
    values = arr.tolist() if arr.ndim == 1 else arr.ravel().tolist()
    for value, low, high in zip(values, bounds[1], bounds[2], strict=True):
        if not low <= value <= high:
            return False
    return True


_GONE = "gone"  # a reply item: the worker's end of the bell closed, no reply came
_ACTION, _ERROR = Kind.ACTION, Kind.ERROR  # a module name is read faster than an enum's


# ---- the policy --------------------------------------------------------------------------


class SandboxedPolicy:
    """A submitted policy running in its own sandbox (see the module docstring).

    Args:
        bundle: an opened bundle (``root``: the extracted folder, ``manifest``).
        limits: resource limits and deadlines (default: :class:`SandboxLimits`).
        env_spec: the env it races in (:func:`env_spec_of`, :func:`make_env_spec`); default:
            from the manifest's declared ``env`` and ``action_mode``.
        pool: the :class:`SandboxPool` that ``close()`` gives it back to, if any.

    Attributes:
        name: the manifest's name.
        mode: ``"bwrap"`` or ``"seccomp"`` (the sandbox it runs in).
        sandbox_id: the latest sandbox's id (in its worker's command line, for audits).
        failure: the failure that ended it, if any.
        race_deadline: ``time.monotonic()`` value past which it is retired ``timeout`` (the
            race's wall-clock limit; None: none). No wait outlasts it.
    """

    def __init__(
        self,
        bundle: Bundle,
        limits: SandboxLimits | None = None,
        env_spec: dict[str, Any] | None = None,
        pool: SandboxPool | None = None,
    ) -> None:
        self.bundle = bundle
        self.pool = pool
        self._pooled = False  # idle in its pool
        self.scratch: Path | None = None  # a folder removed at shutdown (the bundle's copy)
        self.name = bundle.manifest.name
        self.limits = limits or SandboxLimits()
        self.env_spec = env_spec or spec_for_manifest(bundle.manifest)
        self.space = action_space_of(self.env_spec)
        self._box_bounds = _box_bounds(self.space)
        self.mode = sandbox_mode()
        self.failure: PolicyFailure | None = None
        self.sandbox_id: str | None = None  # of the latest start (it is in the worker's argv)
        self.hello: dict[str, Any] = {}
        self.bank = self.limits.overage_s
        self.race_deadline: float | None = None
        self.step_times: list[float] = []
        self._output = _Output()
        self._proc: SandboxProcess | None = None
        self._channel: Channel | None = None
        self._bell = -1  # the channel's bell while it may still ring (-1: ended or closed)
        self._poller = select.poll()  # polls the bell alone
        self._lock = threading.Lock()  # _pull may run on another waiting thread
        self._output_fd = -1
        self._reader: threading.Thread | None = None
        self._started_at = 0.0
        self._sent_at: float | None = None
        self._ready = False
        self._seq = 0  # the number of the latest request (READY comes as 0)
        self._posted = 0  # requests posted since the start (READY counts as one)
        self._rung = 0  # wake-ups read from the bell since the start
        self._rung_at_post = 0  # … when the current request was posted
        self._reply: tuple[float, Frame | ProtocolError | str] | None = None  # to _seq
        self._wakeups = False  # it holds one count of the process's fast wake-ups
        self._spin_limit = 0.0  # the longest it spins for a reply, s (scheduling module)
        self._spin_s = 0.0  # … for the next one: twice the last step time, within the limit

    # ---- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Spawn the sandbox (returns at once; the policy loads inside). Idempotent.

        Raises:
            SandboxError: the sandbox could not be started.
        """
        if self._proc is not None:
            return
        # First the settings: a malformed one fails before anything is held or started.
        self._spin_limit, self._spin_s = spin_limit_s(), 0.0
        self._hold_wakeups()
        self.failure = None
        self.bank = self.limits.overage_s
        self._ready = False
        self._seq = self._rung = self._rung_at_post = 0
        self._posted = 1  # READY answers the start itself
        self._reply = None
        channel = Channel(request_bytes_for(self.env_spec.get("obs_shape", [])))
        out_r, out_w = os.pipe()  # the worker's stdout and stderr
        args = ["--channel", channel.worker_arg(), "--spec", json.dumps(self.env_spec)]
        cpu = PLACEMENT.next_cpu()  # bound there for good (scheduling module)
        try:
            self._proc = SandboxProcess(
                args,
                self.bundle.root,
                self.limits,
                pass_fds=channel.worker_fds,
                output_fd=out_w,
                mode=self.mode,
                cpu=cpu,
            )
        except BaseException:
            channel.close()
            for fd in (out_r, out_w):
                os.close(fd)
            self._free_wakeups()
            raise
        finally:
            channel.spawned()  # the worker has its copies (or there is no worker)
        os.close(out_w)
        self.sandbox_id = self._proc.id
        self._channel = channel
        self._bell = channel.bell
        self._poller = select.poll()
        self._poller.register(channel.bell, select.POLLIN)
        self._output_fd = out_r
        self._started_at = time.monotonic()
        self._reader = threading.Thread(
            target=_drain_output,
            args=(out_r, self._output),
            name=f"sandbox-output-{self.name}",
            daemon=True,
        )
        self._reader.start()

    def close(self) -> None:
        """Ask the worker to stop, then kill the whole tree; idempotent.

        A policy of a :class:`SandboxPool` that is healthy (started, loaded, no failure, no
        request outstanding) goes back to its pool instead, still running.
        """
        if self._pooled:
            return
        if self.pool is not None and self._reusable():
            self.pool.give_back(self)
            return
        self.shutdown()

    def shutdown(self) -> None:
        """Stop the worker and kill the whole tree, pool or not; idempotent."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        channel = self._channel
        if proc.poll() is None and self.failure is None and channel is not None:
            with contextlib.suppress(OSError, ProtocolError):  # never blocks: see Channel.post
                channel.post(encode(Kind.CLOSE, seq=self._next_seq()))
                proc.wait(0.5)
        proc.kill()
        self._not_waiting()
        with self._lock:
            self._channel, self._bell = None, -1
            if channel is not None:
                channel.close()
        if self._reader is not None:
            self._reader.join(5.0)
            if not self._reader.is_alive():
                with contextlib.suppress(OSError):
                    os.close(self._output_fd)
        self._reader = None
        self._free_wakeups()
        if self.scratch is not None:
            shutil.rmtree(self.scratch, ignore_errors=True)
            self.scratch = None

    def _reusable(self) -> bool:
        return (
            self._proc is not None
            and self._proc.poll() is None
            and self._ready
            and self.failure is None
            and self._sent_at is None
            and self._bell >= 0
        )

    def _hold_wakeups(self) -> None:
        """Count this policy among the holders of the process's fast wake-ups
        (:mod:`submissions.scheduling`) while its sandbox is active; idempotent."""
        if not self._wakeups:
            WAKEUPS.acquire()
            self._wakeups = True

    def _free_wakeups(self) -> None:
        if self._wakeups:
            self._wakeups = False
            WAKEUPS.release()

    def _recycle(self) -> None:
        """Fresh per-race state (on leaving the pool): the bank, the race deadline, step
        times, the output kept."""
        self.bank = self.limits.overage_s
        self.race_deadline = None
        self.step_times = []
        self._spin_s = 0.0
        self._output.clear()

    def __enter__(self) -> SandboxedPolicy:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- the Policy protocol -------------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """Start if needed, wait until loaded (start-up allowance), then reset it.

        Raises:
            PolicyFailure: it failed to load, crashed, or was too slow.
        """
        self.start()
        if not self._ready:
            frame = self._wait(self._started_at + self.limits.startup_s, "start up")
            if frame.kind != Kind.READY:
                self._fail(
                    PolicyCrash(f"policy {self.name!r}: expected READY, got {frame.kind.name}")
                )
            with contextlib.suppress(ValueError):
                hello = json.loads(frame.text)  # from the worker, but the policy could forge it
                self.hello = hello if isinstance(hello, dict) else {}
            if self.mode == "seccomp" and not self.hello.get("landlock"):
                log.warning(
                    "policy %r runs in the seccomp fallback without Landlock: its file "
                    "access is limited by uid permissions only",
                    self.name,
                )
            self._ready = True
            allowance_end = self._started_at + self.limits.startup_s
        else:
            allowance_end = time.monotonic() + self.limits.step_deadline_s + self.bank
        if self.race_deadline is not None:
            allowance_end = min(allowance_end, self.race_deadline)
        seed_arr = np.array([] if seed is None else [seed], dtype=np.int64)
        self._post(Kind.RESET, seed_arr)
        frame = self._wait(allowance_end, "reset")
        if frame.kind != Kind.OK:
            self._fail(PolicyCrash(f"policy {self.name!r}: expected OK, got {frame.kind.name}"))

    def act(self, obs: Any) -> Any:
        """Send one observation and wait for the action (``send`` then ``receive``)."""
        self.send(obs)
        return self.receive()

    def send(self, obs: Any) -> None:
        """Send an observation; the step's clock starts now.

        Raises:
            PolicyFailure: it has already failed, answered ahead, or its worker is gone.
            ProtocolError: ``obs`` does not fit the channel (larger than the env spec's
                observation): the caller's mistake, not the policy's.
        """
        if self.failure is not None:
            raise self.failure
        if not self._ready:
            self.reset(None)
        self._check_race_deadline()
        sent = time.monotonic()  # the step's clock starts before the request is visible
        self._post(Kind.ACT, obs)
        self._sent_at = sent
        with _WAITING_LOCK:
            _WAITING.add(self)

    def receive(self) -> Any:
        """The action for the last observation sent (float32 array, or int if discrete).

        Raises:
            PolicyFailure: crash, timeout (deadline and bank spent) or invalid action.
        """
        if self.failure is not None:
            raise self.failure
        if self._sent_at is None:
            raise SubmissionError("receive() without send()")
        sent, self._sent_at = self._sent_at, None
        deadline = self.limits.step_deadline_s
        until = sent + deadline + self.bank
        if self.race_deadline is not None:
            until = min(until, self.race_deadline)
        try:
            frame, arrived = self._wait_timed(until, "act")
        finally:
            self._not_waiting()
        took = arrived - sent
        self.step_times.append(took)
        self._spin_s = min(2 * took, self._spin_limit) if took <= self._spin_limit else 0.0
        self.bank -= max(0.0, took - deadline)
        if self.bank < 0:
            self._fail(self._timeout(f"took {took:.3f} s"))
        if frame.kind is not _ACTION:  # (a module constant: on every step's path)
            if frame.kind == Kind.INVALID:
                self._fail(PolicyInvalid(f"policy {self.name!r}: {frame.text}"))
            self._fail(PolicyCrash(f"policy {self.name!r}: expected ACTION, got {frame.kind.name}"))
        return self._action(frame.array)

    def _action(self, arr: NDArray[Any]) -> Any:
        """``arr`` as the action it is (float32 array, or int if discrete), once checked
        against the action space (:func:`arena.race.action_problem`).

        Raises:
            PolicyInvalid: it is not an action of the space.
        """
        if self._box_bounds is not None and _surely_within(arr, self._box_bounds):
            return arr.astype(np.float32)
        problem = action_problem(arr, self.space)  # the rule (and what is wrong)
        if problem is not None:
            self._fail(PolicyInvalid(f"policy {self.name!r}: {problem}"))
        if isinstance(self.space, spaces.Discrete):
            return int(arr)
        return arr.astype(np.float32)

    # ---- reports -------------------------------------------------------------------------

    @property
    def output(self) -> str:
        """What the worker printed (capped: first 4 KiB and last 16 KiB)."""
        return self._output.text()

    @property
    def stats(self) -> dict[str, Any]:
        """Sandbox mode, steps, step times (s), overage used (s), bytes printed, failure."""
        times = self.step_times
        return {
            "mode": self.mode,
            "steps": len(times),
            "mean_step_s": round(float(np.mean(times)), 6) if times else None,
            "max_step_s": round(max(times), 6) if times else None,
            "overage_used_s": round(self.limits.overage_s - max(self.bank, 0.0), 6),
            "output_bytes": self._output.total,
            "landlock_abi": self.hello.get("landlock"),
            "failure": None if self.failure is None else self.failure.dnf_reason,
        }

    # ---- internals -----------------------------------------------------------------------

    def _not_waiting(self) -> None:
        with _WAITING_LOCK:
            _WAITING.discard(self)

    def _post(self, kind: Kind, array: Any) -> None:
        """Number and post a request (never blocks); its reply is the only one that counts.

        Raises:
            PolicyFailure: the reply slot already holds this number (answered ahead), or the
                worker's end of the ring is closed.
            ProtocolError: the request does not fit the channel (the caller's mistake).
        """
        channel = self._channel
        assert channel is not None  # started
        seq = (self._seq + 1) % SEQ_MODULO or 1  # 0 is READY's
        frame = encode(kind, array, seq)
        if len(frame) > channel.request_bytes:  # before any state changes: not its fault
            raise ProtocolError(
                f"a {kind.name} request of {len(frame)} bytes does not fit the channel's "
                f"{channel.request_bytes} (the env spec's obs_shape is "
                f"{self.env_spec.get('obs_shape')})"
            )
        self._seq = seq
        if channel.reply_seq() == seq:  # an honest slot holds the previous reply's number
            self._fail(
                PolicyInvalid(
                    f"policy {self.name!r} broke the protocol: a reply numbered {seq} was "
                    "there before its request (answers sent ahead)"
                )
            )
        with self._lock:
            self._reply = None
            self._rung_at_post = self._rung
            self._posted += 1
        try:
            channel.post(frame)
        except BrokenPipeError:
            self._gone(f"{kind.name} request")

    def _pull(self, now: float) -> None:
        """Read the bell (never blocks) and, if the current request's reply has come, take a
        copy of it, timestamped ``now``."""
        with self._lock:
            channel = self._channel
            if channel is None or self._bell < 0:
                return
            count, ended = channel.drain()
            self._rung += count
            if ended:
                self._bell = -1
            if self._reply is not None:
                return
            if self._rung > self._rung_at_post:
                # An honest worker rings only after writing its reply, and the host drains
                # every ring before taking a reply: a ring since the request with the slot
                # numbered otherwise is a stale, forged or scribbled reply.
                seq = channel.reply_seq()
                frame: Frame | ProtocolError | str
                if seq != self._seq:
                    frame = ProtocolError(
                        f"a reply numbered {seq} rung in while waiting for the reply to {self._seq}"
                    )
                else:
                    try:
                        frame = channel.take()
                    except ProtocolError as err:
                        frame = err
                self._reply = (now, frame)
            elif ended:
                self._reply = (now, _GONE)

    def _spin(self, timeout: float) -> bool:
        """Busy-wait up to the spin budget (and ``timeout`` s) until the reply slot holds
        the current request's number, then take the reply (:mod:`submissions.scheduling`:
        how the host waits). Returns whether a reply was taken; False sends the caller to
        ``poll`` (budget spent, or the number came before its bell: the bell decides)."""
        channel = self._channel
        budget = min(self._spin_s, timeout)
        if channel is None or budget <= 0:
            return False
        peek, seq, clock = channel.reply_seq, self._seq, time.perf_counter
        end = clock() + budget
        try:
            while peek() != seq:
                if clock() >= end:
                    return False
        except ValueError:  # the channel was closed meanwhile (shut down from another thread)
            return False
        self._pull(time.monotonic())
        return self._reply is not None

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) % SEQ_MODULO or 1  # 0 is READY's
        return self._seq

    def _check_race_deadline(self) -> None:
        if self.race_deadline is not None and time.monotonic() >= self.race_deadline:
            self._fail(
                PolicyTimeout(f"policy {self.name!r}: the race's wall-clock limit was reached")
            )

    def _wait(self, until: float, what: str) -> Frame:
        return self._wait_timed(until, what)[0]

    def _wait_timed(self, until: float, what: str) -> tuple[Frame, float]:
        """The reply to the current request (READY: 0) and its arrival time.

        Raises:
            PolicyFailure: nothing by ``until`` (timeout), more wake-ups than requests, a
                broken frame or a reply numbered otherwise (invalid), an ERROR reply or the
                worker's end (crash).
        """
        while self._reply is None and self._bell >= 0:
            if self._rung > self._posted:
                break
            left = until - time.monotonic()
            if left <= 0:
                self._pull(time.monotonic())  # what came while the host was busy elsewhere
                break
            _pump(self, left)
        if self._rung > self._posted:
            self._fail(
                PolicyInvalid(
                    f"policy {self.name!r} broke the protocol: {self._rung} wake-ups for "
                    f"{self._posted} requests (it woke the host unasked)"
                )
            )
        got = self._reply
        if got is None:
            self._check_race_deadline()
            if what == "act":
                self._fail(self._timeout("no action"))
            self._fail(
                PolicyTimeout(
                    f"policy {self.name!r} did not {what} within its {self.limits.startup_s:g} s "
                    "start-up allowance"
                )
            )
        arrived, item = got
        if isinstance(item, ProtocolError):
            self._fail(PolicyInvalid(f"policy {self.name!r} broke the protocol: {item}"))
        if isinstance(item, str):
            self._gone(what)
        if item.seq != self._seq:  # the slot changed between the peek and the copy
            self._fail(
                PolicyInvalid(
                    f"policy {self.name!r} broke the protocol: a {item.kind.name} reply "
                    f"numbered {item.seq} while waiting for the reply to {self._seq}"
                )
            )
        if item.kind is _ERROR:
            self._fail(PolicyCrash(f"policy {self.name!r}: {item.text}"))
        return item, arrived

    def _gone(self, what: str) -> NoReturn:
        """Its end of the channel closed: it exited (crash), or, still running, closed the
        channel itself (invalid). Waits at most :data:`EXIT_WAIT_S` to tell which, taking
        the replies of the other cars meanwhile (their clocks are theirs, not its)."""
        status = None
        end = time.monotonic() + EXIT_WAIT_S
        while self._proc is not None and (status := self._proc.poll()) is None:
            left = end - time.monotonic()
            if left <= 0:
                break
            _pump(self, min(left, 0.02))
        if status is None:
            self._fail(
                PolicyInvalid(
                    f"policy {self.name!r} broke the protocol: it closed its channel ({what})"
                )
            )
        last = self.output.strip().splitlines()[-1:] or ["(no output)"]
        self._fail(
            PolicyCrash(f"policy {self.name!r}: its worker exited ({status}): {last[0][:300]}")
        )

    def _timeout(self, detail: str) -> PolicyTimeout:
        return PolicyTimeout(
            f"policy {self.name!r} missed its {self.limits.step_deadline_s:g} s deadline with "
            f"its {self.limits.overage_s:g} s overage bank spent ({detail})"
        )

    def _fail(self, failure: PolicyFailure) -> NoReturn:
        """Record ``failure`` (its text capped), kill the sandbox, raise."""
        if self.failure is None:
            text = str(failure)
            capped = cap_text(text, MAX_DETAIL)
            self.failure = failure if capped == text else type(failure)(capped)
        if self._proc is not None:
            self._proc.stop()  # at once: shutdown() reaps it, off the other cars' clocks
        raise self.failure


class SandboxPool:
    """Started sandboxes kept between the races of one batch, keyed by bundle, env spec and
    limits; :meth:`policy` hands out an idle one (or a new one), and a pooled policy's
    ``close()`` brings it back while healthy (any failure kills it as usual).

    The trade: a policy keeps its process, and so its memory, from one race of the batch to
    the next (``reset(seed)`` starts each race; its bank and deadlines start afresh). Only
    the same bundle ever reuses a sandbox, so nothing crosses between submissions. Use it
    as a context manager: leaving it kills every sandbox it holds.
    """

    def __init__(self) -> None:
        self._idle: dict[str, list[SandboxedPolicy]] = {}

    @staticmethod
    def _key(bundle: Bundle, limits: SandboxLimits | None, env_spec: dict[str, Any]) -> str:
        return json.dumps([str(bundle.root), repr(limits), env_spec], sort_keys=True)

    def policy(
        self,
        bundle: Bundle,
        limits: SandboxLimits | None = None,
        env_spec: dict[str, Any] | None = None,
    ) -> SandboxedPolicy:
        """A sandboxed policy for ``bundle``: an idle, still-running one if there is one."""
        spec = env_spec or spec_for_manifest(bundle.manifest)
        limits = limits or SandboxLimits()
        idle = self._idle.get(self._key(bundle, limits, spec))
        if idle:
            policy = idle.pop()
            policy._pooled = False
            policy._hold_wakeups()
            policy._recycle()
            policy.name = bundle.manifest.name
            return policy
        return SandboxedPolicy(bundle, limits, spec, pool=self)

    def give_back(self, policy: SandboxedPolicy) -> None:
        """Keep ``policy`` (healthy, running) for a later race."""
        key = self._key(policy.bundle, policy.limits, policy.env_spec)
        policy._free_wakeups()  # idle between races: its CPUs may sleep
        policy._pooled = True
        self._idle.setdefault(key, []).append(policy)

    def retain(self, needed: Mapping[str, int]) -> None:
        """Kill the idle sandboxes beyond ``needed[str(bundle root)]`` per bundle (none for
        a bundle not in ``needed``): what the next race cannot use is not kept running."""
        for key, policies in list(self._idle.items()):
            keep = needed.get(str(policies[0].bundle.root), 0) if policies else 0
            for policy in policies[keep:]:
                policy._pooled = False
                policy.shutdown()
            del policies[keep:]
            if not policies:
                del self._idle[key]

    @property
    def idle(self) -> int:
        """Sandboxes waiting for a race."""
        return sum(len(v) for v in self._idle.values())

    def close(self) -> None:
        """Kill every idle sandbox."""
        idle, self._idle = self._idle, {}
        for policies in idle.values():
            for policy in policies:
                policy._pooled = False
                policy.shutdown()

    def __enter__(self) -> SandboxPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _bundle_opponent(path: Path, env: RacingEnv) -> SandboxedPolicy:
    """A bundle as an opponent in :mod:`agents.gym_env` (its loader hook): extracted into a
    private folder (removed when the policy is closed) and run in its sandbox."""
    scratch = Path(tempfile.mkdtemp(prefix="slipstream-opponent-"))
    try:
        policy = SandboxedPolicy(open_bundle(path, scratch / "bundle"), env_spec=env_spec_of(env))
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    policy.scratch = scratch
    return policy


register_bundle_loader(_bundle_opponent)
