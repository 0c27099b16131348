"""`create_app(registry, settings=...)`: the service's FastAPI application.

The app holds no map state of its own: every route reads or feeds the `MapRegistry` it is given
(whose integration workers the caller starts). What the app adds is per-app: its Prometheus
registry (`ServiceMetrics`), the tile PNG cache, and the static files of the web viewer.
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic import BaseModel

from fleetmap.api import (
    errors,
    routes_data,
    routes_import,
    routes_maps,
    routes_service,
    routes_session,
    routes_snapshot,
    routes_tiles,
    static,
)
from fleetmap.api.cors import JsonCORS
from fleetmap.api.cross_site import CrossSiteWrites
from fleetmap.api.events import router as events_router
from fleetmap.api.http_semantics import (
    GZIP_LEVEL,
    GZIP_MINIMUM_BYTES,
    JSON_ETAG_MAX_BYTES,
    DefaultHeaders,
    HeadAsGet,
    JsonETags,
    NegotiatedGZip,
)
from fleetmap.api.ingest_priority import IngestGate, IngestPriority
from fleetmap.api.loopback_host import LoopbackHostOnly
from fleetmap.api.security_headers import SecurityHeaders
from fleetmap.api.signin_limit import SignInLimit
from fleetmap.api.state import ApiState
from fleetmap.api_models import (
    MAX_POINTS,
    RegionJson,
    ReplacedEvent,
    RobotsDeltaEvent,
    RobotsEvent,
    TilesEvent,
)
from fleetmap.auth import (
    CHALLENGE,
    SESSION_COOKIE,
    SESSION_PATH,
    AuthMiddleware,
    TokenFile,
    TokenSet,
    is_read_request,
    required_role,
)
from fleetmap.failed_signins import (
    DEFAULT_MAX_CLIENTS,
    DEFAULT_MAX_FAILURES,
    DEFAULT_WINDOW,
    SignInLimiter,
)
from fleetmap.metrics import ROBOT_SERIES_IDLE, IntegrationMetrics, ServiceMetrics, StatusCounter
from fleetmap.registry import MapRegistry
from fleetmap.wire import ScanMessage

log = logging.getLogger("fleetmap.api")

#: The web viewer in a source checkout: <repo>/clients/web.
DEFAULT_WEB_DIR = Path(__file__).resolve().parents[3] / "clients" / "web"
#: Environment variable naming the web viewer's directory (overrides the defaults below).
WEB_DIR_ENV = "FLEETMAP_WEB_DIR"


def default_web_dir() -> Path:
    """Where the web viewer is when `ApiSettings.web_dir` is None: $FLEETMAP_WEB_DIR; else the source
    checkout's clients/web (an editable install); else ./clients/web (an installed package run from the
    project directory, as in the Docker image); else the checkout path (then `/` answers 404)."""
    if os.environ.get(WEB_DIR_ENV):
        return Path(os.environ[WEB_DIR_ENV])
    for candidate in (DEFAULT_WEB_DIR, Path.cwd() / "clients" / "web"):
        if (candidate / "index.html").is_file():
            return candidate
    return DEFAULT_WEB_DIR


DESCRIPTION = """\
Shared occupancy, count and TSDF maps built from a fleet's 2D laser scans.

Robots publish scans over Zenoh (see docs/protocol.md) or `POST /maps/{map_id}/scans`; clients read
cells, rays (where they first meet an obstacle), regions, tiles, TSDF surfaces and exports, and
follow changes live with `GET /maps/{map_id}/events`. Coordinates are metres in the map frame;
cell `(i, j)` of a map with resolution `res` covers `[i*res, (i+1)*res) x [j*res, (j+1)*res)`.
Every error is JSON `{"detail": "..."}`. See docs/api.md.

