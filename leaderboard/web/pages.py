"""HTML pages of the leaderboard, server-rendered with Jinja2 (no JavaScript framework).

============================  ============================================  =====================
page                          shows                                         JSON twin (``/api``)
============================  ============================================  =====================
``/``                         leaderboard: rank, name, author, ordinal, μ,  ``/leaderboard``
                              σ, races, win rate, car, robustness score
                              (paginated); ``?q=`` search, ``?car=`` one
                              car class, ``?order=robust`` by robustness
``/submissions/{id}``         versions with validation races and reasons,   ``/submissions/{id}``
                              every race (position, Δμ, Δσ, penalties,
                              best lap), best laps by track, head to head,
                              rating history chart, the robustness run's
                              grid (every point)
``/races``                    all races, newest first (paginated); filters  ``/races``
                              ``track``, ``kind``, ``submission``
``/races/{id}``               results (race time + penalties = total), what ``/races/{id}``
                              each penalty was for, events timeline linked
                              to the 2D race map (``#t=12.3``), embedded 3D
                              replay, lap-time chart; the signed-in owner's
                              logs (``/api/races/{id}/logs``)
``/tracks``                   the race tracks, race counts, lap records     ``/tracks``
``/tracks/{name}``            track plot, records, recent races             ``/tracks/{name}``
``/tracks/{name}/plot.png``   the track plot image (cached in data_dir)
``/users/{name}``             a user's submissions                          ``/users/{name}``
``/tournaments``              the tournaments: format, car, progress,       ``/tournaments``
                              leader
``/tournaments/{id}``         the final (highlighted, replay embedded),     ``/tournaments/{id}``
                              standings (points per place), every heat
                              with its replay link
``/compete``                  every command from nothing to a ranked entry
``/signin``, ``/signout``     sign in with an API token (owner-only logs)
============================  ============================================  =====================

Pages read through :mod:`leaderboard.queries` (the same functions as the JSON API), so the
two never disagree.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Coroutine
from datetime import datetime
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import quote, urlencode

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.routing import APIRoute
from fastapi.templating import Jinja2Templates
from markupsafe import Markup

from leaderboard import auth, queries, tournaments
from leaderboard.api.deps import IdPath, PageDep, SessionDep, SettingsDep
from leaderboard.cache import cache_for
from leaderboard.errors import NotFound
from leaderboard.matchmaking import library_tracks, track_pool
from leaderboard.models import MU0, SIGMA0
from leaderboard.web.charts import car_hex, lap_time_svg, rating_history_svg
from leaderboard.web.session import SignedIn, ViewerDep, session_router
from leaderboard.web.trackplots import track_image
from tracks import load_track
from tracks.errors import TrackError
from tracks.library import RANDOM_PREFIX

# Opponents in a submission's head-to-head table, most met first (``?opponents=all``: every
# one): a veteran met ~200, and their rows were most of the page's size and rendering time.
HEAD_TO_HEAD_ROWS = 20

WEB_DIR = Path(__file__).parent
STATIC_DIR = WEB_DIR / "static"
TEMPLATES_DIR = WEB_DIR / "templates"


class _PageRoute(APIRoute):
    """A page route that answers a missing object with the site's 404 page (not JSON)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def handle(request: Request) -> Response:
            try:
                return await handler(request)
            except (NotFound, TrackError) as err:
                context = {"status_code": 404, "message": str(err)}
                return templates.TemplateResponse(request, "error.html", context, status_code=404)

        return handle


web_router = APIRouter(include_in_schema=False, route_class=_PageRoute)


def _pct(value: float | None) -> str:
    """``0.4567`` → ``"45.7%"``; None → an em dash."""
    return "—" if value is None else f"{100.0 * value:.1f}%"


def _secs(value: float | None) -> str:
    """Seconds with millisecond precision, ``m:ss.sss`` from a minute up; None → a dash."""
    if value is None or not math.isfinite(value):
        return "—"
    if value < 60.0:
        return f"{value:.3f} s"
    minutes, seconds = divmod(value, 60.0)
    return f"{int(minutes)}:{seconds:06.3f}"


def _when(value: datetime | str | None) -> str:
    """A stored UTC time as ``YYYY-MM-DD HH:MM``; None → a dash."""
    if value is None:
        return "—"
    if isinstance(value, str):
        value = datetime.fromisoformat(value)
    # As strftime("%Y-%m-%d %H:%M") writes it, in a fifth of the time (a page has ~50).
    return f"{value.year:04d}-{value.month:02d}-{value.day:02d} {value.hour:02d}:{value.minute:02d}"


def _size(n_bytes: int | None) -> str:
    """A byte count in KiB/MiB (0, a baseline with no file, shows as a dash)."""
    if not n_bytes:
        return "—"
    if n_bytes < 1024 * 1024:
        return f"{n_bytes / 1024:.1f} KiB"
    return f"{n_bytes / (1024 * 1024):.1f} MiB"


