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

Every race has a wall-clock limit (:attr:`RaceJob.wall_clock_s`; by default
:func:`race_wall_clock_s`: ``3 ×`` the simulated race's time limit plus the sandbox's start-up
allowance). A sandboxed car still racing when it is reached is retired ``timeout``, so a
policy that answers just under its step deadline every step cannot stretch a race without
bound; baselines run in-process and finish the race at simulator speed.

What a policy can make the host keep is capped: each car's ``dnf_detail`` (the failure's
text, in the result and in the replay's ``dnf`` events) at 4 KiB
(:data:`~submissions.protocol.MAX_TEXT`), and its worker's stdout/stderr at the first 4 KiB
and the last 16 KiB (:attr:`JobResult.logs`).

This module imports nothing heavy at import time (the leaderboard's web process builds jobs);
the simulator, torch and the sandbox are imported inside :func:`run_race_job`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from submissions.bundle import DEFAULT_CAR, EnvSpec, car_names, open_bundle
from submissions.errors import BundleError, SubmissionError

if TYPE_CHECKING:
    from agents.policy import Policy
    from submissions.bundle import Bundle
    from submissions.remote import SandboxedPolicy, SandboxPool
    from submissions.sandbox import SandboxLimits

log = logging.getLogger(__name__)
BASELINE_NAMES = ("pursuit", "gap", "random")  # agents.baselines.BASELINES (tested equal)
JOB_ID = re.compile(r"[A-Za-z0-9_.-]{1,128}")
MIN_CARS, MAX_CARS = 2, 8
CONTROL_HZ = 20  # control steps per simulated second of an evaluation race
PROGRESS_EVERY_S = 1.0  # how often a running job rewrites its progress file, s
WALL_CLOCK_FACTOR = 3.0  # wall-clock seconds allowed per simulated second of the step limit
MAX_DETAIL = 4096  # bytes of a car's dnf_detail kept (= submissions.protocol.MAX_TEXT)


def race_wall_clock_s(max_steps: int, startup_s: float, control_hz: int = CONTROL_HZ) -> float:
    """The default wall-clock limit of a race, s: ``WALL_CLOCK_FACTOR`` × its simulated time
    limit (``max_steps / control_hz`` s) plus the start-up allowance ``startup_s``.

    >>> race_wall_clock_s(400, 60.0)
    120.0
    """
    return WALL_CLOCK_FACTOR * max_steps / control_hz + startup_s


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
        wall_clock_s: the race's wall-clock limit from the job's start, s (None: the
            default, :func:`race_wall_clock_s`).
        car: the car preset every car drives (:data:`arena.cars.CAR_PRESETS`); None: the
            one the bundles' manifests declare (they must agree), else ``"f1tenth"``. A
            bundle that declares another car than the job's is refused.
        solo: a time trial: one entrant alone is allowed (races take 2 to 8).
        robustness: not a race but a robustness run (:mod:`submissions.robustness`): the one
            entrant drives solo laps, one run per perturbation (names to values, as
            ``reset(options={"perturbation": ...})`` takes), in the same sandbox.
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
    wall_clock_s: float | None = None
    car: str | None = None
    solo: bool = False
    robustness: tuple[dict[str, float], ...] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.job_id, str) or not JOB_ID.fullmatch(self.job_id):
            raise SubmissionError(f"job id {self.job_id!r} must match {JOB_ID.pattern}")
        if self.robustness is not None and (len(self.entrants) != 1 or not self.robustness):
            raise SubmissionError("a robustness job takes one entrant and at least one point")
        fewest = 1 if self.solo or self.robustness is not None else MIN_CARS
        if not fewest <= len(self.entrants) <= MAX_CARS:
            raise SubmissionError(
                f"a race job takes {fewest} to {MAX_CARS} entrants, not {len(self.entrants)}"
            )
        if self.car is not None and self.car not in car_names():
            raise SubmissionError(f"unknown car {self.car!r}; one of {', '.join(car_names())}")
        if self.laps < 1:
            raise SubmissionError(f"laps must be at least 1, not {self.laps}")
        if self.wall_clock_s is not None and not self.wall_clock_s > 0:
            raise SubmissionError(f"wall_clock_s must be positive, not {self.wall_clock_s}")

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
            wall = doc.get("wall_clock_s")
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
                wall_clock_s=None if wall is None else float(wall),
                car=None if doc.get("car") is None else str(doc["car"]),
                solo=bool(doc.get("solo", False)),
                robustness=None
                if doc.get("robustness") is None
                else tuple(
                    {str(k): float(v) for k, v in point.items()} for point in doc["robustness"]
                ),
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
        sandbox: ``"bwrap"`` or ``"seccomp-weak"`` (the weakest mode any bundle ran under:
            :func:`submissions.sandbox.mode_label`), or ``"none"`` when only baselines raced.
        duration_s: wall-clock seconds of the job.
        error: set by an executor when the job failed for good (raised, or its worker died
            more than ``max_retries`` times); one line.
        attempts: how many times an executor ran the job.
        entrants: the job's entrants (``Entrant`` as dicts), car ``i`` first.
        logs: per sandboxed car (``"car_i"``, owner-only on the site): ``output``, its
            worker's stdout/stderr (the first 4 KiB, a ``[… N bytes not kept …]`` line, the
            last 16 KiB) and ``sandbox_mode`` (``"bwrap"`` or ``"seccomp-weak"``). Each car of
            ``result["cars"]`` also has ``dnf_detail``: its failure's text (≤ 4 KiB) or None.
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
    logs: dict[str, dict[str, str]] = field(default_factory=dict)

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


