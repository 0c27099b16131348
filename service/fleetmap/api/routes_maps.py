"""Map lifecycle (list, create, read, delete) and scans over HTTP."""

from __future__ import annotations

import asyncio
from typing import Annotated, cast

from fastapi import APIRouter, Body, Request, Response

from fleetmap import codec
from fleetmap.api.conditional import Conditions, tag_map
from fleetmap.api.config_body import MapConfigBody, PastTodaysLimits
from fleetmap.api.errors import ApiError, error_responses
from fleetmap.api.http_semantics import created_status
from fleetmap.api.revocation import refuse_if_revoked
from fleetmap.api.state import MapId, RobotId, State
from fleetmap.api.strict_requests import StrictRoute, limit_json_values
from fleetmap.api_models import (
    MapInfo,
    MapList,
    ScanResult,
    map_info,
    map_summary,
    tile_windows,
)
from fleetmap.config import MapConfig
from fleetmap.map_entry import IngestRejected
from fleetmap.registry import MapNotFound
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING

router = APIRouter(route_class=StrictRoute)
# A configuration holds a few dozen values (`PUT /maps/{map_id}`): far more is no configuration.
limit_json_values("/maps/{map_id}", 1024, "the values of a map configuration")

#: Scan bodies up to this size are decoded on the event loop (a 1081-beam JSON scan is about 10 KB and
#: decodes in well under a millisecond: a thread hop would cost more); larger ones in a thread.
DECODE_ON_LOOP_BYTES = 256 * 1024


# -- maps -------------------------------------------------------------------------------------------


@router.get("/maps", tags=["maps"], summary="List maps", response_model=MapList)
def list_maps(state: State) -> MapList:
    """Every map with its resolution, layers and counters (no cell statistics: see GET /maps/{map_id})."""
    registry = state.registry
    return MapList(maps=[map_summary(e, registry.lock) for e in sorted(registry.list(), key=lambda e: e.id)])


@router.put(
    "/maps/{map_id}",
    tags=["maps"],
    summary="Create a map",
    response_model=MapInfo,
    responses={
        201: {"model": MapInfo, "description": "Created"},
        **error_responses(409, 412, 413, 415, 422, 503, 507),
    },
)
def put_map(
    map_id: MapId,
    state: State,
    request: Request,
    response: Response,
    conditions: Conditions,
    # Not `| None`: then a JSON null was taken for no body, the server's default configuration;
    # without it FastAPI still gives the default for no body (not validated), and refuses a null.
    config: Annotated[
        MapConfigBody,
        Body(
            description="The map's configuration; every field is optional. No body: the server's "
            "default configuration (a JSON null is refused)."
        ),
    ] = None,  # type: ignore[assignment]
) -> MapInfo:
    """Creates the map (201, with its `Location`), answering once it is stored (with durable
    storage). If it exists with the same configuration, nothing changes (200); with a different one,
    409, naming each field that differs (the map's value first): delete it first.
    Configurations compare after defaults and presets are resolved, so `{}` equals the defaults
    written out, and `layers` in any order. 503: the map was created but could not be stored; the
    service retries, and the same PUT answers 200 once it is stored. `If-None-Match: *`: create
    only (412 if the map exists, even with the same configuration); `If-Match`: only if the map
    exists with that `ETag` (412 otherwise, before the configurations are compared). 507: a new
    map of a configuration whose one tile needs more than the whole memory budget
    (`--max-memory`), which could never hold one: nothing is made. The answer carries the map's
    `ETag`. 401, nothing made, if the request's token was revoked while its body arrived
    (`refuse_if_revoked`)."""
    refuse_if_revoked(request.scope)  # its body came after the token was checked
    expect = conditions.expectation(map_id)
    # What the body's validator gives (typed as a MapConfig, for the spec), None for no body.
    given = cast("MapConfig | PastTodaysLimits | None", config)
    if isinstance(given, PastTodaysLimits):  # the configuration of a map stored before a limit
        expect = given.only_as_its_map(expect)
        given = given.config
    entry, created = state.registry.create(map_id, given, wait=True, expect=expect)
    created_status(request, response, map_id, created=created)
    tag_map(response, entry)
    return map_info(entry, state.registry.lock)


