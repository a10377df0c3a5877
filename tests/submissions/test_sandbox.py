"""The sandbox from the inside (a probe policy reports what it sees), its limits, deadlines,
clean-up, and how the race drives sandboxed and two-phase policies."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.baselines import make_baseline
from agents.loading import DEFAULT_LAYOUT
from arena.env import RacingEnv
from arena.race import action_problem, run_race
from submissions import sandbox
from submissions.errors import SandboxError
from submissions.remote import (
    PolicyCrash,
    PolicyTimeout,
    SandboxedPolicy,
    action_space_of,
    env_spec_of,
    make_env_spec,
)
from submissions.sandbox import CGROUP_ROOT, SandboxLimits, sandbox_mode

from .conftest import FAST, MakeBundle, sandbox_processes

PROBE = """
import ctypes, json, os, resource, socket, sys

def _try(fn):
    try:
        return fn()
    except OSError as err:
        return "OSError:" + (err.strerror or type(err).__name__)

def _libc_call(name, *args):
    libc = ctypes.CDLL(None, use_errno=True)
    ret = getattr(libc, name)(*args)
    return "ok" if ret >= 0 else "OSError:" + os.strerror(ctypes.get_errno())

def _fork():
    pid = os.fork()
    if pid == 0:
        os._exit(0)
    os.waitpid(pid, 0)
    return "ok"

def _write(path, mb):
    with open(path, "wb") as fh:
        fh.write(b"x" * (mb << 20))
    os.remove(path)
    return "ok"

class Policy:
    def __init__(self, env_spec):
        lines = open("/proc/self/status").read().splitlines()
        status = dict(line.split(":\\t", 1) for line in lines if ":\\t" in line)
        facts = {
            "uid": os.getuid(),
            "env": sorted(os.environ),
            "pids": _try(lambda: sorted(int(p) for p in os.listdir("/proc") if p.isdigit())),
            "seccomp": status.get("Seccomp", "").strip(),
            "no_new_privs": status.get("NoNewPrivs", "").strip(),
            "cap_eff": status.get("CapEff", "").strip(),
            "cap_bnd": status.get("CapBnd", "").strip(),
            "groups": os.getgroups(),
            "proc_net": _try(lambda: open("/proc/self/net/unix").read(100) or "ok"),
            "socketpair": _try(lambda: socket.socketpair() and "ok"),
            "memfd_create": _try(lambda: os.close(os.memfd_create("probe")) or "ok"),
            "shmget": _libc_call("shmget", 0, 4096, 0o1666),
            "msgget": _libc_call("msgget", 0, 0o1666),
            "mq_open": _libc_call("mq_open", b"/slipstream-probe", 0o100 | 2, 0o666, None),
            "sethostname": _try(lambda: socket.sethostname("pwned") or "ok"),
            "fork": _try(_fork),
            "nofile": resource.getrlimit(resource.RLIMIT_NOFILE)[0],
            "as_mb": resource.getrlimit(resource.RLIMIT_AS)[0] >> 20,
            "fsize_mb": resource.getrlimit(resource.RLIMIT_FSIZE)[0] >> 20,
            "cpu": resource.getrlimit(resource.RLIMIT_CPU)[0],
            "socket_inet": _try(lambda: socket.socket(socket.AF_INET).close() or "ok"),
            "socket_unix": _try(lambda: socket.socket(socket.AF_UNIX).close() or "ok"),
            "tmp_small": _try(lambda: _write(os.path.join(os.environ["TMPDIR"], "a"), 1)),
            "tmp_too_big": _try(lambda: _write(os.path.join(os.environ["TMPDIR"], "b"), 3)),
            "spec": env_spec,
        }
        print("PROBE " + json.dumps(facts), flush=True)

    def act(self, obs):
        return [0.0, 0.5]
