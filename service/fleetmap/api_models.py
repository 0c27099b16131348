"""The REST API's request and response models, and their conversion from the service's types.

One definition of every JSON body the API sends or takes: the FastAPI routes (`fleetmap.api`) use
these as response models, so `openapi/openapi.json` describes them, and the Python client
(`fleetmap_client.rest`) parses answers with them. This module imports no web framework, only
pydantic and fleetmap's own modules, so a client can import it without FastAPI; and of the engine
only modules that load no numba (`cell_queries`, `config`, `scan`: the engine's types are type-only
imports), so a client does not load numba and the compiled kernels either.

Conversions from registry and engine objects (`MapEntry`, `RobotState`, `GridMap.cells`, ...)
live here and nowhere else, so the JSON shape is decided in one place.

Conventions:
- Map points are metres in the map frame; cell `(i, j)` covers `[i*res, (i+1)*res) x [j*res, (j+1)*res)`.
- A cell window `[i0, j0, i1, j1]` is the cells with `i0 <= i < i1` and `j0 <= j < j1`.
- Values a map does not hold (a layer it does not keep) are `null`; an unknown cell's float values are
  `null` too, except `probability`, which is 0.5 for an unknown cell.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeVar, get_args, overload

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from fleetmap.auth import Role
from fleetmap.cell_queries import MAX_RAYS, RAY_STATUS_NAMES, STATE_NAMES, UnknownCells, cell_edge
from fleetmap.config import MAX_COORDINATE, MapConfig
from fleetmap.scan import Pose2D

if TYPE_CHECKING:  # the conversions' argument types only: a client parsing answers loads none of them
    # The engine's types too: `grid_map` and `tiles` load numba and compile the kernels. No model
    # field has one of these types, so pydantic never needs them resolved.
    from fleetmap.grid_map import GridMap, RaycastResult
    from fleetmap.map_entry import MapEntry
    from fleetmap.persistence import StorageHealth
    from fleetmap.robot_state import RobotState
    from fleetmap.tiles import TileKey

#: Points one `POST /maps/{map_id}/cells` request may ask for.
MAX_POINTS = 100_000

StateName = Literal["unknown", "free", "occupied"]
assert set(get_args(StateName)) == set(STATE_NAMES.values())
#: Why a ray stopped (`GridMap.cast_rays`' `RAY_STATUS_NAMES`).
RayStatusName = Literal["occupied", "unknown", "max_range"]
assert set(get_args(RayStatusName)) == set(RAY_STATUS_NAMES.values())
#: The layers a region or a tile can be read as (`grid_map.REGION_LAYERS`, which `api.state` holds
#: it to: this module may not import the engine): the routes' `layer` parameter, the client's `Layer`.
RegionLayer = Literal["log_odds", "probability", "state", "hits", "misses", "tsdf", "tsdf_weight"]
#: A map coordinate in a JSON body: a finite number (strict: no strings or booleans), metres.
Coordinate = Annotated[float, Field(strict=True, ge=-MAX_COORDINATE, le=MAX_COORDINATE, allow_inf_nan=False)]
# Fixed-length arrays are lists with a length, not tuples: OpenAPI 3.1's `prefixItems` (what tuples
# become) is still unknown to many generators and validators; `items` + min/max length is not.
#: `[i0, j0, i1, j1]`: the cells with i0 <= i < i1 and j0 <= j < j1.
CellWindow = Annotated[list[int], Field(min_length=4, max_length=4)]
#: `[x, y]`, metres.
Point = Annotated[list[float], Field(min_length=2, max_length=2)]


class _Model(BaseModel):
    """Answers ignore unknown fields when parsed, so an older client reads a newer server's answer."""

    model_config = ConfigDict(extra="ignore")


# -- errors and health ------------------------------------------------------------------------------


class ErrorItem(_Model):
    """One problem found in a request."""

    loc: list[str | int] = Field(description="where: e.g. ['query', 'x'] or ['body', 'points', 3, 0]")
    msg: str
    type: str


