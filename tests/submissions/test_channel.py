"""The shared-memory channel, and the host's side of the protocol against a scripted worker.

No sandbox here (fast): the first half attacks :class:`submissions.channel.Channel` itself
(the sealed region, the doorbells, reads of a slot that changes under the reader); the
second drives a real :class:`~submissions.remote.SandboxedPolicy` whose worker is a thread
of the test process speaking over the same channel (:class:`FakeProcess` stands in for
:class:`~submissions.sandbox.SandboxProcess`), so each hostile timing is exact rather than
hoped for. The same attacks from inside real sandboxes, both modes, are in
``test_hostile_protocol.py``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arena.race import action_problem
from submissions import remote
from submissions.channel import (
    FIRST_COPY,
    REPLY_BYTES,
    WAKE_READ,
    Channel,
    WorkerChannel,
    _read_frame,
    request_bytes_for,
)
from submissions.protocol import (
    HEADER,
    Frame,
    Kind,
    ProtocolError,
    encode,
    encode_json,
)
from submissions.remote import (
    PolicyCrash,
    PolicyInvalid,
    PolicyTimeout,
    SandboxedPolicy,
    _box_bounds,
    _surely_within,
    action_space_of,
    make_env_spec,
)
from submissions.sandbox import SandboxLimits

from .conftest import MakeBundle

OBS = np.arange(105, dtype=np.float32)
QUICK = SandboxLimits(step_deadline_s=0.1, overage_s=0.2, startup_s=2.0)


@pytest.fixture
def channel() -> Iterator[Channel]:
    ch = Channel(request_bytes_for([105]))
    try:
        yield ch
    finally:
        ch.close()


def _memfd(ch: Channel) -> int:
    return ch.worker_fds[0]


# ---- the region --------------------------------------------------------------------------


def test_the_region_is_sealed_anonymous_memory_of_a_fixed_size(channel: Channel) -> None:
    """What a worker holding the descriptor might try, from someone who read channel.py:
    shrink the file under the host's mapping (the host would SIGBUS), grow it, fallocate
    past its end, add a write seal, remove the seals. Each refused; the host's mapping
    stays whole and readable."""
    fd = _memfd(channel)
    size = os.fstat(fd).st_size
    assert size == channel.request_bytes + REPLY_BYTES and size % os.sysconf("SC_PAGE_SIZE") == 0
    link = os.readlink(f"/proc/self/fd/{fd}")
    assert link.startswith("/memfd:") and "/dev/shm" not in link  # nothing anyone can open
    assert os.fstat(fd).st_nlink == 0
    for attempt in (
        lambda: os.ftruncate(fd, 0),
        lambda: os.ftruncate(fd, size * 2),
        lambda: os.posix_fallocate(fd, size, 1 << 20),
        lambda: fcntl.fcntl(fd, fcntl.F_ADD_SEALS, fcntl.F_SEAL_WRITE),
    ):
        with pytest.raises(OSError) as err:
            attempt()
        assert err.value.errno in (errno.EPERM, errno.EBUSY)
    seals = fcntl.fcntl(fd, fcntl.F_GET_SEALS)
    assert seals & fcntl.F_SEAL_SHRINK and seals & fcntl.F_SEAL_GROW and seals & fcntl.F_SEAL_SEAL
    assert os.fstat(fd).st_size == size
    channel.memory[size - 1 : size] = b"x"  # the last byte of the host's mapping: no fault
    assert channel.memory[size - 1 : size] == b"x"


def test_posting_never_blocks_when_the_worker_stops_reading(channel: Channel) -> None:
    """A worker that never reads its ring (and shrank it to one page): the host posts 20,000
    requests, far more than the pipe holds; each returns at once."""
    with contextlib.suppress(OSError):
        fcntl.fcntl(channel.worker_fds[1], 1031, 4096)  # F_SETPIPE_SZ on the worker's end
    start = time.monotonic()
    for seq in range(1, 20_001):
        channel.post(encode(Kind.ACT, OBS, seq))
    assert time.monotonic() - start < 5.0
    with pytest.raises(ProtocolError, match="does not fit"):  # the slot's size is the host's
        channel.post(encode(Kind.ACT, np.zeros(1 << 16, np.float32), 1))


def test_the_bell_is_counted_bounded_and_ends_with_the_worker(channel: Channel) -> None:
    bell_w = channel.worker_fds[2]
    assert channel.drain() == (0, False)
    os.write(bell_w, b"\x01")
    assert channel.drain() == (1, False)
    os.write(bell_w, b"\x01" * 50_000)  # a flood: one drain reads one bounded chunk
    assert channel.drain() == (WAKE_READ, False)
    channel.spawned()  # the host's copy of the worker's end is closed: only the worker's …
    while channel.drain()[0]:
        pass
    assert channel.drain() == (0, True)  # … and with none left, the bell has ended


def test_a_reply_is_decoded_from_copies_and_bounded_by_its_slot(channel: Channel) -> None:
    start = channel.request_bytes
    good = encode(Kind.ACTION, np.array([0.5, -0.5], np.float32), 7)
    channel.memory[start : start + len(good)] = good
    assert channel.reply_seq() == 7
    frame = channel.take()
    assert frame.kind == Kind.ACTION and frame.array.tolist() == [0.5, -0.5]
    channel.memory[start : start + 4] = b"\0\0\0\0"  # the worker scribbles after the take
    assert frame.array.tolist() == [0.5, -0.5]  # the host holds its own copy
    oversize = HEADER.pack(b"SL", Kind.ACTION, 5, 1, 7, REPLY_BYTES) + (REPLY_BYTES).to_bytes(
        8, "little"
    )
    channel.memory[start : start + len(oversize)] = oversize
    with pytest.raises(ProtocolError, match="-byte slot"):
        channel.take()


class _TornMemory:
    """A slot the worker rewrites between the host's two copies: the first read (the head)
    sees ``first``, every later one ``then``."""

    def __init__(self, first: bytes, then: bytes) -> None:
        self.reads = [first, then]

    def __getitem__(self, index: slice) -> bytes:
        data = self.reads[0] if len(self.reads) > 1 else self.reads[-1]
        if len(self.reads) > 1:
            self.reads.pop(0)
        return data[index]


LONG = encode(Kind.ERROR, np.full(2000, ord("x"), np.uint8), 3)  # longer than FIRST_COPY


@pytest.mark.parametrize(
    "then",
    [
        encode(Kind.ERROR, np.full(3000, ord("y"), np.uint8), 3),  # longer than the head said
        encode(Kind.ERROR, np.full(100, ord("y"), np.uint8), 3),  # shorter
        HEADER.pack(b"SL", Kind.ERROR, 5, 8, 3, 2000) + b"\xff" * 64,  # 8 absurd axes
    ],
    ids=["grown", "shrunk", "absurd-axes"],
)
def test_a_slot_rewritten_between_the_two_copies_is_refused(then: bytes) -> None:
    """The time-of-check/time-of-use race of a shared slot, made exact: the first copy
    describes one frame, the full copy holds another. The full copy is checked again on
    its own, so the mismatch is a ProtocolError (the policy's ``invalid``), never a read
    past the frame or a numpy error."""
    assert len(LONG) > FIRST_COPY
    torn = _TornMemory(LONG + b"\0" * 4096, then + b"\0" * 4096)
    with pytest.raises(ProtocolError):
        _read_frame(torn, 0, REPLY_BYTES)  # type: ignore[arg-type]


def test_a_small_frame_is_decoded_from_one_copy() -> None:
    """An action fits the first copy: what the slot holds afterwards does not matter."""
    action = encode(Kind.ACTION, np.array([0.25, -0.5], np.float32), 3)
    torn = _TornMemory(action + b"\0" * 4096, b"garbage" * 1000)
    frame = _read_frame(torn, 0, REPLY_BYTES)  # type: ignore[arg-type]
    assert frame.seq == 3 and frame.array.tolist() == [0.25, -0.5]


def test_worker_side_round_trip(channel: Channel) -> None:
    worker = WorkerChannel(",".join(str(os.dup(fd)) for fd in channel.worker_fds))
    channel.spawned()
    try:
        channel.post(encode(Kind.ACT, OBS, 1))
        request = worker.request(0)
        assert request is not None and request.seq == 1
        np.testing.assert_array_equal(request.array, OBS)
        worker.reply(encode(Kind.ACTION, np.ones(2, np.float32), 1))
        assert channel.drain() == (1, False)
        assert channel.reply_seq() == 1 and channel.take().array.tolist() == [1.0, 1.0]
        with pytest.raises(ProtocolError, match="exceeds"):
            worker.reply(encode(Kind.ACTION, np.zeros(REPLY_BYTES, np.uint8), 2))
    finally:
        for fd in (worker.ring, worker.bell):
            os.close(fd)
        worker.memory.close()


EDGES = [-1 - 2e-6, -1 - 1e-6, -1 - 9e-7, -1 - 5e-7, -1.0, 0.0, 1.0, 1 + 5e-7, 1 + 9e-7,
         1 + 1e-6, 1 + 2e-6, 3.0, 1e30, float("nan"), float("inf"), float("-inf")]  # fmt: skip


@settings(max_examples=400, deadline=None)
@given(
    dtype=st.sampled_from([np.float32, np.float64, np.int32, np.int64, np.uint8, np.bool_]),
    shape=st.sampled_from([(2,), (1,), (3,), (2, 1), ()]),
    data=st.data(),
)
def test_the_shortcut_accepts_only_what_action_problem_accepts(
    dtype: type, shape: tuple[int, ...], data: st.DataObject
) -> None:
    """The host's quick acceptance of Box actions (remote._surely_within) never accepts
    what arena.race.action_problem refuses, at the edge of the tolerance included."""
    space = action_space_of(make_env_spec())
    bounds = _box_bounds(space)
    assert bounds is not None
    n = int(np.prod(shape))
    if np.dtype(dtype).kind == "f":
        values = data.draw(
            st.lists(st.sampled_from(EDGES) | st.floats(-1.5, 1.5), min_size=n, max_size=n)
        )
    else:
        values = data.draw(st.lists(st.integers(-2, 2), min_size=n, max_size=n))
    with np.errstate(all="ignore"):
        arr = np.array(values, dtype=np.float64).astype(dtype).reshape(shape)
    if _surely_within(arr, bounds):
        assert action_problem(arr, space) is None
    if shape == (2,) and np.dtype(dtype).kind == "f" and all(-1 <= v <= 1 for v in values):
        assert _surely_within(arr, bounds)  # and the common case does take the shortcut


# ---- the host against a scripted worker --------------------------------------------------


class _Killed(Exception):
    pass


class FakeWorker:
    """The worker's side, scripted: a thread of the test process on a real channel."""

    def __init__(self, spec: str) -> None:
        self.channel = WorkerChannel(spec)
        self.killed = threading.Event()
        self.last = 0

    @property
    def memory(self) -> Any:
        return self.channel.memory

    @property
    def reply_at(self) -> int:
        return len(self.channel.memory) - REPLY_BYTES

    def ready(self) -> None:
        self.channel.reply(encode_json(Kind.READY, {"name": "fake", "landlock": 1}))

    def next(self) -> Frame:
        frame = self.channel.request(self.last)
        if frame is None or self.killed.is_set():
            raise _Killed
        self.last = frame.seq
        return frame

    def answer(self, frame: Frame) -> None:
        """The honest answer to ``frame``."""
        if frame.kind == Kind.RESET:
            self.channel.reply(encode(Kind.OK, seq=frame.seq))
        else:
            self.channel.reply(encode(Kind.ACTION, np.zeros(2, np.float32), frame.seq))

    def serve(self, n: int) -> None:
        for _ in range(n):
            self.answer(self.next())

    def forge(self, frame: bytes, ring: bool = True) -> None:
        self.memory[self.reply_at : self.reply_at + len(frame)] = frame
        if ring:
            os.write(self.channel.bell, b"\x01")

    def close_bell(self) -> None:
        os.close(self.channel.bell)
        self.channel.bell = -1

    def hang(self) -> None:
        self.killed.wait(30)
        raise _Killed


Script = Callable[[FakeWorker], None]


class FakeProcess:
    """Stands in for SandboxProcess: runs ``script`` on a thread over the real channel."""

    script: Script = staticmethod(lambda w: None)
    made: ClassVar[list[FakeProcess]] = []

    def __init__(
        self,
        worker_args: Sequence[str],
        bundle_root: Path,
        limits: SandboxLimits,
        *,
        pass_fds: Sequence[int],
        output_fd: int,
        mode: str | None = None,
        cpu: int | None = None,
    ) -> None:
        spec = worker_args[list(worker_args).index("--channel") + 1]
        self.worker = FakeWorker(",".join(str(os.dup(int(fd))) for fd in spec.split(",")))
        self.id = f"fake{len(FakeProcess.made)}"
        self.pid = os.getpid()
        self.status: int | None = None
        self.killed = False
        self._output = os.dup(output_fd)
        FakeProcess.made.append(self)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            type(self).script(self.worker)
            self.status = 0
        except _Killed:
            self.status = -9
        except OSError:
            self.status = 1
        finally:
            self.close_channel()

    def close_channel(self) -> None:
        channel = self.worker.channel
        for fd in (channel.ring, channel.bell, self._output):
            if fd >= 0:
                os.close(fd)
        channel.ring = channel.bell = self._output = -1

    def poll(self) -> int | None:
        return self.status if not self.thread.is_alive() else None

    def wait(self, timeout: float) -> int | None:
        self.thread.join(timeout)
        return self.poll()

    def stop(self) -> None:
        self.killed = True
        self.worker.killed.set()

    def kill(self) -> None:
        self.stop()


@pytest.fixture
def scripted(
    monkeypatch: pytest.MonkeyPatch, make_python_bundle: MakeBundle
) -> Iterator[Callable[[Script], SandboxedPolicy]]:
    """``scripted(script)``: a SandboxedPolicy whose worker runs ``script`` (see above)."""
    monkeypatch.setattr(remote, "SandboxProcess", FakeProcess)
    monkeypatch.setattr(remote, "EXIT_WAIT_S", 0.5)
    bundle = make_python_bundle("class Policy: pass", name="scripted", driver=False)
    made: list[SandboxedPolicy] = []

    def make(script: Script) -> SandboxedPolicy:
        monkeypatch.setattr(FakeProcess, "script", staticmethod(script))
        policy = SandboxedPolicy(bundle, QUICK)
        made.append(policy)
        return policy

    yield make
    for policy in made:
        policy.shutdown()


def test_an_honest_scripted_worker_races_steps(scripted: Callable[[Script], Any]) -> None:
    def honest(w: FakeWorker) -> None:
        w.ready()
        while True:
            w.answer(w.next())

    policy = scripted(honest)
    policy.reset(3)
    for _ in range(50):
        assert policy.act(OBS).tolist() == [0.0, 0.0]
    assert policy.failure is None and len(policy.step_times) == 50


def test_an_answer_already_in_the_slot_when_its_request_comes_is_invalid(
    scripted: Callable[[Script], Any],
) -> None:
    """Answers sent ahead: the reply to request 3 is written before request 3 exists."""

    def honest(w: FakeWorker) -> None:
        w.ready()
        while True:
            w.answer(w.next())

    policy = scripted(honest)
    policy.reset(0)  # request 1
    policy.act(OBS)  # request 2, answered; the worker now waits for 3
    worker = FakeProcess.made[-1].worker
    worker.forge(encode(Kind.ACTION, np.zeros(2, np.float32), 3), ring=False)
    with pytest.raises(PolicyInvalid, match="answers sent ahead"):
        policy.act(OBS)


def test_wake_ups_unasked_for_are_invalid_at_once(scripted: Callable[[Script], Any]) -> None:
    """Three extra rings after the reset: the next wait refuses them without waiting for
    the deadline; a flood of 100 KiB of rings likewise, in one bounded read."""

    def rings(w: FakeWorker) -> None:
        w.ready()
        w.answer(w.next())
        w.next()  # the host waits for this one's answer now
        os.write(w.channel.bell, b"\x01" * 3)
        w.hang()

    policy = scripted(rings)
    policy.reset(0)
    start = time.monotonic()
    with pytest.raises(PolicyInvalid, match="woke the host unasked"):
        policy.act(OBS)
    assert time.monotonic() - start < QUICK.step_deadline_s

    def floods(w: FakeWorker) -> None:
        w.ready()
        with contextlib.suppress(OSError):
            os.set_blocking(w.channel.bell, False)
            os.write(w.channel.bell, b"\x01" * (100 << 10))
        w.hang()

    with pytest.raises(PolicyInvalid, match="woke the host unasked"):
        scripted(floods).reset(0)


def test_a_reply_never_rung_in_is_a_timeout(scripted: Callable[[Script], Any]) -> None:
    """The right answer in the slot, but no wake-up: it does not count."""

    def silent(w: FakeWorker) -> None:
        w.ready()
        w.answer(w.next())
        frame = w.next()
        w.forge(encode(Kind.ACTION, np.zeros(2, np.float32), frame.seq), ring=False)
        w.hang()

    policy = scripted(silent)
    policy.reset(0)
    with pytest.raises(PolicyTimeout, match="no action"):
        policy.act(OBS)


def test_a_stale_reply_rung_again_is_invalid(scripted: Callable[[Script], Any]) -> None:
    """The previous reply left in the slot and rung in for the new request: only the reply
    numbered like the current request counts, and an honest worker rings only after
    writing it, so this is a breach, refused at once."""

    def stale(w: FakeWorker) -> None:
        w.ready()
        w.answer(w.next())
        w.next()
        os.write(w.channel.bell, b"\x01")  # the slot still holds the reset's OK (seq 1)
        w.hang()

    policy = scripted(stale)
    policy.reset(0)
    with pytest.raises(PolicyInvalid, match="numbered 1 rung in"):
        policy.act(OBS)


@pytest.mark.parametrize(
    ("forged", "match"),
    [
        (HEADER.pack(b"SL", Kind.ACTION, 1, 1, 2, 1 << 40) + (1 << 38).to_bytes(8, "little"),
         "exceeds"),
        (HEADER.pack(b"SL", Kind.ACTION, 1, 2, 2, 0) + (0).to_bytes(8, "little")
         + (1 << 63).to_bytes(8, "little"), "shape"),
        (HEADER.pack(b"SL", Kind.ACTION, 9, 1, 2, 8) + (2).to_bytes(8, "little"), "dtype"),
        (HEADER.pack(b"PK", Kind.ACTION, 1, 1, 2, 8) + (2).to_bytes(8, "little"), "magic"),
        (encode(Kind.ACTION, np.array([np.nan, 0.0], np.float32), 2), "NaN"),
        (encode(Kind.ACTION, np.array([1e30, 0.0]), 2), "outside"),
        (encode(Kind.ACTION, np.array([True, False]), 2), "not a number"),
        (encode(Kind.ACTION, np.zeros(3, np.float32), 2), "shape"),
    ],
    ids=["1TiB", "0x2^63", "dtype-9", "magic", "nan", "1e30", "bool", "3-values"],
)  # fmt: skip
def test_forged_replies_are_invalid(
    scripted: Callable[[Script], Any], forged: bytes, match: str
) -> None:
    def forge(w: FakeWorker) -> None:
        w.ready()
        w.answer(w.next())
        w.next()
        w.forge(forged)
        w.hang()

    policy = scripted(forge)
    policy.reset(0)
    with pytest.raises(PolicyInvalid, match=match):
        policy.act(OBS)


def test_a_closed_channel_is_an_exit_or_a_violation(scripted: Callable[[Script], Any]) -> None:
    """Its end of the channel closes: the worker exited (crash, ``error``), or it is still
    running after EXIT_WAIT_S and closed the channel on purpose (``invalid``)."""

    def exits(w: FakeWorker) -> None:
        w.ready()
        w.answer(w.next())
        w.next()  # … and the thread ends: its descriptors close

    policy = scripted(exits)
    policy.reset(0)
    with pytest.raises(PolicyCrash, match="exited"):
        policy.act(OBS)

    def closes(w: FakeWorker) -> None:
        w.ready()
        w.answer(w.next())
        w.next()
        w.close_bell()
        w.hang()

    policy = scripted(closes)
    policy.reset(0)
    with pytest.raises(PolicyInvalid, match="closed its channel"):
        policy.act(OBS)
