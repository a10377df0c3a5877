"""How sandboxed policies are scheduled: which CPU each starts on, and fast wake-ups.

Every step of a sandboxed policy is two hand-overs between processes: the host wakes the
worker with the observation, the worker wakes the host with the action
(:mod:`submissions.channel`). Two things decide what a hand-over costs, both measured on
this project's 2-vCPU VM by ``bench/sandbox_overhead.py`` (which shows them side by side):

**Where the worker runs.** The kernel places a new process when it starts and then keeps a
sleeping process on the CPU it last ran on whenever that CPU is idle at its wake-up: a
worker that started on the host's CPU stays there for good, and the two Python processes
then take turns on one core, each evicting the other's working set (the pursuit policy's
``act`` took 72 µs there against 54 µs on a core of its own, and the host's side of the
step slowed alike). :data:`PLACEMENT` picks the CPU each new sandbox starts on: round robin
over the host's allowed CPUs, starting with the one after the CPU the host runs on, so a
lone sandbox gets a core of its own and a race's four share the cores evenly with the host
(two each on two cores). The sandbox is only *started* there: the worker widens its CPU
mask back to the host's before it says ``READY`` (``--cpus``), so the kernel's load
balancer still moves it where the load asks.

**How fast an idle CPU wakes.** When the CPU that should run the woken process is idle,
cpuidle has usually halted it, and waking a halted CPU costs an inter-processor interrupt;
in a virtual machine the halt and that interrupt each leave the guest (a VM exit), and the
woken code then runs on caches the halt has cooled: a one-byte pipe ping-pong between two
processes took ~45 µs here. The kernel's PM QoS interface is how a process asks for short
wake-ups: it writes a latency bound (a 32-bit integer, µs) to ``/dev/cpu_dma_latency`` and
keeps the file open. With 0, cpuidle keeps idle CPUs in its polling state instead of
halting them, so a wake-up is a flag the polling CPU sees at once, without an interrupt
(the same ping-pong: ~7 µs). The request lasts while the file is open and the kernel drops
it when the file is closed, also when the process dies: nothing of it outlives its holder.

:data:`WAKEUPS` holds one such request for this process while at least one sandboxed policy
is active (:class:`submissions.remote.SandboxedPolicy` takes it when its sandbox starts or
leaves a pool, and gives it back when it is shut down or returns to its pool). The trade:
while it is held, idle CPUs poll instead of sleeping, which costs power and, on a shared
host, the idle cores' CPU time; a CPU with work to do is not slowed.
``SLIPSTREAM_CPU_LATENCY_US`` sets it: unset or ``0`` asks for polling, ``N`` for wake-ups
within N µs (cpuidle may then halt CPUs whose halt state wakes faster than that), ``off``
asks for nothing. Opening the file needs root (its mode is 0600): anywhere else nothing is
asked and races run as before (logged once). A sandboxed policy cannot reach the file:
bubblewrap's ``/dev`` does not hold it, and the fallback's uid may not open it.
"""

from __future__ import annotations

import ctypes
import logging
import os
import struct
import threading
from pathlib import Path

from submissions.errors import SandboxError

log = logging.getLogger(__name__)

DEVICE = Path("/dev/cpu_dma_latency")  # the kernel's PM QoS CPU-latency file
LATENCY_ENV = "SLIPSTREAM_CPU_LATENCY_US"  # unset/"0": poll; "N": N µs; "off": no request
OFF = ("off", "none", "no")
MAX_LATENCY_US = 2_000_000_000  # the kernel's default (no constraint) and its largest value


def requested_latency_us() -> int | None:
    """The wake-up latency to ask for, µs (``SLIPSTREAM_CPU_LATENCY_US``); None: none.

    Raises:
        SandboxError: the variable is neither ``off`` nor an integer within
            ``0..MAX_LATENCY_US``.
    """
    raw = os.environ.get(LATENCY_ENV, "").strip().lower()
    if raw in OFF:
        return None
    if not raw:
        return 0
    try:
        value = int(raw)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_LATENCY_US:
        raise SandboxError(
            f"{LATENCY_ENV} must be 'off' or an integer number of µs within "
            f"0..{MAX_LATENCY_US}, not {raw!r}"
        )
    return value


class LatencyRequest:
    """A reference-counted PM QoS CPU-latency request (see the module docstring).

    :meth:`acquire` opens the request unless it is open (or the setting is ``off``),
    :meth:`release` closes it when the last holder lets go; thread-safe. Failing to open
    it is not an error: the request is an optimisation, so the holder runs without it
    (``held`` stays False).

    Args:
        device: the PM QoS file (:data:`DEVICE`; tests point it elsewhere).
    """

    def __init__(self, device: Path = DEVICE) -> None:
        self.device = device
        self._lock = threading.Lock()
        self._holders = 0
        self._fd = -1
        self._warned = False

    @property
    def held(self) -> bool:
        """Whether the request is in force now (its file open)."""
        return self._fd >= 0

    @property
    def holders(self) -> int:
        """How many :meth:`acquire` calls have not been released yet."""
        return self._holders

    def acquire(self) -> bool:
        """Count one more holder; open the request if it is not open. Returns ``held``.

        Raises:
            SandboxError: ``SLIPSTREAM_CPU_LATENCY_US`` is malformed.
        """
        latency = requested_latency_us()
        with self._lock:
            self._holders += 1
            if self._fd < 0 and latency is not None:
                self._fd = self._open(latency)
            return self._fd >= 0

    def release(self) -> None:
        """Count one holder less; close the request with the last (extra calls: no-op)."""
        with self._lock:
            if self._holders == 0:
                return
            self._holders -= 1
            if self._holders == 0 and self._fd >= 0:
                fd, self._fd = self._fd, -1
                os.close(fd)

    def _open(self, latency_us: int) -> int:
        """The request's open file, or -1 when it cannot be made (said once)."""
        fd = -1
        try:
            fd = os.open(self.device, os.O_WRONLY | os.O_CLOEXEC)
            os.write(fd, struct.pack("=i", latency_us))
        except OSError as err:
            if fd >= 0:
                os.close(fd)
            if not self._warned:
                self._warned = True
                log.info("no fast wake-ups for sandboxed policies (%s: %s)", self.device, err)
            return -1
        return fd


WAKEUPS = LatencyRequest()  # this process's request, held while a sandboxed policy is active


def current_cpu() -> int | None:
    """The CPU the calling thread runs on now (``sched_getcpu``); None if unknown."""
    try:
        cpu = int(ctypes.CDLL(None, use_errno=True).sched_getcpu())
    except (OSError, AttributeError):
        return None
    return cpu if cpu >= 0 else None


class Placement:
    """The CPU each new sandbox of this process starts on (see the module docstring).

    Attributes:
        enabled: whether :meth:`next_cpu` picks CPUs at all (False: the kernel places them).
    """

    def __init__(self) -> None:
        self.enabled = True
        self._started = 0
        self._lock = threading.Lock()

    def next_cpu(self) -> int | None:
        """The CPU for the next sandbox: round robin over this process's allowed CPUs,
        starting with the one after the CPU it runs on; None with one allowed CPU (or when
        disabled)."""
        if not self.enabled:
            return None
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) < 2:
            return None
        here = current_cpu()
        first = cpus.index(here) + 1 if here in cpus else 0
        with self._lock:
            k, self._started = self._started, self._started + 1
        return cpus[(first + k) % len(cpus)]

    def reset(self) -> None:
        """Start the round robin afresh: the next sandbox is placed as the first was."""
        with self._lock:
            self._started = 0


PLACEMENT = Placement()  # where this process's sandboxes start