class ErrorResponse(_Model):
    """Every error answer: `detail` says what is wrong in words; `errors` lists each problem found
    when a request failed validation."""

    detail: str
    errors: list[ErrorItem] | None = None


#: `StorageStatus.last_error` to a client that may not read the maps.
WITHHELD_STORAGE_ERROR = (
    "storage failed (what failed, and the maps it concerns, are shown with a read token: this "
    "service requires one to read)"
)


class StorageStatus(_Model):
    """The data directory's health (`DurableStore.health`)."""

    ok: bool = Field(
        description="false while the last journal commit or a map's last snapshot failed, while a "
        "map holds scans whose journal commit failed (its next snapshot makes them durable), and while "
        "a map's creation, restore or deletion is not stored"
    )
    last_error: str | None = Field(
        description="the latest storage failure, kept after recovery (it names maps and files: to a "
        "client without a read token, where the service requires one, only that there was one)"
    )
    last_error_at: float | None = Field(description="when it happened, Unix time")
    scans_not_durable: int = Field(description="scans applied whose journal commit failed, since start")
    maps_awaiting_snapshot: list[str] = Field(
        description="maps holding such scans, until their next snapshot (empty to a client without a "
        "read token, where the service requires one: map ids are what reads need it for)"
    )
    map_changes_not_stored: list[str] = Field(
        description="maps whose creation, restore or deletion could not be stored yet: retried until "
        "it is, and meanwhile none of the map's scans is made durable (empty to a client without a "
        "read token, where the service requires one)"
    )

    def withheld(self) -> StorageStatus:
        """This status as a client that may not read the maps sees it: whether storage is ok, when
        it last failed and how many scans are not durable, but not which maps, nor the error's text
        (it names maps and the data directory's files)."""
        return self.model_copy(
            update={
                "last_error": None if self.last_error is None else WITHHELD_STORAGE_ERROR,
                "maps_awaiting_snapshot": [],
                "map_changes_not_stored": [],
            }
        )


#: The keys of `Health.zenoh` under which `fleetmap serve` adds its ROS side's status
#: (`serve_ros.zenoh_status`): the ROS scan ingest's (`--ros-scans`) and the ROS map publisher's
#: (`--ros-publish-map`). They name maps, topics and robots' namespaces.
ZENOH_ROS_SCANS = "ros"
ZENOH_ROS_MAPS = "ros_maps"


def withheld_zenoh_status(status: dict[str, Any]) -> dict[str, Any]:
    """`Health.zenoh` as a client that may not read the maps sees it: the Zenoh session's own status,
    without the ROS parts (`ZENOH_ROS_SCANS`, `ZENOH_ROS_MAPS`), which name the maps they build and
    publish, their topics and the robots' namespaces (map ids are what reads need a token for)."""
    return {key: value for key, value in status.items() if key not in (ZENOH_ROS_SCANS, ZENOH_ROS_MAPS)}


class Health(_Model):
    """`GET /healthz`."""

    status: Literal["ok", "degraded"] = Field(
        default="ok", description="`degraded` while storage is not ok (see `storage`); the service still runs"
    )
    maps: int = Field(description="maps held")
    robots_online: int = Field(description="robots with a live liveliness token, over all maps")
    queue_depth: int = Field(description="scans waiting for integration")
    zenoh: dict[str, Any] | None = Field(
        default=None,
        description="the Zenoh session's status, if any, with its ROS side's under `ros` and `ros_maps` "
        "(left out to a client without a read token, where the service requires one: they name maps)",
    )
    storage: StorageStatus | None = Field(
        default=None, description="durable storage's health; null with --in-memory"
    )


def storage_status(health: StorageHealth) -> StorageStatus:
    return StorageStatus.model_validate(health, from_attributes=True)


class Session(_Model):
    """`POST /session`: the browser is signed in; its session cookie stands for the token on reads."""

    role: Role = Field(
        description="the token's role; the session cookie unlocks reads only, whatever the role (writes "
        "need the token itself in an Authorization header)"
    )


# -- maps -------------------------------------------------------------------------------------------


