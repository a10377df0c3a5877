"""The website in a real headless Chromium (Playwright driving Debian's /usr/bin/chromium).

A seeded leaderboard is served by uvicorn on loopback; the tests check that the leaderboard
renders its rows and that a race page's embedded viser player loads its ``.viser`` replay and
draws the cars (pixels of the cars' colours on its WebGL canvas). Screenshots are kept under
``artifacts/browser/``. Software WebGL (SwiftShader) draws only a few frames per second, so
the tests wait for the player's playback bar, pause, and look at a still frame.
"""

from __future__ import annotations

import json
import shutil
import socket
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import pytest

from leaderboard.app import create_app
from leaderboard.web.pages import viewer_url
from leaderboard.web.viewer import VIEWER_PREFIX
from tests.leaderboard.site_data import Site, fake_replay, seed_site

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# Flags known to work here: no sandbox as root, no GPU, and no calls home (the network is closed).
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts" / "browser"
TIMEOUT_MS = 120_000  # software WebGL on a loaded 2-core machine is slow
REPLAY_RACE = 4  # the first ranked race; races 1-3 validate the three baselines

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="chromium is not installed"),
]


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Site:
    """The three baselines and two ranked races; race 4 has a real ``.viser`` replay."""
    return seed_site(tmp_path_factory.mktemp("browser-site"), ranked=2, viser=[REPLAY_RACE])


@pytest.fixture(scope="module")
def base_url(site: Site) -> Iterator[str]:
    """The seeded site served by uvicorn in a thread on a free loopback port."""
    import uvicorn

    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(create_app(site.settings), log_level="warning", lifespan="on")
    )
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Headless Chromium (a fresh profile per launch)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


PLAYER_LEFT_OUT = (
    "<!doctype html><title>3D player left out</title><p>The 3D player is left out of this "
    "test; test_race_page_embeds_a_working_player checks it on a race page.</p>"
)


def leave_out_the_player(target: Any) -> None:
    """Answer ``/viewer/`` with a placeholder page in ``target`` (a page or a context).

    The player's software WebGL keeps the CPU busy for as long as it is open (seconds per
    frame on a loaded machine), and every step of the page waits behind it. Tests of what
    lies beside the player (the race map, the owner's logs, a tournament's heats) leave it
    out; the tests of the player itself load it.
    """
    target.route(
        lambda url: urlsplit(url).path.startswith(VIEWER_PREFIX + "/"),
        lambda route: route.fulfill(status=200, content_type="text/html", body=PLAYER_LEFT_OUT),
    )


def _shot(page: Any, name: str, **kwargs: Any) -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    out = ARTIFACTS / f"{name}.png"
    page.screenshot(path=str(out), **kwargs)
    return out


def colour_pixels(png: bytes, rgb: tuple[int, int, int], tol: float = 60.0) -> int:
    """How many pixels of a PNG lie within ``tol`` (RGB distance) of the hue-matched colour.

    Shading darkens or lightens a car's faces, so each pixel is compared after scaling it to
    the colour's brightness.
    """
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)
    target = np.asarray(rgb, dtype=np.float64)
    brightness = img.sum(axis=-1, keepdims=True)
    scaled = img * (target.sum() / np.maximum(brightness, 1.0))
    close = np.linalg.norm(scaled - target, axis=-1) < tol
    saturated = img.max(axis=-1) - img.min(axis=-1) > 60  # not grey, white or black
    return int(np.count_nonzero(close & saturated))


def test_leaderboard_renders_its_rows(browser: Any, base_url: str) -> None:
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(base_url + "/", timeout=TIMEOUT_MS)
        rows = page.locator("table#leaderboard tbody tr")
        rows.first.wait_for(timeout=TIMEOUT_MS)
        assert rows.count() == 3
        names = [rows.nth(i).locator("td").nth(1).inner_text().split()[0] for i in range(3)]
        with urllib.request.urlopen(base_url + "/api/leaderboard") as response:
            api = json.load(response)["items"]
        assert names == [item["name"] for item in api]
        assert sorted(names) == ["gap", "pursuit", "random"]
        _shot(page, "leaderboard", full_page=True)
        page.get_by_role("link", name="pursuit", exact=True).click()
        page.wait_for_url("**/submissions/*", timeout=TIMEOUT_MS)
        assert page.locator("svg.chart polyline").count() >= 2  # the rating history chart
        _shot(page, "submission", full_page=True)
    finally:
        page.close()


