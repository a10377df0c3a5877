"""The sandbox a submitted policy runs in: bubblewrap, rlimits, cgroups, seccomp, Landlock.

Every uploaded policy runs in its own process tree, started by :class:`SandboxProcess`:

=================  ==========================================  ===============================
concern            ``"bwrap"`` mode (the default)              ``"seccomp"`` mode (fallback)
=================  ==========================================  ===============================
allowed            always                                      only when the operator passed
                                                               ``--allow-weak-sandbox`` (else
                                                               :class:`SandboxError`: fail closed)
filesystem         empty read-only root; binds of ``/usr``,    the host's, narrowed by Landlock
                   the Python install, the venv, the           (read: the same paths and a
                   project's packages (``/app``) and the       read-only link tree of the bundle;
                   bundle (``/submission``); a size-capped     write: one folder, a size-capped
                   tmpfs on ``/tmp``                           tmpfs where it can be mounted)
``/proc``          its own pid namespace's                     a few files of its own process
                                                               (``status``, ``stat``...), never
                                                               ``net/`` or another pid
network, IPC       new network and IPC namespaces; seccomp     seccomp: every ``socket()`` and
                   refuses every ``socket()``/``socketpair``   ``socketpair``, SysV IPC, POSIX
                   SysV IPC, POSIX message queues and          mqueue and ``memfd_create``
                   ``memfd_create``                            refused; Landlock denies TCP
                                                               bind/connect too
the channel        inherited descriptors only: its own sealed memfd (mapped shared) and two
                   pipe ends (:mod:`submissions.channel`); nothing named, nothing another
                   sandbox holds
processes          pid namespace (sees only itself), cgroup    ONE process: ``fork``/``vfork``/
                   ``pids.max`` (root) or ``RLIMIT_NPROC``     ``clone`` without ``CLONE_THREAD``
                                                               refused (threads allowed);
                                                               ``setsid``/``setpgid`` refused;
                                                               signals, ``prlimit``, pidfds of
                                                               itself only (the sandboxes share
                                                               a uid: :func:`seccomp_filter`);
                                                               its parent-death signal fixed
identity           uid/gid 65534 in a user namespace, no       uid/gid 65534 on the host (when
                   capabilities, new session, cleared env      the runner is root), no groups,
                                                               every capability dropped (bounding
                                                               set too), ``no_new_privs``,
                                                               cleared env; Landlock scopes
                                                               signals to the sandbox
host metadata      nothing of the host is bound writable       ``chmod``/``chown``/``utime``/
                                                               ``*xattr``/``mknod`` refused;
                                                               ``setpriority``/``sched_set*`` on
                                                               anything but itself refused
memory, CPU, …     ``RLIMIT_AS``/cgroup memory, CPU seconds, a cgroup CPU quota (``cpus``
                   cores for the whole sandbox), open files, file size, no core dumps
lifetime           parent-death signal on the outermost process; its own folder, cgroups,
                   process group and mount are removed by :meth:`SandboxProcess.kill`, or by
                   :func:`reap` / :func:`reap_stale` when the host process itself died
=================  ==========================================  ===============================

Both modes also refuse ``ptrace``, ``mount``, ``unshare``/``setns``, namespace-creating
``clone`` flags, ``bpf``, ``perf_event_open``, kernel keyrings, ``userfaultfd``, module
loading, ``sethostname``/``setdomainname``, setting the clock and ``syslog``.
:func:`sandbox_mode` picks the mode: ``bwrap`` when user namespaces work; else the fallback,
but only when :func:`weak_sandbox_allowed` (the operator's ``--allow-weak-sandbox``, carried
to job processes in ``SLIPSTREAM_ALLOW_WEAK_SANDBOX=1``); ``SANDBOX=seccomp`` forces the
fallback and still needs that permission; ``SANDBOX=bwrap`` insists on bubblewrap. A result
raced in the fallback says so: :func:`mode_label` gives ``"seccomp-weak"``.

The cgroup caps (v1 ``pids``, ``memory`` and ``cpu`` hierarchies under ``/sys/fs/cgroup``) are
used where the folder is writable (root here); ``RLIMIT_NPROC`` is not enforced for root, so
without them the process cap rests on the pid namespace (bwrap) or the fork ban (fallback),
and nothing caps the cores a sandbox's threads use.
Run by a non-root user, the fallback keeps that user's uid (it cannot change it; the user has
no capabilities to drop) and its writable folder is capped by ``RLIMIT_FSIZE`` only.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import logging
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from submissions.errors import SandboxError

log = logging.getLogger(__name__)

BWRAP = "/usr/bin/bwrap"
SANDBOX_UID = 65534  # "nobody": inside bwrap's user namespace, and on the host in the fallback
UID_ENV = "SLIPSTREAM_SANDBOX_UID"  # another unprivileged uid[:gid] for the fallback
WEAK_ENV = "SLIPSTREAM_ALLOW_WEAK_SANDBOX"  # "1": the operator allowed the seccomp fallback
WEAK_LABEL = "seccomp-weak"  # what a result raced in the fallback records (fits 16 chars)
SANDBOX_PREFIX = "slipstream-sbx-"  # <tmp>/slipstream-sbx-<host pid>-<id>: one per sandbox
JOB_PREFIX = "slipstream-job-"  # <tmp>/slipstream-job-<executor pid>-<id>: a job's scratch
CGROUP_ROOT = Path("/sys/fs/cgroup")
CGROUP_HIERARCHIES = ("pids", "memory", "cpu")  # the v1 hierarchies a sandbox gets a cgroup in
PACKAGES = ("tracks", "arena", "agents", "submissions")  # what a worker may import of ours
APP = "/app"  # where the packages appear inside bwrap
MODES = ("bwrap", "seccomp")
CPU_PERIOD_US = 100_000  # the cgroup CPU quota's period, µs (the kernel's default)
MIN_CPUS, MAX_CPUS = 0.01, 1024.0  # cores a sandbox may be given (the quota's bounds)
THREAD_ENV = {  # one thread per math library: 2 cores are shared by every car
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}
_MIB = 1 << 20


@dataclass(frozen=True)
class SandboxLimits:
    """Resource limits and deadlines of one sandboxed policy.

    Attributes:
        memory_mb: address space (``RLIMIT_AS``) and cgroup memory cap, MiB (≥ 1024:
            importing torch alone reserves about 620 MiB).
        cpu_seconds: CPU time of each process, s (``RLIMIT_CPU``; SIGKILL 5 s later).
        open_files: open file descriptors per process (``RLIMIT_NOFILE``).
        file_size_mb: largest file it may write, MiB (``RLIMIT_FSIZE``).
        max_processes: tasks (processes and threads) in its tree (cgroup ``pids.max``).
        cpus: CPU cores its processes may use together, at most (cgroup CPU quota; a
            sandbox of many busy processes or threads counts as ``cpus`` cores, not as
            many: it cannot starve the race, the other cars or other jobs).
        tmpfs_mb: size of its private ``/tmp``, MiB (bwrap mode).
        step_deadline_s: wall time for one action, s, from sending the observation.
        startup_s: wall time to load the policy and answer the first reset, s.
        overage_s: Kaggle-style bank, s: time over ``step_deadline_s`` is drawn from it;
            the policy times out when it is spent.
    """

    memory_mb: int = 2048
    cpu_seconds: int = 600
    open_files: int = 256
    file_size_mb: int = 64
    max_processes: int = 64
    cpus: float = 1.0
    tmpfs_mb: int = 256
    step_deadline_s: float = 0.25
    startup_s: float = 60.0
    overage_s: float = 10.0

    def __post_init__(self) -> None:
        if self.memory_mb < 1024:
            raise SandboxError(
                f"memory_mb must be at least 1024 (torch needs it), got {self.memory_mb}"
            )
        for name in ("cpu_seconds", "file_size_mb", "max_processes", "tmpfs_mb"):
            if getattr(self, name) < 1:
                raise SandboxError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.open_files < 16:
            raise SandboxError(
                f"open_files must be at least 16 (Python needs them), got {self.open_files}"
            )
        if not MIN_CPUS <= self.cpus <= MAX_CPUS:
            raise SandboxError(f"cpus must be within {MIN_CPUS}..{MAX_CPUS}, got {self.cpus}")
        for name in ("step_deadline_s", "startup_s"):
            if not getattr(self, name) > 0:
                raise SandboxError(f"{name} must be positive, got {getattr(self, name)}")
        if self.overage_s < 0:
            raise SandboxError(f"overage_s must not be negative, got {self.overage_s}")


# ---- which mode --------------------------------------------------------------------------


@functools.cache
def bwrap_works() -> bool:
    """Whether bubblewrap can create the namespaces we need here (probed once)."""
    if not os.access(BWRAP, os.X_OK):
        return False
    probe = [BWRAP, "--unshare-all", "--unshare-user", "--die-with-parent", "--cap-drop", "ALL"]
    probe += [*_system_binds(), "--", "/usr/bin/true"]
    try:
        done = subprocess.run(probe, capture_output=True, timeout=20, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def allow_weak_sandbox() -> None:
    """The operator allows the seccomp fallback (``--allow-weak-sandbox``); logged.

    Sets ``SLIPSTREAM_ALLOW_WEAK_SANDBOX=1`` in this process's environment, so the job
    processes it starts (and Ray tasks, see :mod:`submissions.executors`) inherit it.
    """
    os.environ[WEAK_ENV] = "1"
    log.warning(
        "--allow-weak-sandbox: where bubblewrap cannot run, untrusted policies run in the "
        "weaker seccomp fallback; every such result is recorded as %r",
        WEAK_LABEL,
    )


def weak_sandbox_allowed() -> bool:
    """Whether the operator allowed the fallback (``SLIPSTREAM_ALLOW_WEAK_SANDBOX=1``)."""
    return os.environ.get(WEAK_ENV, "").strip() == "1"


def sandbox_mode() -> str:
    """``"bwrap"`` where namespaces work, else ``"seccomp"`` if the operator allowed it.

    ``SANDBOX=seccomp`` forces the fallback (for tests), which still needs the operator's
    permission; ``SANDBOX=bwrap`` requires bwrap.

    Raises:
        SandboxError: ``SANDBOX`` names no mode, requires bwrap where it does not work, or
            the fallback would be needed and was not allowed (fail closed).
    """
    wanted = os.environ.get("SANDBOX", "auto").strip().lower() or "auto"
    if wanted not in (*MODES, "auto"):
        raise SandboxError(f"SANDBOX={wanted!r}: expected bwrap, seccomp or auto")
    if wanted != "seccomp" and bwrap_works():
        return "bwrap"
    if wanted == "bwrap":
        raise SandboxError(f"SANDBOX=bwrap but {BWRAP} cannot create namespaces here")
    if not weak_sandbox_allowed():
        why = "SANDBOX=seccomp asks for" if wanted == "seccomp" else "bubblewrap cannot run here:"
        raise SandboxError(
            f"{why} the weaker seccomp fallback, and untrusted policies do not run in it "
            "unless the operator passes --allow-weak-sandbox"
        )
    _warn_fallback()
    return "seccomp"


def mode_label(mode: str) -> str:
    """What a result records for a sandbox ``mode``: ``"bwrap"``, or ``"seccomp-weak"``."""
    return WEAK_LABEL if mode == "seccomp" else mode


@functools.cache
def _warn_fallback() -> None:
    log.warning(
        "submitted policies run in the weaker seccomp fallback (allowed by the operator): "
        "rlimits + seccomp + Landlock + an unprivileged uid, no namespaces"
    )


# ---- seccomp -----------------------------------------------------------------------------

_CLONE_NEW = (0x00020000, 0x02000000, 0x04000000, 0x08000000, 0x10000000, 0x20000000, 0x40000000)
_DENIED = (
    "ptrace",
    "process_vm_readv",
    "process_vm_writev",
    "mount",
    "umount2",
    "pivot_root",
    "chroot",
    "unshare",
    "setns",
    "bpf",
    "perf_event_open",
    "keyctl",
    "add_key",
    "request_key",
    "userfaultfd",
    "kexec_load",
    "kexec_file_load",
    "init_module",
    "finit_module",
    "delete_module",
    "io_uring_setup",  # io_uring can open sockets without the socket() syscall
    "io_uring_enter",
    "io_uring_register",
    "open_by_handle_at",
    "swapon",
    "swapoff",
    "reboot",
)


_DENIED_BOTH = (  # neither a policy nor the channel needs these (pipes need no socket)
    "socket",
    "socketpair",
    "memfd_create",  # the channel's region is the host's memfd, inherited: no new ones
    "memfd_secret",
    "shmget",
    "shmat",
    "shmctl",
    "shmdt",
    "msgget",
    "msgsnd",
    "msgrcv",
    "msgctl",
    "semget",
    "semop",
    "semtimedop",
    "semctl",
    "mq_open",
    "mq_unlink",
    "mq_timedsend",
    "mq_timedreceive",
    "mq_notify",
    "mq_getsetattr",
    "sethostname",
    "setdomainname",
    "settimeofday",
    "clock_settime",
    "clock_adjtime",
    "adjtimex",
    "syslog",
    "acct",
    "quotactl",
    "iopl",
    "ioperm",
    "vhangup",
    "name_to_handle_at",
)
_DENIED_FALLBACK = (  # host metadata and host processes: bwrap shows the policy neither
    "fork",
    "vfork",
    "setsid",
    "setpgid",
    "chmod",
    "fchmod",
    "fchmodat",
    "fchmodat2",
    "chown",
    "fchown",
    "lchown",
    "fchownat",
    "utime",
    "utimes",
    "futimesat",
    "utimensat",
    "setxattr",
    "lsetxattr",
    "fsetxattr",
    "removexattr",
    "lremovexattr",
    "fremovexattr",
    "mknod",
    "mknodat",
    "link",
    "linkat",
    "sched_setattr",
    "ioprio_set",
    "setuid",
    "setreuid",
    "setresuid",
    "setfsuid",
    "setgid",
    "setregid",
    "setresgid",
    "setfsgid",
    "setgroups",
    "capset",
)
_CLONE_THREAD = 0x00010000


_OWN_PID_ONLY = (  # fallback: these act on the process given first; only on the worker's own
    "kill",  # (0 or -1 included: its group, every process it may signal)
    "tkill",
    "tgkill",
    "rt_sigqueueinfo",
    "rt_tgsigqueueinfo",
    "pidfd_open",
)
_SELF_ZERO_ONLY = ("prlimit64", "get_robust_list", "migrate_pages", "move_pages")  # pid 0: itself
_CROSS_PROCESS = ("kcmp", "pidfd_getfd", "process_madvise")  # another process's files/memory
_PR_SET_PDEATHSIG = 1


@functools.lru_cache(maxsize=16)  # bwrap's is one program; the fallback's, one per worker
def seccomp_filter(mode: str, pid: int | None = None) -> bytes:
    """The seccomp BPF program for ``mode`` (built with libseccomp on the trusted side).

    In the fallback every sandbox runs as the same unprivileged uid, so what one process
    may do to another of its uid would reach the race's other sandboxes (and any host
    process of that uid): signals, rlimits (``prlimit64``), another process's files or
    memory. Landlock scopes signals and ptrace-like access where the kernel has it (signals
    from ABI 6 on, not ``prlimit64`` at all); the filter refuses them whatever the kernel:
    the signal calls and ``pidfd_open`` only on ``pid`` (the worker itself; the filter is
    built once it is known: :class:`SandboxProcess` hands it over after the start), the
    others only on pid 0 (itself), ``kcmp``/``pidfd_getfd``/``process_madvise`` never.

    Raises:
        SandboxError: libseccomp (``pyseccomp``) is not available.
    """
    try:
        import pyseccomp as sc  # noqa: PLC0415 - only the trusted side builds the filter
    except (ImportError, OSError) as err:  # OSError: the libseccomp shared library is missing
        raise SandboxError(f"the sandbox needs libseccomp (pyseccomp): {err}") from err
    filt = sc.SyscallFilter(sc.ALLOW)
    denied = (*_DENIED, *_DENIED_BOTH, *(_DENIED_FALLBACK if mode == "seccomp" else ()))
    for name in denied:
        _deny(filt, sc.ERRNO(errno.EACCES if "socket" in name else errno.EPERM), name)
    for flag in _CLONE_NEW:
        filt.add_rule(sc.ERRNO(errno.EPERM), "clone", sc.Arg(0, sc.MASKED_EQ, flag, flag))
    filt.add_rule(sc.ERRNO(errno.ENOSYS), "clone3")  # flags behind a pointer: make libc use clone
    if mode == "seccomp":
        # One process: threads (CLONE_THREAD) only, so the parent-death signal ends all of it.
        eperm = sc.ERRNO(errno.EPERM)
        filt.add_rule(eperm, "clone", sc.Arg(0, sc.MASKED_EQ, _CLONE_THREAD, 0))
        # Scheduling and priority of itself only (pid/who 0); never of a host process.
        for name in ("sched_setscheduler", "sched_setparam", "sched_setaffinity"):
            filt.add_rule(eperm, name, sc.Arg(0, sc.NE, 0))
        filt.add_rule(eperm, "setpriority", sc.Arg(1, sc.NE, 0))
        if pid is None:
            raise SandboxError("the fallback's filter needs the worker's pid")
        for name in _OWN_PID_ONLY:
            _deny(filt, eperm, name, sc.Arg(0, sc.NE, pid))
        for name in _SELF_ZERO_ONLY:
            _deny(filt, eperm, name, sc.Arg(0, sc.NE, 0))
        for name in _CROSS_PROCESS:
            _deny(filt, eperm, name)
        # Its parent-death signal stays: cleared, a policy's thread outlived a SIGKILLed host.
        filt.add_rule(eperm, "prctl", sc.Arg(0, sc.EQ, _PR_SET_PDEATHSIG))
    with tempfile.TemporaryFile() as fh:
        filt.export_bpf(fh)
        fh.seek(0)
        return fh.read()


def _deny(filt: object, action: object, name: str, *args: object) -> None:
    try:
        filt.add_rule(action, name, *args)  # type: ignore[attr-defined]
    except (RuntimeError, ValueError, OSError):  # a syscall this architecture does not have
        log.debug("seccomp: no syscall %s on this architecture", name)


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def _check(ret: int, what: str) -> int:
    if ret < 0:
        err = ctypes.get_errno()
        raise OSError(err, f"{what}: {os.strerror(err)}")
    return ret


def no_new_privs() -> None:
    """``prctl(PR_SET_NO_NEW_PRIVS)``: no setuid gains; required for unprivileged filters."""
    _check(_libc().prctl(38, 1, 0, 0, 0), "PR_SET_NO_NEW_PRIVS")


def apply_seccomp(program: bytes) -> None:
    """Install a seccomp BPF ``program`` on the calling thread (and its future children)."""

    class SockFprog(ctypes.Structure):
        _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]

    if not program or len(program) % 8:  # empty: the host never wrote it (it failed)
        raise SandboxError("seccomp program is not a whole number of instructions")
    buf = ctypes.create_string_buffer(program, len(program))
    prog = SockFprog(len(program) // 8, ctypes.addressof(buf))
    no_new_privs()
    _check(_libc().prctl(22, 2, ctypes.byref(prog), 0, 0), "PR_SET_SECCOMP")


# ---- Landlock (seccomp mode) ------------------------------------------------------------

_LL_CREATE, _LL_ADD_RULE, _LL_RESTRICT = 444, 445, 446  # same numbers on every architecture
_FS_EXECUTE, _FS_WRITE_FILE, _FS_READ_FILE, _FS_READ_DIR = 1, 2, 4, 8
_FS_FILE_RIGHTS = _FS_EXECUTE | _FS_WRITE_FILE | _FS_READ_FILE | (1 << 14) | (1 << 15)
_FS_READ = _FS_EXECUTE | _FS_READ_FILE | _FS_READ_DIR


def landlock_abi() -> int:
    """The kernel's Landlock ABI version (0: unavailable)."""
    libc = _libc()
    libc.syscall.restype = ctypes.c_long
    ret = libc.syscall(_LL_CREATE, None, ctypes.c_size_t(0), ctypes.c_uint32(1))
    return max(int(ret), 0)