Authentication: when the server runs with API tokens (`fleetmap serve --auth-tokens FILE`), requests
send `Authorization: Bearer <token>`. Writing (POST scans, PUT and DELETE maps, DELETE regions, PUT snapshots
and imports) needs a token with the `write` or `admin` role; reading is open unless the server requires
a `read` token (`--require-read-token`); `/healthz` and the web viewer's files are always open. A
missing or unknown token is a 401, a token whose role is too low a 403. Without tokens the server
only listens on loopback. A browser, whose tiles and event streams cannot send a header, signs in
with `POST /session`: its session cookie then stands for the token on reads (never on writes). See
docs/security.md.
"""

TAGS = [
    {"name": "service", "description": "Health and metrics."},
    {"name": "maps", "description": "Create, inspect and delete maps."},
    {"name": "ingest", "description": "Scans over HTTP, for clients without Zenoh."},
    {"name": "queries", "description": "Cells, rays, regions and surfaces of a map."},
    {"name": "tiles", "description": "PNG tiles for Leaflet (CRS.Simple)."},
    {"name": "export", "description": "Whole-map exports."},
    {"name": "events", "description": "Server-sent events for live clients."},
    {"name": "session", "description": "Browser sign-in: a cookie standing for an API token on reads."},
]


@dataclass
class ApiSettings:
    """Options of the app. Everything has a default."""

    #: Directory of the web viewer (index.html, app.js and its modules, ...), served at `/` and `/static/`.
    #: None: `default_web_dir()` ($FLEETMAP_WEB_DIR, the checkout's clients/web, ./clients/web).
    web_dir: Path | None = None
    #: Origins allowed by CORS (e.g. ["http://localhost:5173"]); empty: no CORS headers.
    cors_origins: list[str] = field(default_factory=list)
    #: API tokens (`--auth-tokens`, a `TokenFile` read again on SIGHUP); None: no token is asked
    #: for (the service then binds to loopback only).
    tokens: TokenSet | TokenFile | None = None
    #: With `tokens`: reading needs a `read` token too, not only writing.
    require_read_token: bool = False
    #: With `tokens`: failed sign-ins (`POST /session` answered 401) from one client address within
    #: `signin_window` seconds before its sign-ins are answered 429 until the window has passed
    #: (`fleetmap.api.signin_limit`), and how many addresses are tracked at most.
    signin_max_failures: int = DEFAULT_MAX_FAILURES
    signin_window: float = DEFAULT_WINDOW
    signin_max_clients: int = DEFAULT_MAX_CLIENTS
    #: Answer only requests whose `Host` names this machine (`localhost`, a loopback address), 403
    #: to others: a web page whose name was pointed at 127.0.0.1 (DNS rebinding) must not reach a
    #: service without tokens (`fleetmap.api.loopback_host`). `fleetmap serve` sets it without tokens
    #: and without `--insecure`.
    loopback_hosts_only: bool = False
    #: Called by GET /healthz for the Zenoh session's status (`fleetmap serve` passes
    #: `serve_ros.zenoh_status`, the session's and its ROS parts').
    zenoh_status: Callable[[], dict[str, Any]] | None = None
    #: The registry's integration hook. None: the `IntegrationMetrics` whose `on_integrated` the
    #: registry was built with, or, if the registry has no hook, a new one installed on it.
    metrics: IntegrationMetrics | None = None
    #: Seconds after which the counters of a robot neither online nor heard leave /metrics (`serve
    #: --metrics-robot-idle`; `fleetmap.metrics.ROBOT_SERIES_IDLE`): robot ids that came and went
    #: must not grow the scrape for good. Its `fleetmap_robot_online` stays.
    metrics_robot_idle: float = ROBOT_SERIES_IDLE
    #: Seconds POST /scans waits for the integration before answering 503.
    scan_timeout: float = 10.0
    #: Points per POST /cells request (413 past it). At most `MAX_POINTS`: the request model refuses
    #: longer lists before validating them, with the same 413.
    max_points: int = MAX_POINTS
    #: Cells per region / surface (npy, png).
    max_region_cells: int = 16 * 1024 * 1024
    #: Cells per export (`GET /maps/{id}/export`: nav2 zip or PNG of the whole map): 8192 x 8192,
    #: 409.6 m square at 0.05 m. An export holds 3 bytes a cell at most while it is made, a region
    #: 4 or more: the Freiburg campus map (6,039 x 6,059 cells, 36.6 M) exports in 0.5 s with 110 MB
    #: at its peak (PNG: 0.5 s, 77 MB); under the region's limit it could not be exported at all.
    max_export_cells: int = 64 * 1024 * 1024
    #: The map's cells an export reads (its window at the map's resolution): past it 413. An export
    #: at k times the map's resolution reads k * k cells for each it writes; this bounds its time
    #: (about 10 s for the 2^30 cells of a 1.6 km square at 0.05 m) where `max_export_cells` bounds
    #: its memory.
    max_export_read_cells: int = 1 << 30
    #: Cells per region as JSON (much bigger per cell than npy).
    max_json_cells: int = 1024 * 1024
    #: Bytes of a request body (413 past it). A scan's payload has its own, smaller limit, the same as
    #: over Zenoh: `fleetmap.codec.InputLimits.max_payload_bytes` (4 MiB; also 413).
    max_body_bytes: int = 16 * 1024 * 1024
    #: Bytes the tiles of an uploaded snapshot may hold (`PUT /maps/{id}/snapshot`: its tiles.npz, and
    #: all its arrays together; 413 past it, before anything is decompressed). None: what the memory
    #: budget for all maps' tiles holds (`--max-memory`), or without a budget the memory this process
    #: may use (`memory_budget.available_memory`): every map the service could hold can be restored,
    #: whatever its size. (A fixed 4 GiB refused the snapshots of maps of more than about 3,200 tiles
    #: with every layer, which the service downloads, stores and restarts with.)
    max_snapshot_tile_bytes: int | None = None
    #: Bytes of a snapshot upload's body (413 past it). None: as much as the file may hold
    #: decompressed (the tiles' limit, `MAX_SNAPSHOT_META_BYTES` of map.json) and 1 MiB of zip
    #: structure, so that every map an upload may hold can be sent. (`max_body_bytes` refused the
    #: snapshot of a map of 342 tiles, 17.8 MB, that the service had itself written.)
    max_snapshot_body_bytes: int | None = None
    #: Uploads (`PUT .../snapshot`, `PUT .../import`) in progress at once, from their head to their
    #: answer (a slow body until its deadline); past it a new one is refused with 503 before its body
    #: is read. Each
    #: holds up to 17 MiB of memory for its body (`fleetmap.upload_spool`), disk of its size in the
    #: temporary directory (and of its tiles.npz decompressed, if that is compressed), and a worker
    #: thread while it is read (asyncio's pool has 5 on one core). Without it they were bounded only
    #: by the HTTP connections (1024): 16 GiB of memory from slow bodies, or a 1 MiB upload each
    #: making the service write 4 GiB (a compressed tiles.npz of zeros), filling the disk.
    max_uploads: int = 4
    #: Snapshot downloads (`GET .../snapshot`) in progress at once, from their head to the last byte
    #: sent; past it a new one is refused with 503. Each holds a copy of its map's tiles in memory
    #: while its file is written, then the file, of about the map's compressed size, in the
    #: temporary directory until it is sent: without a limit, a reader could make the service hold
    #: as many copies of its biggest map as it opened requests.
    max_downloads: int = 4
    #: Reads of windows of more than `LARGE_READ_CELLS` cells (`GET .../region`, `.../surface`,
    #: `.../export`) in progress at once, from the request to the last byte of the answer sent; past
    #: it a new one is refused with 503 (`api.large_reads`). A region of 16 Mi cells holds about
    #: 450 MB while it is made and its answer (64 MB as npy) until the client has read it: without a
    #: limit, the thread pool's 40 workers and slow readers held as many as a client sent.
    max_large_reads: int = 4
    #: Rendered tiles kept in memory.
    tile_cache_size: int = 4096
    #: Seconds between two polls of an event stream (and so the most often an event is sent).
    events_period: float = 0.1
    #: Seconds of silence after which an event stream sends a `: keepalive` comment (`serve
    #: --events-keepalive`): a stream never stays silent much longer, so clients can take a longer
    #: silence for a dead connection (the Python client's `EVENTS_READ_TIMEOUT` is three of these).
    keepalive: float = 15.0
    #: Event streams open at once (all maps, all clients); past it a new one is refused with 503.
    #: Each holds memory and polls every `events_period`: thousands would starve ingest.
    max_event_streams: int = 256
    #: Ingest before reads (`fleetmap.api.ingest_priority`): while the oldest scan waiting for integration
    #: has waited longer than this many seconds, new HTTP requests wait; 0 switches it off.
    ingest_backlog: float = 0.01
    #: The longest a request waits for the ingest backlog to clear, seconds; then it is served anyway.
    max_read_delay: float = 1.0


def _integration_metrics(registry: MapRegistry, given: IntegrationMetrics | None) -> IntegrationMetrics:
    """The IntegrationMetrics fed by this registry's workers (see ApiSettings.metrics)."""
    if given is not None:
        return given
    # The registry's own hook, if it is an IntegrationMetrics': server.py need not wire it twice.
    hook = registry.on_integrated
    owner = getattr(hook, "__self__", None)
    if isinstance(owner, IntegrationMetrics):
        return owner
    metrics = IntegrationMetrics()
    if hook is None:
        registry.on_integrated = metrics.on_integrated
    else:
        log.warning("the registry's on_integrated hook is not IntegrationMetrics: no latency histograms")
    return metrics


