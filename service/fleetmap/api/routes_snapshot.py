"""A map as one file: download it for backup, upload it to restore or to move a map between servers."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from typing import Any

from fastapi import APIRouter, Request, Response

from fleetmap.api.conditional import Conditions, Preconditions, tag_map
from fleetmap.api.errors import ApiError, error_responses, validation_detail
from fleetmap.api.http_semantics import created_status
from fleetmap.api.state import MapId, State
from fleetmap.api.strict_requests import StrictRoute
from fleetmap.api_models import MapInfo, map_info
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.registry import MapEntry, MapNotFound
from fleetmap.storage_format import SNAPSHOT_FORMAT, SnapshotError, map_from_snapshot_file, snapshot_file

router = APIRouter(tags=["maps"], route_class=StrictRoute)

MEDIA_TYPE = "application/zip"


#: The request body of an upload of a zip file (OpenAPI), and the answer of an upload that replaced a
#: map: `PUT .../snapshot` and `PUT .../import`.
ZIP_UPLOAD = {
    "requestBody": {
        "required": True,
        "content": {MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
    }
}
REPLACED: dict[int | str, dict[str, Any]] = {
    200: {"model": MapInfo, "description": "Replaced the map that had this id"}
}


@router.get(
    "/maps/{map_id}/snapshot",
    summary="Download a map as one file",
    response_class=Response,
    responses={
        200: {
            "content": {MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
            "description": f"a {SNAPSHOT_FORMAT} zip: map.json (configuration) and tiles.npz (every layer)",
        },
        **error_responses(404, 422),
    },  # fmt: skip
)
async def get_snapshot(map_id: MapId, state: State) -> Response:
    """The whole map (configuration and every tile of every layer) as one zip file, consistent: it
    is taken under the map's lock, between two scans. `PUT` it to this or another server to restore."""
    entry = state.entry(map_id)
    data = await asyncio.to_thread(snapshot_file, map_id, entry.gmap)
    return Response(
        data, media_type=MEDIA_TYPE,
        headers={"Content-Disposition": f'attachment; filename="{map_id}.fleetmap.zip"'},
    )  # fmt: skip


@router.put(
    "/maps/{map_id}/snapshot",
    summary="Restore a map from a snapshot file",
    response_model=MapInfo,
    status_code=201,
    openapi_extra=ZIP_UPLOAD,
    responses={**REPLACED, **error_responses(412, 413, 415, 422, 503, 507)},
)
async def put_snapshot(
    map_id: MapId, request: Request, response: Response, state: State, conditions: Conditions
) -> MapInfo:
    """Replace map `map_id` (201 with its `Location` when it did not exist, else 200) with the map in
    the uploaded snapshot file, durably: the answer comes once it is stored. Its robots' statistics
    start afresh; scans queued for the old map are dropped. 422 if the body is not a fleetmap
    snapshot, or holds a tile or a cell value the service could not have made; 413 if a part of it
    decompresses to more than its limit (see the docs); 507 if its tiles need more memory than the
    budget (`--max-memory`) leaves; none changes anything. 503 if the map was installed but could not
    be stored. `If-Match` / `If-None-Match: *` as for `PUT /maps/{map_id}` (412, nothing changed)."""
    body = await request.body()
    try:
        return await install_upload(
            state, map_id, response, lambda _config, free: map_from_snapshot_file(body, free_bytes=free),
            conditions,
        )  # fmt: skip
    except SnapshotError as exc:
        if not exc.errors:
            raise ApiError(exc.status, str(exc)) from None
        detail, items = validation_detail(exc.errors)  # one line per problem, as for PUT /maps
        raise ApiError(exc.status, f"snapshot {detail}", errors=items) from None


async def install_upload(
    state: State,
    map_id: str,
    response: Response,
    read: Callable[[MapConfig | None, int | None], GridMap],
    conditions: Preconditions,
) -> MapInfo:
    """Install the map an upload holds as map `map_id`, replacing any map of that id, durably: what
    `PUT .../snapshot` and `PUT .../import` share. `read(config, free_bytes)` makes the map on a
    worker thread from the configuration of the map it replaces (None for a new id) and the bytes
    the memory budget leaves counting the replaced map's (None without a budget); whatever it raises
    for a bad upload propagates with nothing changed. Sets 201 (with `Location`) for a new map, else
    200; NotDurable (503) if the map was installed but could not be stored. `conditions` (the
    request's If-Match / If-None-Match) are checked before the upload is read, sparing a doomed
    upload's seconds of work, and again where the map is installed, under the registry's lock, so
    that of two uploads sent with the same ETag one is installed and the other gets 412."""
    replaced: MapEntry | None = None
    with contextlib.suppress(MapNotFound):
        replaced = state.registry.get(map_id)
    conditions.check(map_id, replaced)
    # The room the memory budget leaves, counting the map this replaces (its bytes go back).
    budget = state.registry.memory_budget
    free = None if budget is None else budget.free()
    if free is not None and replaced is not None:
        free += replaced.gmap.memory_bytes()
    config = None if replaced is None else replaced.gmap.config
    gmap = await asyncio.to_thread(read, config, free)
    # Whether a map was replaced is known only where it is, under the registry's lock: the map
    # looked up above, before the upload was read (seconds, for a big one), may have been created,
    # deleted or replaced by another writer since, and a 201 Created for an upload that replaced
    # another writer's map (or a 200 for one that found none) misinformed the client.
    check = conditions.expectation(map_id)
    found: list[MapEntry | None] = []

    def expect(old: MapEntry | None) -> None:
        if check is not None:
            check(old)
        found.append(old)

    # On a worker thread: storing a big map's tiles takes seconds (the event loop serves on).
    try:
        entry = await asyncio.to_thread(state.registry.replace, map_id, gmap, wait=True, expect=expect)
    except ApiError:  # a precondition failed: the old map is untouched, its tiles still good
        raise
    except BaseException:  # also when it could not be stored: the old map's tiles are gone all the same
        state.tiles.drop_map(map_id)
        raise
    state.tiles.drop_map(map_id)
    created_status(response, map_id, created=found[-1] is None)
    tag_map(response, entry)
    return map_info(entry, state.registry.lock)