def landlock_restrict(read: Sequence[str], write: Sequence[str]) -> int:
    """Confine this process (and children) to reading ``read`` and writing ``write``.

    Also, where the kernel offers them: no TCP bind/connect (ABI ≥ 4), no signals to
    processes outside the sandbox and no abstract Unix sockets (ABI ≥ 6). Paths that do not
    exist are skipped.

    Returns:
        The Landlock ABI used; 0 when the kernel has no Landlock (nothing was restricted).
    """
    abi = landlock_abi()
    if abi == 0:
        return 0
    handled = (1 << 13) - 1
    handled |= (1 << 13) if abi >= 2 else 0  # REFER
    handled |= (1 << 14) if abi >= 3 else 0  # TRUNCATE
    handled |= (1 << 15) if abi >= 5 else 0  # IOCTL_DEV
    fields = [handled, 0b11 if abi >= 4 else 0, 0b11 if abi >= 6 else 0]
    size = 8 * (1 + (abi >= 4) + (abi >= 6))
    attr = (ctypes.c_uint64 * 3)(*fields)
    libc = _libc()
    libc.syscall.restype = ctypes.c_long
    ruleset = _check(
        libc.syscall(_LL_CREATE, ctypes.byref(attr), ctypes.c_size_t(size), ctypes.c_uint32(0)),
        "landlock_create_ruleset",
    )
    try:
        for paths, access in ((read, _FS_READ), (write, handled)):
            for path in paths:
                _landlock_allow(libc, ruleset, path, access & handled)
        no_new_privs()
        _check(libc.syscall(_LL_RESTRICT, ruleset, ctypes.c_uint32(0)), "landlock_restrict_self")
    finally:
        os.close(ruleset)
    return abi


