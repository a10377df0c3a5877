"""The replay player's leash and the offline API docs, in a real headless Chromium (issue 13).

The attack is the one issue 13's review ran: viser's player runs the JavaScript that a
``.viser`` file carries (``RunJavascriptMessage``, executed with ``new Function``), so
``/viewer/?playbackPath=<a file on another server>`` ran an attacker's script on the site's
origin. Here: a foreign ``playbackPath`` is refused outright; a hostile file that made it into
``/replays/`` is stopped by the viewer's Content-Security-Policy (no ``unsafe-eval``), while a
real replay still plays; and ``/docs`` and ``/redoc`` render with every off-site request
blocked (the machine has no internet).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from leaderboard.app import create_app
from tests.leaderboard.site_data import Site, seed_site
from tests.leaderboard.test_security import Served, serve

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
]
TIMEOUT_MS = 120_000
REPLAY_RACE = 4  # the first ranked race (races 1-3 validate the baselines); a real .viser
HOSTILE_RACE = 999_001
# viser's bundled Gaussian-splat sorter (Sorter.wasm, emscripten embind) builds functions with
# `new Function` when it loads; without 'unsafe-eval' it fails. Replays have no splats.
SPLAT_SORTER_EVAL = "Evaluating a string as JavaScript violates"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.component("chromium"),
    pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="chromium is not installed"),
]


def hostile_viser(source: str) -> bytes:
    """A ``.viser`` recording (viser 1.1.1 layout) whose one message runs ``source``."""
    import msgspec
    import zstandard

    payload = msgspec.msgpack.encode(
        {
            "durationSeconds": 1.0,
            "messages": [[0.0, {"type": "RunJavascriptMessage", "source": source}]],
            "viserVersion": "1.1.1",
            "binaryBufferLengths": [],
        }
    )
    inner = len(payload).to_bytes(8, "little") + payload
    return len(inner).to_bytes(8, "little") + zstandard.ZstdCompressor().compress(inner)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Site:
    """Three baselines and one ranked race with a real replay; plus a hostile replay file."""
    site = seed_site(tmp_path_factory.mktemp("leash"), ranked=1, viser=[REPLAY_RACE])
    evil = "window.__pwned = document.domain; alert('pwned ' + document.domain)"
    (site.settings.replays_dir / f"{HOSTILE_RACE}.viser").write_bytes(hostile_viser(evil))
    return site


@pytest.fixture(scope="module")
def served(site: Site) -> Iterator[Served]:
    """The site under uvicorn on loopback."""
    with serve(create_app(site.settings)) as s:
        yield s


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Headless Chromium."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def _watch(page: Any) -> tuple[list[str], list[str], list[str]]:
    """Collect (dialogs, page errors, console lines) of ``page``."""
    dialogs: list[str] = []
    errors: list[str] = []
    console: list[str] = []

    def on_dialog(dialog: Any) -> None:
        dialogs.append(dialog.message)
        dialog.dismiss()

    page.on("dialog", on_dialog)
    page.on("pageerror", lambda err: errors.append(str(err)))
    page.on("console", lambda msg: console.append(msg.text))
    return dialogs, errors, console


def test_player_plays_a_real_replay_under_its_policy(browser: Any, served: Served) -> None:
    # A small window: software WebGL's cost grows with the pixels, and a drawn scene is a
    # drawn scene at any size (the cars at 1280x720 and in a close-up: test_browser.py).
    page = browser.new_page(viewport={"width": 480, "height": 300})
    dialogs, errors, console = _watch(page)
    try:
        response = page.goto(
            f"{served.url}/viewer/?playbackPath=/replays/{REPLAY_RACE}.viser&hideViserLogo",
            timeout=TIMEOUT_MS,
        )
        assert response is not None and response.status == 200
        assert "unsafe-eval'" not in response.headers["content-security-policy"].replace(
            "'wasm-unsafe-eval'", ""
        )
        page.locator("input.mantine-NumberInput-input").first.wait_for(timeout=TIMEOUT_MS)
        canvas = page.locator("canvas").first
        canvas.wait_for(timeout=TIMEOUT_MS)
        # Only the scene counts: hide the player's "software WebGL" notice over the canvas.
        page.add_style_tag(content=".mantine-Notification-root{display:none!important}")
        page.wait_for_timeout(2000)
        png = canvas.screenshot(timeout=TIMEOUT_MS)
    finally:
        page.close()
    assert any("File loaded" in line for line in console), console[:20]
    assert not dialogs
    assert [e for e in errors if SPLAT_SORTER_EVAL not in e] == [], errors
    import io

    import numpy as np
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # the scene is drawn, not blank


def test_foreign_playback_path_is_refused(browser: Any, served: Served) -> None:
    page = browser.new_page()
    dialogs, _errors, _console = _watch(page)
    try:
        # Another origin (another port) serving the hostile file, as in the review's attack.
        foreign = f"http://localhost:{served.port}/replays/{HOSTILE_RACE}.viser"
        response = page.goto(f"{served.url}/viewer/?playbackPath={foreign}", timeout=TIMEOUT_MS)
        assert response is not None and response.status == 400
        page.wait_for_timeout(1000)
        assert page.evaluate("window.__pwned") is None
    finally:
        page.close()
    assert not dialogs


def test_script_in_a_same_origin_replay_does_not_run(browser: Any, served: Served) -> None:
    page = browser.new_page()
    dialogs, errors, console = _watch(page)
    try:
        response = page.goto(
            f"{served.url}/viewer/?playbackPath=/replays/{HOSTILE_RACE}.viser", timeout=TIMEOUT_MS
        )
        assert response is not None and response.status == 200
        page.wait_for_function(
            "() => document.querySelector('canvas') !== null", timeout=TIMEOUT_MS
        )
        page.wait_for_timeout(5000)  # the file is fetched, decoded and its messages applied
        assert page.evaluate("window.__pwned") is None
    finally:
        page.close()
    assert not dialogs, dialogs
    assert any("File loaded" in line for line in console), console[:20]
    assert any(SPLAT_SORTER_EVAL in e or "unsafe-eval" in e for e in errors + console)


@pytest.mark.parametrize(
    ("path", "ready"), [("/docs", ".opblock"), ("/redoc", "[data-section-id]")]
)
def test_api_docs_render_offline(browser: Any, served: Served, path: str, ready: str) -> None:
    page = browser.new_page()
    blocked: list[str] = []

    def only_local(route: Any) -> None:
        if route.request.url.startswith(served.url):
            route.continue_()
        else:
            blocked.append(route.request.url)
            route.abort()

    page.route("**/*", only_local)
    _dialogs, errors, _console = _watch(page)
    try:
        page.goto(served.url + path, timeout=TIMEOUT_MS)
        page.locator(ready).first.wait_for(timeout=TIMEOUT_MS)
        count = page.locator(ready).count()
    finally:
        page.close()
    assert count >= 5  # one per API operation (or section)
    assert blocked == [] and errors == []
