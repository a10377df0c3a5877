"""Hostile policies against the worker protocol: nothing a policy sends can wedge the host.

Each case is an attack from the outside review of issue 12 ("any upload can hang a race
forever", "the host's frame queue is unbounded", "a malformed frame shape kills the host's
reader thread", "a policy answering just under the 0.25 s deadline stretches a 4 s race to
150 s", "15 MiB in, 11 MiB replay"), rebuilt from its description by someone who read
``submissions/protocol.py``: the policy finds its protocol pipes in its own ``sys.argv``
(``--in``/``--out``) and writes raw frames on them itself. Per request, the host counts only
the reply numbered like its request and arriving after it (see :mod:`submissions.remote`).
"""

from __future__ import annotations

import gzip
import json
import resource
import struct
import textwrap
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np
import pytest

from submissions.bundle import make_bundle
from submissions.jobs import Entrant, RaceJob, race_wall_clock_s, run_race_job
from submissions.protocol import HEADER, MAX_TEXT, FrameDecoder, Kind, encode
from submissions.remote import (
    _FLOOD,
    MAX_QUEUED,
    PolicyTimeout,
    SandboxedPolicy,
    _queue_frames,
)
from submissions.sandbox import SandboxLimits

from .conftest import (
    MakeBundle,
    manifest_for,
    python_source,
    race_against_pursuit,
    sandbox_processes,
)

# Short bank: a policy that merely stops answering is retired in about a second.
QUICK = SandboxLimits(step_deadline_s=0.25, overage_s=1.0, startup_s=60.0)
# A bank so long that a failure reported within seconds cannot have come from it.
FAST_BANK = SandboxLimits(step_deadline_s=0.25, overage_s=30.0, startup_s=60.0)

# Shared by the attacks: the policy's own protocol pipes and the frame helpers.
PIPES = """
import fcntl, os, struct, sys, time
import numpy as np
from submissions.protocol import Kind, encode, write_all

FD_IN = int(sys.argv[sys.argv.index("--in") + 1])
FD_OUT = int(sys.argv[sys.argv.index("--out") + 1])


def shrink(fd):
    try:
        fcntl.fcntl(fd, 1031, 4096)  # F_SETPIPE_SZ: the smallest pipe there is
    except OSError:
        pass
"""


def attack(body: str) -> str:
    """:data:`PIPES` then ``body`` (dedented)."""
    return PIPES + textwrap.dedent(body)


def race_contained(policy: SandboxedPolicy, reason: str, within_s: float) -> str:
    """Race ``policy`` against pursuit; it retires with ``reason`` and the race ends in
    ``within_s``; the pursuit car finishes; nothing of the sandbox survives. Its detail."""
    start = time.monotonic()
    result = race_against_pursuit(policy)
    took = time.monotonic() - start
    car, other = result.cars
    assert (car.status, car.dnf_reason) == ("dnf", reason), policy.output[-2000:]
    assert other.status == "finished"
    assert took < within_s, f"the race took {took:.1f} s"
    assert policy.sandbox_id is not None and sandbox_processes(policy.sandbox_id) == []
    assert policy.failure is not None
    return str(policy.failure)