@router.get(
    "/maps/{map_id}",
    tags=["maps"],
    summary="A map's configuration and statistics",
    response_model=MapInfo,
    responses=error_responses(404, 422),
)
def get_map(map_id: MapId, state: State, response: Response) -> MapInfo:
    """`{"id", "config", "resolution", "tile_size", "stats": {"scans_integrated", "scans_rejected",
    "robots": {robot_id: {...}}, "bounds", "tiles", "memory_bytes", "version"}}`. `bounds` is
    `[xmin, ymin, xmax, ymax]` in metres of the observed cells, or null for an empty map. The
    `ETag` is the map's (strong; it changes when the map is created, replaced or restarted, not with
    scans): send it as `If-Match` with a write to make the write fail (412) if the map changed
    meanwhile. With `If-None-Match` holding it the answer is a 304 (same map, same configuration);
    the answer is `no-store`, since its statistics change while the tag stays."""
    entry = state.entry(map_id)
    tag_map(response, entry)
    return map_info(entry, state.registry.lock)


@router.delete(
    "/maps/{map_id}",
    tags=["maps"],
    summary="Delete a map",
    status_code=204,
    response_class=Response,
    responses=error_responses(404, 412, 422, 503),
)
def delete_map(map_id: MapId, state: State, conditions: Conditions) -> Response:
    """Removes the map, its robots and its queued scans, answering once that is stored (with durable
    storage). Event streams of the map end. 503: removed, but the removal could not be stored; the
    service retries, and the same DELETE answers 204 once it is stored. `If-Match`: only if the map
    has that `ETag` (412 otherwise, the map untouched); no map is a 404 as without it (a 412 when
    its deletion is still being stored)."""
    try:
        state.registry.delete(map_id, wait=True, expect=conditions.expectation(map_id))
    except ApiError:  # a precondition failed: nothing was removed
        raise
    except BaseException:  # also when the removal could not be stored: the map is gone from memory
        state.tiles.drop_map(map_id)  # its tiles can never be served again (new maps get a new generation)
        raise
    state.tiles.drop_map(map_id)
    return Response(status_code=204)


# -- scans ------------------------------------------------------------------------------------------

_SCAN_BODY = {
    "requestBody": {
        "required": True,
        "description": "One scan: the JSON `ScanMessage` (Content-Type application/json), or its binary "
        f"encoding (Content-Type {BINARY_ENCODING}, see docs/protocol.md).",
        "content": {
            JSON_ENCODING: {"schema": {"$ref": "#/components/schemas/ScanMessage"}},
            BINARY_ENCODING: {"schema": {"type": "string", "format": "binary"}},
        },
    }
}


