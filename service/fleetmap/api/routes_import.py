"""Start a map from a ROS nav2 map: upload the zip `GET /maps/{id}/export?format=ros` gives, or any
map_server `map.yaml` zipped with its image. It installs as a snapshot upload does."""

from __future__ import annotations

import email.message
import threading
from typing import IO, Annotated, Literal

from fastapi import APIRouter, Query, Request, Response

from fleetmap.api.conditional import Conditions
from fleetmap.api.errors import ApiError, error_responses
from fleetmap.api.routes_snapshot import (
    MEDIA_TYPE,
    REPLACED,
    UPLOAD_ERRORS,
    ZIP_UPLOAD,
    install_upload,
)
from fleetmap.api.state import MapId, State
from fleetmap.api.strict_requests import StrictRoute
from fleetmap.api_models import MapInfo
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.memory_budget import UploadReservation
from fleetmap.nav2_import import Nav2ImportError, map_from_nav2_zip

router = APIRouter(tags=["maps"], route_class=StrictRoute)


def _is_zip_media_type(content_type: str | None) -> bool:
    message = email.message.Message()
    message["content-type"] = content_type or ""
    return message.get_content_type() == MEDIA_TYPE


@router.put(
    "/maps/{map_id}/import",
    summary="Start a map from a ROS nav2 map (map.yaml and its image, zipped)",
    response_model=MapInfo,
    status_code=201,
    openapi_extra=ZIP_UPLOAD,
    responses={**REPLACED, **UPLOAD_ERRORS, **error_responses(409)},
)
async def put_import(
    map_id: MapId,
    request: Request,
    response: Response,
    state: State,
    conditions: Conditions,
    format: Annotated[
        Literal["ros"], Query(description="ros: a zip of a nav2 map_server map.yaml and its image")
    ] = "ros",
    snap_origin: Annotated[
        bool,
        Query(
            description="move an origin off the map's cell grid to the nearest cell edge (by at most "
            "half a cell on each axis) instead of refusing the map: SLAM tools put the origin anywhere, "
            "and map_saver writes it rounded"
        ),
    ] = False,
) -> MapInfo:
    """Replace map `map_id` (201 with its `Location` when it did not exist, else 200) with a map whose
    occupancy layer holds the uploaded nav2 map, read as map_server reads it, durably: the answer
    comes once it is stored. The new map's configuration is that of the map it replaces, else the
    server's default with the YAML's resolution; its other layers start unknown, its robots afresh,
    and scans queued for the old map are dropped. 415 unless the body is a zip sent as
    `application/zip`; 422 naming the field or the image at fault (a rotated map, an origin off the
    cell grid, another resolution than the replaced map's, an image that is not 8-bit grey, more
    tiles than `max_tiles`; with `snap_origin`, an origin off the grid is moved to the nearest cell
    edge instead); 413 for an image or a file past its limit; 507 if its tiles need more
    memory than the budget leaves (its body, at most 16 MiB, is kept in memory: only a body limit
    raised past that, `ApiSettings.max_body_bytes`, goes to the temporary directory as a snapshot's,
    and may find no room there, 507 too, or fail to write or read it, 503); 503 (`Retry-After: 5`),
    before the body is read, if the server already holds its limit of uploads in progress
    (snapshots and imports, 4 by default); none changes anything. 503 if it was installed but could
    not be stored. `If-Match` / `If-None-Match: *` as for `PUT /maps/{map_id}` (412, nothing
    changed; before the body is read). 409, nothing changed, if while the upload was read (with the
    configuration of the map there then) the map was deleted, or made or replaced with another
    configuration. One image is read at a time in the server (its decoding takes memory outside
    `--max-memory`): an import sent while another is read waits for it."""
    del format  # one format for now: the parameter names it, as GET .../export's does
    content_type = request.headers.get("content-type")
    if not _is_zip_media_type(content_type):
        sent = f"not {content_type!r}" if content_type else "none was given"
        raise ApiError(415, f"the body must be a zip file, with Content-Type: {MEDIA_TYPE} ({sent})")
    defaults = state.registry.default_config

    # Its body is not held in memory while it is read, as a snapshot's; one of the uploads in progress.
    # Stopped by `stop` only while it waits for its turn to decode (one image at a time in the
    # process): its body is at most 16 MiB and its image 64 Mpixels, read in a few seconds.
    def read(
        body: IO[bytes],
        config: MapConfig | None,
        reservation: UploadReservation | None,
        stop: threading.Event,
    ) -> GridMap:
        return map_from_nav2_zip(
            body, config, defaults, reservation=reservation, snap_origin=snap_origin, stop=stop
        )

    try:
        return await install_upload(state, map_id, request, response, read, conditions, reads_config=True)
    except Nav2ImportError as exc:
        raise ApiError(exc.status, f"nav2 map: {exc}") from None
