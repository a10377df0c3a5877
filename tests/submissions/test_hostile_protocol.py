"""Hostile policies against the worker protocol: nothing a policy does can wedge the host.

Each case is an attack from the outside review of issue 12 ("any upload can hang a race
forever", "the host's frame queue is unbounded", "a malformed frame shape kills the host's
reader thread", "a policy answering just under the 0.25 s deadline stretches a 4 s race to
150 s", "15 MiB in, 11 MiB replay"), and the attacks on the shared-memory channel that
replaced the frame pipes (scribbling the region, wake-ups ahead of time or never, closed
descriptors, forged values, mapping past the region), rebuilt by someone who read
``submissions/channel.py`` and ``submissions/worker.py``: the policy finds its channel (the
worker's ``WorkerChannel``) with ``gc`` and writes the region and the bell itself. Several
attackers race at once against an honest pursuit car (one sandbox start-up each, in
parallel), in both sandbox modes. The exact timings of the same attacks, without a
sandbox, are in ``test_channel.py``.
"""

from __future__ import annotations

import gzip
import json
import struct
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.baselines import make_baseline
from agents.loading import DEFAULT_LAYOUT
from arena.race import run_race
from submissions.bundle import make_bundle
from submissions.channel import REPLY_BYTES
from submissions.jobs import Entrant, RaceJob, race_wall_clock_s, run_race_job
from submissions.protocol import HEADER, MAX_TEXT
from submissions.remote import EXIT_WAIT_S, PolicyTimeout, SandboxedPolicy
from submissions.sandbox import SandboxLimits

from .conftest import MakeBundle, manifest_for, python_source, sandbox_processes

# Short bank: a policy that merely stops answering is retired in about a second.
QUICK = SandboxLimits(step_deadline_s=0.25, overage_s=1.0, startup_s=60.0)

# Shared by the attacks: the policy's own channel, found the way an attacker would.
CHANNEL = """
import ctypes, errno, gc, json, mmap, os, stat, struct, threading
from submissions.channel import REPLY_BYTES
from submissions.protocol import Kind, encode


def channel():
    return next(o for o in gc.get_objects() if type(o).__name__ == "WorkerChannel")


def request_seq(ch):
    return struct.unpack_from("<H", ch.memory, 6)[0]  # the observation frame's number


def forge(ch, frame, ring=True):
    at = len(ch.memory) - REPLY_BYTES
    ch.memory[at : at + len(frame)] = frame
    if ring:
        os.write(ch.bell, b"\\x01")


def memfds():
    found = []
    for fd in range(1024):
        try:
            st = os.fstat(fd)
        except OSError:
            continue
        if stat.S_ISREG(st.st_mode) and st.st_nlink == 0:
            found.append([fd, st.st_ino, st.st_size])
    return found


def signalable():
    # the pids near its own that it may signal (kill(pid, 0) allowed)
    me = os.getpid()
    found = []
    for pid in range(max(1, me - 5000), me + 5000):
        try:
            os.kill(pid, 0)
        except OSError:
            continue
        found.append(pid)
    return found
"""


def attack(body: str) -> str:
    """:data:`CHANNEL` then ``body`` (dedented)."""
    return CHANNEL + textwrap.dedent(body)


def race_many(
    bundles: dict[str, str], make_python_bundle: MakeBundle, limits: SandboxLimits
) -> tuple[dict[str, tuple[str, str | None, str]], dict[str, SandboxedPolicy], float]:
    """Race one sandboxed car per ``name: body`` (all started at once) and an honest
    in-process pursuit car; the pursuit car finishes and nothing of any sandbox survives.
    Returns ``{name: (status, dnf_reason, detail)}``, the policies and the seconds taken."""
    policies = {
        name: SandboxedPolicy(make_python_bundle(body, name=name.replace("-", "_")), limits)
        for name, body in bundles.items()
    }
    pursuit = make_baseline("pursuit", DEFAULT_LAYOUT)
    start = time.monotonic()
    result, replay = run_race([*policies.values(), pursuit], track="oval", laps=1, seed=0)
    took = time.monotonic() - start
    assert result.cars[-1].status == "finished", result.cars[-1]
    details = {
        e["car"]: str(e.get("detail", ""))
        for e in (replay.events if replay else [])
        if e["type"] == "dnf"
    }
    out = {}
    for (name, policy), car in zip(policies.items(), result.cars, strict=False):
        assert policy.sandbox_id is not None and sandbox_processes(policy.sandbox_id) == []
        out[name] = (car.status, car.dnf_reason, details.get(car.agent, ""))
    return out, policies, took


