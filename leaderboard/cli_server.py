"""``slipstream serve | worker | submit | users``: run the leaderboard and talk to it.

* ``serve``: the web app (API + site) under uvicorn, on 127.0.0.1:8000 by default, in
  ``--web-workers`` processes (:func:`leaderboard.serving.serve_processes`).
* ``worker``: claim races from the queue, run them (local processes or ``--ray-address``),
  store results and ratings; ``--once`` runs one batch, ``--max-races N`` stops after N.
* ``submit BUNDLE --server URL --token T``: upload a bundle zip or folder.
* ``users add NAME``: create a user on the database and print their API token (once).

``--db`` and ``--data-dir`` override ``SLIPSTREAM_DATABASE_URL`` / ``SLIPSTREAM_DATA_DIR``.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import Any

from leaderboard.errors import LeaderboardError
from leaderboard.settings import Settings


def _db_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", default=None, metavar="URL", help="database URL (default: SQLite)")
    p.add_argument("--data-dir", type=Path, default=None, help="bundles, replays, SQLite file")


def settings_from(args: argparse.Namespace, **extra: Any) -> Settings:
    """Settings from the environment, with ``--db`` / ``--data-dir`` on top."""
    kwargs: dict[str, Any] = dict(extra)
    if getattr(args, "db", None):
        kwargs["database_url"] = args.db
    if getattr(args, "data_dir", None):
        kwargs["data_dir"] = args.data_dir
    return Settings(**kwargs)


def register(sub: Any) -> None:
    """Add ``serve``, ``worker``, ``submit`` and ``users`` to the ``slipstream`` subcommands."""
    p = sub.add_parser("serve", help="run the leaderboard web service (API + website)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=8000, help="port to listen on")
    p.add_argument(
        "--web-workers",
        type=int,
        default=None,
        metavar="N",
        help="server processes sharing the port ($SLIPSTREAM_WEB_WORKERS; default 1); "
        "in-memory rate limits are divided between them",
    )
    _db_options(p)
    p.set_defaults(handler=serve_command)

    w = sub.add_parser(
        "worker",
        help="run queued races (matchmaking, sandboxed evaluation, ratings)",
        description="Claim races with a lease, run them, store results and rating updates "
        "exactly once. Without --once or --max-races it runs until interrupted.",
    )
    _db_options(w)
    w.add_argument("--workers", type=int, default=1, help="races at once")
    w.add_argument("--ray-address", default=None, help="run races on this Ray cluster")
    stop = w.add_mutually_exclusive_group()
    stop.add_argument("--once", action="store_true", help="run one batch, then exit")
    stop.add_argument("--max-races", type=int, default=None, help="exit after N races")
    w.add_argument(
        "--no-schedule", action="store_true", help="only run queued races; schedule none"
    )
    w.add_argument("--lease-s", type=float, default=None, help="lease length, s")
    w.add_argument(
        "--allow-weak-sandbox",
        action="store_true",
        help="where bubblewrap cannot run, race bundles in the weaker seccomp fallback "
        "(logged and recorded on every result) instead of refusing to start",
    )
    w.add_argument("--json", action="store_true", help="print the summary as JSON")
    w.set_defaults(handler=worker_command)

    s = sub.add_parser("submit", help="upload a submission bundle to a leaderboard server")
    s.add_argument("bundle", type=Path, help="bundle zip, or a folder with manifest.json")
    s.add_argument(
        "--server",
        default=os.environ.get("SLIPSTREAM_SERVER", "http://127.0.0.1:8000"),
        help="leaderboard URL ($SLIPSTREAM_SERVER)",
    )
    s.add_argument(
        "--token", default=os.environ.get("SLIPSTREAM_TOKEN"), help="API token ($SLIPSTREAM_TOKEN)"
    )
    s.add_argument("--submission", type=int, default=None, help="add a version to this id")
    s.add_argument("--json", action="store_true", help="print the server's answer as JSON")
    s.set_defaults(handler=submit_command)

    u = sub.add_parser("users", help="manage leaderboard users")
    usub = u.add_subparsers(dest="users_command", required=True, metavar="ACTION")
    add = usub.add_parser("add", help="create a user and print their API token")
    add.add_argument("name", help="user name ([A-Za-z0-9_.-], at most 64)")
    add.add_argument("--admin", action="store_true", help="may create users over the API")
    add.add_argument("--json", action="store_true", help="print name and token as JSON")
    _db_options(add)
    add.set_defaults(handler=users_add_command)


def serve_command(args: argparse.Namespace) -> int:
    """Run ``slipstream serve``."""
    # Lazy: keeps `slipstream --help` fast; only this command needs uvicorn.
    from leaderboard.serving import default_web_workers, serve_processes  # noqa: PLC0415

    settings = settings_from(args)
    workers = args.web_workers or settings.web_workers or default_web_workers()
    if args.host not in (*settings.allowed_hosts, "0.0.0.0", "::", "*"):
        settings.allowed_hosts.append(args.host)  # the address served is a name it answers to
    elif args.host in ("0.0.0.0", "::") and "*" not in settings.allowed_hosts:
        print(
            f"answering only Host: {', '.join(settings.allowed_hosts)} "
            "(set SLIPSTREAM_ALLOWED_HOSTS to the names clients use)",
            file=sys.stderr,
        )
    processes = f"{workers} processes" if workers > 1 else "one process"
    print(
        f"leaderboard on http://{args.host}:{args.port}/ (API docs at /docs; {processes})",
        file=sys.stderr,
    )
    serve_processes(settings, args.host, args.port, workers)  # head, body, keep-alive timeouts
    return 0


def worker_command(args: argparse.Namespace) -> int:
    """Run ``slipstream worker``."""
    from rich.console import Console  # noqa: PLC0415 - lazy: keeps `slipstream --help` fast

    from leaderboard.worker import Worker, WorkerStats  # noqa: PLC0415 - lazy, as above

    extra = {"lease_s": args.lease_s} if args.lease_s else {}
    settings = settings_from(args, **extra)
    console = Console(stderr=True)
    worker = Worker(
        settings,
        workers=args.workers,
        ray_address=args.ray_address,
        schedule=not args.no_schedule,
        allow_weak_sandbox=args.allow_weak_sandbox,
    )

    def hand_back(signum: int, frame: object) -> None:
        # First SIGTERM / Ctrl-C: hand the running races back (no attempt spent) and exit.
        console.print("[bold]worker[/] stopping: handing the running races back")
        signal.signal(signum, signal.default_int_handler)  # a second one interrupts hard
        worker.request_stop()

    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, hand_back)

    with console.status("[bold]worker[/] waiting for races") as status:

        def progress(stats: WorkerStats) -> None:
            status.update(
                f"[bold]worker[/] {stats.completed} races stored, {stats.failed} failed, "
                f"{stats.discarded} discarded"
            )

        try:
            stats = worker.run(max_races=args.max_races, once=args.once, progress=progress)
        finally:
            worker.close()
    summary = {
        "completed": stats.completed,
        "failed": stats.failed,
        "discarded": stats.discarded,
        "handed_back": stats.handed_back,
        "stalled": stats.stalled,
    }
    if args.json:
        print(json.dumps(summary))
    else:
        console.print(
            f"{stats.completed} races stored, {stats.failed} failed, "
            f"{stats.discarded} results discarded (lease lost)"
        )
    return 0


def bundle_bytes(path: Path) -> bytes:
    """A bundle as zip bytes (a folder is zipped, files in sorted order)."""
    if path.is_file():
        return path.read_bytes()
    if not (path / "manifest.json").is_file():
        raise LeaderboardError(f"{path}: not a bundle zip or a folder with manifest.json")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for f in sorted(p for p in path.rglob("*") if p.is_file()):
            zf.write(f, f.relative_to(path).as_posix())
    return buf.getvalue()


def submit_command(args: argparse.Namespace) -> int:
    """Run ``slipstream submit``."""
    import httpx  # noqa: PLC0415 - only this command talks HTTP

    if not args.token:
        raise LeaderboardError("an API token is needed: --token T or $SLIPSTREAM_TOKEN")
    if not args.bundle.exists():
        raise LeaderboardError(f"{args.bundle}: no such file or folder")
    server = args.server.rstrip("/")
    url = f"{server}/api/submissions"
    if args.submission is not None:
        url += f"/{args.submission}/versions"
    from submissions.cli_bundle import bundle_for_upload  # noqa: PLC0415 - wraps checkpoints

    with tempfile.TemporaryDirectory(prefix="slipstream-submit-") as tmp:
        bundle, note = bundle_for_upload(args.bundle, Path(tmp))
        if note:
            print(note, file=sys.stderr)
        name = bundle.name if bundle.is_file() else f"{bundle.name}.zip"
        try:
            response = httpx.post(
                url,
                headers={"Authorization": f"Bearer {args.token}"},
                files={"file": (name, bundle_bytes(bundle), "application/zip")},
                timeout=120,
            )
        except httpx.HTTPError as err:
            raise LeaderboardError(f"cannot reach {server}: {err}") from None
    try:
        body = response.json()
    except ValueError:
        body = {"detail": response.text[:200]}
    if response.status_code >= 400:
        raise LeaderboardError(f"upload refused ({response.status_code}): {body.get('detail')}")
    if args.json:
        print(json.dumps(body))
    else:
        print(
            f"uploaded {body['name']} v{body['version']} (submission {body['submission_id']}); "
            f"validation race {body['validation_race_id']}: {server}/submissions/"
            f"{body['submission_id']}"
        )
    return 0


def users_add_command(args: argparse.Namespace) -> int:
    """Run ``slipstream users add``."""
    from leaderboard import auth  # noqa: PLC0415 - lazy: keeps `slipstream --help` fast
    from leaderboard.db import connect, session_scope  # noqa: PLC0415

    settings = settings_from(args)
    settings.ensure_dirs()
    with connect(settings.db_url, migrate=True) as sessions, session_scope(sessions) as session:
        user, token = auth.create_user(session, name=args.name, is_admin=args.admin)
        name = user.name
    if args.json:
        print(json.dumps({"name": name, "token": token}))
    else:
        print(f"user {name} created; API token (shown once): {token}")
    return 0
