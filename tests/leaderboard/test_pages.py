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
from leaderboard.models import Race, Submission
from leaderboard.settings import Settings
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
    race_ids = [int(r[0].lstrip("#")) for r in page.tables["my-races"]]
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


def test_submission_page_journey(client: TestClient, site: Site) -> None:
    """Every race with position, μ/σ change, penalties, best lap; bests; head to head."""
    sid = _submission_id(site, "gap")
    page = parse(client.get(f"/submissions/{sid}").text)
    races = page.tables["my-races"]
    entries = {
        int(r[0].lstrip("#")): r for r in races
    }  # race, track, kind, position, status, best, penalties, total, dμ, dσ
    for race_id, row in entries.items():
        detail = client.get(f"/api/races/{race_id}").json()
        mine = next(e for e in detail["entries"] if e["submission_id"] == sid)
        if detail["status"] != "finished":
            assert row[3] == "—"
            continue
        assert row[3] == f"{mine['position']}/{len(detail['entries'])}"
        if detail["kind"] == "ranked":
            assert float(row[8]) == pytest.approx(mine["mu_after"] - mine["mu_before"], abs=0.006)
            assert float(row[9]) == pytest.approx(
                mine["sigma_after"] - mine["sigma_before"], abs=0.006
            )
        else:
            assert row[8] == "—"
    ranked_rows = [r for r in races if r[2] == "ranked"]
    assert ranked_rows
    bests = page.tables["track-bests"]
    for track, best, _race in bests:
        laps = [float(r[5].split()[0]) for r in ranked_rows if r[1] == track and r[5] != "—"]
        assert float(best.split()[0]) == pytest.approx(min(laps), abs=1e-3)
    h2h = {r[0]: r for r in page.tables["head-to-head"]}
    # the fake runner's skill order: pursuit > gap > random, and random never finishes
    if "pursuit" in h2h:
        assert int(h2h["pursuit"][3]) == 0 and int(h2h["pursuit"][4]) == int(h2h["pursuit"][2])
    if "random" in h2h:
        assert int(h2h["random"][3]) == int(h2h["random"][2]) and int(h2h["random"][4]) == 0
    versions = page.tables["versions"]
    assert versions[0][5].startswith("#") and "passed" in versions[0][6]


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
    assert "→" in rows[0][11]  # μ before → after
    assert page.iframes == [viewer_url(f"/replays/{race_id}.viser")]
    svg = re.search(r"<svg.*?</svg>", response.text, re.S)
    assert svg is not None
    # Two finishers with two laps each: four dots, in their cars' colours.
    assert svg.group(0).count("<circle") == 4
    finisher_cars = {int(r[1].removeprefix("car_")) for r in rows[:2]}
    for car in finisher_cars:
        assert charts.car_hex(car) in svg.group(0)


def test_race_page_shows_race_time_penalties_and_events(client: TestClient, site: Site) -> None:
    """The fake runner's car_1 caused a collision (+5 s) in every ranked race (site_data)."""
    job = next(j for j in site.runner.jobs if len(j.entrants) == 3)
    response = client.get(f"/races/{job.job_id}")
    page = parse(response.text)
    by_car = {r[1]: r for r in page.tables["results"]}
    race_time, penalty, total = by_car["car_1"][6:9]
    assert penalty == "+5 s"
    assert float(total.split()[0]) == pytest.approx(float(race_time.split()[0]) + 5.0, abs=1e-3)
    assert by_car["car_0"][7] == "—"
    # what the penalty was for, linked to that moment of the replay
    assert "collision with car_0 (at fault) at 2.0 s" in response.text
    assert "#t=2.00" in page.links
    # the timeline: the contact once, with who was at fault; laps with times; off-tracks
    events = re.findall(r'<li class="ev-(\w+)"><a href="#t=([0-9.]+)">', response.text)
    assert [e[0] for e in events] == ["off_track", "collision", "lap"]
    name_0, name_1 = job.entrants[0].name, job.entrants[1].name
    assert f"{name_1} hit {name_0} ({name_1} at fault)" in response.text
    assert f"{name_0} lap 1 in 4.000 s" in response.text
    # the 2D race map is wired to the raw log; no inline script anywhere
    assert f'data-replay="/replays/{job.job_id}.replay.json.gz"' in response.text
    assert '<script src="/static/race_map.js"' in response.text
    assert not re.search(r"<script(?![^>]*\bsrc=)", response.text)
    assert client.get("/static/race_map.js").status_code == 200


def test_validation_race_has_no_penalties(client: TestClient) -> None:
    response = client.get("/races/1")
    assert "No time penalties in validation races." in response.text
    assert 'id="penalties"' not in response.text