def _landlock_allow(libc: ctypes.CDLL, ruleset: int, path: str, access: int) -> None:
    class PathBeneath(ctypes.Structure):
        _pack_ = 1
        _fields_ = [("allowed_access", ctypes.c_uint64), ("parent_fd", ctypes.c_int32)]

    try:
        fd = os.open(path, os.O_PATH | os.O_CLOEXEC)
    except OSError:
        return
    try:
        if not os.path.isdir(path):
            access &= _FS_FILE_RIGHTS
        rule = PathBeneath(access, fd)
        _check(libc.syscall(_LL_ADD_RULE, ruleset, 1, ctypes.byref(rule), 0), "landlock_add_rule")
    finally:
        os.close(fd)


# ---- cgroups -----------------------------------------------------------------------------


@dataclass
class CgroupCaps:
    """Per-sandbox cgroup v1 folders (``pids``, ``memory``, ``cpu``) where they can be made.

    Attributes:
        dirs: the folders made (empty when cgroups are not writable here).
    """

    dirs: list[Path] = field(default_factory=list)

    @classmethod
    def create(cls, name: str, limits: SandboxLimits) -> CgroupCaps:
        """Make ``slipstream/<name>`` under each writable hierarchy and set its caps."""
        settings = {
            "pids": {"pids.max": limits.max_processes + 4},  # + bwrap's own processes
            "memory": {"memory.limit_in_bytes": limits.memory_mb * _MIB},
            "cpu": {  # the whole tree gets `cpus` cores per period, however many tasks it has
                "cpu.cfs_period_us": CPU_PERIOD_US,
                "cpu.cfs_quota_us": max(1000, round(limits.cpus * CPU_PERIOD_US)),
            },
        }
        caps = cls()
        for hierarchy, values in settings.items():
            parent = CGROUP_ROOT / hierarchy / "slipstream"
            try:
                parent.mkdir(exist_ok=True)
                path = parent / name
                path.mkdir()
                for key, value in values.items():
                    (path / key).write_text(str(value))
            except OSError:
                continue
            caps.dirs.append(path)
        return caps

    @classmethod
    def existing(cls, name: str) -> CgroupCaps:
        """The folders ``slipstream/<name>`` that exist (to reap a sandbox whose host died)."""
        found = (CGROUP_ROOT / h / "slipstream" / name for h in CGROUP_HIERARCHIES)
        return cls([d for d in found if d.is_dir()])

    @property
    def procs_files(self) -> list[str]:
        """The ``cgroup.procs`` files a new process writes its pid to."""
        return [str(d / "cgroup.procs") for d in self.dirs]

    def pids(self) -> set[int]:
        """Every process still in the sandbox's cgroups."""
        found: set[int] = set()
        for d in self.dirs:
            with contextlib.suppress(OSError, ValueError):
                found.update(int(p) for p in (d / "cgroup.procs").read_text().split())
        return found

    def kill_all(self, patience_s: float = 5.0) -> None:
        """SIGKILL every process in the cgroups until none is left (a fork bomb included),
        for at most ``patience_s`` s (0: one pass, no waiting)."""
        end = time.monotonic() + patience_s
        while pids := self.pids():
            for pid in pids:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(pid, signal.SIGKILL)
            if time.monotonic() >= end:
                return
            time.sleep(0.01)

    def remove(self) -> None:
        """Remove the folders (they must be empty: call :meth:`kill_all` first)."""
        for d in self.dirs:
            for _ in range(100):  # the kernel releases a killed task's cgroup a moment later
                try:
                    d.rmdir()
                    break
                except FileNotFoundError:
                    break
                except OSError:
                    time.sleep(0.01)
        self.dirs.clear()


