"""Static mounts: viser's prebuilt replay player at ``/viewer/``, replay files at ``/replays/``.

Replays are static files. After each race the worker records a ``.viser`` file; the site
serves it as it is (already zstd-compressed; ``StaticFiles`` gives ETag, ``If-None-Match`` and
``Range``) and embeds viser's one-file player (818 KB, fetched once and cached by the
browser)::

    <iframe src="/viewer/?playbackPath=/replays/<race id>.viser&hideViserLogo">

The player is the ``client/build/index.html`` that the pinned ``viser`` wheel ships — exactly
what ``viser-build-client --out-dir DIR`` copies, no Node needed. It is copied once into
``<data_dir>/viewer/`` so that a deployment keeps the player that matches its recorded files
(the player warns when a file's viser version differs). ``viser`` is found without importing
it: the import alone costs the web process ~50 MiB.

The player runs JavaScript that a ``.viser`` file or a websocket server sends it, so it is kept
on a short leash (issue 13): every request under ``/viewer`` (``/viewer/``, ``/viewer//``,
``/viewer/index.html``, ...: any path the static files would answer with the player) is
answered only when its ``playbackPath``, if any, is exactly ``/replays/<race id>.viser`` (same
origin) and its other parameters are display settings (:data:`VIEWER_PARAMS`; no
``websocket``); anything else is 400. It is served with its own
Content-Security-Policy (:func:`viewer_csp`): its two inline scripts allowed by hash (the
loader and the code it unpacks), WebAssembly but no ``eval``/``new Function``, connections to
the site only.
"""

from __future__ import annotations

import html
import importlib.util
import logging
import os
import re
import shutil
import tempfile
from functools import lru_cache
from os import PathLike
from pathlib import Path
from typing import Protocol
from urllib.parse import parse_qsl

from fastapi import FastAPI
from starlette.responses import PlainTextResponse, Response
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Receive, Scope, Send

from leaderboard.security import csp_hash
from leaderboard.web.pages import STATIC_DIR

log = logging.getLogger(__name__)

VIEWER_PREFIX = "/viewer"
REPLAYS_PREFIX = "/replays"
STATIC_PREFIX = "/static"
# Content types by file name ending; StaticFiles would guess text/plain for ".viser".
REPLAY_TYPES = {
    ".viser": "application/octet-stream",
    ".replay.json.gz": "application/gzip",
}
REPLAY_MAX_AGE = 7 * 24 * 3600  # s: a race's replay never changes once written
VIEWER_MAX_AGE = 3600  # s: the player changes only when viser is upgraded
PLAYBACK_PATH = re.compile(r"^/replays/[0-9]{1,12}\.viser$")
_VECTOR = re.compile(r"^-?[0-9.eE+-]{1,24}(,-?[0-9.eE+-]{1,24}){0,2}$")
# The player's URL parameters that only change the display, with the values each may take.
VIEWER_PARAMS: dict[str, re.Pattern[str]] = {
    "playbackPath": PLAYBACK_PATH,
    "hideViserLogo": re.compile(r"^[a-z0-9]{0,8}$"),
    "darkMode": re.compile(r"^[a-z0-9]{0,8}$"),
    "showStats": re.compile(r"^[a-z0-9]{0,8}$"),
    "initialCameraPosition": _VECTOR,
    "initialCameraLookAt": _VECTOR,
    "initialCameraUp": _VECTOR,
    "initialCameraFov": _VECTOR,
    "initialCameraNear": _VECTOR,
    "initialCameraFar": _VECTOR,
}
# The packed player: <script data-p="base88(zstd(css + js))" data-ss=.. data-cs=..>loader</script>
_PACKED = re.compile(r'<script data-p="([^"]*)"([^>]*)>(.*?)</script>', re.S)
_B88 = "!#$%()*+,-./0123456789:;=?@ABCDEFGHIJKLMNOPQRSTUVWXYZ[\\]^_abcdefghijklmnopqrstuvwxyz{|}~"


class WebSettings(Protocol):
    """The settings the static mounts read (the service's Settings has them)."""

    @property
    def data_dir(self) -> Path:
        """Folder of the service's files (database, uploads, caches)."""
        ...

    @property
    def replays_dir(self) -> Path:
        """Folder of ``<race id>.viser`` and ``<race id>.replay.json.gz`` files."""
        ...


