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
"""

from __future__ import annotations

import importlib.util
import logging
import os
import shutil
import tempfile
from os import PathLike
from pathlib import Path
from typing import Protocol

from fastapi import FastAPI
from starlette.responses import PlainTextResponse, Response
from starlette.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send

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
        app.mount(
            VIEWER_PREFIX,
            CachedStaticFiles(directory=viewer, max_age=VIEWER_MAX_AGE, types={}, html=True),
            name="viewer",
        )
    replays = Path(settings.replays_dir)
    replays.mkdir(parents=True, exist_ok=True)
    app.mount(
        REPLAYS_PREFIX,
        CachedStaticFiles(directory=replays, max_age=REPLAY_MAX_AGE, types=REPLAY_TYPES),
        name="replays",
    )


__all__ = ["ensure_viewer", "mount", "viser_client_build"]