"""


def probe(
    make_python_bundle: MakeBundle, limits: SandboxLimits
) -> tuple[SandboxedPolicy, dict[str, Any]]:
    policy = SandboxedPolicy(make_python_bundle(PROBE, name="probe", driver=False), limits)
    policy.reset(0)
    return policy, probe_facts(policy)


def probe_facts(policy: SandboxedPolicy) -> dict[str, Any]:
    """The facts the probe printed. It printed them before it said READY, but its output is
    drained by a thread of its own, which a loaded machine may not have run yet: give it a
    few seconds."""
    for _ in range(500):
        lines = [x for x in policy.output.splitlines() if x.startswith("PROBE ")]
        if lines:
            facts: dict[str, Any] = json.loads(lines[0][len("PROBE ") :])
            return facts
        time.sleep(0.02)
    raise AssertionError(f"no PROBE line in {policy.output[-2000:]!r}")


def test_the_probe_sees_a_confined_world(mode: str, make_python_bundle: MakeBundle) -> None:
    limits = replace(FAST, open_files=64, file_size_mb=2, memory_mb=1536, cpu_seconds=77)
    policy, facts = probe(make_python_bundle, limits)
    try:
        assert policy.mode == mode
        assert facts["seccomp"] == "2" and facts["no_new_privs"] == "1"
        # no socket of any family (pipes need none), no SysV IPC, no mqueue, no hostname
        keys = ("socket_inet", "socket_unix", "socketpair", "shmget", "msgget", "mq_open")
        for key in (*keys, "memfd_create"):  # its one region is the host's, inherited
            assert facts[key].startswith("OSError"), key
        assert facts["sethostname"].startswith("OSError")
        # /proc/self/net/unix: none in the fallback, its own empty namespace's in bwrap
        assert facts["proc_net"].startswith("OSError") or facts["proc_net"].count("\n") == 1
        assert facts["uid"] == 65534 and facts["groups"] in ([], [65534])
        assert facts["cap_eff"] == "0000000000000000"
        assert (facts["nofile"], facts["as_mb"], facts["fsize_mb"], facts["cpu"]) == (
            64,
            1536,
            2,
            77,
        )
        assert facts["tmp_small"] == "ok"
        assert facts["tmp_too_big"].startswith("OSError")  # RLIMIT_FSIZE
        assert set(facts["env"]) <= {
            "PATH", "HOME", "TMPDIR", "PYTHONPATH", "PYTHONNOUSERSITE", "PYTHONDONTWRITEBYTECODE",
            "LANG", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "LC_CTYPE", "PWD",
        }  # fmt: skip
        assert facts["spec"] == make_env_spec()
        if mode == "bwrap":
            assert len(facts["pids"]) <= 3  # bwrap's init, the worker (and nothing of the host)
            assert facts["fork"] == "ok"  # the pid namespace contains its children
        else:
            assert str(facts["pids"]).startswith("OSError")  # Landlock hides /proc
            assert facts["proc_net"].startswith("OSError")
            assert facts["groups"] == []
            assert facts["cap_bnd"] == "0000000000000000"  # the bounding set is empty too
            assert facts["fork"].startswith("OSError")  # one process: nothing outlives it
        assert policy.sandbox_id is not None
        assert sandbox_processes(policy.sandbox_id)
    finally:
        policy.close()
    assert sandbox_processes(policy.sandbox_id) == []
    assert not list((CGROUP_ROOT / "pids" / "slipstream").glob(f"{policy.sandbox_id}*"))


def test_the_private_tmpfs_is_size_capped(mode: str, make_python_bundle: MakeBundle) -> None:
    # Many small files, each under RLIMIT_FSIZE: only the folder's quota stops them.
    body = (
        PROBE.replace('"tmp_small"', '"tmp_fill"')
        .replace(
            '_write(os.path.join(os.environ["TMPDIR"], "a"), 1)',
            '[_keep(os.path.join(os.environ["TMPDIR"], f"f{i}"), 1) for i in range(8)]',
        )
        .replace(
            "def _write(",
            "def _keep(path, mb):\n    open(path, 'wb').write(b'x' * (mb << 20))\n\ndef _write(",
        )
    )
    limits = replace(FAST, tmpfs_mb=4)
    policy = SandboxedPolicy(make_python_bundle(body, driver=False), limits)
    try:
        policy.reset(0)
        facts = probe_facts(policy)
    finally:
        policy.close()
    assert str(facts["tmp_fill"]).startswith("OSError")  # ENOSPC: 8 x 1 MiB in a 4 MiB tmpfs


def test_limits_are_checked() -> None:
    with pytest.raises(SandboxError, match="1024"):
        SandboxLimits(memory_mb=512)
    with pytest.raises(SandboxError, match="step_deadline_s"):
        SandboxLimits(step_deadline_s=0)
    with pytest.raises(SandboxError, match="overage_s"):
        SandboxLimits(overage_s=-1)


def test_sandbox_mode_honours_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SANDBOX", "seccomp")
    monkeypatch.setenv(sandbox.WEAK_ENV, "1")
    assert sandbox_mode() == "seccomp"
    monkeypatch.setenv("SANDBOX", "chroot")
    with pytest.raises(SandboxError, match="SANDBOX"):
        sandbox_mode()


@pytest.mark.parametrize(
    ("forced", "bwrap_ok", "allowed", "expected"),
    [
        ("", True, "", "bwrap"),
        ("", True, "1", "bwrap"),  # allowing the fallback never prefers it
        ("", False, "1", "seccomp"),
        ("", False, "", SandboxError),  # fail closed: no namespaces, no permission
        ("", False, "yes", SandboxError),  # only "1" allows it
        ("seccomp", True, "", SandboxError),  # SANDBOX=seccomp still needs the flag
        ("seccomp", True, "1", "seccomp"),
        ("bwrap", False, "1", SandboxError),
        ("bwrap", True, "", "bwrap"),
    ],
)
def test_the_sandbox_fails_closed(
    monkeypatch: pytest.MonkeyPatch,
    forced: str,
    bwrap_ok: bool,
    allowed: str,
    expected: str | type[Exception],
) -> None:
    monkeypatch.setenv("SANDBOX", forced)
    monkeypatch.setenv(sandbox.WEAK_ENV, allowed)
    monkeypatch.setattr(sandbox, "bwrap_works", lambda: bwrap_ok)
    if isinstance(expected, str):
        assert sandbox_mode() == expected
    else:
        with pytest.raises(expected, match=r"allow-weak-sandbox|cannot create namespaces"):
            sandbox_mode()


def test_results_say_when_the_fallback_ran() -> None:
    assert sandbox.mode_label("seccomp") == "seccomp-weak"
    assert sandbox.mode_label("bwrap") == "bwrap"
    assert len(sandbox.mode_label("seccomp")) <= 16  # the races.sandbox column


def test_allowing_the_fallback_is_logged_and_inherited(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.delenv(sandbox.WEAK_ENV, raising=False)
    assert not sandbox.weak_sandbox_allowed()
    with caplog.at_level(logging.WARNING, logger="submissions.sandbox"):
        sandbox.allow_weak_sandbox()
    assert sandbox.weak_sandbox_allowed() and os.environ[sandbox.WEAK_ENV] == "1"
    assert "--allow-weak-sandbox" in caplog.text


def test_without_namespaces_the_fallback_is_loud(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.delenv("SANDBOX", raising=False)
    monkeypatch.setenv(sandbox.WEAK_ENV, "1")
    monkeypatch.setattr(sandbox, "bwrap_works", lambda: False)
    sandbox._warn_fallback.cache_clear()
    with caplog.at_level(logging.WARNING, logger="submissions.sandbox"):
        assert sandbox_mode() == "seccomp"
    assert "weaker seccomp fallback" in caplog.text
    monkeypatch.setenv("SANDBOX", "bwrap")
    with pytest.raises(SandboxError, match="cannot create namespaces"):
        sandbox_mode()


def test_the_fallback_identity_is_never_root(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sandbox.os, "geteuid", lambda: 0)
    monkeypatch.delenv(sandbox.UID_ENV, raising=False)
    ident = sandbox.fallback_identity()
    assert ident is not None and (ident.uid, ident.gid) == (65534, 65534)
    monkeypatch.setenv(sandbox.UID_ENV, "2000:3000")
    ident = sandbox.fallback_identity()
    assert ident is not None and (ident.uid, ident.gid) == (2000, 3000)
    for bad in ("0", "1000:0", "nobody"):
        monkeypatch.setenv(sandbox.UID_ENV, bad)
        with pytest.raises(SandboxError, match=sandbox.UID_ENV):
            sandbox.fallback_identity()
    monkeypatch.setattr(sandbox.os, "geteuid", lambda: 1000)
    assert sandbox.fallback_identity() is None  # not root: nothing to drop to


SLEEPER = """
import time
class Policy:
    def __init__(self, env_spec):
        self.nap = {nap}
    def act(self, obs):
        time.sleep(self.nap)
        return [0.0, 0.0]
