"""API documentation pages served from installed assets: ``/docs`` (Swagger UI) and ``/redoc``.

FastAPI's own pages load their scripts and styles from a CDN, so on a robot's network or any
machine without internet they are blank. These pages take the same assets from the installed
``fastapi-offline`` package (Swagger UI 5 and ReDoc 2, about 2.8 MB, no code of it runs: only
its static folder is used). When the assets are missing the pages answer 503 with a line that
says what to install, never a page that silently fails.
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

log = logging.getLogger(__name__)

#: Where the assets are mounted.
ASSETS_URL = "/docs-assets"
#: Files the pages need.
ASSET_FILES = ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js", "favicon.png")


def assets_dir() -> Path | None:
    """The installed assets folder, or None when ``fastapi-offline`` or a file is missing."""
    try:
        folder = Path(str(resources.files("fastapi_offline") / "static"))
    except ModuleNotFoundError:
        return None
    if not all((folder / name).is_file() for name in ASSET_FILES):
        return None
    return folder


def _missing() -> HTMLResponse:
    return HTMLResponse(
        "<!doctype html><title>pnvlad API docs unavailable</title><p>The API documentation "
        "assets are not installed: <code>pip install fastapi-offline</code> (a dependency of "
        "pnvlad). The OpenAPI document is at <a href='/openapi.json'>/openapi.json</a>.</p>",
        status_code=503,
    )


def install(app: FastAPI) -> None:
    """Add ``/docs``, its OAuth2 redirect and ``/redoc`` to an app made with
    ``docs_url=None, redoc_url=None``."""
    folder = assets_dir()
    if folder is None:
        log.warning("API docs assets (fastapi-offline) not found: /docs and /redoc answer 503")
    else:
        app.mount(ASSETS_URL, StaticFiles(directory=folder), name="docs-assets")
    openapi_url = app.openapi_url or "/openapi.json"
    redirect_url = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        if folder is None:
            return _missing()
        return get_swagger_ui_html(
            openapi_url=openapi_url,
            title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=redirect_url,
            swagger_js_url=f"{ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{ASSETS_URL}/favicon.png",
        )

    @app.get(redirect_url, include_in_schema=False)
    def swagger_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        if folder is None:
            return _missing()
        return get_redoc_html(
            openapi_url=openapi_url,
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{ASSETS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{ASSETS_URL}/favicon.png",
            with_google_fonts=False,
        )