def _reported(policy: SandboxedPolicy, tag: str) -> Any:
    line = next(x for x in policy.output.splitlines() if x.startswith(tag + " "))
    return json.loads(line[len(tag) + 1 :])


FORGED = {  # name: (the frame written into the reply slot, rung; a word of the detail)
    "nan": ("encode(Kind.ACTION, np.array([np.nan, 0.0], np.float32), seq)", "NaN"),
    "huge": ("encode(Kind.ACTION, np.array([1e300, 1e300]), seq)", "outside"),
    "bool": ("encode(Kind.ACTION, np.array([True, False]), seq)", "not a number"),
    "1tib": ('struct.pack("<2sBBBxHQQ", b"SL", 5, 1, 1, seq, 1 << 40, 1 << 38)', "exceeds"),
    "absurd-shape": (
        'struct.pack("<2sBBBxHQQQ", b"SL", 5, 1, 2, seq, 0, 0, 1 << 63)',
        "shape",
    ),
    "past-slot": (
        f'struct.pack("<2sBBBxHQQ", b"SL", 5, 5, 1, seq, {REPLY_BYTES}, {REPLY_BYTES})',
        "slot",
    ),
}


@pytest.mark.slow
def test_forged_replies_in_the_shared_region_are_invalid(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    """Values written straight into the reply slot and rung in: NaN, 1e300, a bool array
    (wrong dtype), a 1 TiB header, a zero-size (0, 2⁶³) shape, a frame longer than the slot.
    Each is copied out, checked and refused: ``invalid``, its car alone; the pursuit car
    finishes. Two honest sandboxed cars list the memory they can reach (one region each,
    its own: no other car's channel is in reach) and the processes they can signal (only
    their own sandbox's: not each other, not the host)."""
    bodies = {
        name: attack(
            f"""
            class Policy(Driver):
                def attack(self, obs):
                    ch = channel()
                    seq = request_seq(ch)
                    forge(ch, {frame})
                    time.sleep(30)  # never answers otherwise
            """
        )
        for name, (frame, _) in FORGED.items()
    }
    inventory = attack(
        """
        class Policy(Driver):
            def attack(self, obs):
                print("MEMFDS " + json.dumps(memfds()), flush=True)
                print("PIDS " + json.dumps([os.getpid(), signalable()]), flush=True)
        """
    )
    bodies |= {"inventory-a": inventory, "inventory-b": inventory}
    outcome, policies, _ = race_many(bodies, make_python_bundle, QUICK)
    for name, (_, word) in FORGED.items():
        status, reason, detail = outcome[name]
        assert (status, reason) == ("dnf", "invalid"), (name, detail)
        assert word in detail, (name, detail)
    seen, pids = [], []
    for name in ("inventory-a", "inventory-b"):
        assert outcome[name][0] == "finished", outcome[name]
        regions = [r for r in _reported(policies[name], "MEMFDS") if r[2] >= REPLY_BYTES]
        assert len(regions) == 1, regions  # its channel, and no other car's
        seen.append(regions[0][1])
        pids.append(_reported(policies[name], "PIDS"))
    assert seen[0] != seen[1]
    for (me, reach), (other, _) in (pids, pids[::-1]):
        # bwrap: its pid namespace (bwrap's init and itself); the fallback: itself alone
        # (Landlock scopes its signals), never the other car, never the host
        assert set(reach) <= ({1, me} if mode == "bwrap" else {me}), reach
        assert me in reach and (mode == "bwrap" or other not in reach)


TIMING = {
    "rings-ahead": (  # wake-ups before its answer: the host is rung four times for one step
        """
        class Policy(Driver):
            def attack(self, obs):
                os.write(channel().bell, b"\\x01" * 3)
        """,
        "invalid",
        "woke the host unasked",
    ),
    "bell-flood": (  # a thread rings without end (the flood, on the bell)
        """
        class Policy(Driver):
            def attack(self, obs):
                bell = channel().bell
                def ring():
                    while True:
                        os.write(bell, b"\\x01" * 4096)
                threading.Thread(target=ring, daemon=True).start()
        """,
        "invalid",
        "woke the host unasked",
    ),
    "never-rings": (  # the right answer in the slot, never rung in
        """
        class Policy(Driver):
            def attack(self, obs):
                ch = channel()
                forge(ch, encode(Kind.ACTION, np.zeros(2, np.float32), request_seq(ch)), ring=False)
                time.sleep(3600)
        """,
        "timeout",
        "no action",
    ),
    "closes-channel": (  # closes both pipe ends and keeps running
        """
        class Policy(Driver):
            def attack(self, obs):
                ch = channel()
                os.close(ch.bell)
                os.close(ch.ring)
                time.sleep(3600)
        """,
        "invalid",
        "closed its channel",
    ),
    "scribbler": (  # a thread writes garbage over its reply slot without end, from step 3
        """
        class Policy(Driver):
            def attack(self, obs):
                ch = channel()
                at = len(ch.memory) - REPLY_BYTES
                def scribble():
                    while True:
                        ch.memory[at : at + 4096] = os.urandom(4096)
                threading.Thread(target=scribble, daemon=True).start()
        """,
        "invalid",
        "protocol",
    ),
    "past-the-region": (  # resize the sealed region; then read a mapping past its end
        """
        class Policy(Driver):
            def attack(self, obs):
                ch = channel()
                fd, _, size = next(r for r in memfds() if r[2] == len(ch.memory))
                def tried(fn):
                    try:
                        fn()
                    except OSError as err:
                        return "refused:" + errno.errorcode.get(err.errno or 0, "?")
                    except (ValueError, TypeError) as err:
                        return "refused:" + type(err).__name__
                    return "DONE"
                print("ATTACKS " + json.dumps({
                    "shrink": tried(lambda: os.ftruncate(fd, 0)),
                    "grow": tried(lambda: os.ftruncate(fd, size * 4)),
                    "fallocate": tried(lambda: os.posix_fallocate(fd, size, 1 << 20)),
                    "resize": tried(lambda: ch.memory.resize(size * 4)),
                }), flush=True)
                libc = ctypes.CDLL(None, use_errno=True)
                libc.mmap.restype = ctypes.c_void_p
                c = ctypes
                libc.mmap.argtypes = [c.c_void_p, c.c_size_t, c.c_int, c.c_int, c.c_int, c.c_long]
                addr = libc.mmap(None, size * 4, 1, 1, fd, 0)  # PROT_READ, MAP_SHARED
                print("MAPPED", addr not in (None, ctypes.c_void_p(-1).value), flush=True)
                ctypes.string_at(addr + size * 2, 8)  # past the end of the file: SIGBUS
        """,
        "error",
        "exited",
    ),
}


@pytest.mark.slow
def test_attacks_on_the_channel_are_contained(mode: str, make_python_bundle: MakeBundle) -> None:
    """Wake-ups ahead of time, a flood of them, a reply never rung in, closed pipe ends,
    garbage scribbled over the reply slot while the host reads it, and the sealed region
    resized or mapped past its end: each retires its own car with the right reason (the
    closed channel after EXIT_WAIT_S), the pursuit car and an honest sandboxed car finish
    (with a 1 s bank: the host's waits on the attackers — EXIT_WAIT_S included — are not
    charged to it), and the region kept its size."""
    bodies = {name: attack(body) for name, (body, _, _) in TIMING.items()}
    bodies["honest"] = attack("class Policy(Driver):\n    pass\n")
    outcome, policies, took = race_many(bodies, make_python_bundle, QUICK)
    for name, (_, reason, word) in TIMING.items():
        status, got, detail = outcome[name]
        assert (status, got) == ("dnf", reason), (name, detail, policies[name].output[-1500:])
        assert word in detail, (name, detail)
    assert outcome["honest"][0] == "finished", (outcome["honest"], policies["honest"].stats)
    out = policies["past-the-region"].output
    line = next(x for x in out.splitlines() if x.startswith("ATTACKS "))
    results = json.loads(line[len("ATTACKS ") :])
    assert all(v.startswith("refused") for v in results.values()), results
    assert "MAPPED True" in out  # it did map past the end; only its own read faulted
    assert took < 120 + EXIT_WAIT_S


def test_a_policy_answering_just_under_the_deadline_is_cut_by_the_race_wall_clock(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    """0.24 s for every answer, under the 0.25 s deadline: the bank never moves, so only the
    race's wall-clock limit (``race_deadline``, set by the job) bounds it."""
    bundle = make_python_bundle(
        """
        import time
        import numpy as np

        class Policy:
            def act(self, obs):
                time.sleep(0.24)
                return np.zeros(2, np.float32)
        """,
        driver=False,
    )
    with SandboxedPolicy(bundle, QUICK) as policy:
        policy.reset(0)
        start = time.monotonic()
        policy.race_deadline = start + 2.0
        steps = 0
        with pytest.raises(PolicyTimeout, match="wall-clock limit"):
            while True:
                policy.act(np.zeros(8, np.float32))
                steps += 1
        took = time.monotonic() - start
        assert 2.0 <= took < 2.6 and 4 <= steps <= 9
        assert policy.bank > QUICK.overage_s - 0.5  # the bank alone would never have stopped it


def test_default_race_wall_clock_is_three_times_the_step_limit_plus_start_up() -> None:
    assert race_wall_clock_s(400, 60.0, control_hz=20) == 3 * 20.0 + 60.0
    assert race_wall_clock_s(100, 5.0, control_hz=10) == 35.0


def _zip(tmp_path: Path, name: str, body: str, driver: bool = True) -> str:
    source = python_source(body, driver).encode()
    zipped = make_bundle(tmp_path / f"{name}.zip", manifest_for(name), {"agent.py": source})
    return str(zipped)


@pytest.mark.slow
def test_slow_answers_are_bounded_in_a_job_and_the_honest_car_finishes(tmp_path: Path) -> None:
    """The same 0.24 s policy in a whole job: the job's wall clock retires it ``timeout``;
    the baseline keeps racing and finishes."""
    slow = _zip(
        tmp_path,
        "slow",
        """
        class Policy(Driver):
            def act(self, obs):
                time.sleep(0.24)
                return super().act(obs)
        """,
    )
    job = RaceJob(
        "slow",
        (Entrant("slow", slow), Entrant("pursuit", "pursuit")),
        "oval",
        str(tmp_path / "out"),
        laps=1,
        limits=QUICK,
        record_viser=False,
        # A lap at 0.24 s a step would take over a minute; the limit cuts it well before.
        wall_clock_s=8.0,
    )
    res = run_race_job(job)
    slow_car, honest = res.result["cars"]
    assert (slow_car["status"], slow_car["dnf_reason"]) == ("dnf", "timeout")
    assert "wall-clock limit" in slow_car["dnf_detail"]
    assert honest["status"] == "finished" and honest["dnf_detail"] is None
    assert res.duration_s < 8.0 + 60.0


@pytest.mark.slow
def test_15_mib_of_error_text_is_capped_in_result_replay_and_logs(tmp_path: Path) -> None:
    """The issue's 15 MiB error (an 11 MiB public replay): raised as an exception (and so
    printed as a traceback), and forged as the longest ERROR frame its reply slot holds
    (16 KiB: a longer one is refused whole, see the forged replies above)."""
    raised = _zip(
        tmp_path,
        "raiser",
        """
        class Policy(Driver):
            def attack(self, obs):
                raise RuntimeError("x" * (15 << 20))
        """,
    )
    forged = _zip(
        tmp_path,
        "forger",
        attack(
            """
        class Policy(Driver):
            def attack(self, obs):
                ch = channel()
                text = np.frombuffer(b"y" * (REPLY_BYTES - 24), np.uint8)
                forge(ch, encode(Kind.ERROR, text, request_seq(ch)))
                time.sleep(30)
        """,
        ),
    )
    job = RaceJob(
        "loud",
        (Entrant("raiser", raised), Entrant("forger", forged), Entrant("pursuit", "pursuit")),
        "oval",
        str(tmp_path / "out"),
        laps=1,
        limits=QUICK,
        record_viser=False,
    )
    res = run_race_job(job)
    raiser, forger, honest = res.result["cars"]
    assert (raiser["status"], raiser["dnf_reason"]) == ("dnf", "error")
    assert (forger["status"], forger["dnf_reason"]) == ("dnf", "error")
    assert "yyyy" in forger["dnf_detail"]
    assert honest["status"] == "finished"
    assert raiser["dnf_detail"].startswith("PolicyCrash") and "xxxx" in raiser["dnf_detail"]
    for car in (raiser, forger):
        assert 0 < len(car["dnf_detail"].encode()) <= MAX_TEXT
    with gzip.open(res.replay_path, "rt") as fh:
        replay = json.load(fh)
    details = [e["detail"] for e in replay["events"] if "detail" in e]
    assert len(details) == 2 and all(len(d.encode()) <= MAX_TEXT for d in details)
    assert Path(res.replay_path).stat().st_size < 1 << 20
    assert set(res.logs) == {"car_0", "car_1"}
    assert res.logs["car_0"]["sandbox_mode"] in ("bwrap", "seccomp-weak")
    assert "bytes not kept" in res.logs["car_0"]["output"]  # the 15 MiB traceback, cut
    assert len(json.dumps(res.to_dict())) < 100_000


def test_header_layout_is_what_the_attacks_forge() -> None:
    """The attacks above pack headers by hand; they must match the protocol's."""
    assert HEADER.format == "<2sBBBxHQ" and HEADER.size == struct.calcsize("<2sBBBxHQ") == 16