"""


def test_overage_bank_is_drawn_down_then_the_policy_times_out(
    make_python_bundle: MakeBundle,
) -> None:
    # 0.2 s over a 0.1 s deadline per step, a 1 s bank: about five steps, then a timeout.
    limits = replace(FAST, step_deadline_s=0.1, overage_s=1.0)
    bundle = make_python_bundle(SLEEPER.format(nap=0.3), driver=False)
    obs = np.zeros(make_env_spec()["obs_shape"], np.float32)
    with SandboxedPolicy(bundle, limits) as policy:
        policy.reset(0)
        served = 0
        with pytest.raises(PolicyTimeout, match="overage bank"):
            for _ in range(20):
                policy.act(obs)
                served += 1
        assert 2 <= served <= 6
        assert policy.stats["failure"] == "timeout"
        with pytest.raises(PolicyTimeout):  # and it stays failed
            policy.send(obs)


def test_cars_waiting_in_parallel_are_each_timed_from_their_own_send(
    make_python_bundle: MakeBundle,
) -> None:
    # Each takes 0.4 s of a 0.7 s deadline, no bank: collected one after the other, the
    # second would look 0.8 s late if its clock ran while the host waited for the first.
    # (0.3 s of slack for a correct clock: a loaded 2-core CI machine needs it.)
    limits = replace(FAST, step_deadline_s=0.7, overage_s=0.0)
    bundles = [
        make_python_bundle(SLEEPER.format(nap=0.4), name=f"s{i}", driver=False) for i in range(2)
    ]
    obs = np.zeros(make_env_spec()["obs_shape"], np.float32)
    policies = [SandboxedPolicy(b, limits) for b in bundles]
    try:
        for p in policies:
            p.start()
        for p in policies:
            p.reset(0)
        for _ in range(3):
            for p in policies:
                p.send(obs)
            time.sleep(0.6)  # the host is busy elsewhere meanwhile
            actions = [p.receive() for p in policies]
            assert all(a.shape == (2,) for a in actions)
    finally:
        for p in policies:
            p.close()


def test_a_policy_that_fails_to_load_reports_why(make_python_bundle: MakeBundle) -> None:
    bundle = make_python_bundle("raise ImportError('no such wheel')", driver=False)
    with SandboxedPolicy(bundle, FAST) as policy, pytest.raises(PolicyCrash, match="no such wheel"):
        policy.reset(0)


def test_a_sandboxed_pursuit_finishes_like_the_in_process_one(
    make_python_bundle: MakeBundle,
) -> None:
    bundle = make_python_bundle("class Policy(Driver):\n    pass\n", name="pursuit_in_box")
    boxed = SandboxedPolicy(bundle, FAST)
    result, replay = run_race(
        [boxed, make_baseline("pursuit", DEFAULT_LAYOUT)], track="oval", seed=0, record=True
    )
    assert [c.status for c in result.cars] == ["finished", "finished"]
    assert boxed.stats["steps"] > 100 and boxed.stats["failure"] is None
    assert replay is not None and replay.cars[0]["name"] == "pursuit_in_box"
    assert boxed.sandbox_id is not None and sandbox_processes(boxed.sandbox_id) == []  # closed


# ---- the race's side, with in-process stand-ins --------------------------------------------


class Failing:
    """Raises an exception carrying ``dnf_reason`` on its third action."""

    def __init__(self, reason: str) -> None:
        self.name = f"fails-{reason}"
        self.reason = reason
        self.steps = 0
        self.inner = make_baseline("pursuit", DEFAULT_LAYOUT)

    def reset(self, seed: int | None = None) -> None:
        self.inner.reset(seed)

    def act(self, obs: Any) -> Any:
        self.steps += 1
        if self.steps == 3:
            err = RuntimeError("nope")
            err.dnf_reason = self.reason  # type: ignore[attr-defined]
            raise err
        return self.inner.act(obs)


class TwoPhase:
    """Records the order of calls; acts like pursuit."""

    def __init__(self, log: list[str], name: str) -> None:
        self.name = name
        self.log = log
        self.inner = make_baseline("pursuit", DEFAULT_LAYOUT)
        self.pending: Any = None
        self.closed = False

    def start(self) -> None:
        self.log.append(f"start {self.name}")

    def reset(self, seed: int | None = None) -> None:
        self.inner.reset(seed)

    def act(self, obs: Any) -> Any:
        raise AssertionError("a two-phase policy is driven with send/receive")

    def send(self, obs: Any) -> None:
        self.log.append(f"send {self.name}")
        self.pending = self.inner.act(obs)

    def receive(self) -> Any:
        self.log.append(f"receive {self.name}")
        return self.pending

    def close(self) -> None:
        self.closed = True


@pytest.mark.parametrize("reason", ["timeout", "invalid", "error"])
def test_the_race_takes_the_dnf_reason_from_the_exception(reason: str) -> None:
    result, _ = run_race(
        [Failing(reason), make_baseline("pursuit", DEFAULT_LAYOUT)], seed=0, record=False
    )
    assert (result.cars[0].status, result.cars[0].dnf_reason) == ("dnf", reason)
    assert result.cars[1].status == "finished"


def test_two_phase_policies_are_sent_first_collected_last_and_closed() -> None:
    log: list[str] = []
    a, b = TwoPhase(log, "a"), TwoPhase(log, "b")
    result, _ = run_race([a, make_baseline("pursuit", DEFAULT_LAYOUT), b], seed=0, record=False)
    assert all(c.status == "finished" for c in result.cars)
    assert log[:2] == ["start a", "start b"]
    assert log[2:6] == ["send a", "send b", "receive a", "receive b"]
    assert a.closed and b.closed


def test_action_problem_names_each_fault() -> None:
    box = action_space_of(make_env_spec())
    assert action_problem(np.array([0.5, -1.0], np.float32), box) is None
    assert "shape" in str(action_problem(np.zeros(3), box))
    assert "outside" in str(action_problem(np.array([1.5, 0.0]), box))
    assert "NaN" in str(action_problem(np.array([np.nan, 0.0]), box))
    assert "not a number" in str(action_problem("left", box))
    discrete = action_space_of(make_env_spec(action_mode="discrete"))
    assert action_problem(3, discrete) is None
    assert action_problem(2.5, discrete) is not None and action_problem(99, discrete) is not None


def test_make_env_spec_matches_a_real_env() -> None:
    for mode, car in (
        ("continuous", "f1tenth"),
        ("discrete", "f1tenth"),
        ("continuous", "deepracer"),
    ):
        env = RacingEnv(track="oval", n_cars=2, action_mode=mode, car=car)
        try:
            assert env_spec_of(env) == make_env_spec(action_mode=mode, car=car)
            assert env_spec_of(env)["car"] == car  # a policy is told which car it drives
        finally:
            env.close()


def printed_by_a_fresh_interpreter(code: str) -> list[str]:
    """The lines ``code`` prints when run by a new Python (nothing imported yet)."""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return run.stdout.splitlines()


def test_the_sandboxed_worker_starts_without_scipy_or_the_simulator() -> None:
    # Every sandbox start imports submissions.worker; through submissions.errors ->
    # tracks.errors, tracks/__init__ used to import scipy (about 1 s of CPU per sandbox).
    # The package's names still load on use.
    code = (
        "import sys, submissions.worker\n"
        "heavy = ('scipy', 'pybullet', 'torch', 'gymnasium', 'arena.', 'agents.', 'tracks.geo')\n"
        "print(sorted(m for m in sys.modules if m.startswith(heavy)))\n"
        "from tracks import Track, TrackError, load_track\n"
        "import tracks.geometry\n"
        "print(Track is tracks.geometry.Track and load_track('oval').length > 30)\n"
    )
    assert printed_by_a_fresh_interpreter(code) == ["[]", "True"]


def test_a_bundle_built_on_the_baselines_starts_without_jsonschema_or_pil() -> None:
    # Bundles written from the Compete page wrap agents.baselines (so does the bench's
    # pursuit bundle); each of their sandboxes imported jsonschema (track files) and PIL
    # (rendering), about 0.15 s of CPU per start, for nothing a policy does. Both still load
    # where used: a track read from JSON is still checked against the schema.
    code = (
        "import sys, agents.baselines\n"
        "print(sorted(m for m in ('jsonschema', 'PIL') if m in sys.modules))\n"
        "from tracks.formats import track_from_dict\n"
        "try:\n"
        "    track_from_dict({'centre_line': 'no'})\n"
        "except Exception as err:\n"
        "    print(type(err).__name__, 'invalid track JSON' in str(err))\n"
    )
    assert printed_by_a_fresh_interpreter(code) == ["[]", "TrackError True"]


def test_bundle_root_is_read_only_inside(make_python_bundle: MakeBundle) -> None:
    body = """
    class Policy(Driver):
        def attack(self, obs):
            here = os.path.dirname(os.path.abspath(__file__))
            with open(os.path.join(here, "agent.py"), "a") as fh:
                fh.write("# tampered")
    """
    bundle = make_python_bundle(body)
    before = (bundle.root / "agent.py").read_bytes()
    result, _ = run_race([SandboxedPolicy(bundle, FAST)], seed=0, record=False)
    assert (result.cars[0].status, result.cars[0].dnf_reason) == ("dnf", "error")
    assert (bundle.root / "agent.py").read_bytes() == before


def test_a_sandbox_is_reaped_from_its_folder_alone(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    # What the next runner does for a sandbox whose host was SIGKILLed: only the folder
    # <tmp>/slipstream-sbx-<pid>-<id> is known. First the recorded process group alone.
    policy = SandboxedPolicy(make_python_bundle(PROBE, name="probe", driver=False), FAST)
    try:
        policy.reset(0)
        proc = policy._proc
        assert proc is not None and proc.folder is not None and policy.sandbox_id is not None
        folder, sid = proc.folder, policy.sandbox_id
        assert folder.is_dir() and sandbox_processes(sid)
        sandbox._kill_group(folder)
        deadline = time.monotonic() + 10
        while sandbox_processes(sid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert sandbox_processes(sid) == []
        sandbox.reap(folder)
        assert not folder.exists()
        assert sandbox.CgroupCaps.existing(sid).dirs == []
        assert sid not in Path("/proc/self/mounts").read_text()
    finally:
        policy.close()


# ---- policy decisions, exactly ----------------------------------------------------------
# Which mode runs, what a result records, which limits are refused, and which identity and
# paths the fallback gets: each pinned by value and by its whole message.


def sandbox_refusal(fn: Any, *args: Any, **kwargs: Any) -> str:
    """The message of the SandboxError that ``fn(*args, **kwargs)`` raises."""
    with pytest.raises(SandboxError) as info:
        fn(*args, **kwargs)
    return str(info.value)


@pytest.mark.parametrize(
    ("field", "bad", "message"),
    [
        ("memory_mb", 1023, "memory_mb must be at least 1024 (torch needs it), got 1023"),
        ("cpu_seconds", 0, "cpu_seconds must be at least 1, got 0"),
        ("file_size_mb", 0, "file_size_mb must be at least 1, got 0"),
        ("max_processes", 0, "max_processes must be at least 1, got 0"),
        ("tmpfs_mb", -1, "tmpfs_mb must be at least 1, got -1"),
        ("open_files", 15, "open_files must be at least 16 (Python needs them), got 15"),
        ("step_deadline_s", 0.0, "step_deadline_s must be positive, got 0.0"),
        ("step_deadline_s", float("nan"), "step_deadline_s must be positive, got nan"),
        ("startup_s", 0, "startup_s must be positive, got 0"),
        ("startup_s", -1.0, "startup_s must be positive, got -1.0"),
        ("overage_s", -0.001, "overage_s must not be negative, got -0.001"),
        ("cpus", 0.0099, "cpus must be within 0.01..1024.0, got 0.0099"),
        ("cpus", 1024.5, "cpus must be within 0.01..1024.0, got 1024.5"),
        ("cpus", float("nan"), "cpus must be within 0.01..1024.0, got nan"),
    ],
)
def test_each_limit_is_refused_one_past_its_bound(field: str, bad: float, message: str) -> None:
    """A limit one step past its bound (or NaN for a deadline) is refused, naming it."""
    assert sandbox_refusal(SandboxLimits, **{field: bad}) == message


def test_limits_exactly_at_their_bounds_are_accepted() -> None:
    """The bounds are inclusive (a zero overage bank means: no slack at all)."""
    low = SandboxLimits(
        memory_mb=1024, cpu_seconds=1, open_files=16, file_size_mb=1, max_processes=1,
        tmpfs_mb=1, step_deadline_s=1e-6, startup_s=1e-6, overage_s=0.0, cpus=0.01,
    )  # fmt: skip
    assert (low.memory_mb, low.open_files, low.overage_s, low.cpus) == (1024, 16, 0.0, 0.01)
    assert SandboxLimits(cpus=1024.0).cpus == 1024.0
    SandboxLimits()  # the defaults pass


@pytest.mark.parametrize(
    ("value", "allowed"),
    [("1", True), (" 1\n", True), ("", False), ("0", False), ("yes", False), ("11", False)],
)
def test_only_1_allows_the_weak_sandbox(
    monkeypatch: pytest.MonkeyPatch, value: str, allowed: bool
) -> None:
    """SLIPSTREAM_ALLOW_WEAK_SANDBOX: exactly "1" (surrounding blanks ignored) allows it."""
    monkeypatch.setenv(sandbox.WEAK_ENV, value)
    assert sandbox.weak_sandbox_allowed() is allowed
    monkeypatch.delenv(sandbox.WEAK_ENV)
    assert sandbox.weak_sandbox_allowed() is False


def test_allowing_the_weak_sandbox_says_what_results_record(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The operator's --allow-weak-sandbox is logged as a warning naming the recorded label."""
    monkeypatch.delenv(sandbox.WEAK_ENV, raising=False)
    with caplog.at_level(logging.WARNING, logger="submissions.sandbox"):
        sandbox.allow_weak_sandbox()
    assert os.environ[sandbox.WEAK_ENV] == "1"
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (
            logging.WARNING,
            "--allow-weak-sandbox: where bubblewrap cannot run, untrusted policies run in the "
            "weaker seccomp fallback; every such result is recorded as 'seccomp-weak'",
        )
    ]