class Pose(_Model):
    """A sensor pose in the map frame: metres, radians counter-clockwise from +x."""

    x: float
    y: float
    theta: float

    @classmethod
    def of(cls, pose: Pose2D | None) -> Pose | None:
        return None if pose is None else cls(x=pose.x, y=pose.y, theta=pose.theta)


class RobotStats(_Model):
    """What the service knows of one robot on one map."""

    online: bool = Field(description="its liveliness token is alive")
    last_pose: Pose | None = Field(description="pose of its last integrated scan")
    last_seq: int | None = Field(description="sequence number of the last scan accepted")
    last_stamp: float | None = Field(default=None, description="stamp of its last integrated scan")
    scans_integrated: int
    scans_rejected: int = Field(
        description="scans refused: invalid, past the map's max_tiles, or for the memory budget "
        "(see last_error)"
    )
    last_error: str | None = Field(
        description="why the last scan refused (or applied but not made durable, see not_durable) was so"
    )
    lost: int = Field(description="sequence numbers skipped (messages lost before reaching the service)")
    duplicates: int = Field(description="scans ignored because their seq was not new")
    restarts: int = Field(
        default=0,
        description="times its seq started again (a restarted robot; a count that keeps growing means two "
        "robots publish under this id)",
    )
    dropped: int = Field(default=0, description="scans refused because the ingest queue was full")
    not_durable: int = Field(
        default=0,
        description="scans applied whose journal commit failed (storage error); a snapshot saves them",
    )
    id_conflict: bool = Field(
        default=False,
        description="scans of two or more publisher sessions interleaved in the last minute: more than one "
        "robot publishes under this id (the scans of each are integrated; give each robot its own id)",
    )
    id_conflicts: int = Field(
        default=0,
        description="times a publisher session was found publishing at the same time as another one under "
        "this id (two robots: 1)",
    )


class MapStats(_Model):
    scans_integrated: int
    scans_rejected: int
    robots: dict[str, RobotStats]
    bounds: Annotated[list[float], Field(min_length=4, max_length=4)] | None = Field(
        description="[xmin, ymin, xmax, ymax] in metres of every observed cell; null for an empty map"
    )
    tiles: int = Field(description="storage tiles allocated")
    memory_bytes: int = Field(
        description="bytes the map's tiles hold: pools, versions, bookkeeping (what --max-memory counts)"
    )
    version: int = Field(default=0, description="the map's change version (as in the events stream)")


class MapInfo(_Model):
    """`GET /maps/{map_id}`: a map's configuration and statistics."""

    id: str
    config: MapConfig
    resolution: float = Field(description="metres per cell (= config.resolution)")
    tile_size: int = Field(description="cells per storage tile side (= config.tile_size)")
    stats: MapStats


class MapSummary(_Model):
    """One map in `GET /maps`."""

    id: str
    resolution: float
    tile_size: int
    layers: list[str]
    scans_integrated: int
    scans_rejected: int
    robots: int = Field(description="robots seen on this map")
    robots_online: int
    tiles: int
    memory_bytes: int


class MapList(_Model):
    maps: list[MapSummary]


# -- scans ------------------------------------------------------------------------------------------


class ScanResult(_Model):
    """`POST /maps/{map_id}/scans`: what happened to the scan."""

    seq: int
    status: Literal["integrated", "duplicate"] = Field(
        description="integrated: the map now includes it; duplicate: its seq was not new, nothing done"
    )
    cell_updates: int = Field(default=0, description="occupancy / count cell updates applied")
    tsdf_updates: int = Field(default=0, description="TSDF cell updates applied")
    changed_tiles: list[CellWindow] = Field(
        default_factory=list, description="cell windows [i0, j0, i1, j1] of the storage tiles that changed"
    )
    detail: str | None = Field(default=None, description="for a duplicate: why")


# -- cells ------------------------------------------------------------------------------------------


