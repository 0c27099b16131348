"""Errors of the REST API: every error answer is JSON `{"detail": "<what is wrong>"}` (`ErrorResponse`).

Bad input never gives a 500: request validation failures become 422 with a sentence naming the
parameter, fleetmap's own exceptions for bad requests (unknown map, conflicting configuration, invalid
id, a layer the map does not keep, an undecodable scan, a bad tile address) get their 4xx status
here, and anything else is a bug: logged with its traceback and answered 500 with a generic detail.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.routing import Match, Mount
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from fleetmap.api.http_semantics import head_allowed
from fleetmap.api_models import ErrorItem, ErrorResponse
from fleetmap.codec import DecodeError, PayloadTooLarge, UnknownEncoding
from fleetmap.grid_map import LayerUnavailableError, RayLimitError
from fleetmap.map_entry import IngestRejected
from fleetmap.memory_budget import MemoryBudgetError
from fleetmap.registry import InvalidId, MapConflict, MapNotFound, NotDurable
from fleetmap.route_path import path_below, root_path, route_path
from fleetmap.scan import ScanError
from fleetmap.tile_render import TileError
from fleetmap.tiles import TileLimitError
from fleetmap.upload_spool import SpoolFailed

log = logging.getLogger("fleetmap.api")

_DESCRIPTIONS = {
    304: "Not modified: the tile's ETag matches If-None-Match",
    404: "Unknown map (or robot, or path)",
    409: "Conflicts with the map's state or configuration",
    412: "Precondition failed: the map's ETag does not match If-Match (it changed, or is gone), or "
    "If-None-Match: * and the map exists; nothing changed",
    413: "The request asks for too much at once",
    415: "The body is not sent as the route reads it (JSON: application/json; a zip: application/zip; "
    "never with a Content-Encoding, nor a Transfer-Encoding other than chunked)",
    422: "Invalid request: bad parameter, body or id",
    429: "Too many failed attempts from this client address: try again after Retry-After",
    503: "The service is overloaded, or could not store a change: retry later",
    507: "The service's memory budget for map tiles (--max-memory) is used up",
}


#: Seconds a 503 tells the client to wait before it retries (`Retry-After`), unless the route says.
RETRY_AFTER_SECONDS = 1
#: The status of a request whose client went away before its answer began (nginx's 499, "client
#: closed request"): sent to no one, it is only counted (`fleetmap_http_responses_total`). Not a 503:
#: nothing failed, and a dropped download counted as one fired the alert on the API's 5xx answers.
CLIENT_CLOSED_REQUEST = 499
#: The spec of the `Retry-After` header every 503 carries.
_RETRY_AFTER_SPEC = {
    "description": f"seconds to wait before retrying ({RETRY_AFTER_SECONDS} unless the answer says more)",
    "schema": {"type": "integer"},
}


def error_responses(
    *statuses: int, described: dict[int, str] | None = None
) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for the error statuses a route may answer; `described` gives the
    route's own description of a status (and adds it), where the shared one would mislead."""
    descriptions = {s: _DESCRIPTIONS[s] for s in statuses} | (described or {})
    responses: dict[int | str, dict[str, Any]] = {}
    for status, text in sorted(descriptions.items()):
        responses[status] = {"model": ErrorResponse, "description": text}
        if status == 503:  # every one carries it (`_json`): a generated client reads it from the spec
            responses[status]["headers"] = {"Retry-After": _RETRY_AFTER_SPEC}
    return responses


