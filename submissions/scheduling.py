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
(two each on two cores). The sandbox stays bound to that CPU for its whole life (a pooled
one too). An earlier version let the worker widen its mask back to the host's once loaded,
so that the load balancer could move it; measured side by side on the 2-vCPU VM (four
alternating runs of ``bench/sandbox_overhead.py`` each), a lone sandbox's step came out
1.31–1.52× in-process bound and 1.41–2.24× widened (the kernel's wake-ups of a
ping-ponging pair pull the two back onto one CPU now and then, for good), while 4-car races
were within the runs' noise of each other (pooled 0.61–0.69× bound, 0.66–0.71× widened). The
trade: a bound worker cannot flee a CPU that something else keeps busy.

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

**How the host waits.** Even with polling idle CPUs, a host asleep in ``poll`` pays for its
own wake-up after the worker rings: the scheduler switches it in and it returns from the
system call (~3 µs here, of a ~20 µs round trip). When a policy answers fast, the host
instead *spins*: it re-reads the reply slot's sequence number in the shared memory (a
read, no system call) until its reply's number is there, then takes the reply as usual
(bell read, checks), and sleeps in ``poll`` only if nothing came within its budget. The
budget is twice the car's previous step time, at most :func:`spin_limit_s` (so a policy
that takes longer never costs a spin), and the host spins only for the last car it waits
for (the others' workers are idle then) and only where it may run on two CPUs or more
(so it never takes the CPU the worker needs). ``SLIPSTREAM_SPIN_US`` sets the limit
(default :data:`SPIN_US`; ``0`` never spins).

A spin pays only while a CPU is free for the worker: on a busy machine the spinning host
holds a CPU that the worker (or another job) then waits for, and a step measured 15–45 %
*slower* with the spin than without it beside one or two busy processes on 2 vCPUs. So the
host spins only while the machine's CPUs are not contended, as the kernel's pressure
stall information says (:class:`CpuContention`: ``/proc/pressure/cpu``, the share of wall
time in which some runnable task waited for a CPU): above :data:`CONTENDED_SHARE` in the
last sample of :data:`SAMPLE_S` and in :data:`CONTENDED_OF` of the last :data:`RECENT`, it
stops spinning for :data:`BACKOFF_S`, then tries again. One contended sample alone is a burst,
not contention: on the idle 2-vCPU VM the share is ~0.5 % with a sample over 10 % now and
then (a kernel thread's burst), and backing off on each of those refused the spin for a
third to four fifths of a lone policy's steps; beside one busy process the share is 15–35 %
in three samples of four, beside two 57–86 %, so contention still stops the spin after
two samples (after one, once the host has backed off before: the history is kept across
a backoff, and cleared only by a pause). Where the file cannot be read (a kernel without
PSI), the host does not spin.
"""

from __future__ import annotations

import collections
import ctypes
import logging
import os
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

from submissions.errors import SandboxError

log = logging.getLogger(__name__)

DEVICE = Path("/dev/cpu_dma_latency")  # the kernel's PM QoS CPU-latency file
LATENCY_ENV = "SLIPSTREAM_CPU_LATENCY_US"  # unset/"0": poll; "N": N µs; "off": no request
OFF = ("off", "none", "no")
MAX_LATENCY_US = 2_000_000_000  # the kernel's default (no constraint) and its largest value
SPIN_ENV = "SLIPSTREAM_SPIN_US"  # the longest a host spins for a reply, µs ("0": never)
SPIN_US = 200  # its default
MAX_SPIN_US = 100_000
PRESSURE = Path("/proc/pressure/cpu")  # the kernel's CPU pressure stall information
SAMPLE_S = 0.02  # how often the host reads it while it may spin, s
CONTENDED_SHARE = 0.10  # more wall time than this with some task waiting: contended
RECENT = 3  # samples weighed …
CONTENDED_OF = 2  # … of which this many contended stop the spin
BACKOFF_S = 0.25  # how long the host then waits before it may spin again, s


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


def spin_limit_s() -> float:
    """The longest the host spins for one reply, s (``SLIPSTREAM_SPIN_US``, µs; see the
    module docstring); 0 where the host may run on one CPU only.

    Raises:
        SandboxError: the variable is not an integer within ``0..MAX_SPIN_US``.
    """
    raw = os.environ.get(SPIN_ENV, "").strip()
    try:
        value = int(raw) if raw else SPIN_US
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_SPIN_US:
        raise SandboxError(
            f"{SPIN_ENV} must be an integer number of µs within 0..{MAX_SPIN_US}, not {raw!r}"
        )
    if len(os.sched_getaffinity(0)) < 2:
        return 0.0
    return value * 1e-6


def check_settings() -> None:
    """Check ``SLIPSTREAM_CPU_LATENCY_US`` and ``SLIPSTREAM_SPIN_US`` once, where a command
    starts (``slipstream evaluate``, ``slipstream worker``): a typo is the operator's error,
    said in one line, not every sandbox's start failing and its car blamed.

    Raises:
        SandboxError: either is malformed.
    """
    requested_latency_us()
    spin_limit_s()


class CpuContention:
    """Whether this machine's CPUs are free enough for the host to spin (module docstring).

    :meth:`spin_allowed` is called before every spin: a clock read, and every
    :data:`SAMPLE_S` one ``pread`` of the pressure file (its ``some ... total=`` field,
    µs of wall time in which at least one runnable task waited for a CPU). Concurrent
    callers at worst read the file twice.

    Args:
        path: the pressure file (:data:`PRESSURE`; tests point it elsewhere).
        clock: seconds, monotonic (tests drive it).
    """

    def __init__(self, path: Path = PRESSURE, clock: Callable[[], float] = time.monotonic) -> None:
        self.path = path
        self._clock = clock
        self._fd = -2  # -2: not opened yet; -1: cannot be read here
        self._sampled_at: float | None = None  # None: the next call takes a fresh sample
        self._stalled_us = 0
        self._quiet_until = float("-inf")  # no spin before this time (a backoff)
        self._recent: collections.deque[bool] = collections.deque(maxlen=RECENT)

    def spin_allowed(self) -> bool:
        """Whether the CPUs were free enough over the last sample (False without PSI)."""
        now = self._clock()
        if now < self._quiet_until:
            return False
        if self._sampled_at is not None and now - self._sampled_at < SAMPLE_S:
            return True
        stalled = self._read()
        if stalled is None:
            return False
        last, self._sampled_at = self._sampled_at, now
        waited, self._stalled_us = stalled - self._stalled_us, stalled
        if last is not None and now - last > 10 * SAMPLE_S:
            self._recent.clear()  # a pause (between races, say): what came before is stale
            return True
        if last is None:  # a fresh sample (the first, or after a backoff): nothing to compare
            if now - self._quiet_until > 10 * SAMPLE_S:
                self._recent.clear()  # the backoff ended long ago: that was a pause too
            return True
        contended = waited > CONTENDED_SHARE * (now - last) * 1e6
        self._recent.append(contended)
        if contended and sum(self._recent) >= CONTENDED_OF:
            self._quiet_until = now + BACKOFF_S
            self._sampled_at = None
            return False
        return True

    def _read(self) -> int | None:
        """The ``some`` line's ``total=`` (µs), or None where it cannot be read."""
        if self._fd == -2:
            try:
                self._fd = os.open(self.path, os.O_RDONLY | os.O_CLOEXEC)
            except OSError:
                self._fd = -1
        if self._fd < 0:
            return None
        try:
            line = os.pread(self._fd, 256, 0).split(b"\n", 1)[0]
            return int(line.rsplit(b"total=", 1)[1])
        except (OSError, IndexError, ValueError):
            return None


CONTENTION = CpuContention()  # this process's view of the machine's CPU pressure


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
