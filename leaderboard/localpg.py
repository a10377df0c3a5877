"""A throwaway PostgreSQL server in a temporary folder, for tests and benchmarks.

:func:`throwaway_server` runs the installed PostgreSQL binaries (``initdb`` + ``pg_ctl``, Debian
package ``postgresql``) on a Unix socket in a fresh folder, with durability off (``fsync``,
``full_page_writes``), and stops and deletes it afterwards. The test suite's ``pg_server``
fixture and ``bench/leaderboard_load.py --db postgresql`` both use it, so the two measure
the same set-up. Nothing here is used by a deployment, which points ``database_url`` at a
real server.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import create_engine, text

from leaderboard.errors import LeaderboardError

PG_BIN_GLOB = "usr/lib/postgresql/*/bin"  # Debian's layout, under /


class PostgresUnavailable(LeaderboardError):
    """The PostgreSQL binaries are missing, or cannot be run here (root without runuser)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def postgres_bindir() -> Path:
    """The newest installed PostgreSQL ``bin`` folder.

    Raises:
        PostgresUnavailable: no ``initdb`` found.
    """
    bins = sorted(Path("/").glob(PG_BIN_GLOB), key=lambda p: int(p.parent.name))
    if not bins or not (bins[-1] / "initdb").exists():
        raise PostgresUnavailable(
            "PostgreSQL binaries not found (Debian: apt-get install postgresql)"
        )
    return bins[-1]


@contextmanager
def throwaway_server(*extra_options: str) -> Iterator[str]:
    """Start a PostgreSQL server for the duration of the ``with`` block.

    Runs as the ``postgres`` system user when called as root (``initdb`` refuses root).
    Listens on a Unix socket only.

    Args:
        extra_options: more ``-c name=value`` server settings (e.g. ``"shared_buffers=256MB"``).

    Yields:
        An SQLAlchemy URL (psycopg 3) of the server's ``postgres`` database.

    Raises:
        PostgresUnavailable: the binaries are missing or cannot be run as this user.
    """
    bindir = postgres_bindir()
    prefix: list[str] = []
    if os.geteuid() == 0:
        if shutil.which("runuser") is None:
            raise PostgresUnavailable("running as root without runuser: cannot start PostgreSQL")
        prefix = ["runuser", "-u", "postgres", "--"]
    root = Path(tempfile.mkdtemp(prefix="slipstream-pg-", dir="/tmp"))
    data, sock = root / "data", root / "sock"
    sock.mkdir()
    if prefix:
        shutil.chown(root, "postgres")
        shutil.chown(sock, "postgres")
    port = _free_port()

    def run(*cmd: str) -> None:
        subprocess.run([*prefix, *cmd], check=True, capture_output=True, timeout=120)

    try:
        run(str(bindir / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres", "--no-sync")
        opts = " ".join(
            [
                f"-p {port} -k {sock} -c listen_addresses=''",
                "-c fsync=off -c full_page_writes=off",
                *(f"-c {option}" for option in extra_options),
            ]
        )
        run(
            str(bindir / "pg_ctl"),
            *("-D", str(data), "-o", opts, "-l", str(root / "log"), "-w", "start"),
        )
        try:
            yield f"postgresql+psycopg://postgres@/postgres?host={sock}&port={port}"
        finally:
            subprocess.run(
                [*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
                capture_output=True,
                timeout=60,
                check=False,
            )
    finally:
        shutil.rmtree(root, ignore_errors=True)


def create_database(server_url: str, name: str | None = None) -> str:
    """Create a new empty database on the server of ``server_url``; its URL."""
    name = name or f"t_{uuid.uuid4().hex[:12]}"
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{name}"'))
    finally:
        admin.dispose()
    return server_url.replace("/postgres?", f"/{name}?")


def drop_database(server_url: str, database_url: str) -> None:
    """Drop a database made by :func:`create_database` (its connections are closed)."""
    name = database_url.rsplit("/", maxsplit=1)[-1].split("?", maxsplit=1)[0]
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    finally:
        admin.dispose()


__all__ = [
    "PostgresUnavailable",
    "create_database",
    "drop_database",
    "postgres_bindir",
    "throwaway_server",
]