class CellValue(_Model):
    """`GET /maps/{map_id}/cell`: every layer's value in the cell containing (x, y)."""

    x: float
    y: float
    i: int = Field(description="cell index floor(x / resolution)")
    j: int = Field(description="cell index floor(y / resolution)")
    known: bool = Field(
        description="the cell's occupancy was observed (a map without the occupancy layer: its counts; "
        "a TSDF-only map: its TSDF); the TSDF band also reaches cells behind walls where it is false"
    )
    log_odds: float | None = Field(description="null if unknown or the map keeps no occupancy layer")
    probability: float | None = Field(description="occupancy probability; 0.5 if unknown")
    state: StateName | None = Field(description="by the map's occupied_thresh / free_thresh")
    hits: int | None = Field(description="null if the map keeps no counts layer")
    misses: int | None
    tsdf: float | None = Field(
        description="signed distance over the truncation distance, in [-1, 1] (negative behind the "
        "surface); null if unknown or no TSDF layer"
    )
    tsdf_weight: float | None


class CellsRequest(BaseModel):
    """`POST /maps/{map_id}/cells`."""

    model_config = ConfigDict(extra="forbid")

    points: list[Annotated[list[Coordinate], Field(min_length=2, max_length=2)]] = Field(
        max_length=MAX_POINTS, description=f"map points [x, y] in metres, at most {MAX_POINTS}"
    )


class CellsResponse(_Model):
    """The same fields as `CellValue`, each an array with one entry per requested point, in order.
    A field is null as a whole when the map does not keep its layer."""

    count: int
    i: list[int]
    j: list[int]
    known: list[bool]
    log_odds: list[float | None] | None
    probability: list[float] | None
    state: list[StateName] | None
    hits: list[int] | None
    misses: list[int] | None
    tsdf: list[float | None] | None
    tsdf_weight: list[float] | None


# -- rays -------------------------------------------------------------------------------------------


#: `[x, y]`, metres, within the coordinates a map may have.
MapPoint = Annotated[list[Coordinate], Field(min_length=2, max_length=2)]


class RaycastRequest(BaseModel):
    """`POST /maps/{map_id}/raycast`: rays from one point, or each from its own (`GridMap.cast_rays`).
    Exactly one of `origin` and `origins` is given."""

    model_config = ConfigDict(extra="forbid")

    origin: MapPoint | None = Field(
        default=None, description="[x, y], metres, map frame: where every ray starts (or give origins)"
    )
    origins: list[MapPoint] | None = Field(
        default=None,
        max_length=MAX_RAYS,
        description="[[x, y], ...]: where each ray starts, one per angle (rays from many poses in one "
        "request, as a particle filter casts them); instead of origin",
    )
    angles: list[Annotated[float, Field(strict=True, allow_inf_nan=False)]] = Field(
        min_length=1,
        max_length=MAX_RAYS,
        description=f"each ray's direction, radians in the map frame; 1 to {MAX_RAYS} rays",
    )
    max_range: float = Field(
        strict=True,
        gt=0,
        allow_inf_nan=False,
        description="metres a ray goes at most; at most 20000 cells, and rays x cells at most 2**24",
    )
    unknown: UnknownCells = Field(
        default="stop",
        description="stop: a ray stops at its first never-observed cell (status unknown); pass: it "
        "walks through unknown cells",
    )

    @model_validator(mode="after")
    def _one_origin_or_one_per_ray(self) -> RaycastRequest:
        if self.origin is None and self.origins is None:
            raise ValueError("give origin (where every ray starts) or origins (one per angle)")
        if self.origin is not None and self.origins is not None:
            raise ValueError("give origin (where every ray starts) or origins (one per angle), not both")
        if self.origins is not None and len(self.origins) != len(self.angles):
            raise ValueError(f"{len(self.origins)} origins for {len(self.angles)} angles: give one per angle")
        return self

    def ray_origins(self) -> list[float] | list[list[float]]:
        """The origin the rays share, or every ray's: what `GridMap.cast_rays` takes."""
        if self.origins is not None:
            return self.origins
        assert self.origin is not None  # the validator saw to it
        return self.origin


