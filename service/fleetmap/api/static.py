"""Static files: the web viewer (clients/web) at `/` and `/static/`, Leaflet at `/vendor/leaflet/`.

Leaflet comes from the `xstatic-leaflet` package, so the viewer works with no internet access.
"""

from __future__ import annotations

import mimetypes
import os
from pathlib import Path

import xstatic.pkg.leaflet as leaflet
from fastapi import FastAPI, Request
from fastapi.staticfiles import StaticFiles
from starlette.datastructures import Headers
from starlette.responses import FileResponse, Response
from starlette.staticfiles import NotModifiedResponse
from starlette.types import Receive, Scope, Send

from fleetmap.api.errors import ApiError
from fleetmap.api.http_semantics import etag_matches, gzips, joined_field_lines, negotiated
from fleetmap.route_path import root_path

#: Leaflet's files (leaflet.js, leaflet.css, images/).
LEAFLET_DIR = Path(leaflet.BASE_DIR)


def _not_installed(place: Path, scope: Scope) -> ApiError:
    """The 404 of a request for the web viewer where it is not installed, naming the API's pages under
    the path the service is served under (`--root-path`): `/docs` was outside it behind a proxy."""
    return ApiError(
        404, f"the web viewer is not installed ({place} not found); the API is at {root_path(scope)}/docs"
    )


class WholeFileResponse(FileResponse):
    """Starlette's `FileResponse`, always of the whole file: a `Range` (and `If-Range`) is ignored,
    as every other answer of the service ignores it (RFC 9110, 14.2, allows that), and no
    `Accept-Ranges: bytes` invites one. Starlette's ranges refused a bad one with a plain-text 400
    ("Range header: range must be requested") or an empty plain-text 416, where every error answer
    of the service is JSON with a `detail`, and refused a unit other than bytes (`items=0-1`), which
    RFC 9110 says to ignore; the viewer's files are small and read whole."""

    def __init__(self, path: str | os.PathLike[str], status_code: int, stat_result: os.stat_result) -> None:
        super().__init__(path, status_code=status_code, stat_result=stat_result)
        del self.headers["accept-ranges"]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = [(name, value) for name, value in scope["headers"] if name not in (b"range", b"if-range")]
        await super().__call__({**scope, "headers": headers}, receive, send)


class ViewerFiles(StaticFiles):
    """Starlette's `StaticFiles`, whose files are answered whole (`WholeFileResponse`), and whose 304
    says what the 200 it stands for would (RFC 9110, 15.4.5).

    The gzip middleware compresses a file's 200 (1 KiB or more, a compressible type) for a client
    that accepts gzip, adding `Vary: Accept-Encoding`, and `DefaultHeaders` makes its strong `ETag`
    weak (`W/"..."`: other bytes). A 304 has no body, so neither happened to it: a browser holding
    the gzipped file under `W/"x"` revalidated it and was told `"x"`, strong, and no `Vary` on
    `Accept-Encoding`; a cache matching the 304's validator to what it stored (RFC 9111, 4.3.4)
    finds nothing to freshen, and fetches the file again."""

    def is_not_modified(self, response_headers: Headers, request_headers: Headers) -> bool:
        """`If-None-Match` as the API reads it (`etag_matches`, RFC 9110 13.1.2): every field line
        of it (a list header, RFC 9110 5.3). Starlette read the first line alone: a client whose
        tag a proxy put on a second line got the whole file. Without `If-None-Match`, Starlette's
        `If-Modified-Since`."""
        if_none_match = joined_field_lines(request_headers, "if-none-match")
        if if_none_match is None:
            return super().is_not_modified(response_headers, request_headers)
        etag = response_headers.get("etag")
        return etag is not None and etag_matches(if_none_match, etag)

    def file_response(
        self,
        full_path: str | os.PathLike[str],
        stat_result: os.stat_result,
        scope: Scope,
        status_code: int = 200,
    ) -> Response:
        # Starlette's, of a `WholeFileResponse`.
        response: Response = WholeFileResponse(full_path, status_code=status_code, stat_result=stat_result)
        if self.is_not_modified(response.headers, Headers(scope=scope)):
            response = NotModifiedResponse(response.headers)
        if response.status_code != 304:
            return response
        media_type = mimetypes.guess_type(str(full_path))[0] or "text/plain"  # as FileResponse
        if negotiated(stat_result.st_size, media_type):  # its 200 says so, compressed or not
            response.headers.add_vary_header("Accept-Encoding")
        if gzips(Headers(scope=scope), stat_result.st_size, media_type):
            etag = response.headers.get("etag")
            if etag is not None and etag.startswith('"'):
                response.headers["etag"] = f"W/{etag}"
        return response


class _ViewerFolder(ViewerFiles):
    """The viewer's folder, which may not exist (yet): a request while it does not answers 404
    saying so, as `/` does. Starlette's check of the folder raised RuntimeError instead, a 500 with
    a traceback in the log for each file asked for ($FLEETMAP_WEB_DIR misspelt, an install without
    clients/web). The check runs again at the next request until the folder is there."""

    async def check_config(self) -> None:
        # A missing folder is `get_response`'s 404, whose message needs the request's scope; the
        # folder is looked for at every request, so one installed later is served.
        if self.directory is not None and not Path(self.directory).is_dir():
            return
        await super().check_config()

    async def get_response(self, path: str, scope: Scope) -> Response:
        if self.directory is not None and not Path(self.directory).is_dir():
            raise _not_installed(Path(self.directory), scope)
        return await super().get_response(path, scope)


def install(app: FastAPI, web_dir: Path) -> None:
    """Serve `web_dir/index.html` at `/`, `web_dir` at `/static/`, Leaflet at `/vendor/leaflet/`.

    The directory is looked up per request (not checked now), so a viewer installed after start-up,
    or edited while the service runs, is served as it is on disk."""

    viewer_files = _ViewerFolder(directory=web_dir, check_dir=False)

    @app.get("/", include_in_schema=False)
    def index(request: Request) -> Response:
        page = web_dir / "index.html"
        if not page.is_file():
            raise _not_installed(page, request.scope)
        # As the files under /static/ are answered: a browser revalidating the page (`no-cache`, on
        # every load) with its ETag gets 304, not the whole page again.
        return viewer_files.file_response(page, page.stat(), request.scope)

    app.mount("/static", viewer_files, name="static")
    app.mount("/vendor/leaflet", ViewerFiles(directory=LEAFLET_DIR), name="leaflet")
