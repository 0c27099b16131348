"""HTTP conventions every answer follows, whatever route made it: HEAD, caching headers, compression.

- `HEAD` is answered on every `GET` route but the event stream, as the `GET` would be (status and
  headers, `Content-Length` and `ETag` included) without the body. FastAPI routes answer only the
  methods they declare, and tile servers' clients and CDNs check tiles with HEAD. The event stream is
  left out: its `GET` never ends, so a HEAD would hold one of the server's event-stream slots. A
  route whose GET is costly to make may answer a HEAD with less (`is_head`): a map's snapshot
  download sends its headers without writing the file, so without its `Content-Length`.
- `Cache-Control: no-cache` on every answer that does not set its own: map data changes with every
  scan, and a CDN in front would otherwise apply its default lifetime (an hour on some) to answers
  without one and serve stale cells and regions. `no-cache` still lets caches store and revalidate.
  When reading needs a token, every answer is also `private`: a shared cache (a CDN, a proxy) must
  not keep what it would then serve to clients it never saw a token from. It stores no answer to a
  request carrying `Authorization` anyway (RFC 9111, 3.5), but it would store one that a browser's
  session cookie unlocked.
- gzip (Starlette's `GZipMiddleware`, as `create_app` installs it, through `NegotiatedGZip`) for
  clients that accept it (`Accept-Encoding` read as RFC 9110 12.5.3 says: `gzip;q=0` refuses it), for
  answers of at least `GZIP_MINIMUM_BYTES`, except those already compressed (PNG, zip) and the event
  stream (each event must reach the client when it is sent; Starlette's middleware leaves
  `text/event-stream` alone). A gzip answer's strong `ETag` (a static file's) is made weak: the
  compressed bytes are another representation, and a strong validator promises the same bytes
  (RFC 9110, 8.8.1).
- JSON answers to GET of at most `JSON_ETAG_MAX_BYTES` (map lists, map info, cells, health) carry a
  weak `ETag`, a hash of the body, and a request whose `If-None-Match` holds it gets 304 without the
  body: a viewer polling `/maps` downloads the list only when it changed (browsers revalidate by
  themselves). Larger answers (regions) are not hashed: it would cost milliseconds per request, on the
  event loop, for answers rarely asked twice unchanged.
- A map's own `ETag` (`map_etag`: `GET /maps/{id}`, and the writes that made or found the map) is
  strong and names the map, not the bytes (docs/api.md, "Conditional writes"; `conditional`): it
  stays strong when the answer is gzipped, so that a client can send it back as `If-Match`, which
  compares strongly, whatever encoding it accepted. Its answers are `no-store`, and a GET whose
  `If-None-Match` holds it gets 304 as for the hashed ETags.
- A PUT that made its map answers 201 with the map's `Location`, one that replaced it or found it as
  asked 200 (`created_status`).
"""

from __future__ import annotations

import hashlib

from starlette.datastructures import Headers, MutableHeaders
from starlette.middleware.gzip import DEFAULT_EXCLUDED_CONTENT_TYPES, GZipMiddleware
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from fleetmap.route_path import root_path, route_path

#: Answers smaller than this are sent as they are: a few hundred bytes gain nothing worth a
#: Content-Encoding (and a tiny gzip body can be larger than the original).
GZIP_MINIMUM_BYTES = 1024
#: zlib level. Starlette compresses on the event loop, which also serves ingest: the fastest level.
#: A 10,000-point `/cells` answer (610 KiB): level 1 99 KiB for 2-4 ms more a request, level 6 73 KiB
#: for 12.5 ms more (docs/api.md, "HTTP conventions").
GZIP_LEVEL = 1
#: JSON answers up to this size get an ETag (hashing 1 MiB takes about a millisecond).
JSON_ETAG_MAX_BYTES = 1024 * 1024
#: What an answer says about caching when its route says nothing.
DEFAULT_CACHE_CONTROL = "no-cache"
#: Directives that keep an answer out of shared caches already.
_PRIVATE_DIRECTIVES = {"private", "no-store"}


