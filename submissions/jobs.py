"""Evaluation jobs: one headless race, described as plain data, run by a pure function.

A :class:`RaceJob` says who races (car ``i`` is ``entrants[i]``: a baseline by name, or a
bundle by path), where, how far and with which seed; it round-trips through JSON
(:meth:`RaceJob.to_dict` / :meth:`RaceJob.from_dict`) so the leaderboard's queue and Ray can
store and ship it. :func:`run_race_job` runs it anywhere (a process-pool worker, a Ray task,
the command line) and writes two files into ``out_dir``:

* ``<job_id>.replay.json.gz``: the replay log (:mod:`arena.replay`), the source of truth;
* ``<job_id>.viser``: the 3D replay (:mod:`submissions.viser_replay`), when ``record_viser``.

Baselines are our own code and run in-process. Every bundle runs in its own sandboxed worker
(:class:`submissions.remote.SandboxedPolicy`), each job extracting it afresh into a private
temporary folder, so a job depends on nothing but its description and the bundle files. The
race starts them all at once (they load in parallel), drives them two-phase, and retires a car
whose policy fails (to load, in time, or with a valid action) with the failure's reason
(``error`` / ``timeout`` / ``invalid``); the race goes on for the others.

This module imports nothing heavy at import time (the leaderboard's web process builds jobs);
the simulator, torch and the sandbox are imported inside :func:`run_race_job`.
"""

from __future__ import annotations

import re
import tempfile
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from submissions.bundle import EnvSpec, open_bundle
from submissions.errors import SubmissionError

if TYPE_CHECKING:
    from agents.policy import Policy
    from submissions.bundle import Bundle
    from submissions.remote import SandboxedPolicy
    from submissions.sandbox import SandboxLimits

BASELINE_NAMES = ("pursuit", "gap", "random")  # agents.baselines.BASELINES (tested equal)
JOB_ID = re.compile(r"[A-Za-z0-9_.-]{1,128}")
MIN_CARS, MAX_CARS = 2, 8


@dataclass(frozen=True)
class Entrant:
    """One car of a job.

    Attributes:
        name: shown in results and replays.
        source: a baseline name (``pursuit``, ``gap``, ``random``) or the path of a bundle
            zip or folder.
        submission_id: the leaderboard's id for the submission, if any (carried through).
    """

    name: str
    source: str
    submission_id: str | None = None

    @property
    def is_baseline(self) -> bool:
        """True for our own baselines (run in-process); False for bundles (sandboxed)."""
        return self.source in BASELINE_NAMES


@dataclass(frozen=True)
class RaceJob:
    """One race to run (see the module docstring).

    Attributes:
        job_id: names the output files; ``[A-Za-z0-9_.-]{1,128}``.
        entrants: 2–8 cars; car ``i`` is ``entrants[i]``.
        track: anything :func:`tracks.load_track` takes.
        out_dir: folder for the replay files (created).
        laps: race distance.
        seed: seeds the env and the policies.
        ranked: DeepRacer time penalties.
        limits: sandbox limits for the bundles (None: the sandbox's defaults).
        record_viser: also write the ``.viser`` 3D replay.
    """

    job_id: str
    entrants: tuple[Entrant, ...]
    track: str
    out_dir: str
    laps: int = 2
    seed: int = 0
    ranked: bool = True
    limits: SandboxLimits | None = None
    record_viser: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.job_id, str) or not JOB_ID.fullmatch(self.job_id):
            raise SubmissionError(f"job id {self.job_id!r} must match {JOB_ID.pattern}")
        if not MIN_CARS <= len(self.entrants) <= MAX_CARS:
            raise SubmissionError(
                f"a race job takes {MIN_CARS} to {MAX_CARS} entrants, not {len(self.entrants)}"
            )
        if self.laps < 1:
            raise SubmissionError(f"laps must be at least 1, not {self.laps}")

    @property
    def replay_path(self) -> Path:
        """Where the replay log is written."""
        return Path(self.out_dir) / f"{self.job_id}.replay.json.gz"

    @property
    def viser_path(self) -> Path:
        """Where the ``.viser`` replay is written."""
        return Path(self.out_dir) / f"{self.job_id}.viser"

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON."""
        doc = asdict(self)
        doc["entrants"] = [asdict(e) for e in self.entrants]
        doc["limits"] = asdict(self.limits) if self.limits is not None else None
        return doc

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> RaceJob:
        """The job from :meth:`to_dict`'s document.

        Raises:
            SubmissionError: a missing or malformed field.
        """
        try:
            limits = None
            if doc.get("limits") is not None:
                from submissions.sandbox import SandboxLimits  # noqa: PLC0415 - light, lazy

                limits = SandboxLimits(**doc["limits"])
            return cls(
                job_id=doc["job_id"],
                entrants=tuple(Entrant(**e) for e in doc["entrants"]),
                track=str(doc["track"]),
                out_dir=str(doc["out_dir"]),
                laps=int(doc.get("laps", 2)),
                seed=int(doc.get("seed", 0)),
                ranked=bool(doc.get("ranked", True)),
                limits=limits,
                record_viser=bool(doc.get("record_viser", True)),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise SubmissionError(f"malformed race job: {type(err).__name__}: {err}") from None


@dataclass
class JobResult:
    """What a job produced.

    Attributes:
        job_id: the job's id.
        result: :meth:`arena.race.RaceResult.to_dict` (empty when ``error`` is set).
        replay_path: the gzip JSON replay log ("" when ``error`` is set).
        viser_path: the ``.viser`` replay, or None.
        sandbox: ``"bwrap"`` or ``"seccomp"`` (the weakest mode any bundle ran under), or
            ``"none"`` when only baselines raced.
        duration_s: wall-clock seconds of the job.
        error: set by an executor when the job failed for good (raised, or its worker died
            more than ``max_retries`` times); one line.
        attempts: how many times an executor ran the job.
    """

    job_id: str
    result: dict[str, Any]
    replay_path: str
    viser_path: str | None
    sandbox: str
    duration_s: float
    error: str | None = None
    attempts: int = 1
    entrants: list[dict[str, Any]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """The job ran to a race result."""
        return self.error is None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON."""
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> JobResult:
        """The result from :meth:`to_dict`'s document."""
        try:
            return cls(**{k: doc[k] for k in cls.__dataclass_fields__ if k in doc})
        except TypeError as err:
            raise SubmissionError(f"malformed job result: {err}") from None

    @classmethod
    def failed(cls, job: RaceJob, error: str, attempts: int, duration_s: float) -> JobResult:
        """A result for a job that did not produce a race."""
        return cls(
            job_id=job.job_id,
            result={},
            replay_path="",
            viser_path=None,
            sandbox="none",
            duration_s=duration_s,
            error=error,
            attempts=attempts,
            entrants=[asdict(e) for e in job.entrants],
        )