def _version() -> str:
    try:
        return metadata.version("fleetmap")
    except metadata.PackageNotFoundError:  # running from a source tree without installing
        return "0.0.0"


def create_app(registry: MapRegistry, *, settings: ApiSettings | None = None) -> FastAPI:
    """The FastAPI app serving `registry`. The caller starts and closes the registry."""
    settings = settings or ApiSettings()
    app = FastAPI(
        title="fleetmap",
        version=_version(),
        description=DESCRIPTION,
        openapi_tags=TAGS,
        redirect_slashes=False,  # `/maps/` is a 404 naming `/maps` (errors.py), not a redirect
    )
    integration = _integration_metrics(registry, settings.metrics)
    gate = IngestGate(lambda: registry.backlog()[1], settings.ingest_backlog, settings.max_read_delay)
    app.state.fleetmap = ApiState(
        registry=registry,
        settings=settings,
        metrics=ServiceMetrics(registry, integration, settings.metrics_robot_idle),
        web_dir=settings.web_dir if settings.web_dir is not None else default_web_dir(),
        gate=gate,
    )
    if settings.zenoh_status is not None:
        app.state.fleetmap.metrics.watch_zenoh(settings.zenoh_status)
    errors.install(app)
    app.include_router(routes_service.router)
    app.include_router(routes_maps.router)
    app.include_router(routes_data.router)
    app.include_router(routes_tiles.router)
    app.include_router(routes_snapshot.router)
    app.include_router(routes_import.router)
    app.include_router(events_router)
    app.include_router(routes_session.router)
    static.install(app, app.state.fleetmap.web_dir)
    # Middleware, innermost first (each `add_middleware` wraps what is there).
    app.add_middleware(JsonETags)
    # gzip sees every answer as the route made it; the event stream and PNG / zip answers pass as is.
    app.add_middleware(NegotiatedGZip, minimum_size=GZIP_MINIMUM_BYTES, compresslevel=GZIP_LEVEL)
    # Outside gzip: a HEAD's headers (Content-Encoding, Content-Length) are those of the GET.
    app.add_middleware(HeadAsGet)
    app.add_middleware(
        errors.BodyLimitMiddleware,
        max_bytes=settings.max_body_bytes,
        max_snapshot_bytes=app.state.fleetmap.snapshot_body_bytes,
    )
    # A request held back has not been read or run at all.
    app.add_middleware(IngestPriority, gate=gate)
    if settings.tokens is not None:
        app.add_middleware(AuthMiddleware, tokens=settings.tokens, require_read=settings.require_read_token)
        # Outside auth: most failed sign-ins are its 401s, and a refused one must not reach the
        # token check at all.
        limiter = SignInLimiter(
            settings.signin_max_failures, settings.signin_window, settings.signin_max_clients
        )
        app.add_middleware(SignInLimit, limiter=limiter)
    # Outside auth: a viewer whose tiles are refused (401, 403) shows in the counts too.
    metrics = app.state.fleetmap.metrics
    app.add_middleware(StatusCounter, counts=metrics.tile_statuses, only=routes_tiles.is_tile_path)
    # Outside every middleware that waits (the ingest gate, a body being read): a request cancelled
    # at shutdown anywhere in them gets its 503 here, with the CORS and default headers put on it.
    app.add_middleware(errors.ShutdownCutoff)
    # Outside auth and the sign-in limit: a write another site's page started is refused whatever it
    # carries; inside the middleware below, so that its 403 gets their headers.
    app.add_middleware(CrossSiteWrites, allowed_origins=settings.cors_origins)
    if settings.loopback_hosts_only:
        # Outside auth too, for the same reason; its 403 gets the headers of the middleware below.
        app.add_middleware(LoopbackHostOnly)
    # Inside every middleware that puts headers on all answers (below), so that a bug's 500 carries
    # them too: Starlette's own 500 comes from outside them all.
    app.add_middleware(errors.BugAnswer)
    if settings.cors_origins:
        # Outside every middleware that answers by itself, so that every answer to an allowed page
        # carries the CORS headers, the auth middleware's 401 and 403 included: without them the
        # page sees an opaque network error.
        app.add_middleware(
            JsonCORS,
            allow_origins=settings.cors_origins,
            # HEAD too: a page's HEAD with a header a simple request may not carry (`Authorization`,
            # `If-None-Match`) is preflighted, and a refused preflight fails it, though HEAD works
            # wherever GET does (docs/api.md, "HTTP conventions").
            allow_methods=["GET", "HEAD", "PUT", "POST", "DELETE"],
            allow_headers=["*"],
            expose_headers=[
                "ETag",
                "Location",
                "Retry-After",
                "X-Fleetmap-Window",
                "X-Fleetmap-Origin",
                "X-Fleetmap-Resolution",
            ],  # fmt: skip
        )
    # Outermost, as it only adds headers: every answer still carries CORS's (`Vary: Origin`
    # included, which Starlette's CORS middleware puts on every answer, with or without an `Origin`).
    # With a read token required, every answer is `private`: shared caches do not store answers to
    # requests carrying `Authorization`, but they would store those a session cookie unlocked.
    app.add_middleware(DefaultHeaders, private=settings.tokens is not None and settings.require_read_token)
    # Outermost too, for the same reason: every answer, whatever made it, carries them.
    app.add_middleware(SecurityHeaders)
    # Outside everything: every answer the app makes is counted, whichever middleware made it.
    app.add_middleware(StatusCounter, counts=metrics.http_statuses)
    _install_openapi(app)
    return app