def is_event_stream(path: str) -> bool:
    """Whether `path` is a map's event stream, `/maps/{map_id}/events` (ids never hold a `/`)."""
    return path.startswith("/maps/") and path.endswith("/events") and path.count("/") == 3


def joined_field_lines(headers: Headers, name: str) -> str | None:
    """A list header's field lines joined with commas, as one list (RFC 9110, 5.3), or None when it
    is absent: `If-None-Match` and `If-Match` (a tag on a second line, as a proxy merging a client's
    tags sends it, was missed when the first line alone was read), `Accept-Encoding`."""
    lines = headers.getlist(name)
    return ", ".join(lines) if lines else None


#: The scope key `HeadAsGet` sets on the GET a HEAD runs as (`is_head`).
HEAD_SCOPE_KEY = "fleetmap.head"


def is_head(request: Request) -> bool:
    """Whether `request`, a GET to the route, is a HEAD run as a GET by `HeadAsGet`: its body will
    be dropped, so a route may leave out the work of making it."""
    return bool(request.scope.get(HEAD_SCOPE_KEY))


def head_allowed(path: str) -> bool:
    """Whether a HEAD at `path` is answered like the GET there (every path but the event stream)."""
    return not is_event_stream(path)


class HeadAsGet:
    """ASGI middleware: a HEAD request runs as a GET, and its answer's body is dropped (headers kept,
    so `Content-Length` is the GET's). Paths where `head_allowed` is false keep HEAD, so the app
    answers 405 there."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD" or not head_allowed(route_path(scope)):
            await self.app(scope, receive, send)
            return

        async def without_body(message: Message) -> None:
            if message["type"] == "http.response.body":
                message = {**message, "body": b""}
            await send(message)

        # A copy: the server reads the method from its own scope to know it must send no body.
        await self.app({**scope, "method": "GET", HEAD_SCOPE_KEY: True}, receive, without_body)


class DefaultHeaders:
    """ASGI middleware: `Cache-Control: no-cache` on answers without a Cache-Control, `private` added
    to every answer's when `private` (reading needs a token), and a weak `ETag` on gzip answers (see
    the module's docstring). Placed outside the gzip middleware, so that it sees the
    `Content-Encoding`, and outside the auth middleware, so that it covers its answers too."""

    def __init__(self, app: ASGIApp, private: bool = False) -> None:
        self.app = app
        self.private = private

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_defaults(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                cache_control = headers.setdefault("Cache-Control", DEFAULT_CACHE_CONTROL)
                if self.private and not _keeps_out_of_shared_caches(cache_control):
                    headers["Cache-Control"] = f"private, {cache_control}"
                etag = headers.get("ETag")
                gzipped = headers.get("Content-Encoding") == "gzip"
                if etag is not None and gzipped and etag.startswith('"') and not is_map_etag(etag):
                    headers["ETag"] = f"W/{etag}"
            await send(message)

        await self.app(scope, receive, with_defaults)


def _keeps_out_of_shared_caches(cache_control: str) -> bool:
    """Whether a `Cache-Control` value already keeps shared caches from storing the answer."""
    directives = {part.split("=")[0].strip().lower() for part in cache_control.split(",")}
    return bool(directives & _PRIVATE_DIRECTIVES)


def accepts_gzip(accept_encoding: str) -> bool:
    """Whether an `Accept-Encoding` value accepts gzip (RFC 9110, 12.5.3): `gzip` (or `x-gzip`) with
    a weight above 0, or, when it names neither, `*` with a weight above 0. A weight of 0 means "not
    acceptable"; a weight that is no number makes its coding count as unnamed."""
    weights: dict[str, float] = {}
    for item in accept_encoding.split(","):
        coding, *params = (part.strip() for part in item.split(";"))
        weight = 1.0
        for param in params:
            name, _, value = param.partition("=")
            if name.strip().lower() == "q":
                try:
                    weight = float(value)
                except ValueError:
                    weight = -1.0
        if coding and weight >= 0:
            weights.setdefault(coding.lower(), weight)
    for coding in ("gzip", "x-gzip", "*"):
        if coding in weights:
            return weights[coding] > 0
    return False


