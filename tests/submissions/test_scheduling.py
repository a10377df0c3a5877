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
from submissions.scheduling import (
    DEVICE,
    LATENCY_ENV,
    MAX_LATENCY_US,
    WAKEUPS,
    LatencyRequest,
    Placement,
    current_cpu,
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


# A policy that says which CPUs it may run on while it loads (bound to one) and once it has
# said READY (the host's CPUs again), and whether it could open the PM QoS file itself.
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
def test_a_sandbox_starts_on_the_cpu_picked_then_may_run_anywhere_again(
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
        assert json.loads(cpus) == sorted(os.sched_getaffinity(0))
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