@lru_cache(maxsize=1024)  # a few names, each on many rows: Markup.format costs ~10 us
def _track_link(name: str) -> Markup:
    """A link to a track's page (library and generated tracks), else the escaped name."""
    if name in library_tracks() or name.startswith(RANDOM_PREFIX):
        return Markup('<a href="/tracks/{0}">{1}</a>').format(quote(name, safe=""), name)
    return Markup("{0}").format(name)


def make_templates() -> Jinja2Templates:
    """The Jinja2 environment with the site's filters (autoescaping on)."""
    templates = Jinja2Templates(directory=TEMPLATES_DIR)
    filters: dict[str, Any] = {
        "pct": _pct,
        "secs": _secs,
        "when": _when,
        "size": _size,
        "track_link": _track_link,
        "car_colour": car_hex,
    }
    templates.env.filters.update(filters)
    return templates


templates = make_templates()


def _render(
    request: Request, name: str, context: dict[str, Any], viewer: SignedIn | None = None
) -> HTMLResponse:
    """Render template ``name`` with ``context`` (and the signed-in ``viewer``, if any)."""
    return templates.TemplateResponse(request, name, {"viewer": viewer} | context)


def _html(request: Request, name: str, context: dict[str, Any]) -> str:
    """Template ``name`` rendered for a visitor not signed in, as :func:`_render` would."""
    return templates.get_template(name).render({"request": request, "viewer": None} | context)


def _pager(page: queries.Page[Any], base_url: str) -> dict[str, Any]:
    """Template variables of ``_pager.html`` for a page of rows."""
    sep = "&" if "?" in base_url else "?"
    return {"page": page.page, "pages": page.pages, "total": page.total, "base_url": base_url + sep}


def viewer_url(viser_url: str) -> str:
    """The embedded player's URL for a ``.viser`` file served at ``viser_url``.

    >>> viewer_url("/replays/7.viser")
    '/viewer/?playbackPath=/replays/7.viser&hideViserLogo'
    """
    return f"/viewer/?playbackPath={quote(viser_url, safe='/')}&hideViserLogo"


@web_router.get("/", response_class=HTMLResponse)
def leaderboard_page(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    pages: PageDep,
    viewer: ViewerDep,
    q: Annotated[str, Query(max_length=64, description="name or author contains")] = "",
    car: Annotated[str, Query(max_length=16, description="one car class")] = "",
    order: Annotated[Literal["rating", "robust"], Query()] = "rating",
) -> HTMLResponse:
    """The leaderboard: active submissions by ordinal, best first; ``q`` searches it, ``car``
    keeps one car class's ladder, ``order=robust`` ranks by robustness score."""
    q = q.strip()
    car_class = queries.check_car(car)
    page = queries.leaderboard(
        session,
        page=1 if q else pages.page,
        per_page=queries.MAX_PER_PAGE if q else pages.per_page,
        provisional_races=settings.provisional_races,
        max_age_s=settings.cache_max_age_s,
        car=car_class,
        order=order,
    )
    rows = page.items
    if q:  # the snapshot is cached; filtering it costs nothing
        needle = q.lower()
        rows = [r for r in rows if needle in r.name.lower() or needle in r.author.lower()]
    params = {"car": car_class or "", "order": "" if order == "rating" else order}
    query = urlencode({k: v for k, v in params.items() if v})
    context = {
        "nav": "leaderboard",
        "rows": rows,
        "q": q,
        "car": car_class or "",
        "cars": queries.car_classes(),
        "order": order,
        "car_query": urlencode({"car": car_class}) if car_class else "",
        "order_query": f"order={order}" if order != "rating" else "",
        "api_url": "/api/leaderboard" + (f"?{query}" if query else ""),
    }
    base = "/" + (f"?{query}" if query else "")
    pager = (
        {"pages": 1, "page": 1, "total": len(rows), "base_url": base + ("&" if query else "?")}
        if q
        else _pager(page, base)
    )
    return _render(request, "leaderboard.html", context | pager, viewer)


@web_router.get("/races", response_class=HTMLResponse)
def races_page(
    request: Request,
    session: SessionDep,
    pages: PageDep,
    viewer: ViewerDep,
    track: Annotated[str, Query(max_length=128)] = "",
    kind: Annotated[Literal["", "validation", "ranked", "tournament", "robustness"], Query()] = "",
    submission: Annotated[int | None, Query(ge=1, le=2**31 - 1)] = None,
) -> HTMLResponse:
    """All races, newest first; filtered by track, kind and submission."""
    page = queries.races(
        session,
        page=pages.page,
        per_page=pages.per_page,
        track=track or None,
        kind=kind or None,
        submission_id=submission,
    )
    query = {"track": track, "kind": kind, "submission": submission or ""}
    qs = urlencode({k: v for k, v in query.items() if v})
    context = {
        "nav": "races",
        "races": page.items,
        "filters": query,
        "tracks": library_tracks(),
        "api_url": "/api/races" + (f"?{qs}" if qs else ""),
    }
    base = "/races" + (f"?{qs}" if qs else "")
    return _render(request, "races.html", context | _pager(page, base), viewer)


