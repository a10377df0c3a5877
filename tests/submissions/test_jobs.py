"""Race jobs: plain data that round-trips through JSON, and a job function that races
baselines in-process and bundles in their sandboxes, writing the replay files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agents.baselines import BASELINES
from arena.replay import ReplayLog
from arena.version import ENV_VERSION
from submissions.bundle import Manifest, make_bundle
from submissions.errors import BundleError, SubmissionError
from submissions.jobs import BASELINE_NAMES, Entrant, JobResult, RaceJob, run_race_job
from submissions.sandbox import SandboxLimits
from submissions.viser_replay import read_viser

CHECKPOINT = Path(__file__).parents[2] / "agents" / "data" / "ppo_racer.zip"


def checkpoint_bundle(path: Path) -> Path:
    """Our shipped PPO checkpoint wrapped in a bundle."""
    m = Manifest(
        name="ppo_racer", author="slipstream", format="slipstream", entry="policy.zip",
        env_version=ENV_VERSION, env={"lidar_rays": 64, "k_opponents": 3},
    )  # fmt: skip
    return make_bundle(path, m, {"policy.zip": CHECKPOINT})


def python_bundle(path: Path, source: str, name: str = "script") -> Path:
    m = Manifest(name=name, author="t", format="python", entry="agent.py", env_version=ENV_VERSION)
    return make_bundle(path, m, {"agent.py": source.encode()})


def test_baseline_names_match_the_agents_package() -> None:
    assert set(BASELINE_NAMES) == set(BASELINES)


def test_job_round_trips_through_json(tmp_path: Path) -> None:
    job = RaceJob(
        "job-1",
        (Entrant("a", "pursuit", "sub-7"), Entrant("b", str(tmp_path / "x.zip"))),
        "oval",
        str(tmp_path),
        laps=3,
        seed=5,
        ranked=False,
        limits=SandboxLimits(step_deadline_s=0.5),
        record_viser=False,
        wall_clock_s=90.0,
    )
    again = RaceJob.from_dict(json.loads(json.dumps(job.to_dict())))
    assert again == job
    assert again.entrants[0].submission_id == "sub-7"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"job_id": "../escape"}, "job id"),
        ({"entrants": (Entrant("a", "gap"),)}, "2 to 8 entrants"),
        ({"entrants": tuple(Entrant(f"c{i}", "gap") for i in range(9))}, "2 to 8 entrants"),
        ({"laps": 0}, "laps must be at least 1"),
        ({"wall_clock_s": 0.0}, "wall_clock_s must be positive"),
    ],
)
def test_bad_jobs(tmp_path: Path, kwargs: dict[str, object], match: str) -> None:
    base: dict[str, object] = {
        "job_id": "j",
        "entrants": (Entrant("a", "gap"), Entrant("b", "pursuit")),
        "track": "oval",
        "out_dir": str(tmp_path),
    }
    with pytest.raises(SubmissionError, match=match):
        RaceJob(**(base | kwargs))  # type: ignore[arg-type]
    with pytest.raises(SubmissionError, match="malformed race job"):
        RaceJob.from_dict({"job_id": "j"})


def test_baseline_job_writes_result_and_replays(tmp_path: Path) -> None:
    job = RaceJob(
        "base", (Entrant("fast", "pursuit"), Entrant("wide", "gap")), "oval", str(tmp_path), laps=1
    )
    res = run_race_job(job)
    assert res.ok and res.sandbox == "none" and res.job_id == "base"
    assert [c["name"] for c in res.result["cars"]] == ["fast", "wide"]
    assert all(c["status"] == "finished" for c in res.result["cars"])
    replay = ReplayLog.load(Path(res.replay_path))
    assert res.replay_path == str(tmp_path / "base.replay.json.gz")
    assert [c["name"] for c in replay.cars] == ["fast", "wide"]
    assert res.viser_path == str(tmp_path / "base.viser")
    assert read_viser(Path(res.viser_path))["durationSeconds"] > 0
    assert JobResult.from_dict(json.loads(json.dumps(res.to_dict()))) == res


def test_invalid_bundle_fails_the_job(tmp_path: Path) -> None:
    bad = tmp_path / "bad.zip"
    bad.write_bytes(b"not a zip")
    job = RaceJob("bad", (Entrant("x", str(bad)), Entrant("g", "gap")), "oval", str(tmp_path))
    with pytest.raises(BundleError, match="not a valid zip"):
        run_race_job(job)
    assert not list(tmp_path.glob("bad.*.gz"))


@pytest.mark.slow
def test_sandboxed_checkpoint_bundle_races(tmp_path: Path) -> None:
    """Our checkpoint, wrapped in a bundle, drives from inside the sandbox and finishes."""
    bundle = checkpoint_bundle(tmp_path / "ppo.zip")
    job = RaceJob(
        "sbx",
        (Entrant("ppo", str(bundle)), Entrant("pursuit", "pursuit"), Entrant("ppo2", str(bundle))),
        "oval",
        str(tmp_path / "out"),
        laps=1,
        record_viser=False,
    )
    res = run_race_job(job)
    assert res.sandbox in ("bwrap", "seccomp-weak")
    cars = {c["name"]: c for c in res.result["cars"]}
    assert cars["ppo"]["status"] == cars["ppo2"]["status"] == "finished"
    assert cars["pursuit"]["status"] == "finished"
    assert res.viser_path is None and Path(res.replay_path).exists()


@pytest.mark.slow
def test_failing_bundle_retires_only_its_car(tmp_path: Path) -> None:
    """A policy that crashes while loading gets dnf (error); the others still finish."""
    crash = python_bundle(tmp_path / "crash.zip", "raise RuntimeError('broken on purpose')\n")
    job = RaceJob(
        "crash",
        (Entrant("crash", str(crash)), Entrant("gap", "gap")),
        "oval",
        str(tmp_path / "out"),
        laps=1,
        record_viser=False,
    )
    cars = {c["name"]: c for c in run_race_job(job).result["cars"]}
    assert cars["crash"]["status"] == "dnf" and cars["crash"]["dnf_reason"] == "error"
    assert cars["gap"]["status"] == "finished"


COUNTING = """
import numpy as np