def test_answers_sent_ahead_into_a_shrunken_pipe_do_not_wedge_the_race(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    """The issue's critical wedge: answers for the next steps sent at once (numbered right,
    guessed from the step count: RESET is request 1, step k is k + 1), the input pipe shrunk
    to one page, then it never reads again. The host used to take a queued frame as each
    step's answer, fill the pipe and block in write() forever. Five answers ahead stay under
    the flood bound, so it is the arrival-before-request check that catches them."""
    bundle = make_python_bundle(
        attack(
            """
        class Policy(Driver):
            def attack(self, obs):
                shrink(FD_IN)
                for seq in range(self.steps + 1, self.steps + 7):
                    write_all(FD_OUT, encode(Kind.ACTION, np.zeros(2, np.float32), seq))
                time.sleep(3600)  # and never read its input again
        """
        )
    )
    detail = race_contained(SandboxedPolicy(bundle, QUICK), "invalid", within_s=120)
    assert "before its request" in detail


def test_a_policy_that_stops_reading_never_blocks_the_host_write(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    """It answers step 1 itself (a correctly numbered frame) and then neither returns nor
    reads: the next observation (256 KiB, bigger than any pipe) must not block ``send``, and
    ``receive`` gives up within the step deadline plus the bank."""
    bundle = make_python_bundle(
        attack(
            """
        class Policy:
            def __init__(self):
                self.steps = 0

            def act(self, obs):
                self.steps += 1
                shrink(FD_IN)
                write_all(FD_OUT, encode(Kind.ACTION, np.zeros(2, np.float32), self.steps + 1))
                time.sleep(3600)
        """,
        ),
        driver=False,
    )
    with SandboxedPolicy(bundle, QUICK) as policy:
        policy.reset(0)
        np.testing.assert_array_equal(policy.act(np.zeros(8, np.float32)), [0.0, 0.0])
        start = time.monotonic()
        policy.send(np.zeros(1 << 16, np.float32))
        assert time.monotonic() - start < 0.5  # the write did not wait for the reader
        with pytest.raises(PolicyTimeout, match="stopped reading"):
            policy.receive()
        took = time.monotonic() - start
        assert took < QUICK.step_deadline_s + QUICK.overage_s + 2.0


def test_a_flood_of_tiny_valid_frames_is_invalid_and_costs_the_host_no_memory(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    """The issue's flood (a job went from 112 to 940 MiB): 2 million 16-byte OK frames. The
    host keeps at most MAX_QUEUED of them, stops reading, and retires the car; without the
    bound they would cost the host some 600 MB of frame objects."""
    bundle = make_python_bundle(
        attack(
            """
        class Policy(Driver):
            def attack(self, obs):
                chunk = encode(Kind.OK) * 4096
                for _ in range(500):
                    write_all(FD_OUT, chunk)
        """
        )
    )
    policy = SandboxedPolicy(bundle, QUICK)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB
    detail = race_contained(policy, "invalid", within_s=120)
    grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert "flooding" in detail
    assert grown_mib < 64, f"the host grew by {grown_mib:.0f} MiB"
    assert len(policy._frames) <= MAX_QUEUED + 1  # the frames kept, plus the flood mark


def test_the_reader_keeps_at_most_max_queued_frames_then_marks_the_flood() -> None:
    """The bound itself, deterministically: 4096 valid frames in one read."""
    frames: deque[tuple[float, object]] = deque()
    flooded = threading.Event()
    more = _queue_frames(FrameDecoder(), encode(Kind.OK) * 4096, 0.0, frames, flooded)
    assert not more and flooded.is_set()
    items = [item for _, item in frames]
    assert len(items) == MAX_QUEUED + 1 and items[-1] is _FLOOD


def test_a_malformed_frame_shape_is_invalid_not_a_silent_timeout(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    """A zero-size ACTION frame of shape (0, 2**63): numpy refuses to build it (ValueError),
    which killed the host's reader thread, so the car was reported ``timeout`` 10 s later."""
    bundle = make_python_bundle(
        attack(
            """
        class Policy(Driver):
            def attack(self, obs):
                header = struct.pack("<2sBBBxHQ", b"SL", 5, 1, 2, self.steps + 1, 0)
                os.write(FD_OUT, header + struct.pack("<QQ", 0, 1 << 63))
                print("still printing after the bad frame", flush=True)
                time.sleep(30)
        """
        )
    )
    policy = SandboxedPolicy(bundle, FAST_BANK)
    detail = race_contained(policy, "invalid", within_s=60)
    assert "shape" in detail
    assert "still printing after the bad frame" in policy.output  # the reader lived on


def test_a_forged_huge_frame_header_is_refused_at_once(
    mode: str, make_python_bundle: MakeBundle
) -> None:
    """A header announcing a 1 TiB ACTION, then silence: refused from the header alone (the
    host reads replies with a 64 KiB cap), not after the 30 s bank."""
    bundle = make_python_bundle(
        attack(
            """
        class Policy(Driver):
            def attack(self, obs):
                os.write(FD_OUT, struct.pack("<2sBBBxHQ", b"SL", 5, 1, 1, self.steps + 1, 1 << 40))
                time.sleep(60)
        """
        )
    )
    detail = race_contained(SandboxedPolicy(bundle, FAST_BANK), "invalid", within_s=60)
    assert "exceeds" in detail


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
        wall_clock_s=20.0,
    )
    res = run_race_job(job)
    slow_car, honest = res.result["cars"]
    assert (slow_car["status"], slow_car["dnf_reason"]) == ("dnf", "timeout")
    assert "wall-clock limit" in slow_car["dnf_detail"]
    assert honest["status"] == "finished" and honest["dnf_detail"] is None
    assert res.duration_s < 20.0 + 60.0


@pytest.mark.slow
def test_15_mib_of_error_text_is_capped_in_result_replay_and_logs(tmp_path: Path) -> None:
    """The issue's 15 MiB error (an 11 MiB public replay): raised as an exception (and so
    printed as a traceback), and forged as one 15 MiB ERROR frame on the protocol pipe."""
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
                text = np.frombuffer(b"y" * (15 << 20), np.uint8)
                write_all(FD_OUT, encode(Kind.ERROR, text, self.steps + 1))
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
    assert (forger["status"], forger["dnf_reason"]) == ("dnf", "invalid")
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
