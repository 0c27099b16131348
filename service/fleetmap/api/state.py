"""What every route needs: the app's `ApiState` (registry, settings, metrics, tile cache) and the
shared parameter types (validated map and robot ids, coordinates). The layers a route reads,
`api_models.RegionLayer`, are held here to the engine's (`grid_map.REGION_LAYERS`)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, get_args

from fastapi import Depends, Query, Request
from fastapi import Path as PathParam

from fleetmap.api.ingest_priority import IngestGate
from fleetmap.api_models import MAX_COORDINATE, RegionLayer
from fleetmap.grid_map import REGION_LAYERS
from fleetmap.map_entry import MapEntry
from fleetmap.memory_budget import available_memory
from fleetmap.metrics import ServiceMetrics
from fleetmap.registry import MapRegistry
from fleetmap.storage_format import MAX_SNAPSHOT_META_BYTES
from fleetmap.tile_cache import TileCache
from fleetmap.wire import ID_PATTERN

if TYPE_CHECKING:
    from fleetmap.api.app import ApiSettings


class Slots:
    """Requests of a kind in progress, at most `limit` at once. Used on the event loop only (the
    routes, and the responses and callbacks that give the slots back, run there), so it needs no
    lock."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.open = 0
        #: Requests refused because `limit` were in progress (for /metrics).
        self.refused = 0

    def acquire(self) -> bool:
        """Take a slot for a new request; False (counted as refused) when all are taken."""
        if self.open >= self.limit:
            self.refused += 1
            return False
        self.open += 1
        return True

    def release(self) -> None:
        """Give back the slot of a request that ended (once per successful `acquire`)."""
        self.open -= 1


class EventStreamSlots(Slots):
    """The open event streams, at most `limit` at once."""

    def __init__(self, limit: int) -> None:
        super().__init__(limit)
        #: Set by `close_all` when the server shuts down.
        self.closing = False

    def close_all(self) -> None:
        """The server is shutting down: every open stream ends at its next poll (within one events
        period) and a new one is refused. Streams never end by themselves, so without this the
        server's graceful shutdown would wait its whole timeout for them and then cancel them,
        logging an error with a traceback for each."""
        self.closing = True


class ThreadSlots(Slots):
    """`Slots` taken and given back from any thread: by the plain-function routes on the thread pool,
    and by their answers on the event loop once sent (`api.large_reads`)."""

    def __init__(self, limit: int) -> None:
        super().__init__(limit)
        self._lock = threading.Lock()

    def acquire(self) -> bool:
        with self._lock:
            return super().acquire()

    def release(self) -> None:
        with self._lock:
            super().release()


@dataclass
class ApiState:
    registry: MapRegistry
    settings: ApiSettings
    metrics: ServiceMetrics
    web_dir: Path
    gate: IngestGate
    tiles: TileCache = field(init=False)
    event_streams: EventStreamSlots = field(init=False)
    #: The uploads in progress (`routes_snapshot.spooled_body`), at most `settings.max_uploads`.
    uploads: Slots = field(init=False)
    #: The snapshot downloads in progress (`routes_snapshot.get_snapshot`), at most
    #: `settings.max_downloads`.
    downloads: Slots = field(init=False)
    #: The reads of big windows in progress (`api.large_reads`), at most `settings.max_large_reads`.
    large_reads: ThreadSlots = field(init=False)
    #: The limits of a snapshot upload: its tiles' bytes and its body's (`ApiSettings`).
    snapshot_tile_bytes: int = field(init=False)
    snapshot_body_bytes: int = field(init=False)

    def __post_init__(self) -> None:
        budget = self.registry.memory_budget
        tiles = self.settings.max_snapshot_tile_bytes
        if tiles is None:
            tiles = budget.limit if budget is not None and budget.limit is not None else available_memory()
        body = self.settings.max_snapshot_body_bytes
        self.snapshot_tile_bytes = tiles
        self.snapshot_body_bytes = tiles + MAX_SNAPSHOT_META_BYTES + (1 << 20) if body is None else body
        self.tiles = TileCache(self.settings.tile_cache_size, on_render=self.metrics.observe_render)
        self.event_streams = EventStreamSlots(self.settings.max_event_streams)
        self.uploads = Slots(self.settings.max_uploads)
        self.downloads = Slots(self.settings.max_downloads)
        self.large_reads = ThreadSlots(self.settings.max_large_reads)
        self.metrics.watch_tile_cache(self.tiles)
        self.metrics.watch_gate(self.gate)
        self.metrics.watch_slots(self.event_streams, "event_streams", "Event streams (GET /maps/{id}/events)")
        self.metrics.watch_slots(
            self.uploads, "uploads", "Uploads (PUT /maps/{id}/snapshot and /maps/{id}/import)"
        )
        self.metrics.watch_slots(self.downloads, "downloads", "Snapshot downloads (GET /maps/{id}/snapshot)")
        self.metrics.watch_slots(
            self.large_reads, "large_reads", "Reads of big windows (GET /maps/{id}/region, /surface, /export)"
        )

    def entry(self, map_id: str) -> MapEntry:
        """The map, or MapNotFound (answered 404)."""
        return self.registry.get(map_id)


async def get_state(request: Request) -> ApiState:
    # async: a plain function here would cost a thread-pool hop on every request.
    return request.app.state.fleetmap


State = Annotated[ApiState, Depends(get_state)]

MapId = Annotated[
    str,
    PathParam(pattern=ID_PATTERN, description="map id, [A-Za-z0-9_-]{1,64}", examples=["warehouse"]),
]
RobotId = Annotated[
    str,
    Query(pattern=ID_PATTERN, description="robot id, [A-Za-z0-9_-]{1,64}", examples=["robot1"]),
]

assert get_args(RegionLayer) == REGION_LAYERS  # the layers a route takes are those the engine reads


def coordinate(description: str) -> object:
    """A finite map coordinate query parameter, metres."""
    return Query(ge=-MAX_COORDINATE, le=MAX_COORDINATE, allow_inf_nan=False, description=description)