def extract_bundle(entrant: Entrant, env: EnvSpec, tmp: Path, bundles: dict[str, Bundle]) -> Bundle:
    """``entrant``'s bundle, extracted under ``tmp`` once per source (cached in ``bundles``).

    Raises:
        BundleError: the bundle is invalid.
    """
    if entrant.source not in bundles:
        n = len(bundles)
        while (dest := tmp / f"bundle_{n}").exists():  # a source extracted before, changed
            n += 1
        bundles[entrant.source] = open_bundle(Path(entrant.source), dest, env=env)
    return bundles[entrant.source]


def resolve_car(job: RaceJob, env: EnvSpec, tmp: Path, bundles: dict[str, Bundle]) -> str:
    """The car preset the job races (:func:`job_car`), from its bundles' manifests (extracted
    under ``tmp``, cached in ``bundles``): known before any sandbox starts, so each policy
    is told its car (the env spec's ``car``).

    Raises:
        BundleError: a bundle is invalid, declares another car than the job's, or the
            bundles disagree.
    """
    declared = [
        extract_bundle(e, env, tmp, bundles).manifest.car for e in job.entrants if not e.is_baseline
    ]
    return job_car(job, declared)


def open_entrant(
    entrant: Entrant,
    job: RaceJob,
    env: EnvSpec,
    tmp: Path,
    bundles: dict[str, Bundle],
    pool: SandboxPool | None,
    car: str = DEFAULT_CAR,
) -> tuple[Any, Bundle | None]:
    """The policy of one entrant: a baseline in-process, or a bundle (extracted under
    ``tmp`` once per source, cached in ``bundles``) in its sandbox (from ``pool`` if given),
    told that it drives ``car``.

    Returns:
        The policy (named ``entrant.name``) and its bundle (None for a baseline).

    Raises:
        BundleError: the bundle is invalid.
    """
    if entrant.is_baseline:
        from agents.baselines import make_baseline  # noqa: PLC0415 - heavy: the simulator
        from arena.observations import ObservationLayout  # noqa: PLC0415

        policy: Any = make_baseline(
            entrant.source, ObservationLayout(env.lidar_rays, env.k_opponents)
        )
        policy.name = entrant.name
        return policy, None
    bundle = extract_bundle(entrant, env, tmp, bundles)
    return _sandboxed(bundle, job, env, entrant.name, pool, car), bundle


