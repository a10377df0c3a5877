"""The website's HTML pages, charts and static mounts, against a seeded temporary database."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from leaderboard.app import create_app
from leaderboard.models import Submission
from leaderboard.web import charts
from leaderboard.web.pages import viewer_url
from tests.leaderboard.site_data import Site, seed_site


class _Tables(HTMLParser):
    """Collects the text of every table row (cells stripped) by table id, and all links."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self.links: list[str] = []
        self.iframes: list[str] = []
        self._table: str | None = None
        self._row: list[str] | None = None
        self._cell: list[str] | None = None
        self._in_body = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "table":
            self._table = a.get("id") or a.get("class") or "table"
            self.tables.setdefault(self._table, [])
        elif tag == "tbody":
            self._in_body = True
        elif tag == "tr" and self._in_body:
            self._row = []
        elif tag == "td" and self._row is not None:
            self._cell = []
        elif tag == "a" and a.get("href"):
            self.links.append(str(a["href"]))
        elif tag == "iframe":
            self.iframes.append(str(a.get("src")))

    def handle_endtag(self, tag: str) -> None:
        if tag == "td" and self._row is not None and self._cell is not None:
            self._row.append(" ".join("".join(self._cell).split()))
            self._cell = None
        elif tag == "tr" and self._row is not None and self._table is not None:
            self.tables[self._table].append(self._row)
            self._row = None
        elif tag == "tbody":
            self._in_body = False

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def parse(html: str) -> _Tables:
    """Tables, links and iframes of a page."""
    parser = _Tables()
    parser.feed(html)
    return parser


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Site:
    """Three baselines, their validation races and six ranked races (placeholder replays)."""
    return seed_site(tmp_path_factory.mktemp("site"), ranked=6)


@pytest.fixture(scope="module")
def client(site: Site) -> Iterator[TestClient]:
    """A client of an app on the seeded database."""
    with TestClient(create_app(site.settings)) as c:
        yield c


def _page(client: TestClient, url: str) -> _Tables:
    response = client.get(url)
    assert response.status_code == 200, (url, response.text[:300])
    assert response.headers["content-type"].startswith("text/html")
    return parse(response.text)


# ---- leaderboard -----------------------------------------------------------------------------


def test_leaderboard_rows_follow_the_api_order(client: TestClient) -> None:
    page = _page(client, "/")
    rows = page.tables["leaderboard"]
    api = client.get("/api/leaderboard").json()["items"]
    assert [r[1].split()[0] for r in rows] == [item["name"] for item in api]
    assert [r[0] for r in rows] == ["1", "2", "3"]
    assert sorted(r[1].split()[0] for r in rows) == ["gap", "pursuit", "random"]
    ordinals = [float(r[3]) for r in rows]
    assert ordinals == sorted(ordinals, reverse=True)
    top = api[0]
    assert rows[0][2] == "house"
    assert rows[0][3] == f"{top['ordinal']:.2f}"
    assert rows[0][4] == f"{top['mu']:.2f}" and rows[0][5] == f"{top['sigma']:.2f}"
    assert rows[0][6] == str(top["races"])
    assert rows[0][7] == f"{100 * top['win_rate']:.1f}%"
    assert "/api/leaderboard" in page.links and "/docs" in page.links


def test_leaderboard_paginates(client: TestClient) -> None:
    first = _page(client, "/?per_page=2")
    second = _page(client, "/?per_page=2&page=2")
    assert len(first.tables["leaderboard"]) == 2
    assert [r[0] for r in second.tables["leaderboard"]] == ["3"]
    assert "/?page=2" in first.links and "/?page=1" in second.links


def test_empty_leaderboard_says_how_to_upload(tmp_path: Path) -> None:
    from leaderboard.settings import Settings

    with TestClient(create_app(Settings(data_dir=tmp_path))) as c:
        response = c.get("/")
    assert response.status_code == 200
    assert "No ranked submissions yet" in response.text and "slipstream submit" in response.text


# ---- submissions, users ----------------------------------------------------------------------


def _submission_id(site: Site, name: str) -> int:
    from sqlalchemy import select

    from leaderboard.db import make_engine, make_sessionmaker

    engine = make_engine(site.settings.db_url)
    try:
        with make_sessionmaker(engine)() as session:
            sid = session.scalar(select(Submission.id).where(Submission.name == name))
    finally:
        engine.dispose()
    assert sid is not None
    return int(sid)