def _nonblank(png: bytes) -> tuple[int, float]:
    """Distinct colours, and the fraction of pixels that are not near-white, of a PNG."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    distinct = len(np.unique(img.reshape(-1, 3), axis=0))
    return distinct, float(np.mean(img.min(axis=-1) < 200))


def _wait_for_player(frame: Any) -> tuple[Any, Any]:
    """The player's time box and canvas, once the ``.viser`` file is fetched and decoded."""
    time_box = frame.locator("input.mantine-NumberInput-input").first
    time_box.wait_for(timeout=TIMEOUT_MS)
    canvas = frame.locator("canvas").first
    canvas.wait_for(timeout=TIMEOUT_MS)
    return time_box, canvas


def test_race_page_embeds_a_working_player(browser: Any, base_url: str, site: Site) -> None:
    """At 1280x720, the race page's 3D player at its default whole-track view shows every
    car: the track-sized markers in the cars' colours (arena.viser_scene)."""
    from arena.sim import car_colour

    job = site.runner.jobs[REPLAY_RACE - 1]
    page = browser.new_page(viewport={"width": 1280, "height": 720})
    errors: list[str] = []
    # The player's own CSP refuses an eval it tries (reported to H13); other errors count.
    page.on("pageerror", lambda err: "'unsafe-eval'" in str(err) or errors.append(str(err)))
    try:
        page.goto(f"{base_url}/races/{REPLAY_RACE}", timeout=TIMEOUT_MS)
        assert page.locator("table#results tbody tr").count() == len(job.entrants)
        src = page.locator("iframe#replay").get_attribute("src")
        assert src == viewer_url(f"/replays/{REPLAY_RACE}.viser")
        _, canvas = _wait_for_player(page.frame_locator("iframe#replay"))
        page.wait_for_timeout(2000)  # a few software-rendered frames
        frame = canvas.screenshot(timeout=TIMEOUT_MS)
        _shot(page, "race", full_page=True)
    finally:
        page.close()
    assert not errors, errors
    distinct, drawn = _nonblank(frame)
    # A blank canvas has one colour; the grid and the dark road make thousands.
    assert distinct > 50 and drawn > 0.01, (distinct, drawn)
    (ARTIFACTS / "replay_default_view.png").write_bytes(frame)
    # Each car is clearly visible at the default view: its marker arrow, >= 15 px long, covers
    # >= ~60 px of its (lit, so paler) colour. Cars coloured like the red kerbs cannot be told
    # apart from them by colour, so only the others are counted.
    from arena.viser_scene import KERB_COLOURS

    def far_from_kerbs(rgb: tuple[int, int, int]) -> bool:
        return all(np.linalg.norm(np.subtract(rgb, k)) > 100 for k in KERB_COLOURS)

    counted = [i for i in range(len(job.entrants)) if far_from_kerbs(car_colour(i))]
    counts = {i: colour_pixels(frame, car_colour(i), tol=90) for i in counted}
    assert counted and all(n >= 60 for n in counts.values()), counts


def test_replay_player_shows_the_cars(browser: Any, base_url: str, site: Site) -> None:
    from arena.sim import car_colour

    job = site.runner.jobs[REPLAY_RACE - 1]
    start = np.asarray(fake_replay(job).poses[0], dtype=np.float64)  # type: ignore[attr-defined]
    cx, cy = start[:, 0].mean(), start[:, 1].mean()
    # A close-up of the start, from behind and above (URL parameters beat the recorded camera).
    camera = (
        f"&initialCameraPosition={cx:.2f},{cy - 3:.2f},2.5&initialCameraLookAt={cx:.2f},{cy:.2f},0"
    )
    # A small window: software WebGL's cost grows with the pixels; a close-up fills it with
    # the cars anyway (each car ~1,000-4,000 px of its colour here, ~5x that at 960x600).
    page = browser.new_page(viewport={"width": 480, "height": 300})
    try:
        page.goto(
            base_url + viewer_url(f"/replays/{REPLAY_RACE}.viser") + camera, timeout=TIMEOUT_MS
        )
        time_box, canvas = _wait_for_player(page)
        page.keyboard.press("Space")  # pause, then go to t = 0: the cars on the grid
        time_box.fill("0")
        time_box.press("Enter")
        page.mouse.click(240, 125)  # leave the time box (a click without a drag)
        page.add_style_tag(content=".mantine-Notification-root{display:none!important}")
        page.wait_for_timeout(3000)
        frame = canvas.screenshot(timeout=TIMEOUT_MS)
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "replay_closeup.png").write_bytes(frame)
    finally:
        page.close()
    # Every car's colour is on the canvas; blue and yellow appear nowhere else in the scene
    # (the road is grey, the kerbs red and white, the ground white).
    counts = {i: colour_pixels(frame, car_colour(i)) for i in range(len(job.entrants))}
    assert all(n >= 50 for n in counts.values()), counts