def viser_client_build() -> Path | None:
    """The installed viser package's prebuilt client folder, or None if viser is missing."""
    spec = importlib.util.find_spec("viser")  # locates the package without running it
    if spec is None or not spec.submodule_search_locations:
        return None
    build = Path(next(iter(spec.submodule_search_locations))) / "client" / "build"
    return build if (build / "index.html").is_file() else None


def ensure_viewer(data_dir: Path) -> Path | None:
    """The viewer folder ``<data_dir>/viewer`` with ``index.html``, copied there if missing.

    Returns:
        The folder, or None when it is missing and viser is not installed (the site then
        shows races without the 3D replay).
    """
    out = Path(data_dir) / "viewer"
    if (out / "index.html").is_file():
        return out
    build = viser_client_build()
    if build is None:
        log.warning("viser is not installed: no 3D replays (pip install 'slipstream[eval]')")
        return None
    out.mkdir(parents=True, exist_ok=True)
    # Copy to a temporary name, then rename: two server processes may start at once.
    fd, tmp = tempfile.mkstemp(dir=out, prefix=".index-", suffix=".html")
    os.close(fd)
    shutil.copyfile(build / "index.html", tmp)
    os.replace(tmp, out / "index.html")
    return out


class CachedStaticFiles(StaticFiles):
    """StaticFiles with a ``Cache-Control`` max-age and content types by file ending."""

    def __init__(
        self, *, directory: Path, max_age: int, types: dict[str, str], html: bool = False
    ) -> None:
        super().__init__(directory=directory, html=html)
        self.max_age = max_age
        self.types = types

    def file_response(
        self,
        full_path: PathLike[str] | str,
        stat_result: os.stat_result,
        scope: Scope,
        status_code: int = 200,
    ) -> Response:
        """The file, with its content type and caching headers set."""
        response = super().file_response(full_path, stat_result, scope, status_code)
        name = os.fspath(full_path)
        for ending, media_type in self.types.items():
            if name.endswith(ending):
                response.headers["content-type"] = media_type
        response.headers["cache-control"] = f"public, max-age={self.max_age}"
        return response


def _base88(text: str) -> bytes:
    """The player loader's base-88 decoding (5 characters → 4 bytes, a short tail)."""
    index = {c: i for i, c in enumerate(_B88)}
    n, rest = divmod(len(text), 5)
    out = bytearray()
    for i in range(0, 5 * n, 5):
        value = 0
        for c in text[i : i + 5]:
            value = value * 88 + index[c]
        out += value.to_bytes(4, "big")
    if rest > 1:
        value = 0
        for c in text[5 * n :]:
            value = value * 88 + index[c]
        out += value.to_bytes(rest - 1, "big")
    return bytes(out)


def inline_script_hashes(index_html: str) -> list[str]:
    """CSP hashes of the player's inline scripts: its loader, and the code the loader unpacks.

    viser's one-file build packs its CSS and JavaScript (zstd, base 88) into a ``data-p``
    attribute; the loader unpacks them and adds the code as an inline module script.

    Raises:
        ValueError: the page is not a packed viser player (or zstandard is missing).
    """
    match = _PACKED.search(index_html)
    if match is None:
        raise ValueError("not a packed viser player")
    import zstandard  # noqa: PLC0415 - a viser dependency; only to hash the player once

    sizes = dict(re.findall(r'data-(ss|cs)="([0-9]+)"', match.group(2)))
    css, code = int(sizes.get("ss", 0)), int(sizes.get("cs", 0))
    raw = zstandard.ZstdDecompressor().decompress(
        _base88(html.unescape(match.group(1))), max_output_size=css + code
    )
    return [csp_hash(match.group(3)), csp_hash(raw[css : css + code].decode())]


# Keyed on the player page itself, not on its path: every data folder holds a copy of the
# same player, and hashing it (a pure-Python base-88 decode of ~800 KB) costs ~0.2 s.
@lru_cache(maxsize=4)
def _viewer_csp(index_html: str) -> str:
    try:
        scripts = " ".join(inline_script_hashes(index_html))
    except (ValueError, ImportError) as err:
        log.warning("replay viewer: cannot hash its scripts (%s); it will not run", err)
        scripts = "'none'"
    return (
        f"default-src 'none'; script-src {scripts} 'wasm-unsafe-eval'; "
        "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
        "connect-src 'self' data: blob:; worker-src 'self' blob: data:; object-src 'none'; "
        "base-uri 'none'; form-action 'none'; frame-ancestors 'self'"
    )