class ApiError(Exception):
    """An error answer with a status and a detail (raised by routes), and the list of problems of
    a validation failure (`validation_detail`)."""

    def __init__(
        self,
        status: int,
        detail: str,
        headers: dict[str, str] | None = None,
        errors: list[ErrorItem] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.headers = headers
        self.errors = errors


def too_many(count: int | None, what: str, limit: int) -> ApiError:
    """The 413 of a request asking for more `what` than `limit` at once (`count`, if known): one
    wording, whether the route's own check or the request model's cap (`_SIZE_LIMITED_LISTS`)
    caught it."""
    many = f"{count} {what} is" if count is not None else f"asking for more {what} is"
    return ApiError(413, f"{many} more than the limit of {limit} per request")


#: Request-body lists whose `max_length` is a size limit rather than a shape: past it a request asks
#: for too much at once (413, the status docs/api.md gives), it is not malformed (422). The cap stays
#: in the model because pydantic then refuses a huge list at once, without validating every item on
#: the event loop. Validation-error location -> what the list holds.
_SIZE_LIMITED_LISTS: dict[tuple[str | int, ...], str] = {
    ("body", "points"): "points",
    ("body", "angles"): "rays",
    ("body", "origins"): "rays",
}


def _size_limit_error(errors: Sequence[dict[str, Any]]) -> ApiError | None:
    """The 413 for a validation failure that is a size-limited list over its cap, if there is one."""
    for err in errors:
        what = _SIZE_LIMITED_LISTS.get(tuple(err.get("loc", ())))
        ctx = err.get("ctx") or {}
        if what is not None and err.get("type") == "too_long" and "max_length" in ctx:
            count = ctx.get("actual_length")
            return too_many(count if isinstance(count, int) else None, what, int(ctx["max_length"]))
    return None


class BodyTooLarge(StarletteHTTPException):
    """A request body past the limit. An HTTPException, so FastAPI's body parsing passes it on as is
    (it turns other exceptions raised while reading into a 400)."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"the request body is larger than the limit of {limit} bytes")


#: The path of a snapshot upload, `PUT /maps/{map_id}/snapshot` (an id is `[A-Za-z0-9_-]`).
_SNAPSHOT_PATH = re.compile(r"/maps/[A-Za-z0-9_-]+/snapshot")


#: The request headers that say a body is coded (compressed), by their names as ASGI gives them: the
#: header as named to the client, and the codings of it that leave the body as it was sent (none,
#: `identity`; and `chunked`, which the HTTP server undoes itself).
_CODED_BODY_HEADERS = {
    b"content-encoding": ("Content-Encoding", {b"identity"}),
    b"transfer-encoding": ("Transfer-Encoding", {b"chunked"}),
}


def _codings(value: bytes) -> set[bytes]:
    """The codings a `Content-Encoding` or `Transfer-Encoding` value lists, in lower case."""
    return {coding.strip().lower() for coding in value.split(b",")} - {b""}


class BodyLimitMiddleware:
    """Refuse request bodies over `max_bytes` with a JSON 413: at once when Content-Length says so,
    else as soon as the streamed body passes the limit. (Starlette's own limit answers in plain text.)
    And refuse a body sent with a `Content-Encoding` (gzip, say) with 415 and `Accept-Encoding:
    identity` (RFC 9110, 15.5.16): no route decodes one, and a gzipped JSON body was refused as "not
    UTF-8 text", a gzipped snapshot as "not a zip file", which did not say what to change. Likewise
    a transfer coding other than `chunked` (`Transfer-Encoding: gzip, chunked`): the HTTP server
    undoes the chunks only, and handed the routes the gzipped bytes as the body. Only a request with
    a body (a Content-Length above 0, or a Transfer-Encoding): the header says how a body is
    encoded, and a GET or DELETE that carried it (a client library setting it on every request) was
    refused 415 too, /healthz included."""

    def __init__(self, app: ASGIApp, max_bytes: int, max_snapshot_bytes: int | None = None) -> None:
        self.app = app
        self.max_bytes = max_bytes
        #: The limit of `PUT /maps/{id}/snapshot` (None: `max_bytes`): a map's snapshot file, which
        #: a map of a few hundred tiles makes bigger than any other request.
        self.max_snapshot_bytes = max_bytes if max_snapshot_bytes is None else max_snapshot_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes
        if scope["method"] == "PUT" and _SNAPSHOT_PATH.fullmatch(route_path(scope)):
            limit = self.max_snapshot_bytes
        coding, has_body = None, False
        for name, value in scope.get("headers", ()):
            if name == b"content-length" and value.isdigit():
                if int(value) > limit:
                    exc = BodyTooLarge(limit)
                    await _json(exc.status_code, exc.detail)(scope, receive, send)
                    return
                has_body = has_body or int(value) > 0
            elif name == b"transfer-encoding":  # chunked (or another coding): a body, however long
                has_body = True
            header, plain = _CODED_BODY_HEADERS.get(name, ("", set()))
            if header and _codings(value) - plain:
                coding = f"{header} {value.decode('latin-1')[:40]!r}"
        if coding is not None and has_body:
            detail = f"a body with {coding} is not read here: send it uncompressed"
            await _json(415, detail, headers={"Accept-Encoding": "identity"})(scope, receive, send)
            return
        received = 0

        async def limited() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise BodyTooLarge(limit)
            return message

        await self.app(scope, limited, send)


class StartTracker:
    """An ASGI `send` that passes every message on and remembers whether the answer has started
    (`started`): a middleware that answers an exception itself may do so only before that."""

    def __init__(self, send: Send) -> None:
        self._send = send
        self.started = False

    async def __call__(self, message: Message) -> None:
        self.started = self.started or message["type"] == "http.response.start"
        await self._send(message)


class ShutdownCutoff:
    """A request still running when the server's graceful shutdown runs out (a body trickling in, a
    slow client reading a large answer) is cancelled by uvicorn, which answered it 500 "Internal
    Server Error" in plain text and logged an ERROR with a traceback, as for a bug. Here such a
    request gets 503 JSON with Retry-After instead, when its answer has not started (the client
    retries it on the restarted service: every change is idempotent, a scan by its seq), and one
    WARNING line; an answer already under way is cut off (its connection closes), with the same
    line. (uvicorn cancels a request's task only then, when its graceful shutdown times out.)"""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        tracked = StartTracker(send)
        try:
            await self.app(scope, receive, tracked)
        except asyncio.CancelledError:
            method, path = scope.get("method", "?"), scope.get("path", "?")
            fields = {"method": method, "path": path}
            if tracked.started:
                log.warning("shutdown: %s %s was cut off mid-answer", method, path, extra=fields)
                raise  # uvicorn closes the connection (log_format.ShutdownCutoffLog drops its traceback)
            log.warning("shutdown: %s %s was still running; answered 503", method, path, extra=fields)
            detail = "the server is shutting down and this request did not finish in time; retry it"
            await _json(503, detail, headers={"Connection": "close"})(scope, receive, send)


#: The detail of the 500 that answers a bug: nothing internal (the log has it).
BUG_DETAIL = "internal server error (logged on the server)"
#: Scope key: `BugAnswer` logged this request's exception (and answered it, if it could).
_BUG_ANSWERED = "fleetmap.bug_answered"


def _log_bug(scope: Scope, exc: BaseException) -> None:
    method, path = scope.get("method", "?"), scope.get("path", "?")
    fields = {"method": method, "path": path}
    params = scope.get("path_params") or {}
    fields.update({k: v for k, v in params.items() if k in ("map_id", "robot_id")})
    log.error("internal error on %s %s", method, path, exc_info=exc, extra=fields)


class BugAnswer:
    """ASGI middleware: an exception no handler expected (a bug, not bad input) is logged and
    answered 500 `{"detail": BUG_DETAIL}` here, inside the middleware that puts headers on every
    answer (CORS, `DefaultHeaders`, `SecurityHeaders`). Starlette answers it in its
    `ServerErrorMiddleware`, which it always puts outside every middleware of the app: that 500
    carried none of their headers (no `nosniff`, no `Cache-Control`, no CORS). The exception is
    raised on after the answer, so that the server logs it too (as Starlette does); Starlette's
    handler (`_bug`) then sees the answer started and sends nothing. An answer already under way is
    cut off, as before."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        tracked = StartTracker(send)
        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            _log_bug(scope, exc)
            scope[_BUG_ANSWERED] = True
            if not tracked.started:
                await _json(500, BUG_DETAIL)(scope, receive, send)
            raise


def error_answer(status: int, detail: str, headers: dict[str, str] | None = None) -> JSONResponse:
    """The JSON error answer `{"detail": detail}` with `status`, as every error handler makes it, for
    middleware that answers by itself (it runs outside the handlers)."""
    return _json(status, detail, headers=headers)


def _json(
    status: int, detail: str, errors: list[ErrorItem] | None = None, headers: dict[str, str] | None = None
) -> JSONResponse:
    body = ErrorResponse(detail=detail, errors=errors).model_dump(mode="json", exclude_none=True)
    if status == 503 and not any(name.lower() == "retry-after" for name in headers or {}):
        # Every 503 is "retry later" (see _DESCRIPTIONS): say when, as proxies and HTTP clients read it.
        headers = {**(headers or {}), "Retry-After": str(RETRY_AFTER_SECONDS)}
    return JSONResponse(body, status_code=status, headers=headers)


def _where(loc: Sequence[str | int]) -> str:
    """A readable name for a validation error's location."""
    if not loc:
        return "request"
    kind, rest = loc[0], list(loc[1:])
    path = ""
    for part in rest:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    if kind in ("path", "query", "header", "cookie") and path:
        return f"{kind} parameter {path!r}"
    if kind == "body":
        return f"body.{path}" if path else "body"
    return ".".join(str(p) for p in loc)


def _message(err: dict[str, Any]) -> str:
    loc = list(err.get("loc", ()))
    kind = err.get("type", "")
    msg = str(err.get("msg", "invalid"))
    name = loc[-1] if loc else ""
    if kind == "string_pattern_mismatch" and isinstance(name, str) and name.endswith("_id"):
        return (
            f"{name.replace('_', ' ')} {err.get('input')!r} is not a valid id: ids match "
            "[A-Za-z0-9_-]{1,64}"
        )
    if kind == "json_invalid":
        reason = (err.get("ctx") or {}).get("error")
        return f"body is not valid JSON{f' ({reason})' if reason else ''}"
    if kind == "missing":
        return f"{_where(loc)} is required"
    if kind in ("literal_error", "enum") and "input" in err:
        return f"{_where(loc)}: {err['input']!r} is not allowed; {msg[0].lower()}{msg[1:]}"
    return f"{_where(loc)}: {msg.removeprefix('Value error, ')}"


def validation_detail(errors: Sequence[dict[str, Any]]) -> tuple[str, list[ErrorItem]]:
    """A one-line detail (the first problem, and how many more) and the list of all problems."""
    items = [
        ErrorItem(
            loc=[p if isinstance(p, int) else str(p) for p in e.get("loc", ())],
            msg=str(e.get("msg", "")),
            type=str(e.get("type", "")),
        )
        for e in errors
    ]
    if not errors:
        return "invalid request", items
    detail = _message(dict(errors[0]))
    if len(errors) > 1:
        detail += f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})"
    return detail, items


