"""Leaderboard load: latency and throughput of the site and the API on a large database.

1. Fills a fresh database (SQLite by default, or ``--db URL``) with ``--submissions``
   submissions (10,000) and ``--races`` finished ranked races (100,000) of 2–8 cars, with
   their entries, rating history, track records and queue rows — bulk ``INSERT``s, no races
   are simulated.
2. Starts ``slipstream serve`` (uvicorn, one process) on 127.0.0.1.
3. For each endpoint, runs one client, then ``--concurrency`` clients, in a closed loop for
   ``--seconds`` each: the leaderboard page (``/``), ``/api/leaderboard`` (first and a deep
   page), ``/tracks`` and ``/api/tracks``, a track page, ``/api/races``, a random race and
   submission (API and page).
4. Prints, per endpoint, the single-client p50 and the ``--concurrency``-client p50/p99
   latency (ms) and requests/s, and ``--json``. Goals (issue 13): single-client p50 ≤ 20 ms,
   8-client p99 ≤ 150 ms.

The server runs with its rate limits off (``SLIPSTREAM_RATE_LIMITS=false``): a load generator
on one address would otherwise measure 429s.

The load generator runs on the same machine as the server (loopback), so on a 2-core box the
two compete for the CPUs; the figures are a floor.

Usage::

    python bench/leaderboard_load.py [--submissions 10000] [--races 100000]
        [--seconds 5] [--concurrency 8] [--db URL] [--keep DIR] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
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
from dataclasses import asdict, dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import Engine, func, insert, select

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
    if engine.dialect.name == "postgresql":
        with engine.begin() as conn:
            for table in ("users", "submissions", "submission_versions", "races"):
                conn.exec_driver_sql(
                    f"SELECT setval(pg_get_serial_sequence('{table}', 'id'), "
                    f"(SELECT MAX(id) FROM {table}))"
                )
            conn.exec_driver_sql("ANALYZE")
    else:
        with engine.begin() as conn:
            conn.exec_driver_sql("ANALYZE")
    return times


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_server(url: str, data_dir: Path, port: int) -> subprocess.Popen[bytes]:
    """``slipstream serve`` in a subprocess; returns once it answers /api/health."""
    cmd = [sys.executable, "-m", "leaderboard.cli", "serve", "--port", str(port),
           "--db", url, "--data-dir", str(data_dir)]  # fmt: skip
    env = {**os.environ, "SLIPSTREAM_RATE_LIMITS": "false"}
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, env=env)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=2).status_code == 200:
                return proc
        except httpx.HTTPError:
            pass
        if proc.poll() is not None:
            raise RuntimeError("the server exited during start-up")
        time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGTERM)
    raise RuntimeError("the server did not start within 60 s")


async def _load(base: str, paths: list[str], seconds: float, concurrency: int) -> Figures:
    latencies: list[float] = []
    errors = 0
    stop_at = time.perf_counter() + seconds
    rng = random.Random(1)
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    async with httpx.AsyncClient(base_url=base, limits=limits, timeout=30) as client:

        async def one() -> None:
            nonlocal errors
            while time.perf_counter() < stop_at:
                path = rng.choice(paths)
                start = time.perf_counter()
                try:
                    r = await client.get(path)
                    ok = r.status_code == 200
                except httpx.HTTPError:
                    ok = False
                latencies.append(time.perf_counter() - start)
                errors += not ok

        start = time.perf_counter()
        await asyncio.gather(*(one() for _ in range(concurrency)))
        elapsed = time.perf_counter() - start
    qs = statistics.quantiles(latencies, n=100) if len(latencies) > 1 else latencies * 99
    return Figures(
        endpoint=paths[0] if len(paths) == 1 else paths[0].rsplit("/", 1)[0] + "/{id}",
        requests=len(latencies),
        errors=errors,
        p50_ms=round(qs[49] * 1000, 2),
        p99_ms=round(qs[98] * 1000, 2),
        rps=round(len(latencies) / elapsed, 1),
    )


def main(argv: list[str] | None = None) -> int:
    """Fill, serve, load, report."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--submissions", type=int, default=10_000)
    ap.add_argument("--races", type=int, default=100_000)
    ap.add_argument("--seconds", type=float, default=5.0, help="load duration per endpoint")
    ap.add_argument("--concurrency", type=int, default=8, help="clients in a closed loop")
    ap.add_argument("--db", default=None, help="database URL (default: SQLite in --keep)")
    ap.add_argument("--keep", type=Path, default=None, help="data folder to keep (and reuse)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)

    data_dir = args.keep or Path(tempfile.mkdtemp(prefix="slipstream-load-"))
    data_dir.mkdir(parents=True, exist_ok=True)
    url = args.db or f"sqlite:///{(data_dir / 'leaderboard.db').resolve()}"
    engine = make_engine(url)
    upgrade(url, engine=engine)
    with engine.connect() as conn:
        have = conn.execute(select(func.count(Race.id))).scalar() or 0
    fill_s: dict[str, float] = {}
    if have == 0:
        start = time.perf_counter()
        fill_s = fill(engine, args.submissions, args.races)
        fill_s["total"] = round(time.perf_counter() - start, 2)
        print(f"filled in {fill_s['total']} s: {fill_s}", file=sys.stderr)
    with engine.connect() as conn:
        n_subs = conn.execute(select(func.count(Submission.id))).scalar() or 0
        n_races = conn.execute(select(func.count(Race.id))).scalar() or 0
    engine.dispose()

    port = _free_port()
    server = start_server(url, data_dir, port)
    rng = random.Random(0)
    groups = [
        ["/"],
        ["/api/leaderboard"],
        [f"/api/leaderboard?page={n_subs // 100}&per_page=50"],
        ["/api/races"],
        [f"/api/races/{rng.randint(1, n_races)}" for _ in range(200)],
        [f"/api/submissions/{rng.randint(1, n_subs)}" for _ in range(200)],
        [f"/races/{rng.randint(1, n_races)}" for _ in range(200)],
        [f"/submissions/{rng.randint(1, n_subs)}" for _ in range(200)],
        ["/tracks"],
        ["/api/tracks"],
        ["/tracks/monza"],
        ["/api/tracks/monza"],
    ]
    results: list[Figures] = []
    try:
        base = f"http://127.0.0.1:{port}"
        for paths in groups:
            single = asyncio.run(_load(base, paths, args.seconds, 1))
            figures = asyncio.run(_load(base, paths, args.seconds, args.concurrency))
            figures.single_p50_ms = single.p50_ms
            figures.errors += single.errors
            results.append(figures)
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=30)

    report = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
        "database": url.split(":", 1)[0],
        "submissions": n_subs,
        "races": n_races,
        "concurrency": args.concurrency,
        "seconds": args.seconds,
        "fill_s": fill_s,
        "endpoints": [asdict(r) for r in results],
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        from rich.console import Console
        from rich.table import Table

        table = Table(
            title=f"{n_subs:,} submissions, {n_races:,} races, {args.concurrency} clients "
            f"({report['database']})"
        )
        cols = ("endpoint", "requests", "errors", "1-client p50 ms", "p50 ms", "p99 ms", "req/s")
        for col in cols:
            table.add_column(col, justify="left" if col == "endpoint" else "right")
        for r in results:
            table.add_row(
                r.endpoint, str(r.requests), str(r.errors), f"{r.single_p50_ms:.1f}",
                f"{r.p50_ms:.1f}", f"{r.p99_ms:.1f}", f"{r.rps:.0f}",
            )  # fmt: skip
        Console().print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