def test_owner_only_fields_stay_out_of_public_pages(client: TestClient, site: Site) -> None:
    from tests.leaderboard.site_data import FAKE_TRACEBACK

    for race_id in (1, 4, 5):
        html = client.get(f"/races/{race_id}").text
        api = client.get(f"/api/races/{race_id}").text
        for text in (html, api):
            assert "ZeroDivisionError" not in text and "says hello" not in text
    assert "ZeroDivisionError" in FAKE_TRACEBACK


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


def test_generated_tracks_get_plots_too(tmp_path: Path) -> None:
    """A generated track in the race pool, or one a race was run on, has a picture; any other
    seed is a 404 without drawing anything (a picture costs ~0.5 s of CPU)."""
    settings = Settings(data_dir=tmp_path / "data", tracks=["oval", "random:3"])
    app = create_app(settings)
    with TestClient(app) as c:
        response = c.get("/tracks/random%3A3/plot.png")
        assert response.status_code == 200 and response.content[:4] == b"\x89PNG"
        cached = list((settings.data_dir / "cache" / "tracks").glob("random-*.png"))
        assert len(cached) == 1  # named by a hash of the spec, never by the spec itself
        assert c.get("/tracks/random%3A5/plot.png").status_code == 404
        session = app.state.sessionmaker()
        session.add(Race(kind="ranked", track="random:5", seed=1, laps=1))
        session.commit()
        session.close()
        assert c.get("/tracks/random%3A5/plot.png").status_code == 200
    assert len(list((settings.data_dir / "cache" / "tracks").glob("random-*.png"))) == 2


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


# ---- signing in and owner-only logs ---------------------------------------------------------


def _other_user_token(site: Site, name: str) -> str:
    from leaderboard import auth
    from leaderboard.db import make_engine, make_sessionmaker

    engine = make_engine(site.settings.db_url)
    try:
        with make_sessionmaker(engine)() as session:
            existing = session.query(auth.User).filter_by(name=name).one_or_none()
            user = existing or auth.create_user(session, name=name)[0]
            _, token = auth.create_token(session, user=user, label="test")
            session.commit()
            return token
    finally:
        engine.dispose()


def _sign_in(client: TestClient, token: str) -> None:
    form = client.get("/signin")
    csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)
    assert csrf is not None
    response = client.post(
        "/signin", data={"token": token, "csrf": csrf.group(1)}, follow_redirects=False
    )
    assert response.status_code == 303, response.text[:300]


def _dnf_race(site: Site) -> int:
    """A race where the (house-owned) random baseline retired: its fake traceback is stored."""
    return next(
        int(j.job_id)
        for j in site.runner.jobs
        if any(e.name.startswith("random") for e in j.entrants)
    )


def test_owner_sees_logs_others_and_visitors_do_not(site: Site) -> None:
    race = _dnf_race(site)
    with TestClient(create_app(site.settings)) as owner:
        _sign_in(owner, site.token)
        cookie = owner.cookies.get("slipstream_session")
        assert cookie
        html = owner.get(f"/races/{race}").text
        assert 'id="owner-logs"' in html and "ZeroDivisionError" in html
        assert "says hello" in html and "sandbox: bwrap" in html
    with TestClient(create_app(site.settings)) as eve:
        _sign_in(eve, _other_user_token(site, "eve"))
        html = eve.get(f"/races/{race}").text
        assert 'id="signed-in-as"' in html  # signed in, but owns no car here
        assert "owner-logs" not in html and "ZeroDivisionError" not in html
    with TestClient(create_app(site.settings)) as visitor:
        html = visitor.get(f"/races/{race}").text
        assert "owner-logs" not in html and "ZeroDivisionError" not in html
        assert "DNF (time_limit)" in html  # the public status stays


def test_logs_api_gives_only_the_callers_cars(client: TestClient, site: Site) -> None:
    race = _dnf_race(site)
    mine = client.get(
        f"/api/races/{race}/logs", headers={"Authorization": f"Bearer {site.token}"}
    ).json()
    assert {log["name"].split(":")[0] for log in mine} >= {"random"}
    random_log = next(log for log in mine if log["name"].startswith("random"))
    assert "ZeroDivisionError" in random_log["dnf_detail"]
    assert random_log["sandbox_mode"] == "bwrap"
    eve = _other_user_token(site, "eve")
    theirs = client.get(f"/api/races/{race}/logs", headers={"Authorization": f"Bearer {eve}"})
    assert theirs.status_code == 200 and theirs.json() == []
    assert client.get(f"/api/races/{race}/logs").status_code == 401