def negotiated(size: int, media_type: str = "application/json") -> bool:
    """Whether `NegotiatedGZip` negotiates the encoding of a 200 of `size` bytes of `media_type`: at
    least `GZIP_MINIMUM_BYTES`, of a type Starlette does not leave as it is. Such a 200 says `Vary:
    Accept-Encoding` whether it is compressed or not (Starlette's identity responder adds it too, for
    a client that takes no gzip), and so must a 304 standing for it (RFC 9110, 15.4.5), which the
    middleware, finding no body, leaves without."""
    family = f"{media_type.split('/')[0]}/*"
    return (
        size >= GZIP_MINIMUM_BYTES
        and media_type not in DEFAULT_EXCLUDED_CONTENT_TYPES
        and family not in DEFAULT_EXCLUDED_CONTENT_TYPES
    )


def gzips(request_headers: Headers, size: int, media_type: str = "application/json") -> bool:
    """Whether `NegotiatedGZip` compresses a 200 of `size` bytes of `media_type` for a request with
    `request_headers` (read inside it or outside: it leaves `Accept-Encoding: gzip` exactly when
    gzip is acceptable): `negotiated`, and gzip acceptable (`accepts_gzip`). A 304 standing for that
    200 must say the weak tag the compressed 200 would have."""
    offered = joined_field_lines(request_headers, "accept-encoding") or ""
    return negotiated(size, media_type) and accepts_gzip(offered)


class NegotiatedGZip(GZipMiddleware):
    """Starlette's `GZipMiddleware`, deciding from the client's `Accept-Encoding` as `accepts_gzip`
    does. Starlette compresses whenever the header holds the text `gzip`, so a client refusing gzip
    (`gzip;q=0`, as some proxies and tools send) got gzip all the same, bytes it had said it cannot
    read. The middleware sees `Accept-Encoding: gzip` when gzip is acceptable, none otherwise (the
    routes read no `Accept-Encoding`, so they are unaffected).

    The scope's headers are swapped in place, and given back after, rather than the scope copied:
    the router records the route's path parameters in the scope it gets, and the error handler,
    outside every middleware, reads them from the outer one (a bug's log line names its map)."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await super().__call__(scope, receive, send)
            return
        original = scope["headers"]
        offered = joined_field_lines(Headers(scope=scope), "accept-encoding") or ""
        headers = [(k, v) for k, v in original if k.lower() != b"accept-encoding"]
        if accepts_gzip(offered):
            headers.append((b"accept-encoding", b"gzip"))
        scope["headers"] = headers
        try:
            await super().__call__(scope, receive, send)
        finally:
            scope["headers"] = original


def created_status(request: Request, response: Response, map_id: str, *, created: bool) -> None:
    """A PUT's status: 201 with the map's `Location` when it made the map, else 200 (RFC 9110, 9.3.4).
    The `Location` is the map's path under the path the service is served under (`--root-path`):
    `/maps/{map_id}` was outside it behind a proxy that serves the service under a prefix."""
    if created:
        response.status_code = 201
        response.headers["Location"] = f"{root_path(request.scope)}/maps/{map_id}"
    else:
        response.status_code = 200


#: How every map's `ETag` starts (`generation_etag`).
_MAP_ETAG_PREFIX = '"map-'


def generation_etag(generation: int) -> str:
    """The strong entity tag of the map of `generation` (`MapEntry.generation`, which no other map of
    the service, nor of the service before a restart, had): it changes when the map is created,
    replaced, or loaded again, never with a scan."""
    return f'{_MAP_ETAG_PREFIX}{generation}"'


def is_map_etag(etag: str) -> bool:
    """Whether `etag` is a map's (`generation_etag`): a validator of the map, not of an answer's bytes."""
    return etag.startswith(_MAP_ETAG_PREFIX)


def strong_match(tag: str, etag: str) -> bool:
    """RFC 9110 strong comparison (8.8.3.2), as If-Match needs: neither tag is weak and they are equal."""
    return not tag.startswith("W/") and not etag.startswith("W/") and tag == etag


def weak_match(tag: str, etag: str) -> bool:
    """RFC 9110 weak comparison (8.8.3.2), as If-None-Match needs: equal but for a `W/`."""
    return tag.removeprefix("W/") == etag.removeprefix("W/")


def etag_matches(if_none_match: str, etag: str) -> bool:
    """RFC 9110 If-None-Match: a list of (possibly weak) entity tags, or `*`."""
    for candidate in if_none_match.split(","):
        candidate = candidate.strip()
        if candidate == "*" or candidate.removeprefix("W/") == etag.removeprefix("W/"):
            return True
    return False


def json_etag(body: bytes) -> str:
    """The weak ETag of a JSON answer: its content's hash (weak, as its gzip form shares it)."""
    return f'W/"{hashlib.blake2b(body, digest_size=12).hexdigest()}"'


