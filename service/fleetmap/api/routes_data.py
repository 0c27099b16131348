"""Reading maps: one cell, many cells, rays cast through them, dense regions, TSDF surfaces, exports;
and forgetting a region (`DELETE /maps/{id}/region`, the one write here, beside its read).

Reads take the map's lock only inside the engine's read calls (`GridMap.cells`, `region`,
`cast_rays`, ...), which copy what they need (rays read the tiles in place), so a read sees every
tile before or after any scan, never half-way. The routes are plain functions: FastAPI runs them on
its thread pool, so a large read never stalls the event loop.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Query, Response

from fleetmap.api.conditional import Conditions
from fleetmap.api.errors import ApiError, error_responses, too_many
from fleetmap.api.large_reads import large_read
from fleetmap.api.state import MapId, State, coordinate
from fleetmap.api.strict_requests import StrictRoute, limit_json_values
from fleetmap.api_models import (
    MAX_POINTS,
    CellsRequest,
    CellsResponse,
    CellValue,
    RaycastRequest,
    RaycastResponse,
    RegionCleared,
    RegionLayer,
    Surface,
    cell_value,
    cells_json,
    raycast_json,
    region_json,
    surface,
    tile_windows,
)
from fleetmap.cell_queries import EDGE_DIGITS, MAX_RAYS, STATE_FREE, STATE_OCCUPIED
from fleetmap.export import (
    MAX_EXPORT_SCALE,
    Window,
    export_scale,
    known_window,
    map_png,
    map_source,
    nav2_zip,
    npy_bytes,
    png_bytes,
    probability_grey,
)
from fleetmap.grid_map import GridMap, log_odds_to_probability

router = APIRouter(route_class=StrictRoute)
# The most values a valid body holds: a point is two numbers and a comma between them, and one
# between points; a ray an angle and, with `origins`, its two numbers (the slack: the other keys).
limit_json_values("/maps/{map_id}/cells", 2 * MAX_POINTS + 16, f"{MAX_POINTS} points")
limit_json_values("/maps/{map_id}/raycast", 3 * MAX_RAYS + 16, f"{MAX_RAYS} rays")

OptCoordinate = Annotated[float | None, coordinate("metres; give all four bounds or none")]
#: A required bound of a window, metres.
Bound = Annotated[float, coordinate("metres")]


#: A bound within this many cells of a cell edge is that edge (`_edge`).
EDGE_TOLERANCE = 1e-9
#: A bound within this many metres of a cell edge is that edge too (`_edge`): twice the rounding of
#: the origins answers report (`cell_edge`, to the nanometre). At a resolution of more than nine
#: decimals that rounding is more than a billionth of a cell: at the float32 of 0.05 m
#: (0.05000000074505806) up to 1e-8 cells, so the origin of half the windows, asked for again, started
#: the window a cell lower.
EDGE_METRES = 10.0**-EDGE_DIGITS
#: Far from the origin, where a billionth of a cell is below the precision of `bound / resolution`,
#: a bound within this many units in the last place of that quotient of an edge is that edge: the
#: bound and the resolution written in decimal, and the division, each round by half of one.
EDGE_ULPS = 16


def _edge(bound: float, resolution: float) -> int:
    """`floor(bound / resolution)`, but a bound within EDGE_TOLERANCE cells or EDGE_METRES of a cell
    edge (or, far from the origin, within EDGE_ULPS units in the last place of the quotient) is that
    edge, so that every origin an answer reports gives its own window back: written
    in decimal, an edge is rarely one in binary, and 0.15 / 0.05 is 2.9999999999999996 (the float
    0.15 lies below 0.15), so `xmin=0.15` at 0.05 m started the window at cell 2, not 3, and the
    origin a region answer reports (0.15) did not give its own window back. The tolerance does not
    grow with the cell index beyond the quotient's precision: a billionth of the index was half a cell
    at 0.01 m and 5,300 km (a UTM northing), and moved every bound in a cell's upper half to the next
    edge."""
    cells = bound / resolution
    nearest = round(cells)
    tolerance = max(EDGE_TOLERANCE, EDGE_METRES / resolution, EDGE_ULPS * math.ulp(cells))
    return nearest if abs(cells - nearest) <= tolerance else math.floor(cells)


def _window(
    gmap: GridMap,
    bounds: tuple[float | None, float | None, float | None, float | None],
    limit: int | None,
) -> Window:
    """The cells `[floor(xmin/res), floor(xmax/res)) x [floor(ymin/res), floor(ymax/res))` (a bound on
    a cell edge in decimal is that edge: `_edge`), or the
    observed extent when no bound is given. 422 for a partial or empty window, 409 for no bounds on an
    empty map, 413 past `limit` cells (None: any number)."""
    xmin, ymin, xmax, ymax = bounds
    if xmin is None and ymin is None and xmax is None and ymax is None:
        window = known_window(gmap)
        if window is None:
            raise ApiError(
                409, "the map has no observed cell (none yet, or all cleared); give xmin, ymin, xmax and ymax"
            )
    elif xmin is None or ymin is None or xmax is None or ymax is None:
        raise ApiError(422, "give all of xmin, ymin, xmax and ymax, or none of them (the observed extent)")
    else:
        res = gmap.resolution
        window = Window(*(_edge(float(bound), res) for bound in (xmin, ymin, xmax, ymax)))
        if window.i1 <= window.i0 or window.j1 <= window.j0:
            # The cells the bounds make, not a rule of thumb: "xmax at least one cell beyond xmin"
            # was wrong both ways (0.04 to 0.085 at 0.05 m is a column; 0.01 to 0.049 none).
            raise ApiError(
                422,
                f"the window holds no cell: at resolution {res} m the bounds make the cells "
                f"[{window.i0}, {window.i1}) x [{window.j0}, {window.j1}) (floor(bound / resolution) of "
                "each): xmax must lie in a later cell than xmin, and ymax than ymin",
            )
    ny, nx = window.shape
    if limit is not None and window.cells > limit:
        raise ApiError(
            413,
            f"the window has {nx} x {ny} = {window.cells} cells, more than the limit of {limit}; "
            "ask for smaller windows",
        )
    return window


def _window_headers(window: Window, resolution: float) -> dict[str, str]:
    x0, y0 = window.origin(resolution)
    return {
        "X-Fleetmap-Window": f"{window.i0},{window.j0},{window.i1},{window.j1}",
        "X-Fleetmap-Origin": f"{x0!r},{y0!r}",
        "X-Fleetmap-Resolution": repr(resolution),
    }


# -- cells ------------------------------------------------------------------------------------------


@router.get(
    "/maps/{map_id}/cell",
    tags=["queries"],
    summary="Every layer's value in the cell at a point",
    response_model=CellValue,
    responses=error_responses(404, 422),
)
def get_cell(
    map_id: MapId,
    state: State,
    x: Annotated[float, coordinate("map x, metres")],
    y: Annotated[float, coordinate("map y, metres")],
) -> CellValue:
    """The cell containing `(x, y)`: `known`, `log_odds`, `probability` (0.5 if unknown), `state`
    (`occupied` if p > occupied_thresh, `free` if p < free_thresh, else `unknown`), `hits`, `misses`,
    `tsdf`, `tsdf_weight`. A layer the map does not keep is null."""
    return cell_value(state.entry(map_id).gmap, x, y)


@router.post(
    "/maps/{map_id}/cells",
    tags=["queries"],
    summary="Every layer's value at many points",
    response_model=CellsResponse,
    responses=error_responses(404, 413, 415, 422),
)
def post_cells(map_id: MapId, state: State, body: CellsRequest) -> Response:
    """The fields of GET /maps/{map_id}/cell, each an array with one entry per point, in the order
    given: `{"count", "i": [...], "j": [...], "known": [...], "probability": [...], ...}`. An unknown
    cell has `known` false and `probability` 0.5. At most 100000 points per request: more is 413."""
    limit = state.settings.max_points
    if len(body.points) > limit:
        raise too_many(len(body.points), "points", limit)
    gmap = state.entry(map_id).gmap
    points = np.array(body.points, dtype=np.float64).reshape(-1, 2)
    return Response(cells_json(gmap, points), media_type="application/json")


@router.post(
    "/maps/{map_id}/raycast",
    tags=["queries"],
    summary="Where rays from a point, or from many, first meet an obstacle",
    response_model=RaycastResponse,
    responses=error_responses(404, 413, 415, 422),
)
def post_raycast(map_id: MapId, state: State, body: RaycastRequest) -> Response:
    """OctoMap's castRay for many rays: each ray starts at `origin` (or, with `origins`, ray r at
    `origins[r]`: rays from many poses in one request) and goes at map-frame `angle` for at most
    `max_range` metres through the cells of the exact traversal, the origin's cell first. It
    stops at the first occupied cell (p > occupied_thresh, the `state` of /cell; a map without the
    occupancy layer uses its counts, p = hits / (hits + misses)), or with `unknown` "stop" (the
    default) at the first never-observed cell. Answers, one entry per angle in order: `status`
    (`occupied`, `unknown` or `max_range`), `range` (metres to where the ray enters that cell, 0 for
    the origin's own cell, max_range if nothing stopped it), `x`, `y` (that point) and `i`, `j` (the
    cell; for `max_range` the last one visited). 413 past 10000 rays, 20000 cells of `max_range`, or
    2**24 cells of rays x `max_range`; 422 for a map keeping neither occupancy nor counts."""
    gmap = state.entry(map_id).gmap
    result = gmap.cast_rays(body.ray_origins(), body.angles, body.max_range, body.unknown)
    return Response(raycast_json(result), media_type="application/json")


# -- regions ----------------------------------------------------------------------------------------

_REGION_CONTENT = {
    "application/json": {"schema": {"$ref": "#/components/schemas/RegionJson"}},
    "application/octet-stream": {
        "schema": {"type": "string", "format": "binary"},
        "description": "format=npy: a NumPy .npy array, shape (ny, nx)",
    },
    "image/png": {"schema": {"type": "string", "format": "binary"}},
}


#: The headers saying where a region lies (`_window_headers`), as the spec declares them: an npy or
#: png answer carries its window nowhere else, and without bounds the client does not know it.
_WINDOW_HEADER_SPEC = {
    "X-Fleetmap-Window": {
        "description": "the cell window `i0,j0,i1,j1` of the answer (cells i0 <= i < i1, j0 <= j < j1)",
        "schema": {"type": "string", "examples": ["-402,-467,379,259"]},
    },
    "X-Fleetmap-Origin": {
        "description": "`x,y`: the map point of the window's lower-left corner, metres",
        "schema": {"type": "string", "examples": ["-20.1,-23.35"]},
    },
    "X-Fleetmap-Resolution": {"description": "metres per cell", "schema": {"type": "string"}},
}


@router.get(
    "/maps/{map_id}/region",
    tags=["queries"],
    summary="A dense window of one layer (npy, json or png)",
    response_class=Response,
    responses={
        200: {
            "content": _REGION_CONTENT,
            "description": "The window; see the headers",
            "headers": _WINDOW_HEADER_SPEC,
        },
        **error_responses(404, 409, 413, 422, 503),
    },
)
def get_region(
    map_id: MapId,
    state: State,
    xmin: OptCoordinate = None,
    ymin: OptCoordinate = None,
    xmax: OptCoordinate = None,
    ymax: OptCoordinate = None,
    layer: Annotated[RegionLayer, Query(description="the layer to read")] = "probability",
    format: Annotated[Literal["npy", "json", "png"], Query(description="answer format")] = "npy",
) -> Response:
    """The cells with index in `[floor(xmin/res), floor(xmax/res))` x `[floor(ymin/res),
    floor(ymax/res))` (no bounds: the observed extent; a bound within a billionth of a cell, or a
    nanometre, of a cell edge is that edge: `xmin=0.15` at 0.05 m starts at cell 3, though 0.15 /
    0.05 is 2.9999999999999996), as:

    - `npy`: a NumPy array of shape (ny, nx), row 0 = the LOWEST y; float32 with NaN for unknown
      (`log_odds`, `probability`, `tsdf`; `tsdf_weight` 0), uint32 counts (`hits`, `misses`, 0 if
      unknown), uint8 codes for `state` (0 unknown, 1 free, 2 occupied);
    - `json`: `RegionJson`, the same values with null for NaN (at most 1048576 cells);
    - `png`: a grayscale + alpha image, TOP row = highest y, unknown transparent; darker = more
      occupied (`probability`, `log_odds`: 255 (1 - p); `state`: 0 occupied, 254 free), more hits
      (`hits`, `misses`, `tsdf_weight`: scaled to the window's maximum), or more negative distance
      (`tsdf`, the signed distance over the truncation, in [-1, 1]: 127.5 (1 + tsdf)).

    Headers: `X-Fleetmap-Window: i0,j0,i1,j1`, `X-Fleetmap-Origin: x,y` (lower-left corner, metres),
    `X-Fleetmap-Resolution`. 422 if the map does not keep the layer; 413 past 16777216 cells; 503 (with
    `Retry-After`) for a window of more than 1048576 cells while the server already reads its limit
    of such windows at once (4), until their answers are sent."""
    entry = state.entry(map_id)
    gmap = entry.gmap
    # A layer the map does not keep is a 422 saying so before the window is judged (a 409 for no
    # bounds on an empty map, a 413 past the limit, a 422 for no cell: advice that, followed, met
    # this refusal next) and before any slot is taken (a 503 to retry, which no retry could change).
    gmap.layer_source(layer)
    limit = state.settings.max_json_cells if format == "json" else state.settings.max_region_cells
    window = _window(gmap, (xmin, ymin, xmax, ymax), limit)
    with large_read(state.large_reads, window.cells) as read:
        values = gmap.region(layer, window.i0, window.j0, window.i1, window.j1)
        headers = _window_headers(window, gmap.resolution)
        if format == "npy":
            return read.answer(
                npy_bytes(values),
                media_type="application/octet-stream",
                headers={**headers, "Content-Disposition": f'attachment; filename="{map_id}-{layer}.npy"'},
            )
        if format == "png":
            pixels = region_pixels(layer, values)
            return read.answer(png_bytes(pixels), media_type="image/png", headers=headers)
        model = region_json(layer, [window.i0, window.j0, window.i1, window.j1], gmap.resolution, values)
        return read.answer(model.model_dump_json(), media_type="application/json", headers=headers)


@router.delete(
    "/maps/{map_id}/region",
    tags=["maps"],
    summary="Forget a window of cells (make them unknown)",
    response_model=RegionCleared,
    responses=error_responses(404, 409, 412, 422, 503),
)
def delete_region(
    map_id: MapId,
    state: State,
    conditions: Conditions,
    xmin: Bound,
    ymin: Bound,
    xmax: Bound,
    ymax: Bound,
) -> RegionCleared:
    """Makes the cells with index in `[floor(xmin/res), floor(xmax/res))` x `[floor(ymin/res),
    floor(ymax/res))` (a bound on a cell edge in decimal is that edge, as for `GET .../region`)
    unknown again in every layer the map keeps, as before any scan (octomap_server's
    clear of a bounding box): a shelf moved where no robot looks again, the trace of a bad pose.
    All four bounds are required (422 otherwise; DELETE /maps/{map_id} removes a whole map). Scans
    applied before are forgotten there; later ones observe the cells again (so a retry also forgets
    what was observed in between). The changed tiles get new ETags and event streams announce them.
    With durable storage it is journaled in order with the scans and stored before the answer.
    503: nothing was cleared (the service is stopping, or its storage cannot take it), or the cells
    are unknown but that could not be stored yet (the detail says which): the map's next snapshot
    stores it, but a crash before that loses it. `If-Match`: only if the map has that `ETag` (412
    otherwise, nothing cleared). 409: the map was deleted or replaced while the request ran, nothing
    cleared. Needs a `write` token where tokens are set."""
    entry = state.entry(map_id)
    gmap = entry.gmap
    # No cell limit: only stored tiles are visited, whatever the window's size. (Not even an int64's:
    # "everything", 10 000 km each way, is 1.6e19 cells at 5 mm, and was refused with 413.)
    window = _window(gmap, (xmin, ymin, xmax, ymax), limit=None)
    cleared = state.registry.clear_window(entry, window, conditions.expectation(map_id))
    return RegionCleared(
        window=[window.i0, window.j0, window.i1, window.j1],
        cells_cleared=cleared.cells,
        changed_tiles=tile_windows(cleared.changed_tiles, gmap.store.tile_size),
    )


def region_pixels(layer: str, values: np.ndarray) -> np.ndarray:
    """Gray + alpha pixels (h, w, 2) of a region (row 0 = lowest y in, top row = highest y out)."""
    if layer in ("probability", "log_odds"):
        known = ~np.isnan(values)
        p = values if layer == "probability" else log_odds_to_probability(values)
        gray = probability_grey(np.nan_to_num(p, nan=0.5))
    elif layer == "state":
        known = values != 0
        gray = np.where(values == STATE_OCCUPIED, 0.0, np.where(values == STATE_FREE, 254.0, 205.0))
    elif layer == "tsdf":
        # The layer holds the signed distance over the truncation, already in [-1, 1] (not metres).
        known = ~np.isnan(values)
        gray = 127.5 * (1.0 + np.clip(np.nan_to_num(values.astype(np.float64)), -1.0, 1.0))
    else:  # hits, misses, tsdf_weight: counts, 0 = never seen
        v = np.nan_to_num(values.astype(np.float64))
        known = v > 0
        top = float(v.max()) if v.size else 0.0
        gray = 255.0 - 255.0 * v / top if top > 0 else np.full(v.shape, 255.0)
    pixels = np.empty((*values.shape, 2), dtype=np.uint8)
    pixels[..., 0] = np.round(gray).astype(np.uint8)
    pixels[..., 1] = np.where(known, 255, 0).astype(np.uint8)
    return pixels[::-1]


# -- surface ----------------------------------------------------------------------------------------


@router.get(
    "/maps/{map_id}/surface",
    tags=["queries"],
    summary="TSDF zero crossings (surface points)",
    response_model=Surface,
    responses=error_responses(404, 409, 413, 422, 503),
)
def get_surface(
    map_id: MapId,
    state: State,
    xmin: OptCoordinate = None,
    ymin: OptCoordinate = None,
    xmax: OptCoordinate = None,
    ymax: OptCoordinate = None,
) -> Response:
    """Points where the TSDF changes sign between two observed neighbouring cells, placed by linear
    interpolation between the cell centres (sub-cell surface points in metres), that lie in the
    window's cells (as for /region; no bounds: the observed extent), also those between a cell of
    the window and its neighbour outside it: windows side by side share out the surface, each point
    to the one it lies in. 422 if the map keeps no TSDF layer; 503 as for /region, for a window of
    more than 1048576 cells."""
    gmap = state.entry(map_id).gmap
    if not gmap.config.has("tsdf"):
        raise ApiError(422, "this map keeps no 'tsdf' layer: no surface to extract")
    window = _window(gmap, (xmin, ymin, xmax, ymax), state.settings.max_region_cells)
    with large_read(state.large_reads, window.cells) as read:
        points = gmap.surface(window.i0, window.j0, window.i1, window.j1)
        model = surface([window.i0, window.j0, window.i1, window.j1], points)
        return read.answer(model.model_dump_json(), media_type="application/json")


# -- export -----------------------------------------------------------------------------------------


@router.get(
    "/maps/{map_id}/export",
    tags=["export"],
    summary="The map as nav2 map_server files (zip) or a PNG",
    response_class=Response,
    responses={
        200: {
            "content": {
                "application/zip": {"schema": {"type": "string", "format": "binary"}},
                "image/png": {"schema": {"type": "string", "format": "binary"}},
            },
            "description": "The export, as an attachment",
        },
        **error_responses(404, 409, 413, 422, 503),
    },
)
def get_export(
    map_id: MapId,
    state: State,
    format: Annotated[Literal["ros", "png"], Query(description="ros: zip of map.yaml + map.pgm")] = "ros",
    margin: Annotated[int, Query(ge=0, le=1000, description="unknown cells added around the map")] = 2,
    resolution: Annotated[
        float | None,
        Query(
            gt=0,
            # nan was "should be greater than 0", and inf export_scale's refusal: one word for both.
            allow_inf_nan=False,
            description="metres per cell of the export: the map's (default) times a whole number from 1 to "
            f"{MAX_EXPORT_SCALE}; each exported cell shows the most occupied known cell of its block",
        ),
    ] = None,
) -> Response:
    """The observed extent of the map, grown by `margin` cells, exactly as `fleetmap build` writes it:
    `ros`: a zip of `map.yaml` + `map.pgm` (nav2 map_server, trinary: 0 occupied, 254 free, 205
    unknown, by the map's thresholds; origin = lower-left corner); `png`: grayscale, 255 (1 - p),
    unknown 128. p is the occupancy layer's, or for a map keeping only counts (and the TSDF) the count
    model's hits / (hits + misses). `resolution`: coarser than the map's by a whole factor k, each
    exported cell is a block of k x k of the map's cells aligned on multiples of k (the extent grown
    to whole blocks), showing the block's most occupied known cell (unknown only if every cell is
    unknown): obstacles are kept, not averaged away. 409 for a map with no observed cell, 422 for a
    map keeping only the TSDF or a resolution that is not such a multiple, 413 past the export limit
    (counted in exported cells), 503 as for /region when the map spans more than 1048576 cells."""
    gmap = state.entry(map_id).gmap
    if map_source(gmap) is None:
        raise ApiError(422, "this map keeps neither an 'occupancy' nor a 'counts' layer: nothing to export")
    try:
        scale = 1 if resolution is None else export_scale(gmap.resolution, resolution)
    except ValueError as exc:
        raise ApiError(422, str(exc)) from None
    window = known_window(gmap, margin)
    if window is None:
        raise ApiError(409, "the map has no observed cell (none yet, or all cleared): nothing to export")
    window = window.aligned(scale)
    ny, nx = window.shape[0] // scale, window.shape[1] // scale
    if nx * ny > state.settings.max_export_cells:
        limit = state.settings.max_export_cells
        raise ApiError(
            413,
            f"the export spans {nx} x {ny} cells, more than the export limit of {limit} "
            "(`max_export_cells`); export it at a coarser resolution, or read it by /region windows",
        )
    if window.shape[0] * window.shape[1] > state.settings.max_export_read_cells:
        limit = state.settings.max_export_read_cells
        raise ApiError(
            413,
            f"the map spans {window.shape[1]} x {window.shape[0]} of its cells, more than an export reads "
            f"({limit}, `max_export_read_cells`); read it by /region windows",
        )
    with large_read(state.large_reads, window.cells) as read:
        if format == "ros":
            return read.answer(
                nav2_zip(gmap, window, scale=scale),
                media_type="application/zip",
                headers={"Content-Disposition": f'attachment; filename="{map_id}.zip"'},
            )
        return read.answer(
            map_png(gmap, window, scale),
            media_type="image/png",
            headers={"Content-Disposition": f'attachment; filename="{map_id}.png"'},
        )
