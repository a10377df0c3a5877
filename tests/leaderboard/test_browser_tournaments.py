"""A tournament's page in a real headless Chromium (Playwright): standings, every heat with
its replay link, and the final as the highlight with its embedded 3D replay.

The site is :func:`tests.leaderboard.site_data.seed_site` plus a time trial of the three
baselines (made-up results through the real worker; the final gets a real ``.viser``
replay); the browser and the uvicorn server are ``tests/leaderboard/test_browser.py``'s.
Screenshots: ``artifacts/browser/tournament*.png``.
"""

from __future__ import annotations

import json
import urllib.request
from collections.abc import Iterator, Sequence
from typing import Any

import pytest

from leaderboard import tournaments
from leaderboard.db import make_engine, make_sessionmaker
from leaderboard.models import Tournament
from leaderboard.worker import Worker
from submissions.jobs import JobResult, RaceJob
from tests.leaderboard.site_data import FakeRunner, Site, seed_site
from tests.leaderboard.test_browser import (  # noqa: F401 - fixtures used by name
    TIMEOUT_MS,
    _shot,
    base_url,
    browser,
    leave_out_the_player,
    pytestmark,
)


class FinalWithReplay(FakeRunner):
    """:class:`FakeRunner`, with a real ``.viser`` replay for every race that is not a solo
    trial (here: the final)."""

    def __call__(self, jobs: Sequence[RaceJob]) -> Iterator[JobResult]:
        for job in jobs:
            self.jobs.append(job)
            yield self.result(job, real_viser=not job.solo)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Site:
    """The three baselines, one ranked race, and a finished time trial of all three."""
    site = seed_site(tmp_path_factory.mktemp("cup-site"), ranked=1)
    engine = make_engine(site.settings.db_url)
    try:
        with make_sessionmaker(engine)() as session:
            cup = tournaments.create_tournament(
                session, site.settings, name="Autumn cup", fmt="time_trial", top=3,
                tracks=["oval", "bean"], seeds=[7], laps=1, final_size=3,
            )  # fmt: skip
            session.commit()
            site.settings.data_dir.joinpath("cup-id").write_text(str(cup.id))
    finally:
        engine.dispose()
    # 6 trials, then the final (and whatever ranked race the seeding left queued).
    worker = Worker(site.settings, runner=FinalWithReplay(), schedule=False, owner="cup")
    try:
        for _ in range(20):
            worker.run(once=True)
            with worker.sessions() as session:
                if session.get(Tournament, cup.id).status == "finished":  # type: ignore[union-attr]
                    break
    finally:
        worker.close()
    return site


def test_the_tournament_page_shows_standings_heats_and_the_final(
    browser: Any,  # noqa: F811
    base_url: str,  # noqa: F811
    site: Site,
) -> None:
    cup_id = int(site.settings.data_dir.joinpath("cup-id").read_text())
    with urllib.request.urlopen(f"{base_url}/api/tournaments/{cup_id}") as response:
        doc = json.load(response)
    assert doc["status"] == "finished" and doc["final"] is not None
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page.set_default_timeout(TIMEOUT_MS)  # software WebGL on a loaded machine is slow
    errors: list[str] = []
    page.on("pageerror", lambda err: "'unsafe-eval'" in str(err) or errors.append(str(err)))
    try:
        page.goto(base_url + "/tournaments", timeout=TIMEOUT_MS)
        page.get_by_role("link", name="Autumn cup").click()
        page.wait_for_url(f"**/tournaments/{cup_id}", timeout=TIMEOUT_MS)
        rows = page.locator("table#standings tbody tr")
        names = [rows.nth(i).locator("td").nth(1).inner_text().split()[0] for i in range(3)]
        assert names == [r["name"] for r in doc["standings"]]
        assert rows.first.get_attribute("class") == "winner"
        heats = page.locator("table#heats tbody tr")
        assert heats.count() == 7  # six trials and the final
        assert page.locator("table#heats a.replay-link").count() == 7
        final = page.locator("section#final")
        assert final.is_visible()
        assert final.locator("ol.podium li").count() == 3
        src = final.locator("iframe#final-replay").get_attribute("src")
        assert src is not None and f"/replays/{doc['final']['race_id']}.viser" in src
        frame = page.frame_locator("iframe#final-replay")
        frame.locator("canvas").first.wait_for(timeout=TIMEOUT_MS)
        _shot(page, "tournament", full_page=True, timeout=TIMEOUT_MS)
        leave_out_the_player(page)  # the race page's player: test_browser.py checks it
        page.locator("table#heats a.replay-link").last.click()
        page.wait_for_url(f"**/races/{doc['final']['race_id']}#replay", timeout=TIMEOUT_MS)
        assert page.locator("iframe#replay").count() == 1
    finally:
        page.close()
    assert not errors, errors