def _allowed_methods(app: FastAPI, scope: Scope) -> str:
    """The methods some route accepts at this request's path: a mount's (the viewer's files) GET,
    whatever method it is probed with (a mount matches every method; its files take GET only)."""
    # Probed from the app's root: a request refused inside a mount (a POST to a viewer file) has
    # the mount's scope, whose root path ends with the mount's prefix, so no route of the app
    # matched its path and `Allow` was empty.
    base = {**scope, "root_path": root_path(scope)}
    allowed = set()
    for route in app.router.routes:
        if isinstance(route, Mount):
            if route.matches(base)[0] == Match.FULL:
                allowed.add("GET")
            continue
        for method in ("GET", "PUT", "POST", "DELETE", "PATCH"):
            if route.matches({**base, "method": method})[0] == Match.FULL:
                allowed.add(method)
    if "GET" in allowed and head_allowed(route_path(scope)):
        allowed.add("HEAD")  # answered by `HeadAsGet`, in front of the routes
    return ", ".join(sorted(allowed))


def _slash_hint(app: FastAPI, scope: Scope) -> str:
    """For a path with a trailing slash that names a resource without it, the hint to drop the slash.
    (The app does not redirect: one URL per resource, and a redirect's `Location` built from the
    request is wrong behind a TLS-terminating proxy.)"""
    path = route_path(scope)
    if not path.endswith("/") or path == "/":
        return ""
    # The root path (`--root-path`) stays before the bare path: `//` under it is its `/`.
    bare = {**scope, "path": root_path(scope) + (path.rstrip("/") or "/"), "method": "GET"}
    if any(route.matches(bare)[0] != Match.NONE for route in app.router.routes):
        return f" (did you mean {bare['path']}?)"
    return ""


