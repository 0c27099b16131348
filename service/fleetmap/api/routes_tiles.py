"""PNG map tiles for Leaflet, rendered by `fleetmap.tile_render` and cached by `fleetmap.tile_cache`,
with ETags."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool

from fleetmap import tile_render
from fleetmap.api.errors import error_responses
from fleetmap.api.http_semantics import etag_matches, joined_field_lines
from fleetmap.api.state import MapId, State
from fleetmap.api.strict_requests import StrictRoute
from fleetmap.api_models import RegionLayer
from fleetmap.tile_render import MAX_ZOOM, MIN_ZOOM, check_layer, etag_for, tile_version

router = APIRouter(route_class=StrictRoute)


def is_tile_path(path: str) -> bool:
    """Whether `path` is one of `get_tile`'s, `/maps/{map_id}/tiles/{z}/{x}/{y}.png` (ids never
    hold a `/`, and no other route has `/tiles/` and `.png`)."""
    return path.startswith("/maps/") and path.endswith(".png") and "/tiles/" in path


def _convention() -> str:
    """The tile convention, quoted from tile_render's docstring (its one definition)."""
    doc = tile_render.__doc__ or ""
    start, end = doc.find("Tile convention"), doc.find("Versions:")
    section = doc[start:end] if start >= 0 and end > start else doc
    return section.strip()


TILE_DESCRIPTION = f"""\
A 256 x 256 RGBA PNG of one layer. Unexplored space is transparent. `ETag` changes whenever a cell
under the tile changes (and when the map is re-created); send it back as `If-None-Match` to get
`304 Not Modified` while the tile is unchanged. `Cache-Control: no-cache` (`private, no-cache` when
the server requires a read token): clients revalidate, so a change is visible as soon as its scan is
integrated. HEAD answers the headers alone. Leaflet:
`L.tileLayer('/maps/{{map_id}}/tiles/{{z}}/{{x}}/{{y}}.png?layer=probability', {{minZoom: -8, maxZoom: 4,
maxNativeZoom: 4, minNativeZoom: -8}})` on a map with `crs: L.CRS.Simple`.

From fleetmap.tile_render:

{_convention()}

Errors: 422 for a zoom outside {MIN_ZOOM}..{MAX_ZOOM}, a tile beyond the cell range, or an unknown
layer or one the map does not keep; 404 for an unknown map.
"""


#: Caches store a tile and revalidate it before every use, so a change shows as soon as its scan is
#: integrated. (`DefaultHeaders` adds `private` when reading needs a token, as to every answer.)
TILE_CACHE_CONTROL = "no-cache"

#: The caching headers of a tile answer (200 and 304), as the spec declares them.
_TILE_HEADER_SPEC = {
    "ETag": {
        "description": "changes whenever a cell under the tile changes; send it back as If-None-Match",
        "schema": {"type": "string"},
    },
    "Cache-Control": {
        "description": "`no-cache` (`private, no-cache` when reading needs a token): revalidate",
        "schema": {"type": "string"},
    },
}


@router.get(
    "/maps/{map_id}/tiles/{z}/{x}/{y}.png",
    tags=["tiles"],
    summary="A map tile (Leaflet CRS.Simple; zoom 0 = one pixel per cell)",
    description=TILE_DESCRIPTION,
    response_class=Response,
    responses={
        200: {
            "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
            "description": "The tile, with its ETag",
            "headers": _TILE_HEADER_SPEC,
        },
        304: {
            "description": "Not modified: the tile's ETag matches If-None-Match",
            "headers": _TILE_HEADER_SPEC,
        },
        **error_responses(404, 422),
    },
)
async def get_tile(
    request: Request,
    map_id: MapId,
    z: Annotated[int, PathParam(ge=MIN_ZOOM, le=MAX_ZOOM, description="zoom: 2**z pixels per cell")],
    x: Annotated[int, PathParam(description="tile column: cells i in [x*S, (x+1)*S), S = 256 / 2**z")],
    y: Annotated[int, PathParam(description="tile row: cells j in [-(y+1)*S, -y*S)")],
    state: State,
    layer: Annotated[RegionLayer, Query(description="the layer to draw")] = "probability",
    if_none_match: Annotated[str | None, Header(description="an ETag from an earlier answer")] = None,
) -> Response:
    # On the event loop: a revalidation or a cache hit takes microseconds, and a hop to the thread
    # pool would cost more than that (and another thread wanting the GIL). Only renders go there.
    entry = state.entry(map_id)
    # Every field line (the parameter, which documents the header, holds only the first: a tag on a
    # second line got the whole tile).
    if_none_match = joined_field_lines(request.headers, "if-none-match")
    if if_none_match:
        # Answer a revalidation from the version alone: no render, no cache lookup.
        check_layer(entry.gmap, layer)
        etag = etag_for(entry.generation, layer, z, x, y, tile_version(entry.gmap, z, x, y))
        if etag_matches(if_none_match, etag):
            return Response(status_code=304, headers={"ETag": etag, "Cache-Control": TILE_CACHE_CONTROL})
    found = state.tiles.cached(entry, layer, z, x, y)
    if found is None:
        found = await run_in_threadpool(state.tiles.get_or_render, entry, layer, z, x, y)
    png, etag = found
    return Response(png, media_type="image/png", headers={"ETag": etag, "Cache-Control": TILE_CACHE_CONTROL})