def test_submission_page_has_versions_races_and_history(client: TestClient, site: Site) -> None:
    sid = _submission_id(site, "pursuit")
    response = client.get(f"/submissions/{sid}")
    page = parse(response.text)
    api = client.get(f"/api/submissions/{sid}").json()
    assert [r[0] for r in page.tables["versions"]] == ["v1"]
    assert page.tables["versions"][0][2] == "validated"
    race_ids = [int(r[0].lstrip("#")) for r in page.tables["races"]]
    api_races = client.get(f"/api/submissions/{sid}/races").json()["items"]
    assert race_ids == [r["id"] for r in api_races]
    finished = [r for r in api_races if r["status"] == "finished"]
    assert len(finished) == api["races"] + 1  # the ranked races and the validation race
    # The chart: the prior plus one point per rated race, drawn as μ and ordinal lines.
    svg = re.search(r"<svg.*?</svg>", response.text, re.S)
    assert svg is not None and svg.group(0).count("<polyline") == 2
    mu_line = re.search(r'<polyline class="series" points="([^"]+)"', svg.group(0))
    assert mu_line is not None and len(mu_line.group(1).split()) == api["races"] + 1
    assert len(api["rating_history"]) == api["races"] > 0
    assert f"/api/submissions/{sid}" in page.links


def test_submission_text_is_escaped(client: TestClient, site: Site) -> None:
    from leaderboard.db import make_engine, make_sessionmaker

    sid = _submission_id(site, "gap")
    engine = make_engine(site.settings.db_url)
    try:
        with make_sessionmaker(engine)() as session:
            sub = session.get(Submission, sid)
            assert sub is not None
            sub.description = "<script>alert(1)</script>"
            session.commit()
    finally:
        engine.dispose()
    text = client.get(f"/submissions/{sid}").text
    assert "<script>alert(1)</script>" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text


def test_user_page_lists_submissions(client: TestClient) -> None:
    page = _page(client, "/users/house")
    assert sorted(r[0] for r in page.tables["user-submissions"]) == ["gap", "pursuit", "random"]


@pytest.mark.parametrize("url", ["/submissions/9999", "/races/9999", "/users/nobody"])
def test_missing_objects_are_html_404s(client: TestClient, url: str) -> None:
    response = client.get(url)
    assert response.status_code == 404
    assert response.headers["content-type"].startswith("text/html")
    assert "Back to the leaderboard" in response.text


# ---- races -----------------------------------------------------------------------------------


def test_races_page_lists_every_race_newest_first(client: TestClient) -> None:
    rows = _page(client, "/races").tables["races"]
    ids = [int(r[0].lstrip("#")) for r in rows]
    assert ids == sorted(ids, reverse=True)
    finished = sorted(int(r[0].lstrip("#")) for r in rows if r[3] == "finished")
    assert finished == list(range(1, 10))  # the nine races the worker ran
    assert {r[3] for r in rows} <= {"finished", "queued"}  # and the ones it queued after
    assert {r[2] for r in rows} == {"validation", "ranked"}


def test_race_page_results_chart_and_replay(client: TestClient, site: Site) -> None:
    race_id = next(
        int(j.job_id) for j in site.runner.jobs if len(j.entrants) == 3
    )  # a ranked three-car race
    response = client.get(f"/races/{race_id}")
    page = parse(response.text)
    rows = page.tables["results"]
    assert [r[0] for r in rows] == ["1", "2", "3"]
    assert rows[0][2].startswith("pursuit") and rows[1][2].startswith("gap")
    assert rows[2][3] == "DNF (time_limit)" and rows[2][5] == "—"
    assert "→" in rows[0][9]  # μ before → after
    assert page.iframes == [viewer_url(f"/replays/{race_id}.viser")]
    svg = re.search(r"<svg.*?</svg>", response.text, re.S)
    assert svg is not None
    # Two finishers with two laps each: four dots, in their cars' colours.
    assert svg.group(0).count("<circle") == 4
    finisher_cars = {int(r[1].removeprefix("car_")) for r in rows[:2]}
    for car in finisher_cars:
        assert charts.car_hex(car) in svg.group(0)