# ---- the command line --------------------------------------------------------------------


def _system_binds() -> list[str]:
    args = ["--ro-bind", "/usr", "/usr"]
    for name in ("lib", "lib64", "bin", "sbin"):
        if Path(f"/{name}").is_symlink() or not Path(f"/{name}").exists():
            args += ["--symlink", f"usr/{name}", f"/{name}"]
        else:  # not a merged-/usr system: bind the real folder
            args += ["--ro-bind", f"/{name}", f"/{name}"]
    return args


def python_paths() -> list[str]:
    """Folders the worker's Python needs: the base install and the venv (outside /usr)."""
    paths = {os.path.realpath(sys.base_prefix), os.path.realpath(sys.prefix)}
    return sorted(p for p in paths if not p.startswith("/usr/"))


def package_dirs() -> dict[str, str]:
    """The project's packages a worker may import, name → folder on the host."""
    root = Path(__file__).resolve().parent.parent
    return {name: str(root / name) for name in PACKAGES}


def bwrap_command(
    worker_args: Sequence[str], bundle_root: Path, limits: SandboxLimits, seccomp_fd: int
) -> list[str]:
    """The bubblewrap command line that runs the worker (the recipe in the module docstring)."""
    cmd = [BWRAP, "--die-with-parent", "--unshare-all", "--unshare-user"]
    cmd += ["--uid", str(SANDBOX_UID), "--gid", str(SANDBOX_UID), "--new-session"]
    cmd += ["--cap-drop", "ALL", "--clearenv", "--hostname", "sandbox"]
    env = {"PATH": "/usr/bin:/bin", "HOME": "/tmp", "TMPDIR": "/tmp", "PYTHONPATH": APP}
    env |= {"PYTHONNOUSERSITE": "1", "PYTHONDONTWRITEBYTECODE": "1", "LANG": "C.UTF-8"}
    for key, value in (env | THREAD_ENV).items():
        cmd += ["--setenv", key, value]
    # tmpfs first: a later tmpfs would hide binds beneath it.
    cmd += ["--size", str(limits.tmpfs_mb * _MIB), "--tmpfs", "/tmp"]
    cmd += [*_system_binds(), "--proc", "/proc", "--dev", "/dev"]
    cmd += ["--size", str(limits.tmpfs_mb * _MIB), "--tmpfs", "/dev/shm"]
    for path in python_paths():
        cmd += ["--ro-bind", path, path]
    for name, path in package_dirs().items():
        cmd += ["--ro-bind", path, f"{APP}/{name}"]
    cmd += ["--ro-bind", str(bundle_root), "/submission", "--remount-ro", "/", "--chdir", "/tmp"]
    cmd += ["--seccomp", str(seccomp_fd), "--", sys.executable, "-B", "-m", "submissions.worker"]
    return [*cmd, "--root", "/submission", *worker_args]


