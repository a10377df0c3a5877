"""The API documentation pages, ``/docs`` (Swagger UI) and ``/redoc``, working offline.

FastAPI's own pages load Swagger UI, ReDoc and fonts from a CDN, so they are blank on a
machine without internet. Here the same pages (FastAPI's HTML) load the assets from the
``fastapi-offline`` package, served at :data:`ASSETS_PREFIX`, and no web fonts. Each page gets
a Content-Security-Policy that allows its one inline script by hash and nothing from
elsewhere (ReDoc also needs ``blob:`` workers and inline styles).
"""

from __future__ import annotations

import re
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from leaderboard.security import csp_hash

ASSETS_PREFIX = "/static-docs"
ASSETS_DIR = Path(fastapi_offline.__file__).parent / "static"
DOCS_PATHS = ("/docs", "/redoc")
_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.S)
_BASE_CSP = (
    "default-src 'none'; img-src 'self' data:; font-src 'self' data:; connect-src 'self'; "
    "object-src 'none'; base-uri 'self'; form-action 'self'; frame-ancestors 'self'"
)


def _page(response: HTMLResponse, extra: str) -> HTMLResponse:
    """``response`` with a CSP allowing its inline scripts by hash, plus ``extra`` sources."""
    body = bytes(response.body).decode()
    hashes = " ".join(csp_hash(m) for m in _INLINE_SCRIPT.findall(body))
    csp = f"{_BASE_CSP}; script-src 'self' {hashes}; {extra}"
    return HTMLResponse(body, headers={"content-security-policy": csp})


def add_offline_docs(app: FastAPI) -> None:
    """Serve ``/docs`` and ``/redoc`` with packaged assets (create ``app`` with both URLs None)."""
    app.mount(ASSETS_PREFIX, StaticFiles(directory=ASSETS_DIR), name="docs-assets")
    openapi_url = app.openapi_url or "/openapi.json"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        page = get_swagger_ui_html(
            openapi_url=f"{root}{openapi_url}",
            title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{root}{ASSETS_PREFIX}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{ASSETS_PREFIX}/swagger-ui.css",
            swagger_favicon_url=f"{root}{ASSETS_PREFIX}/favicon.png",
            swagger_ui_parameters=app.swagger_ui_parameters,
        )
        return _page(page, "style-src 'self' 'unsafe-inline'; worker-src 'self' blob:")

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        page = get_redoc_html(
            openapi_url=f"{root}{openapi_url}",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}{ASSETS_PREFIX}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{ASSETS_PREFIX}/favicon.png",
            with_google_fonts=False,
        )
        return _page(page, "style-src 'self' 'unsafe-inline'; worker-src 'self' blob:")


__all__ = ["ASSETS_PREFIX", "DOCS_PATHS", "add_offline_docs"]
