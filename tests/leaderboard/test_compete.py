"""The "Compete" page's commands, run as written, reach a ranked submission.

The page (``/compete``) is rendered for a server on a free loopback port; its command blocks
are then run in order in a fresh folder, each as its own ``slipstream`` process, exactly as
a new participant would paste them: ``users add`` (its token feeds the ``export`` lines),
``serve ... &`` and ``worker ... &`` in the background, ``bundle init``, ``bundle check``
(a real sandboxed race), ``submit``, ``status`` and ``logs``. The test only waits where a
person would (for the server to answer, for the validation race to be run) and stops the two
background processes it started at the end.
"""

from __future__ import annotations

import html
import json
import os
import re
import shlex
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from leaderboard.app import create_app
from leaderboard.settings import Settings

SLIPSTREAM = str(Path(sys.executable).parent / "slipstream")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _blocks(page: str) -> dict[str, list[str]]:
    blocks = re.findall(r'<pre class="commands" data-step="(\w+)">(.*?)</pre>', page, re.S)
    return {step: html.unescape(text).strip().splitlines() for step, text in blocks}


def _wait(predicate, timeout: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.5)


def _up(url: str) -> bool:
    try:
        with urllib.request.urlopen(url + "/api/health", timeout=2) as r:
            return bool(r.status == 200)
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.component("bubblewrap")
def test_compete_page_commands_reach_a_ranked_submission(tmp_path: Path) -> None:
    port = _free_port()
    server = f"http://127.0.0.1:{port}"
    with TestClient(create_app(Settings(data_dir=tmp_path / "render")), base_url=server) as client:
        page = client.get("/compete").text
    blocks = _blocks(page)
    assert list(blocks) == ["install", "server", "login", "write", "check", "submit", "logs"]
    assert any("pip install -e" in line for line in blocks["install"])  # we are installed

    work = tmp_path / "participant"
    work.mkdir()
    env = dict(os.environ)
    env.pop("SLIPSTREAM_TOKEN", None)
    background: list[subprocess.Popen[bytes]] = []
    outputs: list[str] = []
    captured: dict[str, str] = {}

    def run(line: str) -> str:
        if line.startswith("export "):
            name, _, value = line.removeprefix("export ").partition("=")
            value = value.replace("<your token>", captured["token"])
            env[name] = value
            return ""
        value = line.replace("RACE_ID", captured.get("race", ""))
        argv = shlex.split(value.removesuffix("&").strip())
        assert argv[0] == "slipstream", line
        argv[0] = SLIPSTREAM
        if line.endswith("&"):
            log = (work / f"bg{len(background)}.log").open("wb")
            background.append(
                subprocess.Popen(argv, cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT)
            )
            return ""
        done = subprocess.run(
            argv, check=False, cwd=work, env=env, capture_output=True, text=True, timeout=300
        )
        assert done.returncode == 0, (line, done.stdout[-2000:], done.stderr[-2000:])
        outputs.append(done.stdout + done.stderr)
        return done.stdout + done.stderr

    try:
        for line in blocks["server"]:
            out = run(line)
            match = re.search(r"API token \(shown once\): (\S+)", out)
            if match:
                captured["token"] = match.group(1)
        _wait(lambda: _up(server), 120, "the server")
        for line in blocks["login"]:
            run(line)
        assert env["SLIPSTREAM_SERVER"] == server
        for line in blocks["write"] + blocks["check"]:
            run(line)
        assert "the server would accept this bundle" in outputs[-1]
        submitted = run(blocks["submit"][0])
        captured["race"] = re.search(r"validation race (\d+)", submitted).group(1)  # type: ignore[union-attr]
        for line in blocks["submit"][1:]:
            run(line)

        def ranked() -> bool:
            done = subprocess.run(
                [SLIPSTREAM, "status", "--json"],
                check=False,
                env=env,
                capture_output=True,
                text=True,
            )
            subs = json.loads(done.stdout)["submissions"] if done.returncode == 0 else []
            return bool(subs) and subs[0]["status"] == "active" and subs[0]["rank"] == 1

        _wait(ranked, 240, "the validation race and a rank")
        logs = run(blocks["logs"][0])
        assert f"race {captured['race']} car_0 my_bot" in logs and "finished" in logs
    finally:
        for proc in background:
            proc.terminate()
        for proc in background:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
