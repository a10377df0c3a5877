"""``SandboxedPolicy``: a submitted policy in its sandbox, driven over the worker protocol.

It implements the :class:`agents.Policy` protocol (``name``, ``reset(seed)``, ``act(obs)``)
plus ``start()`` (spawn the sandbox; the policy loads inside while the host does other
work), two-phase ``send(obs)`` / ``receive()`` (so a race steps all sandboxed cars in
parallel) and ``close()`` (kill the whole process tree).

Deadlines, Kaggle style: each action must arrive within ``step_deadline_s`` of its
observation being sent; time beyond that is drawn from an overage bank of ``overage_s``
seconds for the whole race, and the policy times out when the bank is spent. Loading and
the first reset share a separate start-up allowance (``startup_s``). Arrival times are
taken by a reader thread the moment a frame is complete, so one slow car never eats into
another's deadline.

Failures raise a :class:`PolicyFailure` whose ``dnf_reason`` the race records:

==================  ==============  ===================================================
exception           ``dnf_reason``  when
==================  ==============  ===================================================
``PolicyCrash``     ``"error"``     load failed, the policy raised, the worker died or
                                    broke the protocol
``PolicyTimeout``   ``"timeout"``   deadline and overage bank exhausted, or start-up
                                    took longer than ``startup_s``
``PolicyInvalid``   ``"invalid"``   wrong shape or dtype, NaN/inf, out of the action
                                    space
==================  ==============  ===================================================

After any failure the sandbox is killed at once. The worker's stdout/stderr are drained
continuously and only the first 4 KiB and last 16 KiB are kept (:attr:`output`), so a
policy printing megabytes costs the host nothing but the reading.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import selectors
import threading
import time
from typing import Any, NoReturn

import numpy as np
from gymnasium import spaces

from arena.actions import DiscreteActions
from arena.env import RacingEnv
from arena.observations import ObservationLayout
from arena.race import action_problem
from arena.version import ENV_VERSION
from submissions.bundle import Bundle, Manifest
from submissions.errors import SubmissionError
from submissions.protocol import (
    Frame,
    FrameDecoder,
    Kind,
    ProtocolError,
    encode,
    write_all,
)
from submissions.sandbox import SandboxLimits, SandboxProcess, sandbox_mode

log = logging.getLogger(__name__)
OUTPUT_HEAD = 4 << 10  # bytes of the worker's output kept from the start
OUTPUT_TAIL = 16 << 10  # … and from the end


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
    *, lidar_rays: int = 64, k_opponents: int = 3, action_mode: str = "continuous"
) -> dict[str, Any]:
    """The env spec a sandboxed policy is given (and its actions are checked against).

    Keys: ``obs_mode``, ``obs_shape``, ``action_mode``, ``action_shape`` (``[2]`` or
    ``[]``), ``action_low``/``action_high`` (continuous), ``n_actions`` (discrete),
    ``lidar_rays``, ``k_opponents``, ``env_version``. Matches :class:`arena.env.RacingEnv`
    with the same arguments, without building one.
    """
    spec: dict[str, Any] = {
        "obs_mode": "vector",
        "obs_shape": [ObservationLayout(lidar_rays, k_opponents).size],
        "action_mode": action_mode,
        "lidar_rays": lidar_rays,
        "k_opponents": k_opponents,
        "env_version": ENV_VERSION,
    }
    if action_mode == "discrete":
        return spec | {"action_shape": [], "n_actions": DiscreteActions().n}
    return spec | {"action_shape": [2], "action_low": [-1.0, -1.0], "action_high": [1.0, 1.0]}


def env_spec_of(env: RacingEnv) -> dict[str, Any]:
    """The env spec of a built env (its first car's spaces)."""
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
    """The default env spec for a bundle's manifest (its declared ``env`` and action mode)."""
    return make_env_spec(
        lidar_rays=int(manifest.env.get("lidar_rays", 64)),
        k_opponents=int(manifest.env.get("k_opponents", 3)),
        action_mode=manifest.action_mode,
    )


def action_space_of(spec: dict[str, Any]) -> spaces.Space[Any]:
    """The gymnasium action space an env spec describes."""
    if spec.get("action_mode") == "discrete":
        return spaces.Discrete(int(spec["n_actions"]))
    low = np.asarray(spec["action_low"], dtype=np.float32)
    high = np.asarray(spec["action_high"], dtype=np.float32)
    return spaces.Box(low, high, dtype=np.float32)


# ---- the reader thread -------------------------------------------------------------------


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

    def text(self) -> str:
        skipped = self.total - len(self.head) - len(self.tail)
        gap = f"\n[… {skipped} bytes not kept …]\n".encode() if skipped > 0 else b""
        return bytes(self.head + gap + self.tail).decode("utf-8", "replace")


_EOF = object()
_Item = tuple[float, Any]  # (arrival time, Frame | ProtocolError | _EOF)


def _read_loop(proto_fd: int, output_fd: int, out: queue.Queue[_Item], output: _Output) -> None:
    """Until both pipes end: timestamp and queue each complete frame, drain the output."""
    decoder = FrameDecoder()
    with selectors.DefaultSelector() as sel:
        sel.register(proto_fd, selectors.EVENT_READ)
        sel.register(output_fd, selectors.EVENT_READ)
        while sel.get_map():
            for key, _ in sel.select():
                fd = int(key.fd)
                try:
                    data = os.read(fd, 1 << 16)
                except OSError:
                    data = b""
                now = time.monotonic()
                if fd == output_fd:
                    output.add(data)
                elif data:
                    try:
                        for frame in decoder.feed(data):
                            out.put((now, frame))
                        continue
                    except ProtocolError as err:
                        out.put((now, err))
                    # a broken stream is over: stop listening to it
                else:
                    out.put((now, _EOF))
                if not data or fd == proto_fd:
                    sel.unregister(fd)


# ---- the policy --------------------------------------------------------------------------


class SandboxedPolicy:
    """A submitted policy running in its own sandbox (see the module docstring).

    Args:
        bundle: an opened bundle (``root``: the extracted folder, ``manifest``).
        limits: resource limits and deadlines (default: :class:`SandboxLimits`).
        env_spec: the env it races in (:func:`env_spec_of`, :func:`make_env_spec`); default:
            from the manifest's declared ``env`` and ``action_mode``.

    Attributes:
        name: the manifest's name.
        mode: ``"bwrap"`` or ``"seccomp"`` (the sandbox it runs in).
        sandbox_id: the latest sandbox's id (in its worker's command line, for audits).
        failure: the failure that ended it, if any.
    """

    def __init__(
        self,
        bundle: Bundle,
        limits: SandboxLimits | None = None,
        env_spec: dict[str, Any] | None = None,
    ) -> None:
        self.bundle = bundle
        self.name = bundle.manifest.name
        self.limits = limits or SandboxLimits()
        self.env_spec = env_spec or spec_for_manifest(bundle.manifest)
        self.space = action_space_of(self.env_spec)
        self.mode = sandbox_mode()
        self.failure: PolicyFailure | None = None
        self.sandbox_id: str | None = None  # of the latest start (it is in the worker's argv)
        self.hello: dict[str, Any] = {}
        self.bank = self.limits.overage_s
        self.step_times: list[float] = []
        self._output = _Output()
        self._proc: SandboxProcess | None = None
        self._frames: queue.Queue[_Item] = queue.Queue()
        self._reader: threading.Thread | None = None
        self._to_worker = -1
        self._started_at = 0.0
        self._sent_at: float | None = None
        self._ready = False
        self._reader_fds: tuple[int, ...] = ()

    # ---- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Spawn the sandbox (returns at once; the policy loads inside). Idempotent.

        Raises:
            SandboxError: the sandbox could not be started.
        """
        if self._proc is not None:
            return
        self.failure = None
        self.bank = self.limits.overage_s
        self._ready = False
        self._frames = queue.Queue()
        req_r, req_w = os.pipe()  # host → worker
        rep_r, rep_w = os.pipe()  # worker → host
        out_r, out_w = os.pipe()  # the worker's stdout and stderr
        args = ["--in", str(req_r), "--out", str(rep_w), "--spec", json.dumps(self.env_spec)]
        try:
            self._proc = SandboxProcess(
                args,
                self.bundle.root,
                self.limits,
                pass_fds=(req_r, rep_w),
                output_fd=out_w,
                mode=self.mode,
            )
        except BaseException:
            for fd in (req_r, req_w, rep_r, rep_w, out_r, out_w):
                os.close(fd)
            raise
        self.sandbox_id = self._proc.id
        for fd in (req_r, rep_w, out_w):  # the worker's ends
            os.close(fd)
        self._to_worker = req_w
        self._started_at = time.monotonic()
        self._reader = threading.Thread(
            target=_read_loop,
            args=(rep_r, out_r, self._frames, self._output),
            name=f"sandbox-{self.name}",
            daemon=True,
        )
        self._reader_fds = (rep_r, out_r)
        self._reader.start()

    def close(self) -> None:
        """Ask the worker to stop, then kill the whole tree; idempotent."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None and self.failure is None:
            with contextlib.suppress(OSError):
                write_all(self._to_worker, encode(Kind.CLOSE))
            proc.wait(0.5)
        proc.kill()
        with contextlib.suppress(OSError):
            os.close(self._to_worker)
        if self._reader is not None:
            self._reader.join(5.0)
            if not self._reader.is_alive():
                for fd in self._reader_fds:
                    with contextlib.suppress(OSError):
                        os.close(fd)
        self._reader = None

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
        seed_arr = np.array([] if seed is None else [seed], dtype=np.int64)
        self._write(encode(Kind.RESET, seed_arr))
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
            PolicyFailure: it has already failed, or its input is closed (it died).
        """
        if self.failure is not None:
            raise self.failure
        if not self._ready:
            self.reset(None)
        self._write(encode(Kind.ACT, np.asarray(obs)))
        self._sent_at = time.monotonic()

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
        frame, arrived = self._wait_timed(sent + deadline + self.bank, "act")
        took = arrived - sent
        self.step_times.append(took)
        self.bank -= max(0.0, took - deadline)
        if self.bank < 0:
            self._fail(self._timeout(f"took {took:.3f} s"))
        if frame.kind == Kind.INVALID:
            self._fail(PolicyInvalid(f"policy {self.name!r}: {frame.text}"))
        if frame.kind != Kind.ACTION:
            self._fail(PolicyCrash(f"policy {self.name!r}: expected ACTION, got {frame.kind.name}"))
        problem = action_problem(frame.array, self.space)
        if problem is not None:
            self._fail(PolicyInvalid(f"policy {self.name!r}: {problem}"))
        if isinstance(self.space, spaces.Discrete):
            return int(frame.array)
        return frame.array.astype(np.float32)

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

    def _write(self, data: bytes) -> None:
        try:
            write_all(self._to_worker, data)
        except OSError as err:  # BrokenPipeError: the worker is gone
            self._fail(PolicyCrash(f"policy {self.name!r}: its worker is gone ({err})"))

    def _wait(self, until: float, what: str) -> Frame:
        return self._wait_timed(until, what)[0]

    def _wait_timed(self, until: float, what: str) -> tuple[Frame, float]:
        try:
            arrived, item = self._frames.get(timeout=max(0.0, until - time.monotonic()))
        except queue.Empty:
            if what == "act":
                self._fail(self._timeout("no action"))
            self._fail(
                PolicyTimeout(
                    f"policy {self.name!r} did not {what} within its {self.limits.startup_s:g} s "
                    "start-up allowance"
                )
            )
        if isinstance(item, Frame):
            if item.kind == Kind.ERROR:
                self._fail(PolicyCrash(f"policy {self.name!r}: {item.text}"))
            return item, arrived
        if isinstance(item, ProtocolError):
            self._fail(PolicyCrash(f"policy {self.name!r} broke the protocol: {item}"))
        status = self._proc.wait(2.0) if self._proc is not None else None
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
        """Record ``failure``, kill the sandbox, raise."""
        if self.failure is None:
            self.failure = failure
        if self._proc is not None:
            self._proc.kill()
        raise self.failure
