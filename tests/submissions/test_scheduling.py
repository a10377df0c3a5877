"""Where sandboxes start and the fast wake-ups they hold (:mod:`submissions.scheduling`)."""

from __future__ import annotations

import json
import os
import struct
import time
from pathlib import Path
from typing import Any

import pytest

from agents.baselines import make_baseline
from agents.loading import DEFAULT_LAYOUT
from arena.race import run_race
from submissions.errors import SandboxError
from submissions.remote import SandboxedPolicy, SandboxPool
from submissions.sandbox import SandboxLimits
from submissions.scheduling import (
    BACKOFF_S,
    CONTENDED_SHARE,
    DEVICE,
    LATENCY_ENV,
    MAX_LATENCY_US,
    MAX_SPIN_US,
    RECENT,
    SAMPLE_S,
    SPIN_ENV,
    SPIN_US,
    WAKEUPS,
    CpuContention,
    LatencyRequest,
    Placement,
    current_cpu,
    spin_limit_s,
)

from .conftest import FAST, MakeBundle, race_against_pursuit


def open_fds() -> set[str]:
    """What this process's descriptors point at."""
    found = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            found.add(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:  # the listing's own descriptor, closed by now
            continue
    return found


def test_a_request_is_written_once_and_closed_with_its_last_holder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(LATENCY_ENV, raising=False)
    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    request = LatencyRequest(device)
    assert request.acquire() and request.held
    assert device.read_bytes() == struct.pack("=i", 0)  # the default asks for polling
    assert str(device) in open_fds()  # kept open: the request lasts while the file is
    device.write_bytes(b"")
    assert request.acquire()  # a second holder shares the request: nothing written again
    assert device.read_bytes() == b"" and request.holders == 2
    request.release()
    assert request.held and str(device) in open_fds()
    request.release()
    assert not request.held and request.holders == 0
    assert str(device) not in open_fds()
    request.release()  # an extra release changes nothing
    assert request.holders == 0


@pytest.mark.parametrize(
    ("raw", "written"),
    [("", 0), ("0", 0), ("250", 250), (" 17 ", 17), (str(MAX_LATENCY_US), MAX_LATENCY_US)],
)
def test_the_setting_picks_the_latency_asked_for(
    raw: str, written: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(LATENCY_ENV, raw)
    device = tmp_path / "device"
    device.write_bytes(b"")
    request = LatencyRequest(device)
    assert request.acquire()
    assert struct.unpack("=i", device.read_bytes()) == (written,)
    request.release()


@pytest.mark.parametrize("raw", ["off", "OFF", "none"])
def test_off_asks_for_nothing(raw: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LATENCY_ENV, raw)
    device = tmp_path / "device"
    device.write_bytes(b"untouched")
    request = LatencyRequest(device)
    assert request.acquire() is False and request.holders == 1
    assert device.read_bytes() == b"untouched"
    request.release()


@pytest.mark.parametrize("raw", ["fast", "-1", "1.5", str(MAX_LATENCY_US + 1)])
def test_a_malformed_setting_is_refused_clearly(raw: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LATENCY_ENV, raw)
    request = LatencyRequest(Path("/nonexistent"))
    with pytest.raises(SandboxError, match=LATENCY_ENV) as err:
        request.acquire()
    assert repr(raw.strip().lower()) in str(err.value)
    assert request.holders == 0


def test_a_device_that_cannot_be_opened_costs_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(LATENCY_ENV, raising=False)
    request = LatencyRequest(tmp_path / "missing")
    assert request.acquire() is False and not request.held
    request.release()
    assert request.holders == 0


def _effective_latency() -> int:
    with DEVICE.open("rb") as fh:
        return int(struct.unpack("=i", fh.read(4))[0])


@pytest.mark.skipif(not DEVICE.exists(), reason="this kernel has no PM QoS CPU-latency file")
def test_the_kernel_honours_the_request_while_it_is_held(monkeypatch: pytest.MonkeyPatch) -> None:
    # The kernel's value is the minimum over every process's request, and other test
    # processes race sandboxes (holding 0) at the same time: a distinctive value is asked
    # for, and only a window in which nobody else asks for anything counts as a check.
    monkeypatch.setenv(LATENCY_ENV, "4321")
    request = LatencyRequest()
    if not os.access(DEVICE, os.W_OK):  # not root: nothing is asked, nothing fails
        assert request.acquire() is False
        request.release()
        return
    seen = []
    for _ in range(100):
        before = _effective_latency()
        assert request.acquire()
        held = _effective_latency()
        request.release()
        after = _effective_latency()
        seen.append((before, held, after))
        if before == after == MAX_LATENCY_US and held == 4321:  # nobody else asked meanwhile
            return
        time.sleep(0.05)
    raise AssertionError(f"the kernel never showed the request alone: {seen[-5:]}")


def test_placement_takes_the_cpus_in_turn_after_the_hosts(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {2, 5, 7})
    monkeypatch.setattr("submissions.scheduling.current_cpu", lambda: 5)
    placement = Placement()
    assert [placement.next_cpu() for _ in range(4)] == [7, 2, 5, 7]
    monkeypatch.setattr("submissions.scheduling.current_cpu", lambda: None)  # unknown: first
    assert placement.next_cpu() == 5  # the fifth start, from the first allowed CPU
    placement.reset()
    assert placement.next_cpu() == 2  # the first start again
    placement.enabled = False
    assert placement.next_cpu() is None


def test_placement_leaves_a_single_cpu_to_the_kernel(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3})
    assert Placement().next_cpu() is None


def test_the_current_cpu_is_one_this_process_may_run_on() -> None:
    assert current_cpu() in os.sched_getaffinity(0)


# A policy that says which CPUs it may run on while it loads and once it has said READY
# (bound to one, both times), and whether it could open the PM QoS file itself.
AFFINITY = """
import json, os


class Policy:
    def __init__(self, env_spec):
        print("LOADING " + json.dumps(sorted(os.sched_getaffinity(0))), flush=True)

    def reset(self, seed):
        try:
            fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
            os.write(fd, (7).to_bytes(4, "little"))
            qos = "OPENED"
        except OSError as err:
            qos = f"REFUSED {type(err).__name__}"
        print("READY " + json.dumps(sorted(os.sched_getaffinity(0))) + "|" + qos, flush=True)

    def act(self, obs):
        return [0.0, 0.5]
"""


def printed(policy: SandboxedPolicy, tag: str) -> str:
    """The rest of the first line the policy printed that starts with ``tag`` (its output is
    drained by a thread of its own: give it a few seconds)."""
    for _ in range(500):
        for line in policy.output.splitlines():
            if line.startswith(tag + " "):
                return line[len(tag) + 1 :]
        time.sleep(0.02)
    raise AssertionError(f"no {tag} line in {policy.output[-2000:]!r}")


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU: nothing to place")
def test_a_sandbox_runs_on_the_cpu_picked_for_its_whole_life(
    mode: str, make_python_bundle: MakeBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    picked: list[int | None] = []
    real = Placement.next_cpu

    def spy(self: Placement) -> int | None:
        picked.append(real(self))
        return picked[-1]

    monkeypatch.setattr(Placement, "next_cpu", spy)
    policy = SandboxedPolicy(make_python_bundle(AFFINITY, name="affinity", driver=False), FAST)
    try:
        policy.reset(0)
        assert picked and picked[0] is not None
        assert json.loads(printed(policy, "LOADING")) == [picked[0]]
        cpus, qos = printed(policy, "READY").split("|")
        assert json.loads(cpus) == [picked[0]]  # still bound once loaded
        # The host's PM QoS file is out of the policy's reach in both modes.
        assert "REFUSED" in qos and "OPENED" not in qos
    finally:
        policy.close()


def _holders_during_a_race(policy: Any) -> int:
    holders: list[int] = []

    class Spy:
        name = "spy"

        def reset(self, seed: int | None = None) -> None:
            holders.append(WAKEUPS.holders)

        def act(self, obs: Any) -> Any:
            return [0.0, 0.5]

    run_race([policy, Spy(), make_baseline("pursuit", DEFAULT_LAYOUT)], track="oval", seed=0)
    return holders[0]


def test_a_sandboxed_policy_holds_the_wake_ups_only_while_it_is_active(
    make_python_bundle: MakeBundle,
) -> None:
    bundle = make_python_bundle("class Policy(Driver): pass", name="holder")
    before = WAKEUPS.holders
    with SandboxPool() as pool:
        policy = pool.policy(bundle, FAST)
        assert _holders_during_a_race(policy) == before + 1  # started: held
        policy.close()  # back to its pool, still running: its CPUs may sleep again
        assert pool.idle == 1 and WAKEUPS.holders == before
        again = pool.policy(bundle, FAST)
        assert again is policy and WAKEUPS.holders == before + 1  # out of the pool: held
        assert race_against_pursuit(again).cars[0].status == "finished"
        assert pool.idle == 1 and WAKEUPS.holders == before  # the race gave it back
        pool.policy(bundle, FAST).shutdown()
        assert pool.idle == 0 and WAKEUPS.holders == before
    lone = SandboxedPolicy(bundle, FAST)
    lone.start()
    assert WAKEUPS.holders == before + 1
    lone.close()
    assert WAKEUPS.holders == before


def test_a_malformed_setting_fails_before_any_sandbox_starts(
    make_python_bundle: MakeBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(LATENCY_ENV, "soon")
    policy = SandboxedPolicy(make_python_bundle("class Policy(Driver): pass"), FAST)
    before = WAKEUPS.holders
    with pytest.raises(SandboxError, match=LATENCY_ENV):
        policy.start()
    assert policy.sandbox_id is None and WAKEUPS.holders == before


@pytest.mark.skipif(not os.access(DEVICE, os.W_OK), reason="needs root: the PM QoS file is 0600")
def test_a_killed_holder_leaves_no_request_behind() -> None:
    # A job process SIGKILLed mid-race cannot release its request: the kernel drops it with
    # the process's files, and no program it started holds the file (it is not inheritable),
    # even one started without closing descriptors that outlives it. A child holds a
    # distinctive value, starts such a program, and is killed.
    import signal
    import subprocess
    import sys

    code = (
        "import os, subprocess, sys\n"
        "os.environ['SLIPSTREAM_CPU_LATENCY_US'] = '4322'\n"
        "from submissions.scheduling import WAKEUPS\n"
        "assert WAKEUPS.acquire()\n"
        "orphan = subprocess.Popen(['sleep', '30'], close_fds=False)\n"
        "print(orphan.pid, flush=True)\n"
        "sys.stdin.read()\n"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    orphan = 0
    try:
        assert child.stdout is not None
        orphan = int(child.stdout.readline())
        assert _effective_latency() <= 4322  # its request (or a stricter one of another test)
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(10)
    try:
        assert os.path.exists(f"/proc/{orphan}")  # the program it started lives on
        for _ in range(100):  # the kernel's minimum never again shows the dead child's value
            value = _effective_latency()
            assert value != 4322, "the killed process's request outlived it"
            if value == MAX_LATENCY_US:
                break
            time.sleep(0.05)
    finally:
        os.kill(orphan, signal.SIGKILL)


# ---- how the host waits: the spin ---------------------------------------------------------


@pytest.mark.parametrize(("raw", "limit_us"), [("", SPIN_US), ("0", 0), (" 50 ", 50)])
def test_the_spin_limit_is_the_one_asked_for(
    raw: str, limit_us: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(SPIN_ENV, raw)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    assert spin_limit_s() == pytest.approx(limit_us * 1e-6)


def test_a_host_on_one_cpu_never_spins(monkeypatch: pytest.MonkeyPatch) -> None:
    # spinning there would take the only CPU from the worker it waits for
    monkeypatch.setenv(SPIN_ENV, "500")
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3})
    assert spin_limit_s() == 0.0


@pytest.mark.parametrize("raw", ["fast", "-1", "2.5", str(MAX_SPIN_US + 1)])
def test_a_malformed_spin_setting_fails_before_any_sandbox_starts(
    raw: str, make_python_bundle: MakeBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(SPIN_ENV, raw)
    with pytest.raises(SandboxError, match=SPIN_ENV) as err:
        spin_limit_s()
    assert repr(raw.strip()) in str(err.value)
    policy = SandboxedPolicy(make_python_bundle("class Policy(Driver): pass"), FAST)
    before = WAKEUPS.holders
    with pytest.raises(SandboxError, match=SPIN_ENV):
        policy.start()
    assert policy.sandbox_id is None and WAKEUPS.holders == before


class Pressure:
    """A stand-in ``/proc/pressure/cpu`` and a clock the test drives: ``stall(share, s)``
    lets ``s`` seconds pass with some task waiting for a CPU ``share`` of the time."""

    def __init__(self, path: Path) -> None:
        self.path, self.now, self.total_us = path, 1000.0, 5_000_000
        self.write()

    def write(self) -> None:
        self.path.write_text(
            f"some avg10=1.00 avg60=2.00 avg300=3.00 total={self.total_us}\n"
            "full avg10=0.00 avg60=0.00 avg300=0.00 total=0\n"
        )

    def stall(self, share: float, seconds: float) -> None:
        self.now += seconds
        self.total_us += round(share * seconds * 1e6)
        self.write()


def test_the_host_spins_while_the_cpus_are_free_and_backs_off_when_they_are_not(
    tmp_path: Path,
) -> None:
    pressure = Pressure(tmp_path / "cpu")
    gate = CpuContention(pressure.path, clock=lambda: pressure.now)
    sample = SAMPLE_S * 1.01  # a little over one sample (the clock is a float)
    assert gate.spin_allowed()  # a first sample: nothing to compare yet
    pressure.stall(CONTENDED_SHARE / 2, sample)
    assert gate.spin_allowed()  # a free machine (the ping-pong itself stalls ~1 %)
    pressure.stall(CONTENDED_SHARE * 4, SAMPLE_S / 3)
    assert gate.spin_allowed()  # within a sample: not read again
    pressure.stall(CONTENDED_SHARE * 4, sample)
    assert gate.spin_allowed()  # one contended sample among free ones: a burst, not load
    pressure.stall(CONTENDED_SHARE / 2, sample)
    assert gate.spin_allowed()
    pressure.stall(CONTENDED_SHARE * 4, sample)
    assert not gate.spin_allowed()  # a second within the last three: no spin, for the backoff
    pressure.stall(0.0, BACKOFF_S / 2)
    assert not gate.spin_allowed()  # still backing off, however free the CPUs now are
    pressure.stall(0.0, BACKOFF_S)
    assert gate.spin_allowed()  # tries again, from a fresh sample
    pressure.stall(CONTENDED_SHARE * 1.5, sample)
    assert not gate.spin_allowed()  # still contended: at once (the history outlives a backoff)
    pressure.stall(0.0, BACKOFF_S * 1.01)
    assert gate.spin_allowed()
    for _ in range(RECENT):  # free samples push the contended ones out
        pressure.stall(CONTENDED_SHARE / 2, sample)
        assert gate.spin_allowed()
    pressure.stall(CONTENDED_SHARE * 1.5, sample)
    assert gate.spin_allowed()  # a burst again


def test_a_pause_longer_than_a_few_samples_starts_afresh(tmp_path: Path) -> None:
    # Stalls while nobody asked (between races, say) are not charged to the next spin.
    pressure = Pressure(tmp_path / "cpu")
    gate = CpuContention(pressure.path, clock=lambda: pressure.now)
    assert gate.spin_allowed()
    pressure.stall(0.9, SAMPLE_S * 1.01)
    assert gate.spin_allowed()  # one contended sample before the pause …
    pressure.stall(0.9, 30.0)
    assert gate.spin_allowed()  # … is forgotten with the stalls of the pause
    pressure.stall(0.9, SAMPLE_S * 1.01)
    assert gate.spin_allowed()
    pressure.stall(0.9, SAMPLE_S * 1.01)
    assert not gate.spin_allowed()
    # Nobody asks for a long while after that backoff: its history is stale by then too.
    pressure.stall(0.0, 30.0)
    assert gate.spin_allowed()
    pressure.stall(0.9, SAMPLE_S * 1.01)
    assert gate.spin_allowed()  # one burst: not two of three


@pytest.mark.parametrize("content", [None, "", "some avg10=1.00\n", "garbage total=x\n"])
def test_without_pressure_information_the_host_never_spins(
    content: str | None, tmp_path: Path
) -> None:
    path = tmp_path / "cpu"
    if content is not None:
        path.write_text(content)
    gate = CpuContention(path, clock=time.monotonic)
    assert not gate.spin_allowed() and not gate.spin_allowed()


class CountingPoller:
    """A ``select.poll`` object that counts the calls that may sleep (timeout > 0)."""

    def __init__(self, inner: Any) -> None:
        self.inner, self.sleeps = inner, 0

    def register(self, *args: Any) -> None:
        self.inner.register(*args)

    def poll(self, timeout: int) -> Any:
        self.sleeps += timeout > 0
        return self.inner.poll(timeout)


ZEROS = """
import numpy as np


class Policy:
    def act(self, obs):
        return np.zeros(2, np.float32)
"""


class Gate:
    """A stand-in for :data:`submissions.scheduling.CONTENTION` that says what it is told
    (the real one reads this machine's CPU pressure: its own tests are above)."""

    def __init__(self, free: bool) -> None:
        self.free, self.asked = free, 0

    def spin_allowed(self) -> bool:
        self.asked += 1
        return self.free


def _sleeps_over_steps(policy: SandboxedPolicy, steps: int) -> int:
    """How many of ``steps`` acts the host slept in ``poll`` for (a lone policy)."""
    policy.reset(0)
    counting = CountingPoller(policy._poller)
    policy._poller = counting  # type: ignore[assignment]
    obs = [0.0] * int(policy.env_spec["obs_shape"][0])
    for _ in range(steps):
        policy.act(obs)
    return counting.sleeps


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU: the host never spins")
def test_a_fast_reply_is_taken_without_sleeping_in_poll(
    mode: str, make_python_bundle: MakeBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The limit is raised to 0.1 s so that a loaded test machine (a reply taking far longer
    # than the default's 200 µs) does not decide the outcome; the rule is the same.
    bundle = make_python_bundle(ZEROS, name="zeros", driver=False)
    monkeypatch.setenv(SPIN_ENV, str(MAX_SPIN_US))
    monkeypatch.setattr("submissions.remote.CONTENTION", Gate(free=True))
    spinning = SandboxedPolicy(bundle, FAST)
    try:
        sleeps = _sleeps_over_steps(spinning, 200)
        assert sleeps <= 40, sleeps  # the first step, and a few the machine delayed
        assert 0 < spinning._spin_s <= MAX_SPIN_US * 1e-6
    finally:
        spinning.close()
    monkeypatch.setenv(SPIN_ENV, "0")
    sleeping = SandboxedPolicy(bundle, FAST)
    try:
        assert _sleeps_over_steps(sleeping, 50) == 50
    finally:
        sleeping.close()


def test_contended_cpus_stop_the_spin(
    mode: str, make_python_bundle: MakeBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The gate says the machine is busy: the host sleeps in poll for every reply.
    monkeypatch.setenv(SPIN_ENV, str(MAX_SPIN_US))
    gate = Gate(free=False)
    monkeypatch.setattr("submissions.remote.CONTENTION", gate)
    policy = SandboxedPolicy(make_python_bundle(ZEROS, name="zeros", driver=False), FAST)
    try:
        assert _sleeps_over_steps(policy, 50) == 50
        assert gate.asked >= 40 and policy._spin_s > 0  # it would have spun
    finally:
        policy.close()


SLOW = """
import time
import numpy as np


class Policy:
    def act(self, obs):
        time.sleep(0.004)
        return np.zeros(2, np.float32)
"""


def test_a_policy_slower_than_the_limit_never_costs_a_spin(
    mode: str, make_python_bundle: MakeBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 4 ms a step, against a 1 ms limit: the host sleeps in poll at every step, and its CPU
    # time stays far below the steps' wall time.
    monkeypatch.setenv(SPIN_ENV, "1000")
    policy = SandboxedPolicy(make_python_bundle(SLOW, name="slow", driver=False), FAST)
    try:
        policy.reset(0)
        obs = [0.0] * int(policy.env_spec["obs_shape"][0])
        policy.act(obs)
        assert policy._spin_s == 0.0
        cpu = time.thread_time()
        sleeps = _sleeps_over_steps(policy, 25)
        assert sleeps == 25 and policy._spin_s == 0.0
        assert time.thread_time() - cpu < 0.025  # 25 steps of ≥ 4 ms: ≥ 100 ms of wall time
    finally:
        policy.close()


NUMBER_WITHOUT_BELL = """
import gc, os, struct, time
import numpy as np
from submissions.channel import REPLY_BYTES
from submissions.protocol import Kind, encode


class Policy:
    steps = 0

    def act(self, obs):
        self.steps += 1
        if self.steps < 30:
            return np.zeros(2, np.float32)
        ch = next(o for o in gc.get_objects() if type(o).__name__ == "WorkerChannel")
        seq = struct.unpack_from("<H", ch.memory, 6)[0]
        frame = encode(Kind.ACTION, np.ones(2, np.float32), seq)
        at = len(ch.memory) - REPLY_BYTES
        ch.memory[at : at + len(frame)] = frame  # the reply's number in the slot, never rung
        time.sleep(3600)
"""


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU: the host never spins")
def test_a_reply_number_without_its_bell_is_not_taken_by_the_spin(
    mode: str, make_python_bundle: MakeBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    # An attacker who read the spin: after 29 fast answers (the host spins for the 30th) it
    # writes a well-formed reply with the right number and never rings. The host sees the
    # number, finds no wake-up on the bell, sleeps in poll, and retires the car at its
    # deadline: the bell, not the number, says a reply is complete.
    from submissions.remote import PolicyTimeout

    monkeypatch.setenv(SPIN_ENV, str(MAX_SPIN_US))
    monkeypatch.setattr("submissions.remote.CONTENTION", Gate(free=True))
    quick = SandboxLimits(step_deadline_s=0.25, overage_s=1.0, startup_s=60.0)
    policy = SandboxedPolicy(
        make_python_bundle(NUMBER_WITHOUT_BELL, name="nobell", driver=False), quick
    )
    try:
        policy.reset(0)
        obs = [0.0] * int(policy.env_spec["obs_shape"][0])
        for _ in range(29):
            assert policy.act(obs).tolist() == [0.0, 0.0]
        assert policy._spin_s > 0
        start = time.monotonic()
        with pytest.raises(PolicyTimeout, match="no action"):
            policy.act(obs)
        limit = quick.step_deadline_s + quick.overage_s
        assert time.monotonic() - start < limit + 1.0
    finally:
        policy.close()
