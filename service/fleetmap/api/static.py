"""Static files: the web viewer (clients/web) at `/` and `/static/`, Leaflet at `/vendor/leaflet/`.

Leaflet comes from the `xstatic-leaflet` package, so the viewer works with no internet access.
"""

from __future__ import annotations

from pathlib import Path

import xstatic.pkg.leaflet as leaflet
from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from fleetmap.api.errors import ApiError

#: Leaflet's files (leaflet.js, leaflet.css, images/).
LEAFLET_DIR = Path(leaflet.BASE_DIR)


def install(app: FastAPI, web_dir: Path) -> None:
    """Serve `web_dir/index.html` at `/`, `web_dir` at `/static/`, Leaflet at `/vendor/leaflet/`.

    The directory is looked up per request (not checked now), so a viewer installed after start-up,
    or edited while the service runs, is served as it is on disk."""

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        page = web_dir / "index.html"
        if not page.is_file():
            raise ApiError(404, f"the web viewer is not installed ({page} not found); the API is at /docs")
        return FileResponse(page, media_type="text/html", headers={"Cache-Control": "no-cache"})

    app.mount("/static", StaticFiles(directory=web_dir, check_dir=False), name="static")
    app.mount("/vendor/leaflet", StaticFiles(directory=LEAFLET_DIR), name="leaflet")