class RaycastResponse(_Model):
    """Where each ray stopped, one entry per angle, in order (`GridMap.cast_rays`' `RaycastResult`)."""

    count: int
    status: list[RayStatusName] = Field(
        description="occupied: the ray met a cell with p > occupied_thresh; unknown: a never-observed "
        "cell (with unknown=stop); max_range: neither within max_range"
    )
    range: list[float] = Field(
        description="metres from the origin to where the ray enters the cell it stopped in (0: the "
        "origin's cell); max_range for max_range"
    )
    x: list[float] = Field(description="map x of that point, metres")
    y: list[float] = Field(description="map y of that point, metres")
    i: list[int] = Field(description="the cell the ray stopped in (max_range: its last cell)")
    j: list[int]


# -- regions, surfaces ------------------------------------------------------------------------------


class RegionCleared(_Model):
    """`DELETE /maps/{map_id}/region`: the cells made unknown."""

    window: CellWindow = Field(description="the cells [i0, j0, i1, j1] cleared: i0 <= i < i1, j0 <= j < j1")
    cells_cleared: int = Field(
        description="cells of the window that were observed (in some layer) and are unknown now"
    )
    changed_tiles: list[CellWindow] = Field(
        description="cell windows [i0, j0, i1, j1] of the storage tiles that changed (new versions, ETags)"
    )


class RegionJson(_Model):
    """`GET /maps/{map_id}/region?format=json`: a dense window of one layer."""

    layer: str
    window: CellWindow = Field(description="the cells [i0, j0, i1, j1]")
    resolution: float
    origin: Point = Field(description="map point of the window's lower-left corner")
    shape: Annotated[list[int], Field(min_length=2, max_length=2)] = Field(description="[ny, nx]")
    values: list[list[int | float | None]] = Field(
        description="values[row][col] is cell (i0 + col, j0 + row): row 0 is the LOWEST y. Unknown is "
        "null for log_odds, probability and tsdf, 0 for tsdf_weight and the counts, 0 (unknown) for state "
        "(0 unknown, 1 free, 2 occupied)"
    )


class Surface(_Model):
    """`GET /maps/{map_id}/surface`: TSDF zero crossings."""

    window: CellWindow
    count: int
    points: list[Point] = Field(description="map points [x, y] in metres")


# -- events -----------------------------------------------------------------------------------------


class TilesEvent(_Model):
    """`event: tiles` of `GET /maps/{map_id}/events`: `tiles` lists the cell windows of the storage
    tiles changed since the previous event; or `reset` (tiles absent) tells the client to reload
    everything. Sent without its null field: `{"version", "tiles"}` or `{"version", "reset": true}`."""

    version: int
    tiles: list[CellWindow] | None = None
    reset: bool | None = None


class RobotLive(_Model):
    """A robot as a live viewer shows it."""

    online: bool
    pose: Annotated[list[float], Field(min_length=3, max_length=3)] | None = Field(
        description="[x, y, theta] of its last integrated scan"
    )
    trail: list[Point] = Field(description="recent positions [x, y], oldest first")
    scans_integrated: int


class RobotChange(RobotLive):
    """A robot of a `robots_delta` event: its fields as they are now, except `trail`."""

    trail: list[Point] = Field(
        description="the positions [x, y] appended since the stream's previous robots event, oldest "
        "first: append them to the robot's trail, then keep its last `trail_length`"
    )


class RobotsEvent(_Model):
    """`event: robots` of `GET /maps/{map_id}/events`: every robot of the map."""

    robots: dict[str, RobotLive]

    def apply(self, delta: RobotsDeltaEvent) -> RobotsEvent:
        """The robots after `delta`, the stream's next robots event: the `removed` robots go first
        (a robot forgotten and created again under its id is in both), then each robot of
        `delta.robots` takes its new fields, and its trail the appended points (a robot new to this
        view starts with an empty one), cut to the last `trail_length`."""
        removed = set(delta.removed)
        robots = {rid: robot for rid, robot in self.robots.items() if rid not in removed}
        for rid, change in delta.robots.items():
            before = robots.get(rid)
            trail = (before.trail if before is not None else []) + change.trail
            robots[rid] = RobotLive(
                online=change.online,
                pose=change.pose,
                trail=trail[max(0, len(trail) - delta.trail_length) :],
                scans_integrated=change.scans_integrated,
            )
        return RobotsEvent(robots=dict(sorted(robots.items())))