def _sandboxed(
    bundle: Bundle, job: RaceJob, env: EnvSpec, name: str, pool: SandboxPool | None, car: str
) -> SandboxedPolicy:
    from submissions.remote import SandboxedPolicy, make_env_spec  # noqa: PLC0415 - the sandbox

    spec = make_env_spec(lidar_rays=env.lidar_rays, k_opponents=env.k_opponents, car=car)
    if pool is not None:
        policy = pool.policy(bundle, job.limits, spec)
    else:
        policy = SandboxedPolicy(bundle, job.limits, spec)
    policy.name = name
    return policy


def cap_details(result: dict[str, Any], events: list[dict[str, Any]]) -> None:
    """Cap every ``dnf`` event's detail; copy each car's first one into ``result``."""
    from submissions.protocol import cap_text  # noqa: PLC0415 - light, but keep imports lazy

    details: dict[str, str] = {}
    for event in events:
        if event.get("type") == "dnf" and "detail" in event:
            event["detail"] = cap_text(str(event["detail"]), MAX_DETAIL)
            details.setdefault(str(event.get("car")), event["detail"])
    for car in result.get("cars", []):
        car["dnf_detail"] = details.get(car.get("agent")) if car.get("status") == "dnf" else None


def weakest_mode(modes: list[str]) -> str:
    """What the result records: ``"none"``, ``"bwrap"`` or ``"seccomp-weak"`` (any fallback)."""
    from submissions.sandbox import mode_label  # noqa: PLC0415 - light, but keep imports lazy

    if not modes:
        return "none"
    return mode_label("seccomp" if "seccomp" in modes else modes[0])


def job_car(job: RaceJob, declared: Sequence[str]) -> str:
    """The car preset a job races: ``job.car``, else the one its bundles declare
    (``declared``, one per bundle), else ``"f1tenth"``.

    Raises:
        BundleError: a bundle declares another car than the job's, or the bundles disagree.
    """
    cars = sorted(set(declared))
    if job.car is not None:
        if any(c != job.car for c in cars):
            other = next(c for c in cars if c != job.car)
            raise BundleError(f"a bundle drives the {other!r} car; this race runs {job.car!r}")
        return job.car
    if len(cars) > 1:
        raise BundleError(f"the bundles declare different cars ({', '.join(cars)})")
    return cars[0] if cars else DEFAULT_CAR


def progress_path(job: RaceJob) -> Path:
    """The file a running job keeps its latest step number in (text), rewritten at most
    every :data:`PROGRESS_EVERY_S` s and removed when the job ends: a leaderboard worker
    renews its lease only while this changes."""
    return Path(job.out_dir) / f".{job.job_id}.progress"