#: Models that routes send without FastAPI seeing them as response models (raw JSON bodies, event
#: data) but that clients need in the spec.
EXTRA_SCHEMAS: tuple[type[BaseModel], ...] = (
    ScanMessage, RegionJson, TilesEvent, RobotsEvent, RobotsDeltaEvent, ReplacedEvent,
)  # fmt: skip


def _install_openapi(app: FastAPI) -> None:
    """The generated spec, plus EXTRA_SCHEMAS: POST /scans decodes its body itself (with the same codec
    as Zenoh messages, so FastAPI does not see it as a model), /region answers JSON as raw bytes, and
    event data is not a response at all."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(
                title=app.title,
                version=app.version,
                description=app.description,
                routes=app.routes,
                tags=app.openapi_tags,
            )
            components = schema.setdefault("components", {})
            # Declared optional on each operation (`_declare_security`): whether tokens are needed
            # depends on how the server runs (see DESCRIPTION), and clients of a tokenless server
            # send none.
            components["securitySchemes"] = {
                "bearerToken": {
                    "type": "http",
                    "scheme": "bearer",
                    "description": "an API token (see above)",
                },
                "sessionCookie": {
                    "type": "apiKey",
                    "in": "cookie",
                    "name": SESSION_COOKIE,
                    "description": "a browser's session (POST /session): stands for its token on reads only",
                },
            }
            schemas = components.setdefault("schemas", {})
            for model in EXTRA_SCHEMAS:
                extra = model.model_json_schema(ref_template="#/components/schemas/{model}")
                schemas.update(extra.pop("$defs", {}))
                schemas[model.__name__] = extra
            _declare_json_revalidation(schema)
            _declare_map_etags(schema)
            _declare_security(schema)
            _declare_forbidden(schema)
            app.openapi_schema = _finite(schema)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to extend the schema


def _declare_json_revalidation(schema: dict[str, Any]) -> None:
    """Declare, on every GET that answers JSON, the weak `ETag` its answers carry (`JsonETags`, up to
    JSON_ETAG_MAX_BYTES) and the 304 it gives for a matching `If-None-Match`: the service did both,
    and the spec said neither, so a generated client could not revalidate."""
    etag = {
        # Only JSON answers are hashed: "on answers up to N bytes" promised one on a region's .npy
        # and PNG answers too, which carry none.
        "description": f"a weak validator of a JSON answer of up to {JSON_ETAG_MAX_BYTES} bytes (none on "
        "the operation's other formats): send it back in If-None-Match to get 304 while the answer is "
        "unchanged",
        "schema": {"type": "string"},
    }
    for operations in schema.get("paths", {}).values():
        responses = operations.get("get", {}).get("responses", {})
        ok = responses.get("200", {})
        if "application/json" not in ok.get("content", {}):
            continue
        ok.setdefault("headers", {}).setdefault("ETag", etag)
        responses.setdefault("304", {"description": "Not modified: If-None-Match matches the answer's ETag"})


#: The operations whose answers carry a map's own strong `ETag` (`fleetmap.api.conditional`), and
#: their statuses that do.
_MAP_ETAG_ANSWERS = {
    ("/maps/{map_id}", "get"): ("200",),
    ("/maps/{map_id}", "put"): ("200", "201"),
    ("/maps/{map_id}/snapshot", "put"): ("200", "201"),
    ("/maps/{map_id}/import", "put"): ("200", "201"),
}


def _declare_map_etags(schema: dict[str, Any]) -> None:
    """Declare the map's strong `ETag` on the answers that carry it (in place of the weak hash that
    `_declare_json_revalidation` declares on JSON GETs), a 412's included: a generated client reads
    it there to send it back as `If-Match`. And a 201's `Location`."""
    etag = {
        "description": "the map's strong entity tag: it changes when the map is created, replaced or "
        "loaded again (a restart), not with scans. Send it as If-Match with PUT or DELETE of the map, "
        "or an upload, to have the write refused with 412 if the map changed meanwhile",
        "schema": {"type": "string"},
    }
    paths = schema.get("paths", {})
    for (path, method), statuses in _MAP_ETAG_ANSWERS.items():
        responses = paths[path][method]["responses"]
        for status in statuses:
            responses[status].setdefault("headers", {})["ETag"] = etag
    # The 412 of a failed condition carries the map's ETag (`conditional.Preconditions`), and a 201
    # of a PUT the made map's `Location` (`http_semantics.created_status`): both were sent, and a
    # generated client knew neither from the spec.
    current = {**etag, "description": "the map's current entity tag, when the map exists (send it again)"}
    location = {
        "description": "the map made: /maps/{map_id} (under `--root-path`)",
        "schema": {"type": "string"},
    }
    for operations in paths.values():
        for operation in operations.values():
            responses = operation.get("responses", {})
            if "412" in responses:
                responses["412"].setdefault("headers", {})["ETag"] = current
            if "201" in responses:
                responses["201"].setdefault("headers", {})["Location"] = location
    paths["/maps/{map_id}"]["get"]["responses"]["304"] = {
        "description": "Not modified: If-None-Match holds the map's ETag (the same map, configuration)"
    }