class RobotsDeltaEvent(_Model):
    """`event: robots_delta` of `GET /maps/{map_id}/events?robots=delta`: what changed of the map's
    robots since the stream's previous `robots` or `robots_delta` event (`RobotsEvent.apply` says how
    to apply it). A stream opened with `?robots=delta` sends a full `robots` event first (on connect,
    and after `replaced`), then only these."""

    trail_length: int = Field(ge=0, description="how many trail points the stream keeps per robot")
    robots: dict[str, RobotChange] = Field(description="the robots created or changed since")
    removed: list[str] = Field(description="the robots the service forgot since (apply first)")


class ReplacedEvent(_Model):
    """`event: replaced` of `GET /maps/{map_id}/events`: the map was replaced under its id (`PUT
    /maps/{map_id}/snapshot` or `PUT /maps/{map_id}/import`): new configuration, cells, robots and
    change versions. Reload the map (`GET /maps/{map_id}`) and every tile; the stream goes on with
    the new map's events, whose change versions start at `version` (also the event's id)."""

    id: str
    version: int


class KeepaliveEvent(_Model):
    """`event: keepalive` of `GET /maps/{map_id}/events?keepalive=event`: the stream is alive. Sent
    once when the stream opens and after every `interval` seconds without anything else sent, so a
    client that heard nothing (no event of any kind) for a few intervals knows its connection died
    silently and reconnects. A browser's EventSource never shows `: keepalive` comments to the page:
    this event is how a web page tells a quiet map from a dead stream."""

    interval: float = Field(gt=0, description="seconds of silence after which the server sends one")


# -- conversions ------------------------------------------------------------------------------------


def robot_stats(state: RobotState) -> RobotStats:
    """Call with the registry's lock held (it guards RobotState)."""
    return RobotStats(
        online=state.online,
        last_pose=Pose.of(state.last_pose),
        last_seq=state.last_seq,
        last_stamp=state.last_stamp,
        scans_integrated=state.scans_integrated,
        scans_rejected=state.scans_rejected,
        last_error=state.last_error,
        lost=state.lost,
        duplicates=state.duplicates,
        restarts=state.restarts,
        dropped=state.dropped,
        not_durable=state.not_durable,
        id_conflict=state.in_conflict(time.time()),
        id_conflicts=state.id_conflicts,
    )


def map_info(entry: MapEntry, registry_lock: threading.RLock) -> MapInfo:
    """A map's configuration and statistics. Robot counters are read under `registry_lock` (the
    registry's, which guards them); the bounds under the map's own lock (`known_bounds`)."""
    gmap = entry.gmap
    cells = gmap.known_bounds()
    res = gmap.resolution
    # To the nanometre, as region origins and exports: 2.05, not 2.0500000000000003.
    bounds = None if cells is None else [cell_edge(index, res) for index in cells]
    tiles, memory = len(gmap.store), gmap.memory_bytes()  # no lock needed: see TileStore.memory_bytes
    with registry_lock:
        robots = {rid: robot_stats(state) for rid, state in sorted(entry.robots.items())}
        integrated, rejected = entry.scans_integrated, entry.scans_rejected
    return MapInfo(
        id=entry.id,
        config=entry.config,
        resolution=res,
        tile_size=entry.config.tile_size,
        stats=MapStats(
            scans_integrated=integrated,
            scans_rejected=rejected,
            robots=robots,
            bounds=bounds,
            tiles=tiles,
            memory_bytes=memory,
            version=entry.changes.version,
        ),
    )


