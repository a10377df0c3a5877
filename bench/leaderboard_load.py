"""Leaderboard load: latency and throughput of every page and API endpoint on a large database.

1. Fills a fresh database — SQLite (``--db sqlite``, the default), a throwaway PostgreSQL
   server (``--db postgresql``: :func:`leaderboard.localpg.throwaway_server`, the one the tests
   use) or any ``--db URL`` — with ``--submissions`` submissions (10,000) and ``--races``
   finished ranked races (100,000) of 2–8 cars, with their entries, rating history, track
   records, queue rows and a few hundred validation races — bulk ``INSERT``s, no races are
   simulated.
2. Starts ``slipstream serve --web-workers N`` on 127.0.0.1 (N: ``--web-workers``, default
   ``slipstream serve``'s own default; a list such as ``1,2`` starts one server per count,
   side by side, and measures every endpoint on each in turn, so the counts are compared in
   the same minutes of a shared machine).
3. For each GET endpoint of the app (every API operation and every page; the script checks
   that none is missing), runs one client, then ``--concurrency`` clients, in a closed loop
   for ``--seconds`` each; ids are drawn at random, authenticated endpoints use a token.
4. Prints, per endpoint (and worker count), the single-client p50 and the
   ``--concurrency``-client p50/p99 latency (ms) and requests/s, whether it meets issue 13's
   goals (single-client p50 ≤ 20 ms, 8-client p99 ≤ 150 ms), the machine and its load average
   (before, after, and the range seen between endpoints), and ``--json``.

The server runs with its rate limits off (``SLIPSTREAM_RATE_LIMITS=false``): a load generator
on one address would otherwise measure 429s.

The load generator runs on the same machine as the server (loopback), so on a 2-core box the
two compete for the CPUs; the figures are a floor.

Usage::

    python bench/leaderboard_load.py [--db sqlite|postgresql|URL] [--submissions 10000]
        [--races 100000] [--seconds 5] [--concurrency 8] [--web-workers N[,M...]]
        [--keep DIR] [--only TEXT] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import platform
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
from fastapi.routing import APIRoute
from sqlalchemy import Engine, func, insert, select
from sqlalchemy.orm import Session

from leaderboard import auth, localpg, tournaments
from leaderboard.db import make_engine
from leaderboard.migrations import upgrade
from leaderboard.models import (
    Job,
    Race,
    RaceEntry,
    RatingHistory,
    Submission,
    SubmissionVersion,
    TrackRecord,
    User,
)
from leaderboard.ratings import ordinal
from leaderboard.settings import Settings

TRACKS = ["oval", "bean", "chicanes", "hairpins", "monza", "speedway", "spielberg", "technical"]
CHUNK = 20_000


@dataclass
class Figures:
    """Latency and throughput of one endpoint."""

    endpoint: str
    requests: int
    errors: int
    p50_ms: float
    p99_ms: float
    rps: float
    single_p50_ms: float = 0.0
    web_workers: int = 1


def _chunks(rows: list[dict[str, Any]]) -> Any:
    for i in range(0, len(rows), CHUNK):
        yield rows[i : i + CHUNK]


def _bulk(engine: Engine, model: Any, rows: list[dict[str, Any]]) -> None:
    with engine.begin() as conn:
        for part in _chunks(rows):
            conn.execute(insert(model), part)


def fill(engine: Engine, n_subs: int, n_races: int, seed: int = 0) -> dict[str, float]:
    """Bulk-insert the synthetic leaderboard; seconds per table."""
    rng = random.Random(seed)
    t0 = datetime(2026, 1, 1)
    times: dict[str, float] = {}

    def timed(name: str, model: Any, rows: list[dict[str, Any]]) -> None:
        start = time.perf_counter()
        _bulk(engine, model, rows)
        times[name] = round(time.perf_counter() - start, 2)

    n_users = max(1, n_subs // 10)
    timed(
        "users",
        User,
        [
            {"id": i + 1, "name": f"user{i}", "is_admin": False, "created_at": t0}
            for i in range(n_users)
        ],
    )
    subs = []
    for i in range(n_subs):
        mu, sigma = rng.gauss(25, 4), rng.uniform(1.5, 8.3)
        played = rng.randint(0, 60)
        subs.append(
            {
                "id": i + 1, "user_id": i % n_users + 1, "name": f"racer{i}", "description": "",
                "status": "active", "active_version_id": None, "mu": mu, "sigma": sigma,
                "ordinal": ordinal(mu, sigma), "races": played, "wins": rng.randint(0, played),
                "created_at": t0, "updated_at": t0,
            }
        )  # fmt: skip
    timed("submissions", Submission, subs)
    versions = [
        {
            "id": i + 1, "submission_id": i + 1, "version": 1, "source": f"/bundles/{i + 1}/v1.zip",
            "format": "python", "manifest": {"name": f"racer{i}"}, "size_bytes": 12345,
            "sha256": f"{i:064x}", "status": "validated", "error": None, "created_at": t0,
        }
        for i in range(n_subs)
    ]  # fmt: skip
    timed("submission_versions", SubmissionVersion, versions)
    with engine.begin() as conn:
        conn.execute(Submission.__table__.update().values(active_version_id=Submission.id))  # type: ignore[attr-defined]
    races, entries, history, jobs = [], [], [], []
    records: dict[tuple[str, int], dict[str, Any]] = {}
    for r in range(1, n_races + 1):
        track = TRACKS[r % len(TRACKS)]
        when = t0 + timedelta(seconds=30 * r)
        cars = rng.sample(range(1, n_subs + 1), rng.randint(2, min(8, n_subs)))
        races.append(
            {
                "id": r, "kind": "ranked", "status": "finished", "track": track, "seed": r,
                "laps": 2, "penalties": True, "created_at": when, "started_at": when,
                "finished_at": when, "duration_s": 9.5, "sandbox": "bwrap", "result": None,
                "replay_path": f"{r}.replay.json.gz", "viser_path": f"{r}.viser", "error": None,
            }
        )  # fmt: skip
        jobs.append(
            {"race_id": r, "status": "done", "priority": 10, "attempts": 1, "max_attempts": 3,
             "created_at": when, "updated_at": when}
        )  # fmt: skip
        for pos, sub in enumerate(cars, start=1):
            laps = [20 + pos + rng.random(), 20 + pos + rng.random()]
            mu = rng.gauss(25, 4)
            entries.append(
                {
                    "race_id": r, "car": pos - 1, "submission_id": sub, "version_id": sub,
                    "name": f"racer{sub - 1}:v1", "source": "x", "position": pos, "rank": pos,
                    "status": "finished", "dnf_reason": None, "laps_completed": 2,
                    "best_lap": min(laps), "total_time": sum(laps), "lap_times": laps,
                    "collisions": 0, "at_fault_collisions": 0, "off_track": 0,
                    "mu_before": mu, "sigma_before": 5.0, "mu_after": mu + 0.1,
                    "sigma_after": 4.9,
                }
            )  # fmt: skip
            history.append(
                {"submission_id": sub, "race_id": r, "mu": mu, "sigma": 4.9,
                 "ordinal": ordinal(mu, 4.9), "created_at": when}
            )  # fmt: skip
            key = (track, sub)
            if key not in records or records[key]["best_lap"] > min(laps):
                records[key] = {"track": track, "submission_id": sub, "version_id": sub,
                                "race_id": r, "best_lap": min(laps), "set_at": when}  # fmt: skip
    timed("races", Race, races)
    timed("jobs", Job, jobs)
    timed("race_entries", RaceEntry, entries)
    timed("rating_history", RatingHistory, history)
    timed("track_records", TrackRecord, list(records.values()))
    return times


def sync_sequences(engine: Engine) -> None:
    """PostgreSQL: move the id sequences past the ids the bulk inserts chose themselves."""
    if engine.dialect.name != "postgresql":
        return
    with engine.begin() as conn:
        for table in ("users", "submissions", "submission_versions", "races"):
            conn.exec_driver_sql(
                f"SELECT setval(pg_get_serial_sequence('{table}', 'id'), "
                f"(SELECT MAX(id) FROM {table}))"
            )


GOAL_SINGLE_P50_MS = 20.0  # issue 13: one client at a time
GOAL_LOADED_P99_MS = 150.0  # issue 13: with 8 clients
VALIDATION_RACES = 500  # unrated races mixed in (pages must not count them as ranked)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def add_validation_races(engine: Engine, n_races: int, n_subs: int, seed: int = 1) -> None:
    """A few finished validation races (one submission against a baseline) after the rest."""
    rng = random.Random(seed)
    t0 = datetime(2026, 6, 1)
    with engine.connect() as conn:
        first = (conn.execute(select(func.max(Race.id))).scalar() or 0) + 1
    races, entries = [], []
    for r in range(first, first + n_races):
        sub = rng.randint(1, n_subs)
        races.append(
            {"id": r, "kind": "validation", "status": "finished", "track": "oval", "seed": r,
             "laps": 2, "penalties": False, "created_at": t0, "started_at": t0,
             "finished_at": t0, "duration_s": 9.0, "sandbox": "bwrap", "result": None,
             "replay_path": None, "viser_path": None, "error": None}
        )  # fmt: skip
        for car, (sid, name) in enumerate([(sub, f"racer{sub - 1}:v1"), (None, "pursuit")]):
            entries.append(
                {"race_id": r, "car": car, "submission_id": sid, "version_id": sid,
                 "name": name, "source": "x", "position": car + 1, "rank": car + 1,
                 "status": "finished", "laps_completed": 2, "best_lap": 21.0,
                 "total_time": 42.0, "lap_times": [21.0, 21.0], "collisions": 0,
                 "at_fault_collisions": 0, "off_track": 0}
            )  # fmt: skip
    _bulk(engine, Race, races)
    _bulk(engine, RaceEntry, entries)


def add_tournaments(engine: Engine, n: int = 3) -> None:
    """A few round-robin tournaments of the ladder's top 16 (heats planned, not raced)."""
    with Session(engine) as session:
        settings = Settings(data_dir=Path(tempfile.gettempdir()), tracks=TRACKS)
        for i in range(n):
            tournaments.create_tournament(
                session, settings, name=f"cup {i}", top=16, tracks=TRACKS[:2], seeds=(0, 1)
            )
        session.commit()