#: The 401 and 403 of an operation that needs a token when the server runs with tokens, by the role
#: it needs (`fleetmap.auth.required_role`).
_AUTH_ERRORS = {
    "read": {
        "401": "With API tokens and `--require-read-token`: no token, or an unknown or revoked one "
        "(a session cookie's too)",
    },
    "write": {
        "401": "With API tokens (`--auth-tokens`): no token, or an unknown or revoked one (a session "
        "cookie never stands for a token on a write)",
        "403": "With API tokens: the token's role is too low (a `read` token)",
    },
}
#: The 403s of any request, whatever it needs: a `Host` of another machine (`loopback_hosts_only`),
#: and for a write (`fleetmap.auth.is_read_request`), another site's page (`CrossSiteWrites`).
_ANY_REQUEST_403 = (
    "Without API tokens (and without `--insecure`): a `Host` that names no loopback host (DNS "
    "rebinding: docs/security.md)"
)
_CROSS_SITE_403 = (
    "With or without tokens: a write that a browser says a page of another site started "
    "(`Sec-Fetch-Site`, `Origin`), unless `--cors-origin` allows that page"
)


def _declare_security(schema: dict[str, Any]) -> None:
    """Declare on every operation that may need a token the schemes that carry one, optional (`{}`:
    a server without tokens needs none), and the 401 / 403 it answers without a right one. Declared
    only in the components, the schemes applied to no operation: Swagger UI's Authorize sent the
    token with none of them (every write tried from /docs was a 401), and generated clients had no
    place for it nor a documented 401."""
    error = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}}
    challenge = {"WWW-Authenticate": {"description": CHALLENGE, "schema": {"type": "string"}}}
    for path, operations in schema.get("paths", {}).items():
        if path == SESSION_PATH:  # its own: signing in needs a token (routes_session)
            # Its 401 comes from the auth middleware too, challenge included.
            operations["post"]["responses"]["401"].setdefault("headers", challenge)
            continue
        concrete = re.sub(r"\{[^}]*\}", "x", path)
        for method, operation in operations.items():
            needed = required_role(method.upper(), concrete, require_read=True)
            if needed is None:
                continue
            schemes: list[dict[str, list[str]]] = [{"bearerToken": []}]
            if needed == "read":  # a browser's session cookie stands for its token on reads only
                schemes.append({"sessionCookie": []})
            operation["security"] = [*schemes, {}]
            responses = operation["responses"]
            for status, description in _AUTH_ERRORS[needed].items():
                answer: dict[str, Any] = {"description": description, "content": error}
                if status == "401":
                    answer["headers"] = challenge
                responses.setdefault(status, answer)


def _declare_forbidden(schema: dict[str, Any]) -> None:
    """Declare on every operation the 403s any request may get besides a token's role (after
    `_declare_security`, whose 403 it completes): the spec gave a 403 to writes that need a token
    alone, none to reads, `/healthz` or signing in and out, which answer it all the same."""
    error = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}}
    for path, operations in schema.get("paths", {}).items():
        concrete = re.sub(r"\{[^}]*\}", "x", path)
        for method, operation in operations.items():
            reasons = [_ANY_REQUEST_403]
            if not is_read_request(method.upper(), concrete):
                reasons.append(_CROSS_SITE_403)
            answer = operation["responses"].setdefault("403", {"description": "", "content": error})
            answer["description"] = ". ".join(filter(None, [answer["description"], *reasons]))


def _finite(node: Any) -> Any:
    """The spec without non-finite numbers, which JSON cannot hold: a default of +inf (ScanMessage's
    range_max, "no maximum") is dropped, as omitting the field means exactly that."""
    if isinstance(node, dict):
        return {
            key: _finite(value)
            for key, value in node.items()
            if not (isinstance(value, float) and not math.isfinite(value))
        }
    if isinstance(node, list):
        return [_finite(value) for value in node]
    return node
