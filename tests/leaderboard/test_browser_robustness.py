"""The robustness column and the robust ordering in a real headless Chromium (Playwright).

The site is :func:`tests.leaderboard.site_data.seed_site` with each baseline's robustness run
stored (made-up scores that order the baselines differently from their ratings); the
browser, the uvicorn server and the screenshot helper are ``tests/leaderboard/
test_browser.py``'s. Screenshots: ``artifacts/browser/leaderboard_robust*.png``.
"""

from __future__ import annotations

import json
import urllib.request
from typing import Any

import pytest

from tests.leaderboard.site_data import Site, seed_site
from tests.leaderboard.test_browser import (  # noqa: F401 - fixtures used by name
    TIMEOUT_MS,
    _shot,
    base_url,
    browser,
    pytestmark,
)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Site:
    """The three baselines, their robustness runs and two ranked races."""
    return seed_site(tmp_path_factory.mktemp("robust-site"), ranked=2, robustness=True)


def _api(url: str) -> list[dict[str, Any]]:
    with urllib.request.urlopen(url) as response:
        items: list[dict[str, Any]] = json.load(response)["items"]
    return items


def _names(page: Any) -> list[str]:
    rows = page.locator("table#leaderboard tbody tr")
    rows.first.wait_for(timeout=TIMEOUT_MS)
    return [rows.nth(i).locator("td").nth(1).inner_text().split()[0] for i in range(rows.count())]


def test_the_robust_column_and_ordering_show(browser: Any, base_url: str) -> None:  # noqa: F811
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.set_default_timeout(TIMEOUT_MS)  # software WebGL on a loaded machine is slow
    try:
        page.goto(base_url + "/", timeout=TIMEOUT_MS)
        by_rating = _api(base_url + "/api/leaderboard")
        assert _names(page) == [r["name"] for r in by_rating]
        headers = page.locator("table#leaderboard thead th").all_inner_texts()
        assert "robust" in headers
        cells = page.locator("table#leaderboard tbody td.robust").all_inner_texts()
        assert cells == [f"{r['robust_score']:.2f}" for r in by_rating]
        _shot(page, "leaderboard_robust_column", full_page=True, timeout=TIMEOUT_MS)

        page.locator("a#order-robust").click()
        page.wait_for_url("**/?order=robust", timeout=TIMEOUT_MS)
        by_robust = _api(base_url + "/api/leaderboard?order=robust")
        scores = [r["robust_score"] for r in by_robust]
        assert scores == sorted(scores, reverse=True)
        assert [r["name"] for r in by_robust] != [r["name"] for r in by_rating]  # a new view
        assert _names(page) == [r["name"] for r in by_robust]
        assert page.locator("#order strong").inner_text() == "robustness"
        _shot(page, "leaderboard_robust", full_page=True, timeout=TIMEOUT_MS)

        top = by_robust[0]
        page.locator("table#leaderboard tbody td.robust a").first.click()
        page.wait_for_url(f"**/submissions/{top['submission_id']}#robustness", timeout=TIMEOUT_MS)
        grid = page.locator("table#robust-grid tbody tr")
        assert grid.count() == 9  # the nominal lap and the 8 grid corners
        assert page.locator("#robust-score").inner_text() == f"{top['robust_score']:.2f} m/s"
        _shot(page, "leaderboard_robust_submission", full_page=True, timeout=TIMEOUT_MS)
    finally:
        page.close()