def write_progress(path: Path, step: int) -> None:
    """Replace ``path``'s text with ``step`` (atomically; a failure is only logged)."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(str(step), encoding="utf-8")
        os.replace(tmp, path)
    except OSError:  # progress is advisory: a full disk must not fail the race
        log.warning("could not write the progress file %s", path)


def run_race_job(job: RaceJob) -> JobResult:
    """Run one race job (see the module docstring); a pure function of ``job``.

    Inside :func:`job_batch` (an executor's job process) the job runs in that batch, reusing
    the sandboxes earlier jobs of the batch left running for its bundles.

    Raises:
        SubmissionError: a bundle is invalid (:class:`~submissions.errors.BundleError`), the
            sandbox cannot be set up, or the track does not load.
    """
    if _BATCH is not None:
        return _BATCH.run(job)
    with tempfile.TemporaryDirectory(prefix=f"slipstream-{job.job_id}-") as tmp:
        return _run_job(job, Path(tmp), {}, None)


class JobBatch:
    """What jobs run one after another in one process share: each bundle's extraction and
    its started sandboxes (:class:`~submissions.remote.SandboxPool`), so a batch pays each
    sandbox's start-up once. Use it as a context manager: leaving it kills every sandbox.

    A bundle is extracted once per source file while the file is unchanged (size, mtime,
    inode); a changed file is extracted again and never meets the old one's sandboxes. Before
    each job the pool keeps only the idle sandboxes that job can use (as many per bundle as
    it races), so a batch holds at most one race's sandboxes between jobs.
    """

    def __init__(self) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="slipstream-batch-")
        self.folder = Path(self._tmp.name)
        self._pool: SandboxPool | None = None
        self.bundles: dict[str, Bundle] = {}
        self._stamps: dict[str, tuple[int, ...]] = {}

    @property
    def pool(self) -> SandboxPool:
        """The batch's sandboxes (made on first use: the sandbox's modules load then)."""
        if self._pool is None:
            from submissions.remote import SandboxPool  # noqa: PLC0415 - the sandbox

            self._pool = SandboxPool()
        return self._pool

    def run(self, job: RaceJob) -> JobResult:
        """Run ``job`` in this batch (as :func:`run_race_job` does alone).

        Raises:
            SubmissionError: as :func:`run_race_job`.
        """
        env = EnvSpec.current()
        needed: dict[str, int] = {}
        for entrant in job.entrants:
            if entrant.is_baseline:
                continue
            self._forget_if_changed(entrant.source)
            bundle = extract_bundle(entrant, env, self.folder, self.bundles)
            needed[str(bundle.root)] = needed.get(str(bundle.root), 0) + 1
        if self._pool is not None or needed:  # a baseline-only batch never loads the sandbox
            self.pool.retain(needed)
        return _run_job(job, self.folder, self.bundles, self._pool)

    def _forget_if_changed(self, source: str) -> None:
        try:
            st = os.stat(source)
            stamp: tuple[int, ...] = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
        except OSError:
            stamp = ()
        if self._stamps.get(source) != stamp:
            self.bundles.pop(source, None)  # extracted again, into a new folder
            self._stamps[source] = stamp

    def close(self) -> None:
        """Kill every sandbox of the batch and remove its folder; idempotent."""
        if self._pool is not None:
            self._pool.close()
        self._tmp.cleanup()

    def __enter__(self) -> JobBatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_BATCH: JobBatch | None = None  # the batch run_race_job runs in (set by job_batch)


def preload() -> None:
    """Import what every race needs — the simulator, the track geometry's scipy, the
    baselines, the sandbox's host side — so that a job process's first race does not pay
    for it (about 1.3 s on 2 vCPUs): :func:`job_batch` does it first."""
    import agents.baselines  # noqa: F401, PLC0415
    import arena.race  # noqa: F401, PLC0415
    import submissions.remote  # noqa: F401, PLC0415
    from tracks.geometry import preload as preload_geometry  # noqa: PLC0415

    preload_geometry()


@contextlib.contextmanager
def job_batch() -> Iterator[JobBatch]:
    """Run every :func:`run_race_job` call inside the block in one :class:`JobBatch`
    (what an executor's job process does around its jobs, after :func:`preload`, before
    it says it is ready); the batch is closed on leaving."""
    preload()
    global _BATCH  # noqa: PLW0603 - one batch per process, for the job function's calls
    with JobBatch() as batch:
        previous, _BATCH = _BATCH, batch
        try:
            yield batch
        finally:
            _BATCH = previous


def run_race_jobs(jobs: Sequence[RaceJob]) -> list[JobResult]:
    """Run ``jobs`` one after another in this process, in one :class:`JobBatch` (each
    bundle's sandboxes started once and kept between its races; all killed before it
    returns).

    A job that fails (a :class:`SubmissionError`) gets a :meth:`JobResult.failed` result;
    the others still run.
    """
    results: list[JobResult] = []
    with job_batch():
        for job in jobs:
            begun = time.perf_counter()
            try:
                results.append(run_race_job(job))
            except SubmissionError as err:
                line = f"{type(err).__name__}: {err}".splitlines()[0]
                results.append(JobResult.failed(job, line, 1, time.perf_counter() - begun))
    return results


def _run_job(
    job: RaceJob, tmp: Path, bundles: dict[str, Bundle], pool: SandboxPool | None
) -> JobResult:
    """:func:`run_race_job` with bundles extracted under ``tmp`` (cached by source in
    ``bundles``) and sandboxes from ``pool`` (None: fresh ones, killed after the race)."""
    if job.robustness is not None:
        from submissions.robustness import run_robustness_job  # noqa: PLC0415 - the simulator

        return run_robustness_job(job, tmp, bundles, pool)
    from arena.race import run_race  # noqa: PLC0415 - heavy: the simulator
    from submissions.sandbox import mode_label  # noqa: PLC0415

    start = time.perf_counter()
    started = time.monotonic()
    env = EnvSpec.current()
    out_dir = Path(job.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    policies: list[Policy] = []
    sandboxed: list[SandboxedPolicy] = []
    agents: dict[int, str] = {}  # id(sandboxed policy) → its car

    progress_file = progress_path(job)
    last_write = [0.0]

    def on_step(step: int, max_steps: int) -> None:
        if step == 1 and job.wall_clock_s is None:
            startup = sandboxed[0].limits.startup_s if sandboxed else 0.0
            deadline = started + race_wall_clock_s(max_steps, startup)
            for policy in sandboxed:
                policy.race_deadline = deadline
        now = time.monotonic()
        if now - last_write[0] >= PROGRESS_EVERY_S:
            last_write[0] = now
            write_progress(progress_file, step)

    logs: dict[str, dict[str, str]] = {}
    car = resolve_car(job, env, tmp, bundles)  # before any sandbox starts: each is told it
    try:
        for entrant in job.entrants:
            policy, bundle = open_entrant(entrant, job, env, tmp, bundles, pool, car)
            if bundle is not None:
                if job.wall_clock_s is not None:
                    policy.race_deadline = started + job.wall_clock_s
                agents[id(policy)] = f"car_{len(policies)}"
                sandboxed.append(policy)
            policies.append(policy)
        result, replay = run_race(
            policies,
            track=job.track,
            laps=job.laps,
            seed=job.seed,
            ranked=job.ranked,
            record=True,
            progress=on_step,
            env_kwargs={
                "lidar_rays": env.lidar_rays,
                "k_opponents": env.k_opponents,
                "control_hz": CONTROL_HZ,
                "car": car,
            },
        )
        logs = {
            agents[id(p)]: {"output": p.output, "sandbox_mode": mode_label(p.mode)}
            for p in sandboxed
        }
    finally:
        for policy in sandboxed:
            policy.close()
        progress_file.unlink(missing_ok=True)
    assert replay is not None  # record=True
    doc = result.to_dict()
    doc["car"] = car
    cap_details(doc, replay.events)
    replay.save(job.replay_path)
    viser_path = None
    if job.record_viser:
        from submissions.viser_replay import write_viser  # noqa: PLC0415 - imports viser

        viser_path = str(write_viser(replay, job.viser_path))
    return JobResult(
        job_id=job.job_id,
        result=doc,
        replay_path=str(job.replay_path),
        viser_path=viser_path,
        sandbox=weakest_mode([p.mode for p in sandboxed]),
        duration_s=round(time.perf_counter() - start, 3),
        entrants=[asdict(e) for e in job.entrants],
        logs=logs,
    )


__all__ = [
    "BASELINE_NAMES",
    "Entrant",
    "JobBatch",
    "JobResult",
    "RaceJob",
    "job_batch",
    "job_car",
    "progress_path",
    "race_wall_clock_s",
    "resolve_car",
    "run_race_job",
    "run_race_jobs",
]