@pytest.mark.parametrize(
    ("forced", "bwrap_ok", "allowed", "outcome"),
    [
        (None, True, "", "bwrap"),  # SANDBOX unset: auto
        ("  ", True, "", "bwrap"),  # blank: auto
        (" AUTO ", False, "1", "seccomp"),
        ("Seccomp", True, "1", "seccomp"),  # case and blanks ignored; bwrap not preferred
        (" BWRAP", True, "", "bwrap"),
        ("chroot", True, "1", "SANDBOX='chroot': expected bwrap, seccomp or auto"),
        ("bwrap", False, "1", "SANDBOX=bwrap but /usr/bin/bwrap cannot create namespaces here"),
        (
            None, False, "",
            "bubblewrap cannot run here: the weaker seccomp fallback, and untrusted policies do "
            "not run in it unless the operator passes --allow-weak-sandbox",
        ),
        (
            "seccomp", True, "",
            "SANDBOX=seccomp asks for the weaker seccomp fallback, and untrusted policies do not "
            "run in it unless the operator passes --allow-weak-sandbox",
        ),
    ],
)  # fmt: skip
def test_which_mode_runs_and_why_not(
    monkeypatch: pytest.MonkeyPatch, forced: str | None, bwrap_ok: bool, allowed: str, outcome: str
) -> None:
    """sandbox_mode under each SANDBOX value, bubblewrap state and operator permission: the
    mode chosen, or the whole message of the refusal (fail closed)."""
    if forced is None:
        monkeypatch.delenv("SANDBOX", raising=False)
    else:
        monkeypatch.setenv("SANDBOX", forced)
    monkeypatch.setenv(sandbox.WEAK_ENV, allowed)
    monkeypatch.setattr(sandbox, "bwrap_works", lambda: bwrap_ok)
    if outcome in sandbox.MODES:
        assert sandbox_mode() == outcome
        assert sandbox.mode_label(outcome) == {"bwrap": "bwrap", "seccomp": "seccomp-weak"}[outcome]
    else:
        assert sandbox_refusal(sandbox_mode) == outcome