def fallback_paths(bundle_root: Path, work: Path, app: Path) -> tuple[list[str], list[str]]:
    """What the seccomp-mode worker may read and write (Landlock rules): ``(read, write)``."""
    read = ["/usr", "/lib", "/lib64", "/bin", "/sys/devices/system/cpu", *python_paths()]
    read += [*package_dirs().values(), str(app), str(bundle_root), "/dev/urandom"]
    return read, [str(work), "/dev/null"]


@dataclass(frozen=True)
class Identity:
    """Who the fallback runs as (root runner only).

    Attributes:
        uid: real and effective uid (65534, or ``SLIPSTREAM_SANDBOX_UID``).
        gid: real, effective and file-system gid; no supplementary groups.
        fs_root: keep the *file-system* uid 0 (saved uid 0, set*id calls then refused by
            seccomp, no capabilities at all) because the interpreter lies under a folder
            only root may traverse (``/root/.pyenv``); reads are still only Landlock's list
            and writes only the work folder. False: the file-system uid is ``uid`` too.
    """

    uid: int
    gid: int
    fs_root: bool

    @property
    def files_uid(self) -> int:
        """The owner its work folder needs."""
        return 0 if self.fs_root else self.uid


def fallback_identity() -> Identity | None:
    """The identity the fallback drops to (:class:`Identity`); None when the runner is not
    root (it cannot change its uid, and has no capabilities to drop).

    Raises:
        SandboxError: ``SLIPSTREAM_SANDBOX_UID`` is malformed or names uid/gid 0.
    """
    if os.geteuid() != 0:
        return None
    raw = os.environ.get(UID_ENV, "").strip()
    uid = gid = SANDBOX_UID
    if raw:
        try:
            first, _, second = raw.partition(":")
            uid, gid = int(first), int(second or first)
        except ValueError:
            raise SandboxError(f"{UID_ENV}={raw!r}: expected uid or uid:gid") from None
        if min(uid, gid) <= 0:
            raise SandboxError(f"{UID_ENV}={raw!r}: the sandbox never runs as uid or gid 0")
    paths = [os.path.realpath(sys.executable), *python_paths(), *package_dirs().values()]
    return Identity(uid, gid, fs_root=not all(_others_can_reach(p) for p in paths))