def test_race_map_shows_every_car_follows_one_and_seeks(
    browser: Any, base_url: str, site: Site
) -> None:
    """At 1280x720 the race page's 2D map draws every car >= 15 px long, in its colour;
    the standings and lap counter follow playback; an event link seeks; follow zooms in."""
    from arena.sim import car_colour

    job = site.runner.jobs[REPLAY_RACE - 1]
    page = browser.new_page(viewport={"width": 1280, "height": 720})
    leave_out_the_player(page)  # the map does not need it (it draws the raw replay log)
    errors: list[str] = []
    page.on("pageerror", lambda err: errors.append(str(err)))
    try:
        page.goto(f"{base_url}/races/{REPLAY_RACE}", timeout=TIMEOUT_MS)
        page.locator('#race-map[data-ready="1"]').wait_for(timeout=TIMEOUT_MS)
        canvas = page.locator("#race-map canvas")
        assert int(canvas.get_attribute("data-car-px") or 0) >= 15
        box = canvas.bounding_box()
        assert box is not None and box["y"] + box["height"] > 0
        standings = page.locator("#race-map [data-standings] li")
        assert standings.count() == len(job.entrants)
        assert "lap 1/" in standings.first.inner_text()
        # the timeline's collision link (2.0 s in the fake replay) seeks the map
        page.locator('#events a[href="#t=2.00"]').first.click()
        deadline = time.monotonic() + TIMEOUT_MS / 1000
        while canvas.get_attribute("data-t") != "2.00":  # no eval: the page's CSP forbids it
            assert time.monotonic() < deadline, canvas.get_attribute("data-t")
            page.wait_for_timeout(100)
        assert page.locator("#race-map [data-clock]").inner_text() == "2.0 s"
        shot = canvas.screenshot()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "race_map.png").write_bytes(shot)
        # every car's colour is on the map, each at least a 15 px arrow's worth of pixels
        for i in range(len(job.entrants)):
            assert colour_pixels(shot, car_colour(i)) >= 40, i
        page.locator("#race-map [data-follow]").select_option("1")
        followed = canvas.screenshot()
        (ARTIFACTS / "race_map_follow.png").write_bytes(followed)
        assert int(canvas.get_attribute("data-car-px") or 0) > 18  # zoomed in: true scale
        assert colour_pixels(followed, car_colour(1)) >= colour_pixels(shot, car_colour(1))
        _shot(page, "race_page_720p")
    finally:
        page.close()
    assert not errors, errors


def _sign_in(context: Any, base_url: str, token: str) -> Any:
    page = context.new_page()
    page.goto(base_url + "/signin", timeout=TIMEOUT_MS)
    page.locator('#signin-form input[name="token"]').fill(token)
    page.locator("#signin-form button").click()
    page.wait_for_url("**/users/*", timeout=TIMEOUT_MS)
    return page


def test_only_the_owner_sees_logs(browser: Any, base_url: str, site: Site) -> None:
    from tests.leaderboard.test_pages import _other_user_token

    race = next(
        int(j.job_id)
        for j in site.runner.jobs
        if any(e.name.startswith("random") for e in j.entrants)
    )
    url = f"{base_url}/races/{race}"
    owner = browser.new_context(viewport={"width": 1280, "height": 900})
    other = browser.new_context(viewport={"width": 1280, "height": 900})
    anon = browser.new_context(viewport={"width": 1280, "height": 900})
    for context in (owner, other, anon):
        leave_out_the_player(context)  # logs are the page's; the player is not needed
    try:
        page = _sign_in(owner, base_url, site.token)
        cookie = next(c for c in owner.cookies() if c["name"] == "slipstream_session")
        assert cookie["httpOnly"] and cookie["sameSite"] == "Strict"
        assert page.evaluate("document.cookie").find("slipstream_session") == -1
        page.goto(url, timeout=TIMEOUT_MS)
        logs = page.locator("#owner-logs")
        assert "ZeroDivisionError" in logs.inner_text()
        _shot(page, "race_owner_logs", full_page=True)
        page.locator("#signout").click()
        page.wait_for_url(base_url + "/", timeout=TIMEOUT_MS)
        page.goto(url, timeout=TIMEOUT_MS)
        assert page.locator("#owner-logs").count() == 0  # signed out: gone

        page = _sign_in(other, base_url, _other_user_token(site, "eve_browser"))
        page.goto(url, timeout=TIMEOUT_MS)
        assert page.locator("#signed-in-as").inner_text() == "eve_browser"
        assert page.locator("#owner-logs").count() == 0
        assert "ZeroDivisionError" not in page.content()

        page = anon.new_page()
        page.goto(url, timeout=TIMEOUT_MS)
        assert page.locator("#owner-logs").count() == 0
        assert "ZeroDivisionError" not in page.content()
        assert "DNF (time_limit)" in page.locator("table#results").inner_text()
    finally:
        for context in (owner, other, anon):
            context.close()
