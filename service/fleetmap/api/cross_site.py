"""Cross-site writes: a page on another site must not change maps through its visitor's browser.

A browser lets any page send a "simple" request anywhere without asking the target first (no CORS
preflight): a POST whose body has no `Content-Type`, say, which `fetch(url, {method: 'POST', mode:
'no-cors', body: bytes})` sends. Its answer stays hidden from the page, but the request is made. The
scans route sniffs a body without a type (docs/protocol.md), so any web page a user of a service
without tokens (the default, on `127.0.0.1`) opened could create maps and integrate scans into them:
cross-site request forgery. (With tokens a write needs an `Authorization` header, which no page can
send elsewhere without a preflight the CORS settings refuse, and the session cookie unlocks reads
only.)

`CrossSiteWrites` refuses, with a JSON 403, a write request (`fleetmap.auth.is_read_request` is false;
preflights aside) that a browser says another page started, unless that page's origin is one
`--cors-origin` allows:
- `Sec-Fetch-Site` (every current browser sends it): `same-origin` (the web viewer's own sign-in) and
  `none` (the user typed or bookmarked it) pass; `same-site` and `cross-site` are refused;
- without it (an older browser), an `Origin` header is compared with the request's `Host`: the same
  host and port pass, any other is refused;
- without either, the request is not a browser's page's (the Python client, curl, a robot): it
  passes, as before.
This is the check of Go's `net/http.CrossOriginProtection`. Reads are not checked: they change
nothing, and the page cannot read their answers (CORS allows no other origin unless configured).
"""

from __future__ import annotations

from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from fleetmap.api.errors import error_answer
from fleetmap.auth import is_read_request
from fleetmap.route_path import route_path

#: `Sec-Fetch-Site` values of requests the browser's user or the service's own pages started.
_OWN_REQUESTS = ("same-origin", "none")


class CrossSiteWrites:
    """ASGI middleware refusing (403) writes another page started in a browser, unless its origin is
    in `allowed_origins` (`--cors-origin`; `*` allows every origin). See the module's docstring."""

    def __init__(self, app: ASGIApp, allowed_origins: list[str]) -> None:
        self.app = app
        self.allowed_origins = set(allowed_origins)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] == "OPTIONS"
            or is_read_request(scope["method"], route_path(scope))
        ):
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        origin = headers.get("origin")
        if self._started_elsewhere(headers.get("sec-fetch-site"), origin, headers.get("host")):
            page = f"a page of {origin}" if origin else "a page of another site"
            detail = (
                f"cross-site request refused: {page} may not change anything here; a page served "
                "elsewhere must be allowed with fleetmap serve --cors-origin"
            )
            await error_answer(403, detail)(scope, receive, send)
            return
        await self.app(scope, receive, send)

    def _started_elsewhere(self, fetch_site: str | None, origin: str | None, host: str | None) -> bool:
        """Whether a browser says another page started the request, one `allowed_origins` lacks."""
        if origin is not None and ("*" in self.allowed_origins or origin in self.allowed_origins):
            return False
        if fetch_site is not None:
            return fetch_site.strip().lower() not in _OWN_REQUESTS
        if origin is None:
            return False  # not a page's request: no browser leaves `Origin` out of a write
        # An older browser: the page's origin must name the host the request went to. An origin that
        # is no URL (`null`, from a sandboxed frame or a file) names none.
        try:
            origin_host = urlsplit(origin).netloc
        except ValueError:
            return True
        return not origin_host or host is None or origin_host.lower() != host.strip().lower()