def _others_can_reach(path: str) -> bool:
    """Whether every folder above ``path`` lets other users through (``o+x``)."""
    current = Path(path)
    for folder in [*current.parents, current]:
        try:
            mode = folder.stat().st_mode
        except OSError:
            return False
        if folder != current and not mode & 0o001:
            return False
    return True


def _cap_last() -> int:
    try:
        return int(Path("/proc/sys/kernel/cap_last_cap").read_text())
    except (OSError, ValueError):
        return 63


class _CapHeader(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _CapData(ctypes.Structure):
    _fields_ = [
        ("effective", ctypes.c_uint32),
        ("permitted", ctypes.c_uint32),
        ("inheritable", ctypes.c_uint32),
    ]


_PR_SET_PDEATHSIG, _PR_CAPBSET_DROP, _PR_SET_NO_NEW_PRIVS = 1, 24, 38
_KEPT_FOR_DROP = (6, 7, 8)  # CAP_SETGID, CAP_SETUID, CAP_SETPCAP: dropped by drop_identity


def drop_identity(uid: int) -> None:
    """In the fallback's worker, after exec (``Identity.fs_root``): become ``uid`` with the
    file-system uid 0 and no capability at all (the last three leave the bounding set).

    An exec resets the saved and file-system uids to the effective one, so this part of
    the drop cannot happen before it.
    """
    libc = _libc()
    for cap in _KEPT_FOR_DROP:  # CAP_SETPCAP last: it is what allows the drops
        _check(libc.prctl(_PR_CAPBSET_DROP, cap, 0, 0, 0), "PR_CAPBSET_DROP")
    os.setresuid(uid, uid, 0)  # clears the effective set; the saved uid 0 allows setfsuid(0)
    header = _CapHeader(0x20080522, 0)
    _check(libc.capset(ctypes.byref(header), (_CapData * 2)()), "capset")
    libc.setfsuid(0)  # no capability comes back: the permitted set is empty
    if libc.setfsuid(-1) != 0:  # setfsuid(-1) fails and returns the current fsuid
        raise SandboxError("could not keep the file-system uid")


def _preexec(
    limits: SandboxLimits, procs_files: list[str], identity: Identity | None, cpu: int | None
) -> Callable[[], None]:
    """Runs in the child between fork and exec (system calls only, prepared here).

    Binds it to ``cpu`` (if given), joins the cgroups, sets the rlimits; with ``identity``
    (fallback run by root) drops the bounding set, the groups, the uid/gid and then every
    remaining capability; always sets the parent-death signal last (a credential change
    clears it) and ``no_new_privs``.
    """
    rlimits = [
        (resource.RLIMIT_AS, limits.memory_mb * _MIB),
        (resource.RLIMIT_NOFILE, limits.open_files),
        (resource.RLIMIT_FSIZE, limits.file_size_mb * _MIB),
        (resource.RLIMIT_NPROC, limits.max_processes),  # not enforced for root: cgroup does it
        (resource.RLIMIT_CORE, 0),
        (resource.RLIMIT_RTPRIO, 0),  # no SCHED_FIFO/RR
        (resource.RLIMIT_NICE, 0),  # no raising its priority
    ]
    libc = _libc()
    prctl = libc.prctl
    capset = libc.capset
    header = _CapHeader(0x20080522, 0)  # _LINUX_CAPABILITY_VERSION_3
    nothing = (_CapData * 2)()
    caps = range(_cap_last() + 1)
    parent = os.getpid()
    cpus = None if cpu is None else {cpu}

    def run() -> None:
        if cpus is not None:
            os.sched_setaffinity(0, cpus)
        for path in procs_files:
            fd = os.open(path, os.O_WRONLY)
            try:
                os.write(fd, str(os.getpid()).encode())
            finally:
                os.close(fd)
        for which, value in rlimits:
            resource.setrlimit(which, (value, value))
        resource.setrlimit(resource.RLIMIT_CPU, (limits.cpu_seconds, limits.cpu_seconds + 5))
        if identity is not None:
            for cap in caps:  # the fs_root case keeps three, for drop_identity after exec
                if not identity.fs_root or cap not in _KEPT_FOR_DROP:
                    prctl(_PR_CAPBSET_DROP, cap, 0, 0, 0)
            os.setgroups([])
            gid, uid = identity.gid, identity.uid
            os.setresgid(gid, gid, gid)
            if not identity.fs_root:
                os.setresuid(uid, uid, uid)  # clears the permitted and effective sets
                if capset(ctypes.byref(header), nothing) != 0:  # and the inheritable one
                    os._exit(126)
        prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0)
        prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        if os.getppid() != parent:  # the host died before the line above
            os._exit(1)

    return run