#: fleetmap exceptions that are the client's fault, and their statuses.
_CLIENT_ERRORS: tuple[tuple[type[Exception], int], ...] = (
    (MapNotFound, 404),
    (MapConflict, 409),
    (InvalidId, 422),
    (LayerUnavailableError, 422),
    (RayLimitError, 413),  # a ValueError that asks for too much at once, not a malformed one
    (PayloadTooLarge, 413),  # a DecodeError: Starlette picks the handler of the closest class
    (UnknownEncoding, 415),  # a DecodeError too
    (DecodeError, 422),
    (ScanError, 422),
    (TileError, 422),
    (MemoryBudgetError, 507),  # before its base class: a map whose tiles the budget cannot hold
    (TileLimitError, 409),
)


def _kept_prefix_hint(scope: Scope) -> str:
    """For a path that still starts with the root path once it is taken off (`--root-path /fleetmap`,
    `/fleetmap/fleetmap/maps`), the hint that the proxy in front passed the prefix on: every request
    through it is then a 404, which said nothing of why."""
    root = root_path(scope)
    if path_below(route_path(scope), root) is not None:
        return (
            f" (the service was started with --root-path {root}, for a reverse proxy that strips that "
            "prefix from the requests it passes on; this one still had it)"
        )
    return ""


def install(app: FastAPI) -> None:
    """Register the handlers that turn every error into `ErrorResponse` JSON."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return _json(exc.status, exc.detail, exc.errors, headers=exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            hint = _slash_hint(app, request.scope) or _kept_prefix_hint(request.scope)
            detail = f"no such resource: {request.url.path}{hint}"
        elif exc.status_code == 405 and detail == "Method Not Allowed":
            # Starlette's Allow lists the first matching route's methods only; list every route's.
            allowed = _allowed_methods(app, request.scope)
            detail = f"method {request.method} is not allowed on {request.url.path}; allowed: {allowed}"
            return _json(405, detail, headers={"Allow": allowed})
        elif exc.status_code == 400 and detail == "There was an error parsing the body":
            # FastAPI's answer to a body it cannot even decode (e.g. not UTF-8): one more invalid body.
            return _json(422, "body is not valid JSON (it could not be decoded as UTF-8 text)")
        return _json(exc.status_code, detail, headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        too_big = _size_limit_error(exc.errors())
        if too_big is not None:
            return _json(too_big.status, too_big.detail)
        detail, items = validation_detail(exc.errors())
        return _json(422, detail, items)

    @app.exception_handler(IngestRejected)
    async def _ingest_rejected(request: Request, exc: IngestRejected) -> JSONResponse:
        return _json(exc.status if exc.status >= 400 else 422, exc.reason)

    def _answer(status: int) -> Any:
        async def handler(request: Request, exc: Exception) -> JSONResponse:
            return _json(status, str(exc))  # fleetmap's exceptions carry a sentence for the user

        return handler

    for exc_type, status in _CLIENT_ERRORS:
        app.add_exception_handler(exc_type, _answer(status))
    # Storage, not the client: the change took effect but is not durable; the client may retry.
    app.add_exception_handler(NotDurable, _answer(503))

    @app.exception_handler(SpoolFailed)
    async def _spool_failed(request: Request, exc: SpoolFailed) -> JSONResponse:
        # The service's temporary directory, not the client: 507 when it has no room, else 503 (an
        # I/O error of its disk). Logged, for the operator: the client only sees its upload refused.
        method, path = request.method, request.url.path
        fields = {"method": method, "path": path, "directory": exc.directory}
        level = logging.WARNING if exc.status == 507 else logging.ERROR
        log.log(level, "%s %s refused: %s", method, path, exc, extra=fields)
        return _json(exc.status, str(exc))

    @app.exception_handler(ClientDisconnect)
    async def _client_gone(request: Request, exc: ClientDisconnect) -> JSONResponse:
        # The connection closed before the body arrived whole: the client went away, or its body
        # missed its deadline (--http-body-timeout). Not a bug to log with a traceback (it was, at
        # ERROR, twice per request); the answer goes nowhere (uvicorn drops it: disconnected).
        return _json(400, "the request body was cut off before it arrived whole")

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception) -> JSONResponse:
        # A bug in the middleware outside `BugAnswer` (which answers and logs every other): Starlette
        # calls this from its outermost middleware, and sends the answer only if none started.
        if not request.scope.get(_BUG_ANSWERED):
            _log_bug(request.scope, exc)
        return _json(500, BUG_DETAIL)