def test_bubblewrap_is_not_probed_when_the_fallback_is_forced(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """SANDBOX=seccomp never starts the bwrap probe (tests force it where bwrap hangs)."""
    monkeypatch.setenv("SANDBOX", "seccomp")
    monkeypatch.setenv(sandbox.WEAK_ENV, "1")

    def no_probe() -> bool:
        raise AssertionError("bwrap probed")

    monkeypatch.setattr(sandbox, "bwrap_works", no_probe)
    assert sandbox_mode() == "seccomp"


def test_mode_labels() -> None:
    """Only the fallback is relabelled; any other mode is recorded as itself."""
    assert [sandbox.mode_label(m) for m in ("bwrap", "seccomp", "other")] == [
        "bwrap", "seccomp-weak", "other",
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("raw", "ids"),
    [
        (None, (65534, 65534)),
        ("", (65534, 65534)),
        ("2000", (2000, 2000)),
        (" 2000:3000 ", (2000, 3000)),
        ("1:1", (1, 1)),  # the lowest unprivileged ids
        ("2000:", (2000, 2000)),
    ],
)
def test_the_fallback_identity(
    monkeypatch: pytest.MonkeyPatch, raw: str | None, ids: tuple[int, int]
) -> None:
    """Who the fallback runs as: nobody by default, or SLIPSTREAM_SANDBOX_UID=uid[:gid]."""
    monkeypatch.setattr(sandbox.os, "geteuid", lambda: 0)
    if raw is None:
        monkeypatch.delenv(sandbox.UID_ENV, raising=False)
    else:
        monkeypatch.setenv(sandbox.UID_ENV, raw)
    ident = sandbox.fallback_identity()
    assert ident is not None and (ident.uid, ident.gid) == ids


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        ("nobody", "expected uid or uid:gid"),
        ("1:2:3", "expected uid or uid:gid"),
        (":1000", "expected uid or uid:gid"),
        ("0", "the sandbox never runs as uid or gid 0"),
        ("1000:0", "the sandbox never runs as uid or gid 0"),
        ("0:1000", "the sandbox never runs as uid or gid 0"),
        ("-5", "the sandbox never runs as uid or gid 0"),
    ],
)
def test_a_bad_fallback_uid_is_refused(monkeypatch: pytest.MonkeyPatch, raw: str, why: str) -> None:
    """A malformed or root SLIPSTREAM_SANDBOX_UID is refused, quoting it."""
    monkeypatch.setattr(sandbox.os, "geteuid", lambda: 0)
    monkeypatch.setenv(sandbox.UID_ENV, raw)
    assert sandbox_refusal(sandbox.fallback_identity) == f"SLIPSTREAM_SANDBOX_UID={raw!r}: {why}"