class JsonETags:
    """ASGI middleware: a weak ETag on JSON answers to GET of at most `JSON_ETAG_MAX_BYTES` that have
    none, and 304 for a request whose `If-None-Match` holds it (see the module's docstring); a JSON
    answer that carries its route's own ETag (a map's) gets the 304 the same way. Inside the gzip
    middleware, so that it hashes the JSON itself."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "GET":
            await self.app(scope, receive, send)
            return
        request_headers = Headers(scope=scope)
        if_none_match = joined_field_lines(request_headers, "if-none-match")
        start: Message | None = None
        not_modified = False  # a 304 was sent for the route's own ETag: its body goes nowhere

        async def tagging_send(message: Message) -> None:
            nonlocal start, not_modified
            if not_modified:
                return
            if message["type"] == "http.response.start":
                headers = Headers(raw=message.get("headers", []))
                content_type = headers.get("content-type", "")
                json = message["status"] == 200 and content_type.startswith("application/json")
                own = headers.get("etag")
                if json and own is not None and if_none_match and etag_matches(if_none_match, own):
                    not_modified = True
                    length = int(headers.get("content-length", "0") or 0)
                    await send(_not_modified(message, own, negotiated(length)))
                    await send({"type": "http.response.body", "body": b""})
                    return
                if json and own is None:
                    start = message  # held until the body shows whether it is small and whole
                    return
            elif start is not None and message["type"] == "http.response.body":
                held, start = start, None
                body = message.get("body", b"")
                if not message.get("more_body", False) and len(body) <= JSON_ETAG_MAX_BYTES:
                    etag = json_etag(body)
                    if if_none_match and etag_matches(if_none_match, etag):
                        await send(_not_modified(held, etag, negotiated(len(body))))
                        await send({"type": "http.response.body", "body": b""})
                        return
                    MutableHeaders(scope=held).append("ETag", etag)
                await send(held)
            await send(message)

        await self.app(scope, receive, tagging_send)


def _not_modified(start: Message, etag: str, varies: bool) -> Message:
    """The 304 for a 200's start message: its caching headers, no body headers (RFC 9110, 15.4.5).
    `varies`: the 200's encoding is negotiated (`negotiated`), so it would have said `Vary:
    Accept-Encoding`, compressed or not, which the gzip middleware adds only to answers with a body,
    never to this bodiless one. RFC 9110, 15.4.5: a 304 carries the `Vary` its 200 would have, so a
    cache revalidating a stored answer learns the same selecting header (the 304 said `Vary: Origin`
    alone, or none; and none to a client taking no gzip, whose 200 said `Accept-Encoding`)."""
    kept = [(k, v) for k, v in start.get("headers", []) if k.lower() in (b"cache-control", b"vary")]
    if varies:
        kept.append((b"vary", b"Accept-Encoding"))
    return {"type": "http.response.start", "status": 304, "headers": [*kept, (b"etag", etag.encode())]}