@web_router.get("/races/{race_id}", response_class=HTMLResponse)
def race_page(
    request: Request, session: SessionDep, settings: SettingsDep, race_id: IdPath, viewer: ViewerDep
) -> HTMLResponse:
    """One race: results, lap-time chart and the embedded 3D replay."""
    race = queries.race_detail(session, race_id)
    # Embed the player only when the file is really there (a worker may have failed to write it).
    replay_url = None
    if race.viser_url is not None and (settings.replays_dir / Path(race.viser_url).name).is_file():
        replay_url = viewer_url(race.viser_url)
    map_url = None
    if (
        race.replay_url is not None
        and (settings.replays_dir / Path(race.replay_url).name).is_file()
    ):
        map_url = race.replay_url
    laps = [(e.name, e.lap_times) for e in race.entries]
    context = {
        "nav": "races",
        "race": race,
        "entries": sorted(race.entries, key=lambda e: (e.position is None, e.position, e.car)),
        "replay_url": replay_url,
        "raw_replay_url": race.replay_url,
        "map_replay_url": map_url,
        "laps_svg": lap_time_svg(laps),
        "api_url": f"/api/races/{race_id}",
        # owner-only: the signed-in user's own cars' logs (nobody else's, never for visitors)
        "logs": queries.race_logs(session, race_id, user_id=viewer.user_id) if viewer else [],
    }
    return _render(request, "race.html", context, viewer)


@web_router.get("/submissions/{submission_id}", response_class=HTMLResponse)
def submission_page(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    pages: PageDep,
    submission_id: IdPath,
    viewer: ViewerDep,
    opponents: Annotated[
        Literal["", "all"], Query(description="all: every opponent in the head-to-head table")
    ] = "",
) -> HTMLResponse:
    """One submission: facts, rating history chart, versions and races; the head-to-head
    table lists the :data:`HEAD_TO_HEAD_ROWS` opponents met most (``opponents=all``: all).

    What every visitor sees is cached under :func:`queries.submission_fingerprint` (one
    statement of index look-ups), and rendered once for visitors not signed in; only a
    signed-in viewer's page (its header, whether it owns the submission) is rendered per
    request."""
    fingerprint = queries.submission_fingerprint(session, submission_id)

    def compute() -> tuple[dict[str, Any], str]:
        sub = queries.submission_detail(
            session,
            submission_id,
            races=0,
            provisional_races=settings.provisional_races,
            max_age_s=settings.cache_max_age_s,
            fingerprint=fingerprint,
            cache=False,  # the page made of it is what is kept
        )
        races = queries.submission_entries(
            session, submission_id, page=pages.page, per_page=pages.per_page
        )
        # The chart starts from the prior (race 0), then one point after each rated race.
        history = [(MU0, SIGMA0)] + [(p.mu, p.sigma) for p in sub.rating_history]
        h2h = queries.head_to_head(
            session, submission_id, max_age_s=settings.cache_max_age_s, rated=sub.races
        )
        view = {
            "sub": sub,
            "versions": sub.versions,
            "races": races.items,
            "history_svg": rating_history_svg(history),
            "bests": queries.track_bests(session, submission_id),
            "h2h": h2h if opponents else h2h[:HEAD_TO_HEAD_ROWS],
            "h2h_total": len(h2h),
            "validation": queries.validation_races(session, submission_id),
            "api_url": f"/api/submissions/{submission_id}",
        } | _pager(races, f"/submissions/{submission_id}")
        # Rendered at once for visitors not signed in (most of them): one snapshot per view.
        return view, _html(request, "submission.html", view | {"is_owner": False})

    key = (
        "submission-page",
        submission_id,
        pages.page,
        pages.per_page,
        opponents,
        settings.provisional_races,
    )
    view, html = cache_for(session).get(key, fingerprint, compute, settings.cache_max_age_s)
    if viewer is None:  # every visitor not signed in gets the same page
        return HTMLResponse(html)
    is_owner = viewer.name == view["sub"].author
    return _render(request, "submission.html", view | {"is_owner": is_owner}, viewer)


@web_router.get("/tournaments", response_class=HTMLResponse)
def tournaments_page(
    request: Request, session: SessionDep, pages: PageDep, viewer: ViewerDep
) -> HTMLResponse:
    """Every tournament, newest first, with its progress and leader."""
    page = tournaments.tournament_list(session, page=pages.page, per_page=pages.per_page)
    context = {"nav": "tournaments", "items": page.items, "api_url": "/api/tournaments"}
    return _render(request, "tournaments.html", context | _pager(page, "/tournaments"), viewer)