def reachable_tree() -> Path:
    """A fresh folder right under /tmp, o+x (pytest's tmp_path lies under a 0700 folder)."""
    base = Path(tempfile.mkdtemp(dir="/tmp", prefix="reach-"))
    base.chmod(0o711)
    (base / "a").mkdir(mode=0o711)
    (base / "a" / "f").write_text("x")
    (base / "a" / "f").chmod(0o600)  # the path itself needs no permission for others
    (base / "a" / "priv").mkdir(mode=0o700)
    return base


def test_others_can_reach_checks_every_folder_above(tmp_path: Path) -> None:
    """A path is reachable for the dropped uid when every folder above it has o+x."""
    base = reachable_tree()
    try:
        assert sandbox._others_can_reach(str(base / "a" / "f"))
        assert sandbox._others_can_reach(str(base / "a" / "priv"))  # its own mode is not asked
        assert not sandbox._others_can_reach(str(base / "a" / "priv" / "x"))  # 0700 above
        assert not sandbox._others_can_reach(str(base / "a" / "missing"))
        (base / "a").chmod(0o710)  # group may pass, others may not
        assert not sandbox._others_can_reach(str(base / "a" / "f"))
        assert not sandbox._others_can_reach(str(tmp_path / "x"))  # pytest's tree is 0700
    finally:
        (base / "a").chmod(0o755)
        shutil.rmtree(base)