@router.post(
    "/maps/{map_id}/scans",
    tags=["ingest"],
    summary="Integrate one scan",
    response_model=ScanResult,
    openapi_extra=_SCAN_BODY,
    responses=error_responses(
        404,
        409,
        412,
        413,
        415,
        422,
        503,
        507,
        described={
            415: f"The scan is sent with another Content-Type than {JSON_ENCODING} or {BINARY_ENCODING} "
            "(or none: then its first byte tells), or with a Content-Encoding (or a Transfer-Encoding "
            "other than chunked)",
            429: "The map already holds its most robots (--max-robots-per-map), every one of them online "
            "or with scans waiting: a new robot's scan is refused (and counted on the map)",
        },
    ),
)
async def post_scan(
    map_id: MapId, robot_id: RobotId, request: Request, state: State, conditions: Conditions
) -> ScanResult:
    """The scan a robot would publish over Zenoh, for clients without Zenoh. Answers once the scan is
    integrated (a tile or cell read after the answer includes it), with the cell updates and the
    changed storage tiles; `{"status": "duplicate"}` (200) when `seq` is not above the robot's last
    (seq 0 restarts a robot's sequence). Scans of one robot are integrated in seq order.

    Errors: 404 unknown map when the server does not create maps on first use (or already holds
    the most maps scans may create), or the map was deleted before the scan was integrated; 409 the
    map was replaced (deleted and created again, or restored from a snapshot) before the scan was
    integrated: it is in neither map; 413 a payload over 4 MiB, the limit of every scan as over
    Zenoh (counted as rejected too); 415 a Content-Type that is neither encoding (counted as
    rejected too, as over Zenoh); 422 an invalid scan (counted on the robot as rejected, with the
    reason as its `last_error`); 429 a new robot on a map that holds its most robots
    (`--max-robots-per-map`), all online or with scans waiting; 503 the robot's ingest queue is
    full (retry later with the same seq: it is then integrated, not taken for a duplicate), the
    integration did not finish within the server's timeout (the scan is still integrated), or
    storage failed: the scan was applied but its journal commit failed (counted on the robot as
    `not_durable`; the map's next snapshot saves it, and a retry is a duplicate; see
    `GET /healthz`); 507 the scan needs new tiles that the service's memory budget for all maps
    (`--max-memory`) cannot hold: it is refused whole, counted as rejected, and the map is unchanged
    (sent again with the same seq once memory is freed, it is integrated). `If-Match`: only into the
    map of that `ETag` (412 otherwise, the scan taken nowhere, counted nowhere); `If-None-Match: *`:
    only into a map it makes. 401, nothing changed (nor counted), if the request's token was revoked
    while its body arrived (`refuse_if_revoked`)."""
    registry = state.registry
    body = await request.body()
    refuse_if_revoked(request.scope)  # before it is counted on the robot, too
    content_type = request.headers.get("content-type", "")
    limits = registry.input_limits
    try:
        if len(body) <= DECODE_ON_LOOP_BYTES:
            wire = codec.decode(body, content_type, limits)
        else:  # parsing a few MB of JSON takes tens of ms: not on the loop every request waits on
            wire = await asyncio.to_thread(codec.decode, body, content_type, limits)
    except codec.DecodeError as exc:
        # Counted as over Zenoh, too large or not. A scan whose seq and session id could be read
        # (`scan_id`: its body broke the input limits) is settled as refused with its seq, as Zenoh's
        # ingest does: without it, the robot's next seq counted it as lost too (one scan, two counts).
        reason = str(exc) if exc.scan_id is None else f"scan seq {exc.scan_id[0]} refused: {exc}"
        registry.reject(map_id, robot_id, reason, exc.scan_id)
        raise  # the app's handlers answer it: 413 past the payload limit (PayloadTooLarge), 415 for
        # a media type the codec does not read (UnknownEncoding), else 422
    try:
        future = registry.submit(map_id, robot_id, wire, wait=True, expect=conditions.expectation(map_id))
    except IngestRejected as exc:
        if exc.status == 200:
            return ScanResult(seq=wire.seq, status="duplicate", detail=exc.reason)
        raise ApiError(exc.status, exc.reason) from None
    assert future is not None  # wait=True always returns one
    try:
        tile_size = registry.get(map_id).config.tile_size
    except MapNotFound:  # gone already: the scan was refused and the map it created removed, or deleted
        tile_size = None  # (the future says which)
    timeout = state.settings.scan_timeout
    try:
        # shield: a timeout or a client that goes away must not cancel the registry's Future (the
        # worker still completes it).
        result = await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(future)), timeout)
    except TimeoutError:
        raise ApiError(
            503, f"the scan was queued but not integrated within {timeout:g} s; it will be integrated"
        ) from None
    except IngestRejected as exc:
        raise ApiError(exc.status, exc.reason) from None
    if tile_size is None:  # integrated, then the map was deleted before it was looked up above
        raise MapNotFound(map_id)
    return ScanResult(
        seq=wire.seq,
        status="integrated",
        cell_updates=result.cell_updates,
        tsdf_updates=result.tsdf_updates,
        changed_tiles=tile_windows(result.changed_tiles, tile_size),
    )