@web_router.get("/tournaments/{tournament_id}", response_class=HTMLResponse)
def tournament_page(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    tournament_id: IdPath,
    viewer: ViewerDep,
) -> HTMLResponse:
    """One tournament: the final as the highlight (its 3D replay embedded), the standings
    and every heat with its replay link."""
    detail = tournaments.tournament_detail(session, tournament_id)
    # Embed the player only when the file is really there (as the race page does).
    viser = detail.final.viser_url if detail.final is not None else None
    final_replay = None
    if viser is not None and (settings.replays_dir / Path(viser).name).is_file():
        final_replay = viewer_url(viser)
    context = {
        "nav": "tournaments",
        "t": detail,
        "final_replay": final_replay,
        "api_url": f"/api/tournaments/{tournament_id}",
    }
    return _render(request, "tournament.html", context, viewer)


@lru_cache(maxsize=256)
def _track_facts(name: str) -> dict[str, Any]:
    """Length (m), corner count and a one-line summary of a track, or blanks if unknown.

    Cached (a track's geometry does not change while serving); callers merge it into a new
    dict and never change it.
    """
    try:
        track = load_track(name)
    except TrackError:
        return {"length": None, "corners": None, "summary": None}
    from tracks.plot import default_title  # noqa: PLC0415 - pulls in matplotlib

    return {"length": track.length, "corners": track.n_corners, "summary": default_title(track)}


@web_router.get("/tracks", response_class=HTMLResponse)
def tracks_page(
    request: Request, session: SessionDep, settings: SettingsDep, viewer: ViewerDep
) -> HTMLResponse:
    """The tracks ranked races use, with race counts and lap records."""
    rows = [
        t.model_dump() | _track_facts(t.name)
        for t in queries.tracks(session, track_pool(settings), max_age_s=settings.cache_max_age_s)
    ]
    context = {"nav": "tracks", "tracks": rows, "api_url": "/api/tracks"}
    return _render(request, "tracks.html", context, viewer)


@web_router.get("/tracks/{name}", response_class=HTMLResponse)
def track_page(
    request: Request, session: SessionDep, settings: SettingsDep, name: str, viewer: ViewerDep
) -> HTMLResponse:
    """One track: its plot, the lap records and recent races."""
    detail = queries.track_detail(
        session, name, known=track_pool(settings), max_age_s=settings.cache_max_age_s
    )
    facts = _track_facts(name)
    context = {
        "nav": "tracks",
        "track": detail.model_dump() | facts,
        "records": detail.records,
        "races": detail.recent_races,
        "image_url": f"/tracks/{quote(name, safe='')}/plot.png" if facts["length"] else None,
        "api_url": f"/api/tracks/{quote(name, safe='')}",
    }
    return _render(request, "track.html", context, viewer)


@web_router.get("/tracks/{name}/plot.png")
def track_plot(request: Request, session: SessionDep, settings: SettingsDep, name: str) -> Response:
    """The track seen from above (PNG, drawn once and cached in the data folder).

    Only tracks the site shows: the race pool and tracks a race was run on. A picture costs
    ~0.5 s of CPU, so no visitor can make the server draw one generated seed after another.
    """
    if name not in track_pool(settings) and not queries.track_was_raced(session, name):
        raise NotFound(f"no track {name!r}")
    path = track_image(name, settings.data_dir, max_random=settings.random_track_images)
    return FileResponse(path, media_type="image/png", headers={"cache-control": "max-age=86400"})


@web_router.get("/users/{name}", response_class=HTMLResponse)
def user_page(
    request: Request, session: SessionDep, pages: PageDep, name: str, viewer: ViewerDep
) -> HTMLResponse:
    """A user and their submissions."""
    user = auth.get_user(session, name)
    subs = queries.submissions(session, page=pages.page, per_page=pages.per_page, author=name)
    context = {
        "user": user,
        "submissions": subs.items,
        "api_url": f"/api/users/{quote(name, safe='')}",
    }
    pager = _pager(subs, f"/users/{quote(name, safe='')}")
    return _render(request, "user.html", context | pager, viewer)


@web_router.get("/compete", response_class=HTMLResponse)
def compete_page(request: Request, settings: SettingsDep, viewer: ViewerDep) -> HTMLResponse:
    """From nothing to a ranked submission: every command (tested as written)."""
    server = str(request.base_url).rstrip("/")
    context = {
        "nav": "compete",
        "server": server,
        "port": request.url.port or 8000,
        "laps": settings.race_laps,
        "max_cars": settings.max_cars,
    }
    return _render(request, "compete.html", context, viewer)


web_router.include_router(session_router)
