"""Hostile submissions: each is contained, its car gets the right status, the race goes on.

Every case races a python-format bundle (car 0, sandboxed) against an in-process pursuit
car (car 1) for one lap of the oval. The hostile policy drives like pursuit and attacks on
its third step. "Contained" means: the host is untouched (no connection, no file written,
no secret read, no process left), the race completes, the offender's status is the one
expected, and the other car finishes.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from submissions.bundle import Bundle
from submissions.remote import SandboxedPolicy
from submissions.sandbox import SandboxLimits

from .conftest import FAST, MakeBundle, race_against_pursuit, sandbox_processes

pytestmark = pytest.mark.slow

# name: (policy body, expected (status, dnf_reason), limits)
SIMPLE_CASES: dict[str, tuple[str, tuple[str, str | None], SandboxLimits]] = {
    "crash": (
        """
        class Policy(Driver):
            def attack(self, obs):
                raise ValueError("boom")
        """,
        ("dnf", "error"),
        FAST,
    ),
    "hard-exit": (
        """
        class Policy(Driver):
            def attack(self, obs):
                os._exit(3)
        """,
        ("dnf", "error"),
        FAST,
    ),
    "crash-on-import": ("this is not python(", ("dnf", "error"), FAST),
    "no-such-class": ("class Agent(Driver): pass", ("dnf", "error"), FAST),
    "sleep-past-deadline": (
        """
        class Policy(Driver):
            def attack(self, obs):
                time.sleep(30)
        """,
        ("dnf", "timeout"),
        replace(FAST, step_deadline_s=0.2, overage_s=0.3),
    ),
    "spin-cpu": (
        """
        class Policy(Driver):
            def attack(self, obs):
                while True:
                    pass
        """,
        ("dnf", "timeout"),
        replace(FAST, step_deadline_s=0.2, overage_s=0.3),
    ),
    "slow-start": (
        """
        class Policy(Driver):
            def __init__(self, env_spec):
                time.sleep(30)
        """,
        ("dnf", "timeout"),
        replace(FAST, startup_s=3.0),
    ),
    "allocate-until-oom": (
        """
        class Policy(Driver):
            def attack(self, obs):
                hoard = []
                while True:
                    hoard.append(b"x" * (64 << 20))
        """,
        ("dnf", "error"),
        replace(FAST, memory_mb=1024),
    ),
    "garbage-text": (
        """
        class Policy(Driver):
            def attack(self, obs):
                return "full throttle"
        """,
        ("dnf", "invalid"),
        FAST,
    ),
    "nan": (
        """
        class Policy(Driver):
            def attack(self, obs):
                return np.array([np.nan, 1.0])
        """,
        ("dnf", "invalid"),
        FAST,
    ),
    "wrong-shape": (
        """
        class Policy(Driver):
            def attack(self, obs):
                return np.zeros(3)
        """,
        ("dnf", "invalid"),
        FAST,
    ),
    "out-of-range": (
        """
        class Policy(Driver):
            def attack(self, obs):
                return np.array([5.0, 1.0])
        """,
        ("dnf", "invalid"),
        FAST,
    ),
    "forged-frame": (  # writes a header announcing a 1 TiB frame to the protocol pipe
        """
        import struct
        class Policy(Driver):
            def attack(self, obs):
                fd = int(sys.argv[sys.argv.index("--out") + 1])
                os.write(fd, struct.pack("<2sBBB3xQ", b"SL", 5, 1, 1, 1 << 40))
                time.sleep(30)
        """,
        ("dnf", "error"),
        FAST,
    ),
    "print-megabytes": (
        """
        class Policy(Driver):
            def attack(self, obs):
                line = "spam " * 200
                for _ in range(8000):  # about 8 MB
                    print(line)
                sys.stdout.flush()
        """,
        ("finished", None),
        FAST,
    ),
}


def check_contained(policy: SandboxedPolicy, expected: tuple[str, str | None]) -> None:
    """Race ``policy`` against pursuit; check statuses and that nothing of it survives."""
    result = race_against_pursuit(policy)
    car, other = result.cars
    assert (car.status, car.dnf_reason) == expected, policy.output[-2000:]
    assert other.status == "finished"
    assert policy.sandbox_id is not None
    assert sandbox_processes(policy.sandbox_id) == []


@pytest.mark.parametrize("case", sorted(SIMPLE_CASES))
def test_hostile_policy_is_contained(case: str, make_python_bundle: MakeBundle) -> None:
    body, expected, limits = SIMPLE_CASES[case]
    policy = SandboxedPolicy(make_python_bundle(body, driver=case != "crash-on-import"), limits)
    check_contained(policy, expected)
    if case == "print-megabytes":
        assert policy.stats["output_bytes"] > 7_000_000
        assert len(policy.output) < 24_000  # only the head and the tail are kept


@pytest.fixture
def listener() -> Iterator[tuple[int, list[str]]]:
    """A TCP listener on the host's loopback: (port, peers that connected)."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(0.2)
    peers: list[str] = []
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, addr = server.accept()
            except OSError:
                continue
            peers.append(str(addr))
            conn.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1], peers
    finally:
        stop.set()
        thread.join()
        server.close()