def test_session_cookie_flags_csrf_and_sign_out(site: Site) -> None:
    with TestClient(create_app(site.settings), base_url="https://testserver") as c:
        form = c.get("/signin")
        csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)
        assert csrf is not None
        # a forged sign-in (no matching CSRF cookie value) is refused and opens no session
        bad = c.post("/signin", data={"token": site.token, "csrf": "forged"})
        assert bad.status_code == 403 and "slipstream_session" not in c.cookies
        wrong = c.post("/signin", data={"token": "not-a-token", "csrf": csrf.group(1)})
        assert wrong.status_code == 401 and "Unknown or revoked token" in wrong.text
        ok = c.post(
            "/signin", data={"token": site.token, "csrf": csrf.group(1)}, follow_redirects=False
        )
        flags = ok.headers["set-cookie"].lower()
        assert "slipstream_session=" in flags
        for flag in ("httponly", "samesite=strict", "secure"):
            assert flag in flags
        page = c.get("/races/1").text
        session_csrf = re.search(
            r'action="/signout"><input type="hidden" name="csrf" value="([^"]+)"', page
        )
        assert session_csrf is not None
        # sign-out without the session's CSRF token is refused; with it, the session ends
        assert c.post("/signout", data={"csrf": "forged"}).status_code == 403
        assert 'id="signed-in-as"' in c.get("/races/1").text
        out = c.post("/signout", data={"csrf": session_csrf.group(1)}, follow_redirects=False)
        assert out.status_code == 303
        assert 'id="signin-link"' in c.get("/races/1").text


def test_revoking_the_token_ends_the_session(site: Site) -> None:
    token = _other_user_token(site, "mallory")
    with TestClient(create_app(site.settings)) as c:
        _sign_in(c, token)
        assert 'id="signed-in-as"' in c.get("/").text
        tokens = c.get("/api/tokens", headers={"Authorization": f"Bearer {token}"}).json()
        for row in tokens:
            c.delete(f"/api/tokens/{row['id']}", headers={"Authorization": f"Bearer {token}"})
        assert 'id="signin-link"' in c.get("/").text


def test_races_filters_and_leaderboard_search(client: TestClient) -> None:
    rows = _page(client, "/races?kind=validation").tables["races"]
    assert rows and {r[2] for r in rows} == {"validation"}
    sub = client.get("/api/leaderboard").json()["items"][0]
    rows = _page(client, f"/races?submission={sub['submission_id']}&kind=ranked").tables["races"]
    api = client.get(f"/api/races?submission={sub['submission_id']}&kind=ranked").json()
    assert [int(r[0].lstrip("#")) for r in rows] == [r["id"] for r in api["items"]]
    assert rows and {r[2] for r in rows} == {"ranked"}
    oval = _page(client, "/races?track=oval").tables.get("races", [])
    assert all(r[1] == "oval" for r in oval)
    found = _page(client, "/?q=PURS").tables["leaderboard"]
    assert [r[1].split()[0] for r in found] == ["pursuit"]
    assert "No submission or author matches" in client.get("/?q=nobody-here").text


def test_chart_axis_label_clears_the_top_tick() -> None:
    """Issue 13: the y axis label overlapped the top tick label (11 px text, baselines)."""
    svg = charts.rating_history_svg([(25.0, 8.3), (27.0, 7.0), (26.0, 6.5)])
    label_y = float(re.search(r'class="axis-label" x="[0-9.]+" y="([0-9.]+)"', svg).group(1))  # type: ignore[union-attr]
    tick_ys = [
        float(y)
        for y in re.findall(r'class="tick" x="[0-9.]+" y="([0-9.]+)" text-anchor="end"', svg)
    ]
    assert tick_ys and label_y <= min(tick_ys) - 11


def test_penalty_rules_match_the_race() -> None:
    """The web process lists penalties with its own copy of arena.race's constants."""
    from arena.race import COLLISION_PENALTY, OFF_TRACK_PENALTY
    from leaderboard.results import PENALTY_SECONDS

    assert PENALTY_SECONDS == {"off_track": OFF_TRACK_PENALTY, "collision": COLLISION_PENALTY}


def test_store_result_keeps_owner_fields_private_and_caps_them() -> None:
    """Shapes as submissions.jobs reports them: dnf_detail per car, logs per agent."""
    from leaderboard.results import MAX_DETAIL, split_private

    result = {
        "cars": [
            {"agent": "car_0", "status": "dnf", "dnf_reason": "error", "dnf_detail": "x" * 9000},
            {"agent": "car_1", "status": "finished", "dnf_reason": None, "dnf_detail": None},
        ]
    }
    logs = {"car_0": {"output": "hello\n", "sandbox_mode": "bwrap"}, "nature_0": {"output": "?"}}
    public, private = split_private(result, logs)
    assert all("dnf_detail" not in car for car in public["cars"])
    assert result["cars"][0]["dnf_detail"]  # the caller's document is left alone
    assert set(private) == {0}
    assert len(private[0]["dnf_detail"]) <= MAX_DETAIL + 8
    assert private[0]["output"] == "hello\n" and private[0]["sandbox_mode"] == "bwrap"