def _sandboxed(bundle: Bundle, job: RaceJob, env: EnvSpec, name: str) -> SandboxedPolicy:
    from submissions.remote import SandboxedPolicy, make_env_spec  # noqa: PLC0415 - the sandbox

    spec = make_env_spec(lidar_rays=env.lidar_rays, k_opponents=env.k_opponents)
    policy = SandboxedPolicy(bundle, job.limits, spec)
    policy.name = name
    return policy


def _weakest_mode(modes: list[str]) -> str:
    if not modes:
        return "none"
    return "seccomp" if "seccomp" in modes else modes[0]


def run_race_job(job: RaceJob) -> JobResult:
    """Run one race job (see the module docstring); a pure function of ``job``.

    Raises:
        SubmissionError: a bundle is invalid (:class:`~submissions.errors.BundleError`), the
            sandbox cannot be set up, or the track does not load.
    """
    from agents.baselines import make_baseline  # noqa: PLC0415 - heavy: the simulator
    from arena.observations import ObservationLayout  # noqa: PLC0415
    from arena.race import run_race  # noqa: PLC0415

    start = time.perf_counter()
    env = EnvSpec.current()
    layout = ObservationLayout(env.lidar_rays, env.k_opponents)
    out_dir = Path(job.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    policies: list[Policy] = []
    sandboxed: list[SandboxedPolicy] = []
    with tempfile.TemporaryDirectory(prefix=f"slipstream-{job.job_id}-") as tmp:
        try:
            bundles: dict[str, Bundle] = {}
            for entrant in job.entrants:
                if entrant.is_baseline:
                    policy: Any = make_baseline(entrant.source, layout)
                    policy.name = entrant.name
                else:
                    if entrant.source not in bundles:
                        dest = Path(tmp) / f"bundle_{len(bundles)}"
                        bundles[entrant.source] = open_bundle(Path(entrant.source), dest, env=env)
                    policy = _sandboxed(bundles[entrant.source], job, env, entrant.name)
                    sandboxed.append(policy)
                policies.append(policy)
            result, replay = run_race(
                policies,
                track=job.track,
                laps=job.laps,
                seed=job.seed,
                ranked=job.ranked,
                record=True,
                env_kwargs={"lidar_rays": env.lidar_rays, "k_opponents": env.k_opponents},
            )
        finally:
            for policy in sandboxed:
                policy.close()
    assert replay is not None  # record=True
    replay.save(job.replay_path)
    viser_path = None
    if job.record_viser:
        from submissions.viser_replay import write_viser  # noqa: PLC0415 - imports viser

        viser_path = str(write_viser(replay, job.viser_path))
    return JobResult(
        job_id=job.job_id,
        result=result.to_dict(),
        replay_path=str(job.replay_path),
        viser_path=viser_path,
        sandbox=_weakest_mode([p.mode for p in sandboxed]),
        duration_s=round(time.perf_counter() - start, 3),
        entrants=[asdict(e) for e in job.entrants],
    )


__all__ = ["BASELINE_NAMES", "Entrant", "JobResult", "RaceJob", "run_race_job"]