def test_the_fallback_keeps_file_system_root_only_when_the_interpreter_needs_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """fs_root: the interpreter, its prefixes and our packages must all be reachable by the
    dropped uid; else (a /root/.pyenv interpreter) the file-system uid stays 0."""
    base = reachable_tree()
    try:
        monkeypatch.setattr(sandbox.os, "geteuid", lambda: 0)
        monkeypatch.delenv(sandbox.UID_ENV, raising=False)
        monkeypatch.setattr(sandbox.sys, "executable", str(base / "a" / "f"))
        monkeypatch.setattr(sandbox, "python_paths", lambda: [str(base / "a")])
        monkeypatch.setattr(sandbox, "package_dirs", lambda: {"arena": str(base / "a" / "priv")})
        assert sandbox.fallback_identity() == sandbox.Identity(65534, 65534, fs_root=False)
        for hidden in ("python_paths", "package_dirs"):
            with monkeypatch.context() as m:
                if hidden == "python_paths":
                    m.setattr(sandbox, hidden, lambda: [str(base / "a" / "priv" / "lib")])
                else:
                    m.setattr(sandbox, hidden, lambda: {"arena": str(base / "a" / "priv" / "x")})
                assert sandbox.fallback_identity() == sandbox.Identity(65534, 65534, fs_root=True)
        monkeypatch.setattr(sandbox.sys, "executable", str(base / "a" / "priv" / "python"))
        assert sandbox.fallback_identity() == sandbox.Identity(65534, 65534, fs_root=True)
    finally:
        shutil.rmtree(base)