def add_user(engine: Engine, name: str = "loadtester") -> str:
    """A user with an API token (for the authenticated endpoints); the token."""
    with Session(engine) as session:
        _, token = auth.create_user(session, name=name)
        session.commit()
    return token


def start_server(url: str, data_dir: Path, port: int, web_workers: int) -> subprocess.Popen[bytes]:
    """``slipstream serve`` in a subprocess; returns once it answers /api/health."""
    cmd = [sys.executable, "-m", "leaderboard.cli", "serve", "--port", str(port),
           "--db", url, "--data-dir", str(data_dir), "--web-workers", str(web_workers)]  # fmt: skip
    env = {**os.environ, "SLIPSTREAM_RATE_LIMITS": "false"}
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, env=env)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=2).status_code == 200:
                # One process answered; the others started with it and finish within moments
                # (nothing tells from outside which process answered).
                time.sleep(3.0 if web_workers > 1 else 0.0)
                return proc
        except httpx.HTTPError:
            pass
        if proc.poll() is not None:
            raise RuntimeError("the server exited during start-up")
        time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGTERM)
    raise RuntimeError("the server did not start within 60 s")


async def _load(
    base: str,
    endpoint: str,
    paths: list[str],
    seconds: float,
    concurrency: int,
    headers: dict[str, str],
) -> Figures:
    latencies: list[float] = []
    errors = 0
    rng = random.Random(1)
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    async with httpx.AsyncClient(
        base_url=base, limits=limits, timeout=30, headers=headers
    ) as client:
        stop_at = time.perf_counter() + seconds

        async def one() -> None:
            nonlocal errors
            while not latencies or time.perf_counter() < stop_at:
                path = rng.choice(paths)
                start = time.perf_counter()
                try:
                    r = await client.get(path)
                    ok = r.status_code == 200
                except httpx.HTTPError:
                    ok = False
                latencies.append(time.perf_counter() - start)
                errors += not ok

        # The client's own garbage collections would stall every request in flight and be
        # counted as the server's latency: off while timing, as timeit does.
        gc.collect()
        gc.disable()
        try:
            start = time.perf_counter()
            await asyncio.gather(*(one() for _ in range(concurrency)))
            elapsed = time.perf_counter() - start
        finally:
            gc.enable()
    qs = statistics.quantiles(latencies, n=100) if len(latencies) > 1 else latencies * 99
    return Figures(
        endpoint=endpoint,
        requests=len(latencies),
        errors=errors,
        p50_ms=round(qs[49] * 1000, 2),
        p99_ms=round(qs[98] * 1000, 2),
        rps=round(len(latencies) / elapsed, 1),
    )


