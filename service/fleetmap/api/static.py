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


def _not_installed(place: Path) -> ApiError:
    """The 404 of a request for the web viewer where it is not installed."""
    return ApiError(404, f"the web viewer is not installed ({place} not found); the API is at /docs")


class _ViewerFiles(StaticFiles):
    """The viewer's folder, which may not exist (yet): a request while it does not answers 404
    saying so, as `/` does. Starlette's check of the folder raised RuntimeError instead, a 500 with
    a traceback in the log for each file asked for ($FLEETMAP_WEB_DIR misspelt, an install without
    clients/web). The check runs again at the next request until the folder is there."""

    async def check_config(self) -> None:
        if self.directory is not None and not Path(self.directory).is_dir():
            raise _not_installed(Path(self.directory))
        await super().check_config()


def install(app: FastAPI, web_dir: Path) -> None:
    """Serve `web_dir/index.html` at `/`, `web_dir` at `/static/`, Leaflet at `/vendor/leaflet/`.

    The directory is looked up per request (not checked now), so a viewer installed after start-up,
    or edited while the service runs, is served as it is on disk."""

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        page = web_dir / "index.html"
        if not page.is_file():
            raise _not_installed(page)
        return FileResponse(page, media_type="text/html", headers={"Cache-Control": "no-cache"})

    app.mount("/static", _ViewerFiles(directory=web_dir, check_dir=False), name="static")
    app.mount("/vendor/leaflet", StaticFiles(directory=LEAFLET_DIR), name="leaflet")