def map_summary(entry: MapEntry, registry_lock: threading.RLock) -> MapSummary:
    """A map's line in `GET /maps` (cheap: no scan over the cells)."""
    tiles, memory = len(entry.gmap.store), entry.gmap.memory_bytes()  # no lock needed, as in map_info
    with registry_lock:
        robots = len(entry.robots)
        online = sum(1 for state in entry.robots.values() if state.online)
        integrated, rejected = entry.scans_integrated, entry.scans_rejected
    return MapSummary(
        id=entry.id,
        resolution=entry.config.resolution,
        tile_size=entry.config.tile_size,
        layers=list(entry.config.layers),
        scans_integrated=integrated,
        scans_rejected=rejected,
        robots=robots,
        robots_online=online,
        tiles=tiles,
        memory_bytes=memory,
    )


def tile_windows(keys: list[TileKey] | frozenset[TileKey], tile_size: int) -> list[CellWindow]:
    """Storage tile keys as cell windows, sorted."""
    t = tile_size
    return [[ti * t, tj * t, (ti + 1) * t, (tj + 1) * t] for ti, tj in sorted(keys)]


def _floats(values: np.ndarray) -> list[float | None]:
    """A float array as a list, NaN as None (JSON has no NaN)."""
    return [None if v != v else v for v in values.tolist()]  # v != v: NaN