def viewer_csp(viewer_dir: Path) -> str:
    """The Content-Security-Policy of ``/viewer/`` for the player in ``viewer_dir``.

    Scripts: only the player's own two inline scripts (by SHA-256) and WebAssembly (its zstd
    decoder); no ``'unsafe-eval'``, so a script message smuggled into a replay cannot run
    (the player runs those with ``new Function``). Connections: the site only.
    """
    return _viewer_csp((Path(viewer_dir) / "index.html").read_text(encoding="utf-8"))


def viewer_query_error(query_string: str) -> str | None:
    """Why a ``/viewer/`` query is refused, or None if it is allowed.

    >>> viewer_query_error("playbackPath=/replays/7.viser&hideViserLogo") is None
    True
    >>> viewer_query_error("playbackPath=https://evil.example/x.viser")
    "playbackPath must be /replays/<race id>.viser, not 'https://evil.example/x.viser'"
    """
    params = parse_qsl(query_string, keep_blank_values=True)
    names = [name for name, _ in params]
    for name, value in params:
        pattern = VIEWER_PARAMS.get(name)
        if pattern is None:
            return f"unknown viewer parameter {name[:40]!r}"
        if names.count(name) > 1:
            return f"viewer parameter {name[:40]!r} given twice"
        if not pattern.fullmatch(value):  # fullmatch: "$" would let a trailing newline in
            if name == "playbackPath":
                return f"playbackPath must be /replays/<race id>.viser, not {value[:80]!r}"
            return f"bad value for viewer parameter {name!r}"
    return None


class ViewerGuard:
    """ASGI wrapper of the player's static files: the page only with an allowed query.

    Every path is checked, not only ``/viewer/``: the static files answer ``/viewer//``,
    ``/viewer/./`` and the like with the same player page.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Refuse (400) a request whose query :func:`viewer_query_error` rejects."""
        if scope["type"] == "http":
            error = viewer_query_error(scope.get("query_string", b"").decode("latin-1"))
            if error is not None:
                await PlainTextResponse(error, status_code=400)(scope, receive, send)
                return
        await self.app(scope, receive, send)


async def _viewer_missing(scope: Scope, receive: Receive, send: Send) -> None:
    """An ASGI app for ``/viewer`` when viser is not installed: 404 with a hint."""
    response = PlainTextResponse(
        "3D replay viewer not installed: pip install 'slipstream[eval]'", status_code=404
    )
    await response(scope, receive, send)


def mount(app: FastAPI, settings: WebSettings) -> None:
    """Mount ``/static`` (the site's CSS), ``/viewer`` and ``/replays`` on ``app``.

    Creates ``settings.replays_dir`` if missing and copies the viewer into
    ``settings.data_dir / "viewer"`` on first use.
    """
    app.mount(
        STATIC_PREFIX,
        CachedStaticFiles(directory=STATIC_DIR, max_age=VIEWER_MAX_AGE, types={}),
        name="static",
    )
    viewer = ensure_viewer(Path(settings.data_dir))
    if viewer is None:
        app.mount(VIEWER_PREFIX, _viewer_missing, name="viewer")
    else:
        app.state.viewer_csp = viewer_csp(viewer)
        app.mount(
            VIEWER_PREFIX,
            ViewerGuard(
                CachedStaticFiles(directory=viewer, max_age=VIEWER_MAX_AGE, types={}, html=True)
            ),
            name="viewer",
        )
    replays = Path(settings.replays_dir)
    replays.mkdir(parents=True, exist_ok=True)
    app.mount(
        REPLAYS_PREFIX,
        CachedStaticFiles(directory=replays, max_age=REPLAY_MAX_AGE, types=REPLAY_TYPES),
        name="replays",
    )


__all__ = [
    "VIEWER_PARAMS",
    "ViewerGuard",
    "ensure_viewer",
    "inline_script_hashes",
    "mount",
    "viewer_csp",
    "viewer_query_error",
    "viser_client_build",
]
