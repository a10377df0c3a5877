"""The sandbox a submitted policy runs in: bubblewrap, rlimits, cgroups, seccomp, Landlock.

Every uploaded policy runs in its own process tree, started by :class:`SandboxProcess`:

=================  ==========================================  ===============================
concern            ``"bwrap"`` mode (the default)              ``"seccomp"`` mode (fallback)
=================  ==========================================  ===============================
filesystem         empty read-only root; binds of ``/usr``,    the host's, narrowed by Landlock
                   the Python install, the venv, the           (read: the same paths; write:
                   project's packages (``/app``) and the       only a private temp folder)
                   bundle (``/submission``); a size-capped
                   tmpfs on ``/tmp``
network            new network namespace (no interfaces        seccomp: ``socket()`` other than
                   but a down ``lo``) + seccomp                ``AF_UNIX`` fails (EACCES),
                                                               ``io_uring`` refused; Landlock
                                                               denies TCP bind/connect
processes          pid namespace (sees only itself), cgroup    cgroup ``pids.max`` (root) or
                   ``pids.max`` (root) or ``RLIMIT_NPROC``     ``RLIMIT_NPROC``; ``setsid`` and
                                                               ``setpgid`` refused so the whole
                                                               tree stays in one process group
identity           uid/gid 65534 in a user namespace, no       the caller's uid; Landlock
                   capabilities, new session, cleared env      scopes signals to the sandbox
memory, CPU, …     ``RLIMIT_AS``/cgroup memory, CPU seconds, open files, file size, no core dumps
killed             the process group, every pid in the cgroup, and (bwrap) the pid namespace
=================  ==========================================  ===============================

Both modes also refuse ``ptrace``, ``mount``, ``unshare``/``setns``, namespace-creating
``clone`` flags, ``bpf``, ``perf_event_open``, kernel keyrings, ``userfaultfd`` and module
loading. :func:`sandbox_mode` picks the mode: ``bwrap`` when user namespaces work, else the
weaker ``seccomp`` mode, with a logged warning (never silently); ``SANDBOX=seccomp`` forces
the fallback and ``SANDBOX=bwrap`` insists on bubblewrap.

The cgroup caps (v1 ``pids`` and ``memory`` hierarchies under ``/sys/fs/cgroup``) are used
where the folder is writable (root here); ``RLIMIT_NPROC`` is not enforced for root, so
without them the process cap rests on the pid namespace (bwrap) and the deadlines.
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
import socket
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
SANDBOX_UID = 65534  # "nobody" inside the user namespace
CGROUP_ROOT = Path("/sys/fs/cgroup")
PACKAGES = ("tracks", "arena", "agents", "submissions")  # what a worker may import of ours
APP = "/app"  # where the packages appear inside bwrap
MODES = ("bwrap", "seccomp")
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


def sandbox_mode() -> str:
    """``"bwrap"`` where namespaces work, else ``"seccomp"`` (logged as a warning).

    ``SANDBOX=seccomp`` forces the fallback (for tests); ``SANDBOX=bwrap`` requires bwrap.

    Raises:
        SandboxError: ``SANDBOX`` names no mode, or requires bwrap where it does not work.
    """
    wanted = os.environ.get("SANDBOX", "auto").strip().lower() or "auto"
    if wanted not in (*MODES, "auto"):
        raise SandboxError(f"SANDBOX={wanted!r}: expected bwrap, seccomp or auto")
    if wanted == "seccomp":
        return "seccomp"
    if bwrap_works():
        return "bwrap"
    if wanted == "bwrap":
        raise SandboxError(f"SANDBOX=bwrap but {BWRAP} cannot create namespaces here")
    _warn_fallback()
    return "seccomp"


@functools.cache
def _warn_fallback() -> None:
    log.warning(
        "bubblewrap is unavailable or user namespaces are disabled: submitted policies run in "
        "the weaker seccomp fallback (rlimits + seccomp + Landlock, no filesystem namespace)"
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


@functools.cache
def seccomp_filter(mode: str) -> bytes:
    """The seccomp BPF program for ``mode`` (built with libseccomp on the trusted side).

    Raises:
        SandboxError: libseccomp (``pyseccomp``) is not available.
    """
    try:
        import pyseccomp as sc  # noqa: PLC0415 - only the trusted side builds the filter
    except (ImportError, OSError) as err:  # OSError: the libseccomp shared library is missing
        raise SandboxError(f"the sandbox needs libseccomp (pyseccomp): {err}") from err
    filt = sc.SyscallFilter(sc.ALLOW)
    filt.add_rule(sc.ERRNO(errno.EACCES), "socket", sc.Arg(0, sc.NE, socket.AF_UNIX))
    for name in _DENIED:
        filt.add_rule(sc.ERRNO(errno.EPERM), name)
    for flag in _CLONE_NEW:
        filt.add_rule(sc.ERRNO(errno.EPERM), "clone", sc.Arg(0, sc.MASKED_EQ, flag, flag))
    filt.add_rule(sc.ERRNO(errno.ENOSYS), "clone3")  # flags behind a pointer: make libc use clone
    if mode == "seccomp":  # no pid namespace: keep the tree in one process group
        filt.add_rule(sc.ERRNO(errno.EPERM), "setsid")
        filt.add_rule(sc.ERRNO(errno.EPERM), "setpgid")
    with tempfile.TemporaryFile() as fh:
        filt.export_bpf(fh)
        fh.seek(0)
        return fh.read()


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

    if len(program) % 8:
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
    """Per-sandbox cgroup v1 folders (``pids``, ``memory``) where they can be made.

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
        """SIGKILL every process in the cgroups until none is left (a fork bomb included)."""
        end = time.monotonic() + patience_s
        while (pids := self.pids()) and time.monotonic() < end:
            for pid in pids:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(pid, signal.SIGKILL)
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