# ---- the process -------------------------------------------------------------------------


def _owner_alive(folder: Path) -> bool:
    """Whether the host process named in ``slipstream-...-<pid>-...`` still runs."""
    try:
        pid = int(folder.name.split("-")[2])
    except (IndexError, ValueError):
        return True  # not ours to judge
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _unmount(path: Path) -> None:
    """Lazily unmount ``path`` if something is mounted there (the fallback's tmpfs)."""
    target = str(path)
    try:
        mounts = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return
    if any(line.split(" ")[1:2] == [target] for line in mounts):
        _libc().umount2(target.encode(), 2)  # MNT_DETACH


def _kill_group(folder: Path) -> None:
    """SIGKILL what is left of the process group recorded in ``folder/pgid``: only members
    with the recorded uid and the sandbox's id in their command line (a reused pgid's
    processes are spared)."""
    try:
        pgid, uid = (int(x) for x in (folder / "pgid").read_text().split())
    except (OSError, ValueError):
        return
    marker = folder.name.rsplit("-", 1)[-1].encode()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            status = (entry / "status").read_text()
            cmdline = (entry / "cmdline").read_bytes()
            owner = int(status.split("\nUid:", 1)[1].split()[0])  # real uid (not /proc's owner)
        except (OSError, IndexError, ValueError):
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        if int(fields[2]) == pgid and owner == uid and marker in cmdline:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(int(entry.name), signal.SIGKILL)


def reap(folder: Path) -> None:
    """Remove everything of one sandbox given its folder: processes, cgroups, mount, files.

    For a sandbox whose host process died without :meth:`SandboxProcess.kill` (SIGKILL,
    OOM). The folder is ``<tmp>/slipstream-sbx-<host pid>-<id>``.
    """
    _kill_group(folder)
    cgroups = CgroupCaps.existing(folder.name.rsplit("-", 1)[-1])
    cgroups.kill_all()
    cgroups.remove()
    _unmount(folder / "work")
    shutil.rmtree(folder, ignore_errors=True)


def reap_tree(root: Path) -> int:
    """:func:`reap` every sandbox folder under ``root`` (a job's scratch folder), then
    remove ``root`` itself; returns how many sandboxes were reaped."""
    found = sorted(root.glob(f"{SANDBOX_PREFIX}*")) if root.is_dir() else []
    for folder in found:
        reap(folder)
    for mount in _mounts_under(root):
        _unmount(Path(mount))
    shutil.rmtree(root, ignore_errors=True)
    return len(found)


def _mounts_under(root: Path) -> list[str]:
    try:
        lines = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return []
    prefix = f"{root}/"
    return [m for line in lines if (m := line.split(" ")[1]).startswith(prefix)]


def reap_stale(tmp: Path | None = None) -> int:
    """Reap sandbox and job folders in ``tmp`` whose host process is gone; returns how many.

    Covers a runner that was SIGKILLed: the next one to start cleans up after it.
    """
    base = Path(tmp or tempfile.gettempdir())
    count = 0
    for folder in [*base.glob(f"{SANDBOX_PREFIX}*"), *base.glob(f"{JOB_PREFIX}*")]:
        if not folder.is_dir() or _owner_alive(folder):
            continue
        if folder.name.startswith(JOB_PREFIX):
            reap_tree(folder)
        else:
            reap(folder)
        count += 1
    return count


def _link_tree(src: Path, dst: Path) -> None:
    """A read-only copy of the bundle the fallback's uid can reach (hard links where
    possible: the job's own extraction folder is private to root)."""

    def link_or_copy(a: str, b: str) -> None:
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    shutil.copytree(src, dst, symlinks=True, copy_function=link_or_copy)
    for folder, _dirs, files in os.walk(dst):
        os.chmod(folder, 0o755)
        for name in files:
            path = os.path.join(folder, name)
            if not os.path.islink(path):
                os.chmod(path, 0o644)


def _mount_tmpfs(path: Path, size_mb: int, owner: tuple[int, int] | None) -> bool:
    """A size-capped tmpfs on ``path`` (root only); False where it cannot be mounted."""
    options = f"size={size_mb * _MIB},nr_inodes=4096,mode=0700"
    if owner is not None:
        options += f",uid={owner[0]},gid={owner[1]}"
    flags = 0x2 | 0x4 | 0x8  # MS_NOSUID | MS_NODEV | MS_NOEXEC
    ret = _libc().mount(b"slipstream", str(path).encode(), b"tmpfs", flags, options.encode())
    return ret == 0