def get_routes() -> set[str]:
    """Every GET route of the app: API operations and pages (path templates)."""
    from leaderboard.app import create_app  # a throwaway app, only to list its routes
    from leaderboard.web.pages import web_router
    from leaderboard.web.session import session_router

    with tempfile.TemporaryDirectory() as tmp:
        app = create_app(Settings(data_dir=Path(tmp)))
        api = {path for path, ops in app.openapi()["paths"].items() if "get" in ops}
    pages = {
        r.path
        for router in (web_router, session_router)
        for r in router.routes
        if isinstance(r, APIRoute) and "GET" in (r.methods or ())
    }
    return api | pages | {"/openapi.json", "/docs", "/redoc"}


def endpoint_groups(n_subs: int, n_races: int, token: str) -> list[tuple[str, list[str], bool]]:
    """``(route, paths drawn from, authenticated)`` for every GET route of the app."""
    rng = random.Random(0)
    races = [rng.randint(1, n_races) for _ in range(200)]
    subs = [rng.randint(1, n_subs) for _ in range(200)]
    users = [f"user{rng.randint(0, max(0, n_subs // 10 - 1))}" for _ in range(200)]
    track = TRACKS[4]
    return [
        ("/", ["/"], False),
        ("/ (page 20)", [f"/?page={max(1, n_subs // 500)}"], False),
        ("/api/leaderboard", ["/api/leaderboard"], False),
        ("/api/leaderboard (page 20)", [f"/api/leaderboard?page={max(1, n_subs // 500)}"], False),
        ("/races", ["/races"], False),
        ("/races?track=", [f"/races?track={track}"], False),
        ("/api/races", ["/api/races"], False),
        ("/api/races?submission=", [f"/api/races?submission={s}" for s in subs], False),
        ("/races/{race_id}", [f"/races/{r}" for r in races], False),
        ("/api/races/{race_id}", [f"/api/races/{r}" for r in races], False),
        ("/api/races/{race_id}/logs", [f"/api/races/{r}/logs" for r in races], True),
        ("/submissions/{submission_id}", [f"/submissions/{s}" for s in subs], False),
        ("/api/submissions", ["/api/submissions"], False),
        ("/api/submissions/{submission_id}", [f"/api/submissions/{s}" for s in subs], False),
        (
            "/api/submissions/{submission_id}/races",
            [f"/api/submissions/{s}/races" for s in subs],
            False,
        ),
        ("/tracks", ["/tracks"], False),
        ("/api/tracks", ["/api/tracks"], False),
        ("/tracks/{name}", [f"/tracks/{track}"], False),
        ("/api/tracks/{name}", [f"/api/tracks/{track}"], False),
        ("/tracks/{name}/plot.png", [f"/tracks/{track}/plot.png"], False),
        ("/users/{name}", [f"/users/{u}" for u in users], False),
        ("/api/users/{name}", [f"/api/users/{u}" for u in users], False),
        ("/api/users/me", ["/api/users/me"], True),
        ("/api/tokens", ["/api/tokens"], True),
        ("/tournaments", ["/tournaments"], False),
        ("/api/tournaments", ["/api/tournaments"], False),
        ("/tournaments/{tournament_id}", ["/tournaments/1", "/tournaments/2"], False),
        ("/api/tournaments/{tournament_id}", ["/api/tournaments/1", "/api/tournaments/2"], False),
        ("/api/health", ["/api/health"], False),
        ("/api/jobs", ["/api/jobs"], False),
        ("/compete", ["/compete"], False),
        ("/signin", ["/signin"], False),
        ("/docs", ["/docs"], False),
        ("/redoc", ["/redoc"], False),
        ("/openapi.json", ["/openapi.json"], False),
    ]