def test_race_without_replay_file_shows_no_player(client: TestClient, site: Site) -> None:
    (site.settings.replays_dir / "2.viser").unlink()
    response = client.get("/races/2")
    assert response.status_code == 200
    assert not parse(response.text).iframes
    assert "No 3D replay" in response.text


# ---- tracks ----------------------------------------------------------------------------------


def test_tracks_page_and_records(client: TestClient) -> None:
    rows = _page(client, "/tracks").tables["tracks"]
    assert [r[0] for r in rows] == ["oval", "bean"]
    api = {t["name"]: t for t in client.get("/api/tracks").json()}
    for r in rows:
        assert int(r[3]) == api[r[0]]["races"]
    page = _page(client, "/tracks/bean")
    records = page.tables["records"]
    assert records[0][1] == "pursuit" and len(records) == 2  # random never finished a lap
    assert "/tracks/bean/plot.png" in client.get("/tracks/bean").text


def test_track_plot_is_a_cached_png(client: TestClient, site: Site) -> None:
    response = client.get("/tracks/oval/plot.png")
    assert response.status_code == 200
    assert response.headers["content-type"] == "image/png"
    assert response.content[:4] == b"\x89PNG"
    assert (site.settings.data_dir / "cache" / "tracks" / "oval.png").is_file()


def test_generated_tracks_get_plots_too(client: TestClient, site: Site) -> None:
    response = client.get("/tracks/random%3A3/plot.png")
    assert response.status_code == 200 and response.content[:4] == b"\x89PNG"
    cached = list((site.settings.data_dir / "cache" / "tracks").glob("random-*.png"))
    assert len(cached) == 1  # named by a hash of the spec, never by the spec itself


@pytest.mark.parametrize(
    "url", ["/tracks/nowhere", "/tracks/nowhere/plot.png", "/tracks/..%2F..%2Fetc/plot.png"]
)
def test_unknown_tracks_are_404s(client: TestClient, url: str) -> None:
    assert client.get(url).status_code == 404


# ---- static mounts ---------------------------------------------------------------------------


def test_viewer_and_replays_are_served(client: TestClient) -> None:
    viewer = client.get("/viewer/")
    assert viewer.status_code == 200 and "<html" in viewer.text[:200].lower()
    replay = client.get("/replays/1.viser")
    assert replay.status_code == 200
    assert replay.headers["content-type"] == "application/octet-stream"
    assert "max-age" in replay.headers["cache-control"]
    again = client.get("/replays/1.viser", headers={"if-none-match": replay.headers["etag"]})
    assert again.status_code == 304
    part = client.get("/replays/1.viser", headers={"range": "bytes=0-3"})
    assert part.status_code == 206 and part.content == replay.content[:4]
    assert client.get("/replays/../leaderboard.db").status_code == 404
    assert client.get("/static/style.css").headers["content-type"].startswith("text/css")


# ---- charts and process hygiene --------------------------------------------------------------


def test_charts_handle_no_data() -> None:
    assert "no rated races yet" in charts.rating_history_svg([])
    assert "no completed laps" in charts.lap_time_svg([("a", []), ("b", [])])
    one = charts.rating_history_svg([(25.0, 25.0 / 3)])
    assert one.count("<polyline") == 2


def test_web_process_imports_no_simulator(site: Site) -> None:
    """Every page and API read, on a seeded database, runs without pybullet, torch or viser."""
    code = textwrap.dedent(
        f"""
        import sys
        from fastapi.testclient import TestClient
        from leaderboard.app import create_app
        from leaderboard.settings import Settings
        settings = Settings(data_dir={str(site.settings.data_dir)!r}, tracks=["oval", "bean"])
        urls = ("/", "/races", "/races/4", "/submissions/1", "/users/house", "/tracks",
                "/tracks/oval", "/tracks/oval/plot.png", "/viewer/", "/api/leaderboard",
                "/api/tracks", "/api/races", "/api/races/4", "/api/submissions/1")
        with TestClient(create_app(settings)) as c:
            for url in urls:
                assert c.get(url).status_code == 200, url
        heavy = [m for m in ("pybullet", "torch", "viser") if m in sys.modules]
        print("heavy:", heavy)
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "heavy: []" in out.stdout
