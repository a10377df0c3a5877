"""``slipstream status | logs | tokens | replay``: a participant's view of a leaderboard.

* ``status``: your submissions with their status, rank, rating and races, the versions that
  were rejected (and why), and your races still queued or running.
* ``logs RACE [--submission ID]``: your cars in a race: the DNF reason and its detail (the
  traceback), what your policy printed (the kept head and tail of stdout/stderr), and the
  sandbox it ran in. Only your own cars: the server never sends anyone else's.
* ``tokens list | create [--label L] | revoke ID``: your API tokens (a new token's secret is
  printed once).

* ``replay FILE``: plays a ``.replay.json.gz`` in a live viser scene (the site's renderer,
  :mod:`arena.viser_scene`) or serves a ``.viser`` recording in viser's static player.

The leaderboard commands take ``--server URL`` (default ``$SLIPSTREAM_SERVER`` or
``http://127.0.0.1:8000``), ``--token T`` (default ``$SLIPSTREAM_TOKEN``) and ``--json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from leaderboard.errors import LeaderboardError

DEFAULT_SERVER = "http://127.0.0.1:8000"


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--server",
        default=os.environ.get("SLIPSTREAM_SERVER", DEFAULT_SERVER),
        help="leaderboard URL ($SLIPSTREAM_SERVER)",
    )
    p.add_argument(
        "--token", default=os.environ.get("SLIPSTREAM_TOKEN"), help="API token ($SLIPSTREAM_TOKEN)"
    )
    p.add_argument("--json", action="store_true", help="print the answer as JSON")


def register(sub: Any) -> None:
    """Add ``status``, ``logs``, ``tokens`` and ``replay`` to the ``slipstream`` subcommands."""
    r = sub.add_parser(
        "replay",
        help="play a race replay (.replay.json.gz or .viser) in the browser, locally",
        description="A .replay.json.gz plays in a live viser scene (the site's renderer: "
        "track, cars with markers, labels); a .viser recording opens in viser's static "
        "player, as on the site. Prints the URL to open; Ctrl-C stops.",
    )
    r.add_argument("file", type=Path, help="a .replay.json.gz log or a .viser recording")
    r.add_argument("--port", type=int, default=8080, help="port to serve on (0: any free one)")
    r.add_argument("--speed", type=float, default=1.0, help="race seconds per second")
    r.add_argument("--once", action="store_true", help="play once (or serve once), then exit")
    r.set_defaults(handler=replay_command)

    s = sub.add_parser("status", help="your submissions, ranks and queued races on a leaderboard")
    _common(s)
    s.set_defaults(handler=status_command)

    lg = sub.add_parser(
        "logs", help="your cars' logs of a race: DNF detail, policy output, sandbox"
    )
    lg.add_argument("race", type=int, help="race id (the number in /races/<id>)")
    lg.add_argument("--submission", type=int, default=None, help="only this submission's cars")
    _common(lg)
    lg.set_defaults(handler=logs_command)

    t = sub.add_parser("tokens", help="list, create or revoke your API tokens")
    tsub = t.add_subparsers(dest="tokens_command", required=True, metavar="ACTION")
    tl = tsub.add_parser("list", help="your tokens (id, label, created, last used, revoked)")
    _common(tl)
    tl.set_defaults(handler=tokens_list_command)
    tc = tsub.add_parser("create", help="create a token and print its secret (once)")
    tc.add_argument("--label", default="", help="what the token is for (e.g. the machine)")
    _common(tc)
    tc.set_defaults(handler=tokens_create_command)
    tr = tsub.add_parser("revoke", help="revoke one of your tokens")
    tr.add_argument("id", type=int, help="the token's id (from `slipstream tokens list`)")
    _common(tr)
    tr.set_defaults(handler=tokens_revoke_command)


class Client:
    """A few authenticated calls to the leaderboard API; errors become one-line messages."""

    def __init__(self, server: str, token: str | None) -> None:
        if not token:
            raise LeaderboardError("an API token is needed: --token T or $SLIPSTREAM_TOKEN")
        self.server = server.rstrip("/")
        self.headers = {"Authorization": f"Bearer {token}"}

    def call(self, method: str, path: str, **kwargs: Any) -> Any:
        """``method path`` on the API; the decoded JSON answer (None for 204).

        Raises:
            LeaderboardError: the server cannot be reached or answers with an error.
        """
        import httpx  # noqa: PLC0415 - only these commands talk HTTP

        try:
            response = httpx.request(
                method, self.server + path, headers=self.headers, timeout=30, **kwargs
            )
        except httpx.HTTPError as err:
            raise LeaderboardError(f"cannot reach {self.server}: {err}") from None
        if response.status_code == 204:
            return None
        try:
            body = response.json()
        except ValueError:
            body = {"detail": response.text[:200]}
        if response.status_code >= 400:
            detail = body.get("detail") if isinstance(body, dict) else body
            raise LeaderboardError(f"{method} {path} refused ({response.status_code}): {detail}")
        return body


def _print_json(doc: Any) -> None:
    sys.stdout.write(json.dumps(doc, indent=2, default=str) + "\n")


def _console() -> Any:
    from rich.console import Console  # noqa: PLC0415 - lazy: keeps `slipstream --help` fast

    return Console()


# ---- status -----------------------------------------------------------------------------------


def gather_status(client: Client) -> dict[str, Any]:
    """Your user, submissions (with rank and rejected versions) and waiting races."""
    me = client.call("GET", "/api/users/me")
    subs = client.call("GET", f"/api/users/{me['name']}", params={"per_page": 200})
    out: list[dict[str, Any]] = []
    waiting: list[dict[str, Any]] = []
    for summary in subs["submissions"]["items"]:
        detail = client.call("GET", f"/api/submissions/{summary['id']}")
        out.append(
            {
                "id": detail["id"],
                "name": detail["name"],
                "status": detail["status"],
                "rank": detail.get("rank"),
                "version": detail.get("version"),
                "ordinal": detail["ordinal"],
                "mu": detail["mu"],
                "sigma": detail["sigma"],
                "races": detail["races"],
                "wins": detail["wins"],
                "rejected": [
                    {"version": v["version"], "error": v["error"]}
                    for v in detail["versions"]
                    if v["status"] == "rejected"
                ],
                "pending": [v["version"] for v in detail["versions"] if v["status"] == "pending"],
            }
        )
        for state in ("queued", "running"):
            page = client.call(
                "GET", "/api/races", params={"submission": summary["id"], "status": state}
            )
            waiting += [r | {"submission_id": summary["id"]} for r in page["items"]]
    return {"user": me["name"], "server": client.server, "submissions": out, "waiting": waiting}


def status_command(args: argparse.Namespace) -> int:
    """Run ``slipstream status``."""
    from rich.table import Table  # noqa: PLC0415

    doc = gather_status(Client(args.server, args.token))
    if args.json:
        _print_json(doc)
        return 0
    console = _console()
    table = Table(title=f"{doc['user']} on {doc['server']}")
    for col in ("id", "submission", "status", "rank", "ordinal", "μ ± σ", "races", "wins"):
        table.add_column(col, justify="left" if col in ("submission", "status") else "right")
    for s in doc["submissions"]:
        table.add_row(
            str(s["id"]),
            s["name"] + (f" v{s['version']}" if s["version"] else ""),
            s["status"]
            + (f" (v{', v'.join(map(str, s['pending']))} pending)" if s["pending"] else ""),
            f"#{s['rank']}" if s["rank"] else "–",
            f"{s['ordinal']:.2f}",
            f"{s['mu']:.1f} ± {s['sigma']:.1f}",
            str(s["races"]),
            str(s["wins"]),
        )
    console.print(table)
    for s in doc["submissions"]:
        for r in s["rejected"]:
            console.print(f"[red]rejected[/] {s['name']} v{r['version']}: {r['error']}")
    if doc["waiting"]:
        console.print(
            "waiting: "
            + ", ".join(
                f"race {r['id']} ({r['kind']}, {r['status']}, {r['track']})" for r in doc["waiting"]
            )
        )
    else:
        console.print("no races of yours waiting")
    if not doc["submissions"]:
        console.print("no submissions yet: slipstream bundle init my_bot; slipstream submit my_bot")
    return 0


# ---- logs -------------------------------------------------------------------------------------


def logs_command(args: argparse.Namespace) -> int:
    """Run ``slipstream logs``."""
    params = {"submission": args.submission} if args.submission is not None else {}
    logs = Client(args.server, args.token).call(
        "GET", f"/api/races/{args.race}/logs", params=params
    )
    if args.json:
        _print_json(logs)
        return 0
    if not logs:
        raise LeaderboardError(f"race {args.race} has no cars of yours")
    for log in logs:
        status = log["status"] or "–"
        if log["dnf_reason"]:
            status += f" ({log['dnf_reason']})"
        print(
            f"== race {log['race_id']} car_{log['car']} {log['name']}: {status}; "
            f"sandbox {log['sandbox_mode'] or '–'}"
        )
        if log["dnf_detail"]:
            print("-- error detail --")
            print(log["dnf_detail"].rstrip())
        print("-- output (stdout/stderr) --")
        print((log["output"] or "(nothing printed)").rstrip())
    return 0


# ---- tokens -----------------------------------------------------------------------------------


def tokens_list_command(args: argparse.Namespace) -> int:
    """Run ``slipstream tokens list``."""
    from rich.table import Table  # noqa: PLC0415

    rows = Client(args.server, args.token).call("GET", "/api/tokens")
    if args.json:
        _print_json(rows)
        return 0
    table = Table(title="your API tokens")
    for col in ("id", "label", "prefix", "created", "last used", "revoked"):
        table.add_column(col)
    for r in rows:
        table.add_row(
            str(r["id"]),
            r.get("label") or "",
            r.get("prefix") or "",
            str(r.get("created_at") or "–")[:16],
            str(r.get("last_used_at") or "–")[:16],
            "yes" if r.get("revoked") else "",
        )
    _console().print(table)
    return 0


def tokens_create_command(args: argparse.Namespace) -> int:
    """Run ``slipstream tokens create``."""
    body = Client(args.server, args.token).call("POST", "/api/tokens", json={"label": args.label})
    if args.json:
        _print_json(body)
    else:
        print(f"token {body['id']} created; its secret (shown once): {body['token']}")
    return 0


def tokens_revoke_command(args: argparse.Namespace) -> int:
    """Run ``slipstream tokens revoke``."""
    Client(args.server, args.token).call("DELETE", f"/api/tokens/{args.id}")
    if args.json:
        _print_json({"revoked": args.id})
    else:
        print(f"token {args.id} revoked")
    return 0


# ---- replay ------------------------------------------------------------------------------------


def _serve_viser(path: Path, port: int, once: bool) -> int:
    """Serve viser's static player and ``path`` on loopback; prints the player's URL."""
    import http.server  # noqa: PLC0415
    import shutil  # noqa: PLC0415
    import tempfile  # noqa: PLC0415
    import threading  # noqa: PLC0415
    import urllib.request  # noqa: PLC0415

    from leaderboard.web.viewer import ensure_viewer  # noqa: PLC0415

    with tempfile.TemporaryDirectory(prefix="slipstream-replay-") as tmp:
        root = ensure_viewer(Path(tmp))
        if root is None:
            raise LeaderboardError("the 3D player needs viser: pip install 'slipstream[eval]'")
        shutil.copyfile(path, root / "replay.viser")

        class Quiet(http.server.SimpleHTTPRequestHandler):
            def __init__(self, *a: Any, **kw: Any) -> None:
                super().__init__(*a, directory=str(root), **kw)

            def log_message(self, format: str, *args: Any) -> None:
                return

        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", port), Quiet)
        url = f"http://127.0.0.1:{httpd.server_port}/?playbackPath=/replay.viser"
        print(f"replay of {path.name} at {url}", flush=True)
        thread = threading.Thread(target=httpd.serve_forever, daemon=True)
        thread.start()
        try:
            if once:  # serve the player and the file once each, then stop
                for part in ("/", "/replay.viser"):
                    with urllib.request.urlopen(f"http://127.0.0.1:{httpd.server_port}{part}") as r:
                        r.read()
            else:
                thread.join()
        finally:
            httpd.shutdown()
            httpd.server_close()
    return 0


def replay_command(args: argparse.Namespace) -> int:
    """Run ``slipstream replay``."""
    path: Path = args.file
    if not path.is_file():
        raise LeaderboardError(f"{path}: no such replay file")
    if path.name.endswith(".viser"):
        return _serve_viser(path, args.port, args.once)
    if not path.name.endswith(".replay.json.gz"):
        raise LeaderboardError(f"{path}: not a .replay.json.gz log or a .viser recording")
    import time  # noqa: PLC0415

    from arena.replay import ReplayLog  # noqa: PLC0415 - not in the web process
    from arena.viser_scene import LiveScene, LiveWatcher, replay_car  # noqa: PLC0415

    log = ReplayLog.load(path)
    scene = LiveScene(log.track, log.cars, port=args.port, car=replay_car(log.car))
    print(f"replay of {path.name} at {scene.url} (Ctrl-C stops)", flush=True)
    watcher = LiveWatcher(scene, speed=args.speed)
    try:
        watcher.play(log)
        while not args.once:
            time.sleep(1.0)
            watcher.play(log)
    finally:
        scene.close()
    return 0


__all__ = ["Client", "gather_status", "register"]