def test_the_fallback_reads_and_writes_only_its_lists(tmp_path: Path) -> None:
    """Landlock's lists in the fallback: system folders, the interpreter, our packages, the
    worker's app folder and the bundle read-only; only its work folder (and /dev/null)
    writable. Nothing of /etc, /home, /root, /proc or /tmp."""
    bundle, work, app = tmp_path / "bundle", tmp_path / "work", tmp_path / "app"
    read, write = sandbox.fallback_paths(bundle, work, app)
    assert read == [
        "/usr", "/lib", "/lib64", "/bin", "/sys/devices/system/cpu", *sandbox.python_paths(),
        *sandbox.package_dirs().values(), str(app), str(bundle), "/dev/urandom",
    ]  # fmt: skip
    assert write == [str(work), "/dev/null"]


CROSS_PROCESS_PROBE = """
import ctypes, errno, json, os, resource, signal, sys, threading
from submissions.sandbox import apply_seccomp, seccomp_filter

target = int(sys.argv[1])
libc = ctypes.CDLL(None, use_errno=True)
libc.prlimit.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
old = (ctypes.c_ulong * 2)()

def outcome(fn):
    try:
        fn()
    except OSError as err:
        return errno.errorcode.get(err.errno, str(err.errno))
    return "done"

def c_call(name, *args):
    if getattr(libc, name)(*args) == -1:
        raise OSError(ctypes.get_errno(), name)

def attempts(pid):
    return {
        "kill": outcome(lambda: os.kill(pid, 0)),
        "tgkill": outcome(lambda: c_call("tgkill", pid, pid, 0)),
        "prlimit": outcome(lambda: c_call("prlimit", pid, resource.RLIMIT_CPU, None, old)),
        "pidfd_open": outcome(lambda: os.close(os.pidfd_open(pid))),
        "kcmp": outcome(lambda: c_call("syscall", 312, os.getpid(), pid, 0, 0, 0)),
    }

before = attempts(target)
apply_seccomp(seccomp_filter("seccomp", pid=os.getpid()))
print(json.dumps({
    "before": before,
    "other": attempts(target),
    "every": outcome(lambda: os.kill(-1, 0)),
    "own-kill": outcome(lambda: os.kill(os.getpid(), 0)),
    "own-thread": outcome(lambda: signal.pthread_kill(threading.get_ident(), 0)),
    "own-rlimit": outcome(lambda: resource.setrlimit(resource.RLIMIT_CORE, (0, 0))),
    "own-pidfd": outcome(lambda: os.close(os.pidfd_open(os.getpid()))),
}))
"""


@pytest.mark.skipif(sys.platform != "linux" or os.uname().machine != "x86_64", reason="x86-64")
def test_fallback_filter_refuses_other_processes_whatever_landlock_allows() -> None:
    # The fallback's sandboxes share one uid, and Landlock scopes signals only from ABI 6 on
    # (and rlimits never): the seccomp filter alone must keep a worker from signalling,
    # re-limiting, opening a pidfd on or comparing itself with another process — checked
    # here on a process of the probe's own uid (where the kernel would allow all of it,
    # as "before" shows) with the filter and nothing else — and still let it act on itself.
    target = subprocess.Popen(["sleep", "60"])
    try:
        probe = subprocess.run(
            [sys.executable, "-c", CROSS_PROCESS_PROBE, str(target.pid)],
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
        )
    finally:
        target.kill()
        target.wait()
    got = json.loads(probe.stdout)
    assert set(got["before"].values()) == {"done"}, got  # the kernel allows it unfiltered
    assert set(got["other"].values()) == {"EPERM"}, got
    assert got["every"] == "EPERM"
    for own in ("own-kill", "own-thread", "own-rlimit", "own-pidfd"):
        assert got[own] == "done", got