def _cells_fields(gmap: GridMap, points: np.ndarray) -> dict[str, Any]:
    """The fields of `CellsResponse` in its order, as arrays (None for a layer the map does not keep;
    float values as float64, NaN for null; `state` as a list of names)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    values = gmap.cells(pts)
    res = gmap.resolution
    has_occ, has_counts, has_tsdf = "log_odds" in values, "hits" in values, "tsdf" in values

    def floats(name: str, kept: bool) -> np.ndarray | None:
        # float64: the value a float32 has as a Python float (tolist), which JSON then carries
        return values[name].astype(np.float64) if kept else None

    return {
        "count": len(pts),
        "i": np.floor(pts[:, 0] / res).astype(np.int64),
        "j": np.floor(pts[:, 1] / res).astype(np.int64),
        "known": values["known"],
        "log_odds": floats("log_odds", has_occ),
        "probability": floats("probability", has_occ),
        "state": _STATE_NAMES[values["state"]].tolist() if has_occ else None,
        "hits": values["hits"] if has_counts else None,
        "misses": values["misses"] if has_counts else None,
        "tsdf": floats("tsdf", has_tsdf),
        "tsdf_weight": floats("tsdf_weight", has_tsdf),
    }


#: Names of the state codes, indexable by an array of codes.
_STATE_NAMES = np.array([STATE_NAMES[k] for k in sorted(STATE_NAMES)], dtype=object)


def cells_response(gmap: GridMap, points: np.ndarray) -> CellsResponse:
    """Every kept layer at each map point (rows of (x, y))."""
    fields = _cells_fields(gmap, points)
    for name in ("log_odds", "tsdf"):
        if fields[name] is not None:
            fields[name] = _floats(fields[name])
    return CellsResponse(**{k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in fields.items()})


def cells_json(gmap: GridMap, points: np.ndarray) -> bytes:
    """`cells_response(gmap, points).model_dump_json()`, byte for byte, made straight from the arrays
    (orjson writes a float64 as the same shortest round-trip text as pydantic, and NaN as null) instead
    of through 10 lists of Python objects and their validation: ~5x faster for 10,000 points."""
    import orjson  # here, not at the top: clients import this module for its models only

    return orjson.dumps(_cells_fields(gmap, points), option=orjson.OPT_SERIALIZE_NUMPY)


def cell_value(gmap: GridMap, x: float, y: float) -> CellValue:
    """Every kept layer in the cell containing (x, y)."""
    many = cells_response(gmap, np.array([[x, y]], dtype=np.float64))

    def first(values: list[Any] | None) -> Any:
        return None if values is None else values[0]

    return CellValue(
        x=x,
        y=y,
        i=many.i[0],
        j=many.j[0],
        known=many.known[0],
        log_odds=first(many.log_odds),
        probability=first(many.probability),
        state=first(many.state),
        hits=first(many.hits),
        misses=first(many.misses),
        tsdf=first(many.tsdf),
        tsdf_weight=first(many.tsdf_weight),
    )


#: Names of the ray status codes, indexable by an array of codes.
_RAY_STATUS_NAMES = np.array([RAY_STATUS_NAMES[k] for k in sorted(RAY_STATUS_NAMES)], dtype=object)


def raycast_json(result: RaycastResult) -> bytes:
    """A `RaycastResponse`'s JSON, made straight from the arrays (as `cells_json`): up to 10,000 rays
    without 7 lists of Python objects and their validation."""
    import orjson  # here, not at the top: clients import this module for its models only

    fields = {
        "count": len(result.status),
        "status": _RAY_STATUS_NAMES[result.status].tolist(),
        "range": result.range,
        "x": result.x,
        "y": result.y,
        "i": result.i,
        "j": result.j,
    }
    return orjson.dumps(fields, option=orjson.OPT_SERIALIZE_NUMPY)


def region_json(layer: str, window: CellWindow, resolution: float, values: np.ndarray) -> RegionJson:
    """A dense window (`GridMap.region`'s array, row 0 = lowest y) as JSON."""
    i0, j0, _, _ = window
    if values.dtype.kind == "f":
        rows: list[list[int | float | None]] = [_floats(row) for row in values]
    else:
        rows = values.tolist()
    return RegionJson(
        layer=layer,
        window=window,
        resolution=resolution,
        origin=[cell_edge(i0, resolution), cell_edge(j0, resolution)],
        shape=[int(values.shape[0]), int(values.shape[1])],
        values=rows,
    )


def surface(window: CellWindow, points: np.ndarray) -> Surface:
    pairs = [[float(x), float(y)] for x, y in points.tolist()]
    return Surface(window=window, count=len(pairs), points=pairs)


_Robot = TypeVar("_Robot", bound=RobotLive)


@overload
def robot_live(
    online: bool, pose: Pose2D | None, trail: list[tuple[float, float, float]], scans_integrated: int
) -> RobotLive: ...
@overload
def robot_live(
    online: bool,
    pose: Pose2D | None,
    trail: list[tuple[float, float, float]],
    scans_integrated: int,
    model: type[_Robot],
) -> _Robot: ...
def robot_live(
    online: bool,
    pose: Pose2D | None,
    trail: list[tuple[float, float, float]],
    scans_integrated: int,
    model: type[RobotLive] = RobotLive,
) -> RobotLive:
    """A robot for a live viewer (a `model`: RobotLive, or RobotChange with the new trail points),
    from fields copied under the registry's lock: trail positions rounded to the millimetre (enough
    to draw; keeps the stream small)."""
    return model(
        online=online,
        pose=None if pose is None else [pose.x, pose.y, pose.theta],
        trail=[[round(x, 3), round(y, 3)] for x, y, _ in trail],
        scans_integrated=scans_integrated,
    )


__all__ = [
    "MAX_COORDINATE",
    "MAX_POINTS",
    "CellValue",
    "CellWindow",
    "CellsRequest",
    "CellsResponse",
    "ErrorItem",
    "ErrorResponse",
    "Health",
    "KeepaliveEvent",
    "StorageStatus",
    "MapInfo",
    "MapList",
    "MapStats",
    "MapSummary",
    "MapPoint",
    "Point",
    "Coordinate",
    "Pose",
    "RayStatusName",
    "RaycastRequest",
    "RaycastResponse",
    "RegionJson",
    "RegionLayer",
    "RobotChange",
    "RobotLive",
    "RobotStats",
    "ReplacedEvent",
    "RobotsDeltaEvent",
    "RobotsEvent",
    "ScanResult",
    "Session",
    "StateName",
    "Surface",
    "TilesEvent",
    "cell_value",
    "cells_json",
    "cells_response",
    "map_info",
    "storage_status",
    "map_summary",
    "raycast_json",
    "region_json",
    "robot_live",
    "robot_stats",
    "surface",
    "tile_windows",
]
