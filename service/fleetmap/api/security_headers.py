"""Security headers: what a browser is told about every answer, and about the web viewer's files.

- Every answer: `X-Content-Type-Options: nosniff`. A browser then takes an answer for what its
  `Content-Type` says, never for what its bytes look like: a JSON answer that echoes a map id or a
  robot's name can never be run as a script or a page, nor a tile as anything but an image.
- Every answer: `X-Frame-Options: DENY`, so no other site can show the viewer (or anything else of
  the service) in a frame and trick its user into clicking on it (clickjacking), and
  `Referrer-Policy: no-referrer`. The viewer's address can name an internal host and the map shown
  (`#map=...` is not sent, but the path and query are), and the service reads no `Referer`: so no
  request the page makes, to the service or to the one outside link it shows (Leaflet's attribution),
  says where it came from. (`same-origin` would send it to the service only, which has no use for it.)
- The viewer's files (`GET /`, `/static/...`, `/vendor/leaflet/...`: `fleetmap.auth.is_viewer_file`):
  a `Content-Security-Policy` that allows exactly what the viewer loads, `VIEWER_CSP`. Should a bug
  ever let a map id, robot name or detail into the page as markup, no script it names would run: no
  inline script, no script from elsewhere, nothing sent anywhere but to the service. Everything else
  (JSON, tiles, `/docs`, whose Swagger UI comes from a CDN with an inline script) gets no policy:
  a policy acts only where a browser renders a page, and the API's pages would need their own.
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from fleetmap.auth import is_viewer_file
from fleetmap.route_path import route_path

#: What the web viewer (clients/web, and Leaflet) loads, and nothing more:
#: - scripts (`leaflet.js`; `app.js` and the ES modules it imports from `/static/`) and style sheets
#:   (`leaflet.css`, `style.css`) from the service; no inline script or `style` attribute (Leaflet and
#:   the viewer set styles through the DOM, which a policy does not restrict). A browser runs a module
#:   script only with a JavaScript `Content-Type` (as `nosniff` asks of every script): `/static/`
#:   names a `.js` file `text/javascript` or `application/javascript` (Python's `mimetypes`);
#: - images from the service (tiles, Leaflet's icons) and `data:` ones (the empty favicon, the
#:   transparent image of a failed tile); robot markers are inline SVG markup, not images;
#: - `fetch` and `EventSource` (`connect-src`) to the service only;
#: - no `<base>` (relative URLs keep meaning the service, behind a proxy's path prefix too), no form
#:   submitted by the browser itself: the viewer's forms are handled by its script, and should that
#:   script not run, the sign-in form must not send its token in a URL (`?token=...` in logs and
#:   history);
#: - no frame may hold the viewer (`frame-ancestors`, the policy's `X-Frame-Options`).
VIEWER_CSP = "; ".join(
    [
        "default-src 'none'",
        "script-src 'self'",
        "style-src 'self'",
        "img-src 'self' data:",
        "connect-src 'self'",
        "base-uri 'none'",
        "form-action 'none'",
        "frame-ancestors 'none'",
    ]
)
#: The headers every answer carries (a route may set its own instead).
EVERY_ANSWER = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
}


class SecurityHeaders:
    """ASGI middleware adding `EVERY_ANSWER` to every answer, and `VIEWER_CSP` to the viewer's files
    (see the module's docstring). Placed outside every middleware that answers by itself (auth's 401,
    the body limit's 413, the shutdown's 503), so that their answers carry the headers too."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        viewer = is_viewer_file(route_path(scope))

        async def with_security_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in EVERY_ANSWER.items():
                    headers.setdefault(name, value)
                if viewer:
                    headers.setdefault("Content-Security-Policy", VIEWER_CSP)
            await send(message)

        await self.app(scope, receive, with_security_headers)