def test_network_is_unreachable(
    mode: str, listener: tuple[int, list[str]], make_python_bundle: MakeBundle
) -> None:
    port, peers = listener
    body = f"""
    class Policy(Driver):
        def attack(self, obs):
            failures = []
            for family, addr in ((socket.AF_INET, ("127.0.0.1", {port})),
                                 (socket.AF_INET, ("1.1.1.1", 80)),
                                 (socket.AF_INET6, ("::1", {port}))):
                try:
                    s = socket.socket(family, socket.SOCK_STREAM)
                    s.settimeout(1)
                    s.connect(addr)
                    s.sendall(b"LEAK")
                    return None  # connected: keep driving, and the test fails
                except OSError as err:
                    failures.append(str(err))
            try:
                socket.socket(socket.AF_INET, socket.SOCK_DGRAM).sendto(b"x", ("127.0.0.1", {port}))
                return None
            except OSError as err:
                failures.append(str(err))
            raise RuntimeError("no network: " + "; ".join(failures))
    """
    policy = SandboxedPolicy(make_python_bundle(body), FAST)
    check_contained(policy, ("dnf", "error"))
    assert policy.mode == mode
    assert peers == []
    assert "no network" in policy.output


def test_pickle_payload_in_sb3_zip_cannot_touch_the_host(
    mode: str, tmp_path: Path, sb3_bundle: Callable[[Path], Bundle]
) -> None:
    sentinel = tmp_path / "host" / "SENTINEL"
    sentinel.parent.mkdir()
    policy = SandboxedPolicy(sb3_bundle(sentinel), FAST)
    check_contained(policy, ("dnf", "error"))
    assert policy.mode == mode
    assert "PAYLOAD-RAN" in policy.output  # it ran, inside, and was contained
    assert not sentinel.exists()
    assert list(sentinel.parent.iterdir()) == []


def test_host_files_are_invisible(
    mode: str, tmp_path: Path, home_secret: tuple[Path, str], make_python_bundle: MakeBundle
) -> None:
    key, secret = home_secret
    database = tmp_path / "leaderboard.db"
    database.write_text("SQLite format 3 FAKE-DATABASE\n")
    targets = [
        str(key),
        str(database),
        "/etc/shadow",
        "/proc/1/environ",
        str(Path.cwd() / "pyproject.toml"),
    ]
    body = f"""
    class Policy(Driver):
        def attack(self, obs):
            for path in {targets!r}:
                try:
                    with open(path) as fh:
                        content = fh.read(200)
                except OSError:
                    continue
                if content:  # an empty file (the sandbox's own init's environ) leaks nothing
                    raise RuntimeError("LEAKED " + path + ": " + content)
            for folder in ("/root", {str(tmp_path)!r}, {str(key.parent)!r}):
                try:
                    names = os.listdir(folder)
                except OSError:
                    continue
                if {key.name!r} in names or "leaderboard.db" in names:
                    raise RuntimeError("LISTED " + folder + ": " + ", ".join(names))
    """
    policy = SandboxedPolicy(make_python_bundle(body), FAST)
    check_contained(policy, ("finished", None))
    assert secret not in policy.output and "LEAKED" not in policy.output
    assert key.read_text().startswith("FAKE-SECRET")  # untouched


def test_writes_stay_in_the_private_tmp(
    mode: str, tmp_path: Path, make_python_bundle: MakeBundle
) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    targets = [str(outside / "pwned"), "/usr/pwned", str(Path.cwd() / "pwned"), "/pwned"]
    body = f"""
    import tempfile
    class Policy(Driver):
        def attack(self, obs):
            bundle_dir = os.path.dirname(os.path.abspath(__file__))
            private = os.path.realpath(tempfile.gettempdir()) + os.sep
            for path in {targets!r} + [os.path.join(bundle_dir, "pwned")]:
                try:
                    with open(path, "w") as fh:
                        fh.write("pwned")
                except OSError:
                    continue
                # A checkout under /tmp lies, inside bwrap, under the private tmpfs: a
                # write there is contained (the host-side asserts below check the host).
                if not os.path.realpath(path).startswith(private):
                    raise RuntimeError("WROTE " + path)
            with open(os.path.join(tempfile.gettempdir(), "scratch"), "w") as fh:
                fh.write("private scratch space works")
    """
    bundle = make_python_bundle(body)
    policy = SandboxedPolicy(bundle, FAST)
    check_contained(policy, ("finished", None))
    assert list(outside.iterdir()) == []
    assert not (bundle.root / "pwned").exists()
    assert not (Path.cwd() / "pwned").exists()


def test_fork_bomb_is_capped_and_reaped(mode: str, make_python_bundle: MakeBundle) -> None:
    body = """
    class Policy(Driver):
        def attack(self, obs):
            forks = 0
            while forks < 500:
                try:
                    pid = os.fork()
                except OSError:
                    break
                if pid == 0:
                    time.sleep(600)
                    os._exit(0)
                forks += 1
            print("forked", forks, flush=True)
            if forks >= 500:
                raise RuntimeError("unbounded fork")
    """
    policy = SandboxedPolicy(make_python_bundle(body), replace(FAST, max_processes=16))
    check_contained(policy, ("finished", None))
    assert "forked" in policy.output
