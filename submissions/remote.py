"""``SandboxedPolicy``: a submitted policy in its sandbox, driven over the worker protocol.

It implements the :class:`agents.Policy` protocol (``name``, ``reset(seed)``, ``act(obs)``)
plus ``start()`` (spawn the sandbox; the policy loads inside while the host does other
work), two-phase ``send(obs)`` / ``receive()`` (so a race steps all sandboxed cars in
parallel) and ``close()`` (kill the whole process tree).

Deadlines, Kaggle style: each action must arrive within ``step_deadline_s`` of its
observation being sent; time beyond that is drawn from an overage bank of ``overage_s``
seconds for the whole race, and the policy times out when the bank is spent. Loading and
the first reset share a separate start-up allowance (``startup_s``). Replies are read by
the thread that waits for one, which polls the reply pipes of every car with a request
outstanding at once and timestamps each reply as it comes, so one slow car never eats into
another's deadline (a thread drains the workers' stdout/stderr, off the step's path). A
race may also set :attr:`SandboxedPolicy.race_deadline` (the job's wall-clock limit,
:mod:`submissions.jobs`): no wait outlasts it.

Nothing the policy does can wedge the host:

* the host never blocks writing to it: its input pipe is non-blocking, ``send`` writes what
  fits and ``receive`` finishes the write within the step's deadline (a policy that stops
  reading times out);
* requests are numbered and only the reply to the current one counts; a reply numbered
  otherwise (stale, unprompted, guessed ahead) or one that arrived before its request was
  sent retires the policy as ``invalid`` (it broke the protocol);
* at most :data:`MAX_QUEUED` replies wait on the host and each is at most
  :data:`REPLY_MAX_FRAME` bytes; a policy that floods the host is retired ``invalid``;
* a malformed frame (bad header, shape, size) is ``invalid``: whatever a hostile stream
  provokes in the decoder is reported as a protocol error, never lost;
* every failure's text is capped at :data:`~submissions.protocol.MAX_TEXT` bytes.

Failures raise a :class:`PolicyFailure` whose ``dnf_reason`` the race records:

==================  ==============  ===================================================
exception           ``dnf_reason``  when
==================  ==============  ===================================================
``PolicyCrash``     ``"error"``     load failed, the policy raised, the worker died
``PolicyTimeout``   ``"timeout"``   deadline and overage bank exhausted, start-up took
                                    longer than ``startup_s``, it stopped reading its
                                    input, or the race's wall-clock limit was reached
``PolicyInvalid``   ``"invalid"``   wrong shape or dtype, NaN/inf, out of the action
                                    space; broke the protocol (malformed or oversized
                                    frame, reply out of sequence, flooding)
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
from collections import deque
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from gymnasium import spaces

from agents.gym_env import register_bundle_loader
from arena.actions import DiscreteActions
from arena.env import RacingEnv
from arena.observations import ObservationLayout
from arena.race import action_problem
from arena.version import ENV_VERSION
from submissions.bundle import Bundle, Manifest, open_bundle
from submissions.errors import SubmissionError
from submissions.protocol import (
    MAX_TEXT,
    SEQ_MODULO,
    Frame,
    FrameDecoder,
    Kind,
    ProtocolError,
    cap_text,
    encode,
)
from submissions.sandbox import SandboxLimits, SandboxProcess, sandbox_mode

log = logging.getLogger(__name__)
OUTPUT_HEAD = 4 << 10  # bytes of the worker's output kept from the start
OUTPUT_TAIL = 16 << 10  # … and from the end
REPLY_MAX_FRAME = 64 << 10  # bytes: a reply is an action, an OK or ≤ 4 KiB of text
MAX_QUEUED = 8  # replies waiting on the host; an honest worker has at most 2 (READY, OK)
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

    def clear(self) -> None:
        self.head.clear()
        self.tail.clear()
        self.total = 0

    def text(self) -> str:
        skipped = self.total - len(self.head) - len(self.tail)
        gap = f"\n[… {skipped} bytes not kept …]\n".encode() if skipped > 0 else b""
        return bytes(self.head + gap + self.tail).decode("utf-8", "replace")


_EOF = object()
_FLOOD = object()
_Item = tuple[float, Any]  # (arrival time, Frame | ProtocolError | _EOF | _FLOOD)


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


def _queue_frames(
    decoder: FrameDecoder, data: bytes, now: float, out: deque[_Item], flooded: threading.Event
) -> bool:
    """Queue the frames ``data`` completes; False once the stream is over (error, flood).

    ``out`` holds at most :data:`MAX_QUEUED` frames, then one final item (``_FLOOD``, with
    ``flooded`` set, or the :class:`ProtocolError`); whatever a hostile stream provokes in
    the decoder is a ProtocolError, never an escaping exception.
    """
    try:
        frames = decoder.feed(data)
    except ProtocolError as err:
        out.append((now, err))
        return False
    except Exception as err:
        out.append((now, ProtocolError(f"unreadable frame: {type(err).__name__}: {err}")))
        return False
    for frame in frames:
        if len(out) >= MAX_QUEUED:
            flooded.set()
            out.append((now, _FLOOD))
            return False
        out.append((now, frame))
    return True


# Policies of this process with a request outstanding. Whichever thread waits for a reply
# polls all of their reply pipes at once, so each reply is timestamped when it arrives even
# while the host waits for another car (one slow car never eats into another's deadline),
# and no thread sits between a reply and its reader.
_WAITING: set[SandboxedPolicy] = set()
_WAITING_LOCK = threading.Lock()


def _pump(me: SandboxedPolicy, timeout: float) -> None:
    """Wait up to ``timeout`` s for a reply on ``me``'s pipe or any waiting policy's; read
    and timestamp every reply that came."""
    with _WAITING_LOCK:
        members = {p._from_worker: p for p in _WAITING if p._from_worker >= 0}
    if me._from_worker >= 0:
        members[me._from_worker] = me
    poller = select.poll()
    for fd in members:
        poller.register(fd, select.POLLIN)
    ready = poller.poll(max(0, math.ceil(timeout * 1000)))
    now = time.monotonic()
    for fd, _ in ready:
        members[fd]._pull(now)


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
        self.mode = sandbox_mode()
        self.failure: PolicyFailure | None = None
        self.sandbox_id: str | None = None  # of the latest start (it is in the worker's argv)
        self.hello: dict[str, Any] = {}
        self.bank = self.limits.overage_s
        self.race_deadline: float | None = None
        self.step_times: list[float] = []
        self._output = _Output()
        self._proc: SandboxProcess | None = None
        self._frames: deque[_Item] = deque()  # replies read, not yet taken
        self._flooded = threading.Event()
        self._decoder = FrameDecoder(REPLY_MAX_FRAME)
        self._pull_lock = threading.Lock()
        self._from_worker = -1  # the reply pipe (non-blocking; -1 once over)
        self._output_fd = -1
        self._reader: threading.Thread | None = None
        self._to_worker = -1
        self._started_at = 0.0
        self._sent_at: float | None = None
        self._ready = False
        self._seq = 0  # the number of the latest request (READY comes as 0)
        self._unsent = bytearray()  # what the worker's full input pipe has not taken yet

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
        self._frames = deque()
        self._flooded = threading.Event()
        self._decoder = FrameDecoder(REPLY_MAX_FRAME)
        self._seq = 0
        self._unsent.clear()
        req_r, req_w = os.pipe()  # host → worker
        os.set_blocking(req_w, False)  # never block on a worker that stops reading
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
        os.set_blocking(rep_r, False)
        self._from_worker = rep_r
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
        request or reply outstanding) goes back to its pool instead, still running.
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
        if proc.poll() is None and self.failure is None and not self._unsent:
            with contextlib.suppress(OSError):  # non-blocking: a full pipe just gets killed
                os.write(self._to_worker, encode(Kind.CLOSE))
                proc.wait(0.5)
        proc.kill()
        self._not_waiting()
        with self._pull_lock:
            fds = (self._to_worker, self._from_worker)
            self._from_worker = -1
        for fd in fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        if self._reader is not None:
            self._reader.join(5.0)
            if not self._reader.is_alive():
                with contextlib.suppress(OSError):
                    os.close(self._output_fd)
        self._reader = None
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
            and not self._unsent
            and not self._frames
        )

    def _recycle(self) -> None:
        """Fresh per-race state (on leaving the pool): the bank, the race deadline, step
        times, the output kept."""
        self.bank = self.limits.overage_s
        self.race_deadline = None
        self.step_times = []
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
            frame = self._wait(self._started_at + self.limits.startup_s, "start up", 0)
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
        seq = self._next_seq()
        asked = time.monotonic()
        self._write(encode(Kind.RESET, seed_arr, seq))
        self._flush(allowance_end, "reset")
        frame = self._wait(allowance_end, "reset", seq, asked)
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
        self._check_race_deadline()
        frame = encode(Kind.ACT, np.asarray(obs), self._next_seq())
        self._pull(time.monotonic())  # anything already there came unasked (checked later)
        self._sent_at = time.monotonic()  # before the write: no honest reply precedes it
        self._write(frame)
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
            self._flush(until, "act")
            frame, arrived = self._wait_timed(until, "act", self._seq, sent)
        finally:
            self._not_waiting()
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

    def _not_waiting(self) -> None:
        with _WAITING_LOCK:
            _WAITING.discard(self)

    def _pull(self, now: float) -> None:
        """Read what the reply pipe holds (never blocks); queue its frames as of ``now``."""
        with self._pull_lock:
            while self._from_worker >= 0:
                try:
                    data = os.read(self._from_worker, 1 << 16)
                except (BlockingIOError, InterruptedError):
                    return
                except OSError:
                    data = b""
                if not data:
                    self._frames.append((now, _EOF))
                elif _queue_frames(self._decoder, data, now, self._frames, self._flooded):
                    continue
                # a stream that ended, broke or flooded is over: stop reading it
                with contextlib.suppress(OSError):
                    os.close(self._from_worker)
                self._from_worker = -1

    def _next_item(self, until: float) -> _Item | None:
        """The next reply read (waiting until ``until``), or None."""
        while not self._frames:
            left = until - time.monotonic()
            if left <= 0:
                self._pull(time.monotonic())  # what came while the host was busy elsewhere
                break
            if self._from_worker < 0:
                time.sleep(left)  # nothing more can come
                break
            _pump(self, left)
        return self._frames.popleft() if self._frames else None

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) % SEQ_MODULO or 1  # 0 is READY's
        return self._seq

    def _write(self, data: bytes) -> None:
        """Queue ``data`` for the worker and write what its pipe takes now (never blocks)."""
        self._unsent += data
        self._flush(None, "")

    def _flush(self, until: float | None, what: str) -> None:
        """Write the queued bytes; wait for room until ``until`` (None: do not wait).

        Raises:
            PolicyFailure: the worker is gone (crash), or its input was still full at
                ``until`` (timeout: it stopped reading).
        """
        while self._unsent:
            try:
                n = os.write(self._to_worker, self._unsent)
            except (BlockingIOError, InterruptedError):
                n = 0
            except OSError as err:  # BrokenPipeError: the worker is gone
                self._fail(PolicyCrash(f"policy {self.name!r}: its worker is gone ({err})"))
            del self._unsent[:n]
            if not self._unsent or until is None:
                return
            left = until - time.monotonic()
            if left <= 0:
                self._check_race_deadline()
                self._fail(
                    PolicyTimeout(
                        f"policy {self.name!r} stopped reading its input ({what}: "
                        f"{len(self._unsent)} bytes not taken by the deadline)"
                    )
                )
            select.select([], [self._to_worker], [], left)

    def _check_race_deadline(self) -> None:
        if self.race_deadline is not None and time.monotonic() >= self.race_deadline:
            self._fail(
                PolicyTimeout(f"policy {self.name!r}: the race's wall-clock limit was reached")
            )

    def _wait(self, until: float, what: str, seq: int, asked: float | None = None) -> Frame:
        return self._wait_timed(until, what, seq, asked)[0]

    def _wait_timed(
        self, until: float, what: str, seq: int, asked: float | None = None
    ) -> tuple[Frame, float]:
        """The reply to request ``seq`` (READY: 0), asked at ``asked``, and its arrival time.

        Raises:
            PolicyFailure: nothing by ``until`` (timeout), a flood, a reply numbered
                otherwise or older than its request, a broken frame (invalid), an ERROR
                reply or the worker's end (crash).
        """
        if self._flooded.is_set():
            self._flood()
        got = self._next_item(until)
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
        if self._flooded.is_set():
            self._flood()
        arrived, item = got
        if isinstance(item, Frame):
            if asked is not None and arrived < asked:
                self._fail(
                    PolicyInvalid(
                        f"policy {self.name!r} broke the protocol: a {item.kind.name} reply "
                        "sent before its request (answers sent ahead)"
                    )
                )
            if item.seq != seq:
                self._fail(
                    PolicyInvalid(
                        f"policy {self.name!r} broke the protocol: a {item.kind.name} reply "
                        f"numbered {item.seq} while waiting for the reply to {seq}"
                    )
                )
            if item.kind == Kind.ERROR:
                self._fail(PolicyCrash(f"policy {self.name!r}: {item.text}"))
            return item, arrived
        if isinstance(item, ProtocolError):
            self._fail(PolicyInvalid(f"policy {self.name!r} broke the protocol: {item}"))
        if item is _FLOOD:
            self._flood()
        status = self._proc.wait(2.0) if self._proc is not None else None
        last = self.output.strip().splitlines()[-1:] or ["(no output)"]
        self._fail(
            PolicyCrash(f"policy {self.name!r}: its worker exited ({status}): {last[0][:300]}")
        )

    def _flood(self) -> NoReturn:
        self._fail(
            PolicyInvalid(
                f"policy {self.name!r} broke the protocol: more than {MAX_QUEUED} replies "
                "unasked for (flooding)"
            )
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
            self._proc.kill()
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
            policy._recycle()
            policy.name = bundle.manifest.name
            return policy
        return SandboxedPolicy(bundle, limits, spec, pool=self)

    def give_back(self, policy: SandboxedPolicy) -> None:
        """Keep ``policy`` (healthy, running) for a later race."""
        key = self._key(policy.bundle, policy.limits, policy.env_spec)
        policy._pooled = True
        self._idle.setdefault(key, []).append(policy)

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
