"""Service routes: `GET /healthz` (liveness and a few numbers) and `GET /metrics` (Prometheus)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from fleetmap.api.state import State
from fleetmap.api.strict_requests import StrictRoute
from fleetmap.api_models import Health, storage_status, withheld_zenoh_status
from fleetmap.auth import may_read
from fleetmap.metrics import CONTENT_TYPE

router = APIRouter(route_class=StrictRoute)


@router.get("/healthz", tags=["service"], summary="Liveness and a few numbers", response_model=Health)
def healthz(request: Request, state: State) -> Health:
    """Answers 200 while the service runs, with the number of maps, robots online, the ingest queue
    depth, when the service runs a Zenoh session its status, and when it is durable its storage's
    health. `status` is `degraded` while storage is not ok: a journal commit or a snapshot failed
    (a full or failing disk), or a map holds scans whose journal commit failed until its next
    snapshot. The service goes on integrating and serving meanwhile, and recovers by itself once
    storage works. Open to anyone (liveness probes carry no token); where reading needs a token
    (`--require-read-token`), a client without one is not told which maps storage failed for, nor
    the error (it names maps and files), nor the ROS side's status (it names the maps it builds and
    publishes)."""
    registry = state.registry
    maps = registry.list()
    online = sum(1 for _, _, robot in registry.iter_robots() if robot.online)
    zenoh = state.settings.zenoh_status() if state.settings.zenoh_status else None
    storage = storage_status(registry.durable.health()) if registry.durable is not None else None
    settings = state.settings
    if not may_read(request.scope["headers"], settings.tokens, settings.require_read_token):
        storage = storage.withheld() if storage is not None else None
        zenoh = withheld_zenoh_status(zenoh) if zenoh is not None else None
    return Health(
        status="ok" if storage is None or storage.ok else "degraded",
        maps=len(maps),
        robots_online=online,
        queue_depth=registry.queue.depth(),
        zenoh=zenoh,
        storage=storage,
    )


@router.get(
    "/metrics",
    tags=["service"],
    summary="Prometheus metrics",
    response_class=Response,
    responses={
        200: {
            "content": {"text/plain": {"schema": {"type": "string"}}},
            "description": "Prometheus text exposition format",
        }
    },
)
def metrics(state: State) -> Response:
    """Counters per map and robot (`fleetmap_scans_integrated_total`, `fleetmap_scans_rejected_total`,
    `fleetmap_scans_duplicate_total`, `fleetmap_scans_dropped_total`, labels `map`, `robot`), the
    gauge `fleetmap_scans_lost` (a gap taken back when it was another robot's: it goes down),
    `fleetmap_robot_online`, `fleetmap_queue_depth`,
    `fleetmap_ingest_backlog_seconds` (how long the oldest queued scan has waited), `fleetmap_maps`,
    `fleetmap_map_tiles`, `fleetmap_map_memory_bytes`, and the histograms
    `fleetmap_integration_seconds` (plan + apply of one scan), `fleetmap_ingest_latency_seconds`
    (scan queued to integrated), `fleetmap_tile_render_seconds` (label `layer`; renders only), the
    tile cache's `fleetmap_tile_cache_hits_total`, `fleetmap_tile_renders_total`, and the requests
    held back while scans wait (docs/api.md, "Ingest before reads"):
    `fleetmap_http_delayed_requests_total`, `fleetmap_http_delay_seconds_total`,
    `fleetmap_http_delay_timeouts_total`, `fleetmap_http_requests_waiting`; and the garbage
    collector's `fleetmap_gc_collections_total` (label `generation`) and `fleetmap_gc_frozen_objects`."""
    return Response(state.metrics.render(), media_type=CONTENT_TYPE)