class Policy:
    resets = 0  # per process: a reused sandbox keeps counting

    def __init__(self, env_spec):
        self.car = env_spec["car"]

    def reset(self, seed):
        Policy.resets += 1
        print(f"reset number {Policy.resets} in the {self.car} car", flush=True)

    def act(self, obs):
        return np.array([0.0, 0.2], np.float32)
"""


@pytest.mark.slow
def test_the_executor_reuses_a_bundles_sandbox_between_jobs_and_leaves_nothing(
    tmp_path: Path,
) -> None:
    """One job process (the real path of ``evaluate`` and the leaderboard worker): the
    second job of the same bundle races in the first one's sandbox (its policy process
    counts a second reset) and is handed over before the job queued ahead of it that races
    another bundle; each policy is told its car; a job's logs hold its own race's output
    only; no sandbox or job folder of this process remains afterwards."""
    import os
    import tempfile

    from submissions.executors import LocalExecutor

    bundle = python_bundle(tmp_path / "count.zip", COUNTING, "counter")
    m = Manifest(
        name="dr", author="t", format="python", entry="agent.py", env_version=ENV_VERSION,
        car="deepracer",
    )  # fmt: skip
    deepracer = make_bundle(tmp_path / "dr.zip", m, {"agent.py": COUNTING.encode()})
    jobs = [
        RaceJob(f"batch{i}", (Entrant("counter", str(b)),), "oval", str(tmp_path / "out"),
                laps=1, seed=i, record_viser=False, solo=True)
        for i, b in enumerate((bundle, deepracer, bundle))
    ]  # fmt: skip
    with LocalExecutor(workers=1, keep_warm_s=30.0) as executor:
        results = list(executor.run(jobs))
        assert executor.warm == 1  # kept, with its sandbox, for a next run
    assert [r.job_id for r in results] == ["batch0", "batch2", "batch1"]
    assert all(r.ok for r in results)
    out = [r.logs["car_0"]["output"] for r in results]
    assert "reset number 1 in the f1tenth car" in out[0]
    assert "reset number 2 in the f1tenth car" in out[1]  # the same sandbox, a later job
    assert "reset number 1" not in out[1]
    assert "reset number 1 in the deepracer car" in out[2]
    assert results[2].result["car"] == "deepracer"
    assert results[1].logs["car_0"]["sandbox_mode"] in ("bwrap", "seccomp-weak")
    left = list(Path(tempfile.gettempdir()).glob(f"slipstream-*-{os.getpid()}-*"))
    assert left == []


def test_a_batch_reports_a_bad_bundle_as_a_failed_job_and_runs_the_rest(tmp_path: Path) -> None:
    from submissions.jobs import run_race_jobs

    bad = tmp_path / "bad.zip"
    bad.write_bytes(b"not a zip")
    jobs = [
        RaceJob("bad", (Entrant("x", str(bad)), Entrant("g", "gap")), "oval", str(tmp_path)),
        RaceJob(
            "good",
            (Entrant("a", "pursuit"), Entrant("b", "gap")),
            "oval",
            str(tmp_path),
            laps=1,
            record_viser=False,
        ),
    ]
    bad_result, good_result = run_race_jobs(jobs)
    assert not bad_result.ok and "not a valid zip" in (bad_result.error or "")
    assert good_result.ok and good_result.sandbox == "none" and good_result.logs == {}


# ---- slipstream evaluate --------------------------------------------------------------------


def test_evaluate_plans_validation_then_rotating_races(tmp_path: Path) -> None:
    import argparse

    from submissions.cli import build_jobs

    args = argparse.Namespace(
        against="pursuit,gap", races=4, tracks="oval,bean", laps=1, seed=3, no_viser=True
    )
    jobs = build_jobs(args, tmp_path / "b.zip", "mine", tmp_path / "out")
    validation, *races = jobs
    assert validation.job_id == "mine-validation"
    assert {e.source for e in validation.entrants} == {str(tmp_path / "b.zip")}
    assert len(validation.entrants) == 3
    assert [r.track for r in races] == ["oval", "bean", "oval", "bean"]
    assert [r.seed for r in races] == [3, 4, 5, 6]
    slots = [[e.name for e in r.entrants].index("mine") for r in races]
    assert slots == [0, 1, 2, 0]  # the bundle starts from every grid slot in turn


@pytest.mark.slow
def test_evaluate_command_end_to_end(tmp_path: Path) -> None:
    from leaderboard.cli import main

    bundle = checkpoint_bundle(tmp_path / "ppo.zip")
    out, report = tmp_path / "out", tmp_path / "report.json"
    argv = ["evaluate", str(bundle), "--against", "pursuit", "--races", "1", "--laps", "1"]
    assert main([*argv, "--out", str(out), "--json", str(report)]) == 0
    doc = json.loads(report.read_text())
    assert doc["manifest"]["name"] == "ppo_racer"
    assert doc["validation"]["error"] is None
    (race,) = doc["races"]
    assert {c["name"] for c in race["result"]["cars"]} == {"ppo_racer", "pursuit#1"}
    assert sorted(p.name for p in out.iterdir()) == [
        "ppo_racer-race001.replay.json.gz",
        "ppo_racer-race001.viser",
        "ppo_racer-validation.replay.json.gz",
        "ppo_racer-validation.viser",
    ]


@pytest.mark.slow
def test_evaluate_stops_when_validation_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from leaderboard.cli import main

    bundle = python_bundle(tmp_path / "crash.zip", "raise RuntimeError('broken')\n", "crashy")
    argv = ["evaluate", str(bundle), "--races", "3", "--laps", "1", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("slipstream: error: validation race failed: crashy#0: error")
    assert not list((tmp_path / "o").glob("*race001*"))


@pytest.mark.parametrize(
    ("name", "raw"), [("SLIPSTREAM_SPIN_US", "fast"), ("SLIPSTREAM_CPU_LATENCY_US", "1.5")]
)
def test_evaluate_refuses_a_malformed_scheduling_setting_in_one_line(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    name: str,
    raw: str,
) -> None:
    # Before, a typo here started every sandbox of the validation race in vain and blamed
    # the bundle: "validation race failed: …#0: error".
    from leaderboard.cli import main

    monkeypatch.setenv(name, raw)
    bundle = python_bundle(tmp_path / "ok.zip", "", "fine")
    out = tmp_path / "o"
    assert main(["evaluate", str(bundle), "--races", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"slipstream: error: {name} must be") and repr(raw) in err[-1]
    assert not out.exists()


def test_evaluate_refuses_a_bad_bundle(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from leaderboard.cli import main

    (tmp_path / "b.zip").write_bytes(b"junk")
    assert main(["evaluate", str(tmp_path / "b.zip")]) == 2
    assert "not a valid zip archive" in capsys.readouterr().err