def web_worker_counts(option: str | None) -> list[int]:
    """The ``--web-workers`` option as a list of process counts (default: serve's default).

    Raises:
        SystemExit: not a comma list of positive integers.
    """
    from leaderboard.serving import default_web_workers

    if option is None:
        return [default_web_workers()]
    try:
        counts = [int(part) for part in option.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise SystemExit(f"--web-workers: a comma list of counts >= 1, not {option!r}")
    return counts


def _route_of(label: str) -> str:
    return label.split(" ", 1)[0].split("?", 1)[0]


def _database(choice: str | None, data_dir: Path, stack: ExitStack) -> str:
    """The database URL to fill: SQLite in ``data_dir``, a throwaway PostgreSQL, or a URL."""
    if choice in (None, "sqlite"):
        return f"sqlite:///{(data_dir / 'leaderboard.db').resolve()}"
    if choice in ("postgresql", "postgres", "pg"):
        # Settings a small dedicated server would use: the database fits in memory.
        server = stack.enter_context(
            localpg.throwaway_server("shared_buffers=512MB", "work_mem=16MB", "max_connections=100")
        )
        return localpg.create_database(server, "slipstream_load")
    return choice


def main(argv: list[str] | None = None) -> int:
    """Fill, serve, load, report."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--submissions", type=int, default=10_000)
    ap.add_argument("--races", type=int, default=100_000)
    ap.add_argument("--seconds", type=float, default=5.0, help="load duration per endpoint")
    ap.add_argument("--concurrency", type=int, default=8, help="clients in a closed loop")
    ap.add_argument(
        "--web-workers",
        default=None,
        help="server processes (slipstream serve --web-workers); a comma list compares counts "
        "side by side (default: slipstream serve's default)",
    )
    ap.add_argument(
        "--db",
        default="sqlite",
        help="sqlite (default), postgresql (a throwaway local server) or a database URL",
    )
    ap.add_argument("--keep", type=Path, default=None, help="data folder to keep (and reuse)")
    ap.add_argument("--only", default=None, help="measure only routes containing this text")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)

    missing = get_routes() - {_route_of(label) for label, _, _ in endpoint_groups(1, 1, "")}
    if missing:
        print(f"warning: GET routes not measured: {sorted(missing)}", file=sys.stderr)
    with ExitStack() as stack:
        data_dir = args.keep or Path(tempfile.mkdtemp(prefix="slipstream-load-"))
        data_dir.mkdir(parents=True, exist_ok=True)
        url = _database(args.db, data_dir, stack)
        engine = make_engine(url)
        upgrade(url, engine=engine)
        with engine.connect() as conn:
            have = conn.execute(select(func.count(Race.id))).scalar() or 0
        fill_s: dict[str, float] = {}
        if have == 0:
            start = time.perf_counter()
            fill_s = fill(engine, args.submissions, args.races)
            add_validation_races(engine, VALIDATION_RACES, args.submissions)
            sync_sequences(engine)
            add_tournaments(engine)
            with engine.begin() as conn:  # planner statistics of the whole fill
                conn.exec_driver_sql("ANALYZE")
            fill_s["total"] = round(time.perf_counter() - start, 2)
            print(f"filled in {fill_s['total']} s: {fill_s}", file=sys.stderr)
        token = add_user(engine, f"loadtester{int(time.time())}")
        with engine.connect() as conn:
            n_subs = conn.execute(select(func.count(Submission.id))).scalar() or 0
            n_ranked = (
                conn.execute(select(func.count(Race.id)).where(Race.kind == "ranked")).scalar() or 0
            )
        engine.dispose()

        counts = web_worker_counts(args.web_workers)
        servers: dict[int, tuple[subprocess.Popen[bytes], str]] = {}
        results: list[Figures] = []
        try:
            for n in counts:
                port = _free_port()
                servers[n] = start_server(url, data_dir, port, n), f"http://127.0.0.1:{port}"
            load_before = os.getloadavg()
            loads = [load_before[0]]
            auth_headers = {"Authorization": f"Bearer {token}"}
            for label, paths, authed in endpoint_groups(n_subs, n_ranked, token):
                if args.only and args.only not in label:
                    continue
                headers = auth_headers if authed else {}
                for n in counts:  # each count in turn: compared under the same load
                    base = servers[n][1]
                    # Warm up every process's caches (one connection reaches one process).
                    asyncio.run(_load(base, label, paths, 0.5, args.concurrency, headers))
                    single = asyncio.run(_load(base, label, paths, args.seconds, 1, headers))
                    figures = asyncio.run(
                        _load(base, label, paths, args.seconds, args.concurrency, headers)
                    )
                    figures.single_p50_ms = single.p50_ms
                    figures.errors += single.errors
                    figures.web_workers = n
                    results.append(figures)
                    loads.append(os.getloadavg()[0])
                    print(
                        f"{label} ({n} web workers): 1 client p50 {single.p50_ms} ms; "
                        f"{args.concurrency} clients p50 {figures.p50_ms} ms, p99 "
                        f"{figures.p99_ms} ms, {figures.errors} errors; load {loads[-1]:.2f}",
                        file=sys.stderr,
                    )
        finally:
            for proc, _base in servers.values():
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(timeout=30)
        load_after = os.getloadavg()

    report = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
        "load_average": {
            "before": load_before,
            "after": load_after,
            "min_1min": min(loads),
            "max_1min": max(loads),
        },
        "database": url.split(":", 1)[0],
        "submissions": n_subs,
        "races": n_ranked,
        "concurrency": args.concurrency,
        "web_workers": counts,
        "seconds": args.seconds,
        "fill_s": fill_s,
        "goals": {"single_p50_ms": GOAL_SINGLE_P50_MS, "loaded_p99_ms": GOAL_LOADED_P99_MS},
        "unmeasured_routes": sorted(missing),
        "endpoints": [asdict(r) for r in results],
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        from rich.console import Console
        from rich.table import Table

        table = Table(
            title=f"{n_subs:,} submissions, {n_ranked:,} ranked races, {args.concurrency} "
            f"clients ({report['database']}); load average "
            f"{load_before[0]:.2f} → {load_after[0]:.2f} (range {min(loads):.2f}–{max(loads):.2f})"
        )
        cols = (
            "endpoint", "web workers", "requests", "errors", "1-client p50 ms", "p50 ms",
            "p99 ms", "req/s",
        )  # fmt: skip
        for col in (*cols, "goal"):
            table.add_column(col, justify="left" if col == "endpoint" else "right")
        for r in results:
            ok = r.single_p50_ms <= GOAL_SINGLE_P50_MS and r.p99_ms <= GOAL_LOADED_P99_MS
            table.add_row(
                r.endpoint, str(r.web_workers), str(r.requests), str(r.errors),
                f"{r.single_p50_ms:.1f}",
                f"{r.p50_ms:.1f}", f"{r.p99_ms:.1f}", f"{r.rps:.0f}", "ok" if ok else "MISSED",
            )  # fmt: skip
        Console(width=160).print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