def fallback_paths(bundle_root: Path, tmp: Path) -> tuple[list[str], list[str]]:
    """What the seccomp-mode worker may read and write (Landlock rules): ``(read, write)``."""
    read = ["/usr", "/lib", "/lib64", "/bin", "/sys/devices/system/cpu", *python_paths()]
    read += [*package_dirs().values(), str(bundle_root), "/dev/urandom"]
    return read, [str(tmp), "/dev/null"]


def _preexec(limits: SandboxLimits, procs_files: list[str]) -> Callable[[], None]:
    """Runs in the child between fork and exec: join the cgroups, set the rlimits."""
    rlimits = [
        (resource.RLIMIT_AS, limits.memory_mb * _MIB),
        (resource.RLIMIT_NOFILE, limits.open_files),
        (resource.RLIMIT_FSIZE, limits.file_size_mb * _MIB),
        (resource.RLIMIT_NPROC, limits.max_processes),  # not enforced for root: cgroup does it
        (resource.RLIMIT_CORE, 0),
    ]

    def run() -> None:
        for path in procs_files:
            fd = os.open(path, os.O_WRONLY)
            try:
                os.write(fd, str(os.getpid()).encode())
            finally:
                os.close(fd)
        for which, value in rlimits:
            resource.setrlimit(which, (value, value))
        resource.setrlimit(resource.RLIMIT_CPU, (limits.cpu_seconds, limits.cpu_seconds + 5))

    return run


# ---- the process -------------------------------------------------------------------------


class SandboxProcess:
    """One sandboxed worker process tree; :meth:`kill` ends all of it.

    Args:
        worker_args: arguments for ``submissions.worker`` (the protocol's file descriptors…).
        bundle_root: the extracted bundle, made visible read-only.
        limits: resource limits.
        pass_fds: the descriptors the worker inherits (the protocol pipes).
        output_fd: where the worker's stdout and stderr go (a pipe the host drains).
        mode: ``"bwrap"`` or ``"seccomp"`` (default: :func:`sandbox_mode`).

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
    ) -> None:
        self.mode = mode or sandbox_mode()
        self.id = uuid.uuid4().hex[:12]
        self.limits = limits
        self.cgroups = CgroupCaps.create(self.id, limits)
        self.tmp: Path | None = None
        program = seccomp_filter(self.mode)
        filter_fd = os.memfd_create("slipstream-seccomp", os.MFD_CLOEXEC)
        try:
            os.write(filter_fd, program)
            os.lseek(filter_fd, 0, os.SEEK_SET)
            args = [*worker_args, "--sandbox-id", self.id, "--mode", self.mode]
            if self.mode == "bwrap":
                cmd = bwrap_command(args, bundle_root, limits, filter_fd)
                env: dict[str, str] = {}
                cwd = "/"
            else:
                self.tmp = Path(tempfile.mkdtemp(prefix=f"slipstream-sbx-{self.id}-"))
                cmd = self._fallback_command(args, bundle_root, self.tmp, filter_fd)
                env = self._fallback_env(self.tmp)
                cwd = str(self.tmp)
            self.proc = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=output_fd,
                stderr=output_fd,
                pass_fds=(*pass_fds, filter_fd),
                start_new_session=True,
                env=env,
                cwd=cwd,
                preexec_fn=_preexec(limits, self.cgroups.procs_files),  # noqa: PLW1509 - os calls only
            )
        except (OSError, subprocess.SubprocessError) as err:
            self._cleanup()
            raise SandboxError(f"could not start the sandbox ({self.mode}): {err}") from err
        finally:
            os.close(filter_fd)

    def _fallback_command(
        self, args: list[str], root: Path, tmp: Path, filter_fd: int
    ) -> list[str]:
        app = tmp / ".app"  # the packages, as links: Python lists this folder, not the project
        app.mkdir()
        for name, path in package_dirs().items():
            (app / name).symlink_to(path)
        read, write = fallback_paths(root, tmp)
        cmd = [sys.executable, "-B", "-m", "submissions.worker", "--root", str(root), *args]
        cmd += ["--seccomp-fd", str(filter_fd)]
        for path in read:
            cmd += ["--read", path]
        for path in write:
            cmd += ["--write", path]
        return cmd

    @staticmethod
    def _fallback_env(tmp: Path) -> dict[str, str]:
        env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp), "TMPDIR": str(tmp)}
        env |= {"PYTHONPATH": str(tmp / ".app"), "PYTHONNOUSERSITE": "1"}
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

    def kill(self) -> None:
        """SIGKILL the whole tree (group, cgroups; bwrap takes its pid namespace down too)."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.cgroups.kill_all()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(10)
        self._cleanup()

    def _cleanup(self) -> None:
        self.cgroups.remove()
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.tmp = None