class SandboxProcess:
    """One sandboxed worker process tree; :meth:`kill` ends all of it.

    Each sandbox has a folder ``<tmp>/slipstream-sbx-<host pid>-<id>`` (root-owned, 0711)
    holding its process group id, and in the fallback the bundle's read-only link tree
    (``bundle/``), the package links (``.app/``) and its one writable folder (``work/``,
    a ``tmpfs_mb`` tmpfs where it can be mounted). :func:`reap` removes all of it from
    the folder alone.

    Args:
        worker_args: arguments for ``submissions.worker`` (the protocol's file descriptors…).
        bundle_root: the extracted bundle, made visible read-only.
        limits: resource limits.
        pass_fds: the descriptors the worker inherits (the protocol pipes).
        output_fd: where the worker's stdout and stderr go (a pipe the host drains).
        mode: ``"bwrap"`` or ``"seccomp"`` (default: :func:`sandbox_mode`).
        cpu: the CPU its processes are bound to from the start (None: the kernel places
            them; :mod:`submissions.scheduling`).

    Attributes:
        folder: the sandbox's folder (None once removed).
        identity: the ``(uid, gid)`` of the fallback (None in bwrap mode or as non-root).
        quota: how the writable folder is capped: ``"tmpfs"`` or ``"fsize"``.

    Raises:
        SandboxError: the process could not be started.
    """

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
        self.mode = mode or sandbox_mode()
        self.id = uuid.uuid4().hex[:12]
        self.limits = limits
        self.identity = fallback_identity() if self.mode == "seccomp" else None
        self.quota = "tmpfs" if self.mode == "bwrap" else "fsize"
        self.folder: Path | None = Path(tempfile.gettempdir()) / (
            f"{SANDBOX_PREFIX}{os.getpid()}-{self.id}"
        )
        self.folder.mkdir(mode=0o711)
        self.cgroups = CgroupCaps.create(self.id, limits)
        filter_fd = later = -1  # bwrap reads its filter at its start; the fallback's
        # worker reads a pipe to its end, written once its pid is known (seccomp_filter)
        try:
            if self.mode == "bwrap":
                filter_fd = os.memfd_create("slipstream-seccomp", os.MFD_CLOEXEC)
                os.write(filter_fd, seccomp_filter(self.mode))
                os.lseek(filter_fd, 0, os.SEEK_SET)
            else:
                filter_fd, later = os.pipe()
            args = [*worker_args, "--sandbox-id", self.id, "--mode", self.mode]
            if self.mode == "bwrap":
                cmd = bwrap_command(args, bundle_root, limits, filter_fd)
                env: dict[str, str] = {}
                cwd = "/"
            else:
                work = self._prepare_fallback(bundle_root)
                cmd = self._fallback_command(args, filter_fd)
                env = self._fallback_env(work)
                cwd = str(work)
            self.proc = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=output_fd,
                stderr=output_fd,
                pass_fds=(*pass_fds, filter_fd),
                start_new_session=True,
                env=env,
                cwd=cwd,
                preexec_fn=_preexec(limits, self.cgroups.procs_files, self.identity, cpu),  # noqa: PLW1509 - os calls only
            )
            uid = self.identity.uid if self.identity is not None else os.geteuid()
            (self.folder / "pgid").write_text(f"{self.proc.pid} {uid}\n")
            os.close(filter_fd)
            filter_fd = -1
            if later >= 0:  # the worker waits for it before it reads anything of the bundle
                with contextlib.suppress(BrokenPipeError):  # it died: seen as a crash
                    os.write(later, seccomp_filter(self.mode, pid=self.proc.pid))
        except (OSError, subprocess.SubprocessError, shutil.Error) as err:
            self._cleanup()
            raise SandboxError(f"could not start the sandbox ({self.mode}): {err}") from err
        except BaseException:
            self._cleanup()
            raise
        finally:
            for fd in (filter_fd, later):
                if fd >= 0:
                    os.close(fd)

    def _prepare_fallback(self, root: Path) -> Path:
        """The fallback's folders: ``bundle/`` (read-only), ``.app/``, ``work/`` (writable)."""
        assert self.folder is not None
        _link_tree(root, self.folder / "bundle")
        app = self.folder / ".app"  # the packages, as links: Python lists this, not the project
        app.mkdir(mode=0o755)
        for name, path in package_dirs().items():
            (app / name).symlink_to(path)
        work = self.folder / "work"
        work.mkdir(mode=0o700)
        owner = None
        if self.identity is not None:
            owner = (self.identity.files_uid, self.identity.gid)
        if _mount_tmpfs(work, self.limits.tmpfs_mb, owner):
            self.quota = "tmpfs"
        elif owner is not None:
            os.chown(work, *owner)
        return work

    def _fallback_command(self, args: list[str], filter_fd: int) -> list[str]:
        assert self.folder is not None
        root, work, app = self.folder / "bundle", self.folder / "work", self.folder / ".app"
        read, write = fallback_paths(root, work, app)
        cmd = [sys.executable, "-B", "-m", "submissions.worker", "--root", str(root), *args]
        cmd += ["--seccomp-fd", str(filter_fd)]
        if self.identity is not None and self.identity.fs_root:
            cmd += ["--drop-uid", str(self.identity.uid)]
        for path in read:
            cmd += ["--read", path]
        for path in write:
            cmd += ["--write", path]
        return cmd

    def _fallback_env(self, work: Path) -> dict[str, str]:
        assert self.folder is not None
        env = {"PATH": "/usr/bin:/bin", "HOME": str(work), "TMPDIR": str(work)}
        env |= {"PYTHONPATH": str(self.folder / ".app"), "PYTHONNOUSERSITE": "1"}
        return env | {"PYTHONDONTWRITEBYTECODE": "1", "LANG": "C.UTF-8"} | THREAD_ENV

    @property
    def pid(self) -> int:
        """The outermost process (bwrap, or the worker itself in seccomp mode)."""
        return self.proc.pid

    def poll(self) -> int | None:
        """The exit status, or None while it runs."""
        return self.proc.poll()

    def wait(self, timeout: float) -> int | None:
        """Wait up to ``timeout`` s for it to exit; its status, or None."""
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self) -> None:
        """SIGKILL the whole tree now and return at once (the group, and one pass over its
        cgroups); :meth:`kill` later waits for it and removes what is left. For a race that
        retires a car while others wait on their deadlines."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.cgroups.kill_all(patience_s=0.0)

    def kill(self) -> None:
        """SIGKILL the whole tree (group, cgroups; bwrap takes its pid namespace down too),
        then remove its cgroups and folder (unmounting its tmpfs)."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.cgroups.kill_all()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(10)
        self._cleanup()

    def _cleanup(self) -> None:
        self.cgroups.kill_all()
        self.cgroups.remove()
        if self.folder is not None:
            _unmount(self.folder / "work")
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None
