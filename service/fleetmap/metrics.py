"""Prometheus metrics of the service.

Two sources, so nothing is counted twice:

- Counters the registry already keeps (scans integrated / rejected / lost / duplicates / dropped and
  id conflicts per map and robot, robots online, queue depth and the age of the oldest queued scan,
  tiles and memory per map) are read from the registry when Prometheus scrapes, by
  `RegistryCollector`. The registry stays the one truth. Likewise the tile cache's and the ingest
  gate's counters.
- Latencies only exist as events, so they are observed as they happen: `IntegrationMetrics` is the
  registry's `on_integrated` hook (integration time; from the job's `enqueued_at` and `applied_at`:
  arrival to integrated, arrival to visible, applied to journaled); the tile cache reports render
  times to `ServiceMetrics.observe_render`.

Each app gets its own `CollectorRegistry` (`ServiceMetrics`), so several services (or tests) in one
process never share or clash over metric names.

Wiring (server.py):

    metrics = IntegrationMetrics()
    registry = MapRegistry(..., on_integrated=metrics.on_integrated)
    app = create_app(registry, settings=ApiSettings(...))   # finds `metrics` through the hook
"""

from __future__ import annotations

import gc
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, Counter, Histogram, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from fleetmap.route_path import route_path
from fleetmap.version import installed_version

if TYPE_CHECKING:
    from fleetmap.api.ingest_priority import IngestGate
    from fleetmap.api.state import Slots
    from fleetmap.grid_map import IntegrationResult
    from fleetmap.map_entry import Job, MapEntry
    from fleetmap.registry import MapRegistry
    from fleetmap.tile_cache import TileCache

#: Prometheus' text exposition format.
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

#: `fleetmap_storage_failures_total{operation}`: what `DurableStore.failures` counts.
STORAGE_OPERATIONS = ("journal_commit", "snapshot", "map_change")

#: `fleetmap_zenoh_scans_refused_total{reason}`: the kinds of `ZenohIngest`'s refusals
#: (`map_entry.REFUSAL_KINDS`).
ZENOH_REFUSALS = ("duplicate", "no_map", "too_many_robots", "queue_full", "shutting_down")
#: Why ROS 2 scans (`--ros-scans`) are refused, exported at 0 from the start (fleetmap.ros.ingest).
ROS_REFUSALS = ("invalid_topic", "undecodable", "no_tf", "tf_error", "invalid_scan", "pending_full")

#: Seconds after a robot was last heard (a scan, a refusal, its liveliness token) that its counters
#: leave /metrics, unless it is online (`serve --metrics-robot-idle`). Robot ids come and go (a
#: renamed or replaced robot, a simulation, any Zenoh peer making them up) and a map forgets its
#: robots only once it holds `max_robots_per_map` (1024): without this a map's scrape kept 8 series
#: for every robot it had ever heard, up to 8192, long after they were gone. Its online gauge stays
#: (1 series a robot the map keeps), for alerts on robots gone; the registry keeps the robot
#: (`GET /maps/{id}` shows it), and its counters come back, with the same counts, when it is heard.
ROBOT_SERIES_IDLE = 3600.0

#: Latency buckets in seconds: sub-millisecond integrations up to multi-second backlogs.
LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)


class IntegrationMetrics:
    """Latencies observed by the integration workers. Pass `on_integrated` to `MapRegistry`.

    Its metrics are created unregistered; each `ServiceMetrics` registers them in its own registry.
    `on_integrated` runs on worker threads; prometheus_client's metrics are thread-safe.
    """

    def __init__(self) -> None:
        self.integration_seconds = Histogram(
            "fleetmap_integration_seconds",
            "Time to plan and apply one scan to its map",
            buckets=LATENCY_BUCKETS,
            registry=None,
        )
        self.ingest_latency_seconds = Histogram(
            "fleetmap_ingest_latency_seconds",
            "Time from a scan's arrival in the service (enqueued) to its integration in the map "
            "(with durable storage: to its journal row committed)",
            buckets=LATENCY_BUCKETS,
            registry=None,
        )
        self.visible_latency_seconds = Histogram(
            "fleetmap_ingest_visible_latency_seconds",
            "Time from a scan's arrival in the service (enqueued) to its application to the map, "
            "from when readers (cells, tiles, events) see it",
            buckets=LATENCY_BUCKETS,
            registry=None,
        )
        self.journal_latency_seconds = Histogram(
            "fleetmap_journal_latency_seconds",
            "Time from a scan's application to the map to its journal row committed to disk (fsync): "
            "the time it could be lost in a crash; only with durable storage",
            buckets=LATENCY_BUCKETS,
            registry=None,
        )
        self.cell_updates = Counter(
            "fleetmap_cell_updates",
            "Cell updates applied by integrated scans (occupancy/counts and TSDF)",
            registry=None,
        )

    def on_integrated(self, entry: MapEntry, job: Job, result: IntegrationResult, seconds: float) -> None:
        """The registry's `on_integrated` hook, called once a scan counts as integrated (on the
        journal writer's thread with persistence, else on the worker's). Quick, and never raises."""
        self.integration_seconds.observe(seconds)
        # job.enqueued_at is time.monotonic() when the scan was queued: the service-side latency.
        now = time.monotonic()
        self.ingest_latency_seconds.observe(max(0.0, now - job.enqueued_at))
        if job.applied_at is not None:
            self.visible_latency_seconds.observe(max(0.0, job.applied_at - job.enqueued_at))
            if job.journaled:  # called once its row is committed
                self.journal_latency_seconds.observe(max(0.0, now - job.applied_at))
        self.cell_updates.inc(result.cell_updates + result.tsdf_updates)

    def collectors(self) -> Iterable[Collector]:
        return (
            self.integration_seconds,
            self.ingest_latency_seconds,
            self.visible_latency_seconds,
            self.journal_latency_seconds,
            self.cell_updates,
        )


#: The metric families the collectors fill at scrape time (both have `add_metric(labels, value)`).
_Family = CounterMetricFamily | GaugeMetricFamily


class RegistryCollector(Collector):
    """Reads the registry's counters at scrape time (no double bookkeeping). Every robot a map keeps
    has its `fleetmap_robot_online`; its 7 counters are there while it is online or was heard
    within the last `robot_idle` seconds (`ROBOT_SERIES_IDLE`); a deleted map's go with it."""

    def __init__(self, registry: MapRegistry, robot_idle: float = ROBOT_SERIES_IDLE) -> None:
        self.registry = registry
        self.robot_idle = robot_idle

    def describe(self) -> list[Metric]:
        # Only the names matter here (for clash detection when registering); values come in collect.
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        families = self._families()
        integrated, rejected, lost, duplicates, dropped, not_durable, online, conflicts = families[:8]
        tiles, memory, maps, depth, age, storage_ok, budget_used, budget_limit, queue_limit = families[8:]
        entries = self.registry.list()
        for entry in entries:
            # Tiles and memory need no lock (see TileStore.memory_bytes); the counters need the registry's.
            tiles.add_metric([entry.id], len(entry.gmap.store))
            memory.add_metric([entry.id], entry.gmap.memory_bytes())
        # Only the copy holds the registry's lock, which every scan's submit and integration also
        # take, and one map's at a time (at most `max_robots_per_map` robots): building the
        # families under one hold of it (8 samples a robot) held it for about a second a scrape at
        # 45,000 robots, and every scan waited that long. Maps need not be read at one instant.
        rows: list[tuple[str, str, int, int, int, int, int, int, bool, int, bool]] = []
        heard_since = time.time() - self.robot_idle  # `last_heard` is wall-clock time: it is stored
        for entry in entries:
            with self.registry.lock:
                rows.extend(
                    (entry.id, robot_id, state.scans_integrated, state.scans_rejected, state.lost,
                     state.duplicates, state.dropped, state.not_durable, state.online, state.id_conflicts,
                     state.online or state.last_heard >= heard_since)
                    for robot_id, state in entry.robots.items()
                )  # fmt: skip
        rows.sort(key=lambda row: (row[0], row[1]))
        for map_id, robot_id, ok, bad, gaps, dups, full, lost_commits, is_online, clashes, active in rows:
            labels = [map_id, robot_id]
            # Every robot the map keeps has its online gauge, so that an alert on a robot gone
            # (`fleetmap_robot_online == 0`) goes on firing however long it stays gone; an idle
            # robot's counters do not move, and leave.
            online.add_metric(labels, 1.0 if is_online else 0.0)
            if not active:
                continue
            integrated.add_metric(labels, ok)
            rejected.add_metric(labels, bad)
            lost.add_metric(labels, gaps)
            duplicates.add_metric(labels, dups)
            dropped.add_metric(labels, full)
            not_durable.add_metric(labels, lost_commits)
            conflicts.add_metric(labels, clashes)
        maps.add_metric([], len(entries))
        queued, oldest = self.registry.backlog()
        depth.add_metric([], queued)
        queue_limit.add_metric([], self.registry.queue.total)
        age.add_metric([], oldest)
        if self.registry.durable is not None:
            storage_ok.add_metric([], 1.0 if self.registry.durable.health().ok else 0.0)
        budget = self.registry.memory_budget
        if budget is not None:
            budget_used.add_metric([], budget.used)
            if budget.limit is not None:
                budget_limit.add_metric([], budget.limit)
        yield from families

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        robot = ["map", "robot"]
        return (
            CounterMetricFamily("fleetmap_scans_integrated", "Scans integrated into the map", labels=robot),
            CounterMetricFamily(
                "fleetmap_scans_rejected",
                "Scans refused: undecodable, past the input limits or the map's max_tiles, or needing tiles "
                "the memory budget (--max-memory) cannot hold",
                labels=robot,
            ),
            # A gauge, not a counter: a gap is counted when a later seq arrives, and taken back when it
            # turns out to be another robot's (an id conflict found withdraws the "restart" it made),
            # so it goes down, which a counter must not: Prometheus reads a counter that falls as
            # a reset, and `increase()` then reports the whole value again.
            GaugeMetricFamily(
                "fleetmap_scans_lost",
                "Gaps in the robot's sequence numbers (goes down when a gap turns out to be another robot "
                "publishing under the id)",
                labels=robot,
            ),
            CounterMetricFamily(
                "fleetmap_scans_duplicate", "Scans ignored because their seq was not new", labels=robot
            ),
            CounterMetricFamily(
                "fleetmap_scans_dropped", "Scans refused because the ingest queue was full", labels=robot
            ),
            CounterMetricFamily(
                "fleetmap_scans_not_durable",
                "Scans applied whose journal commit failed (a snapshot saves them once storage works)",
                labels=robot,
            ),
            GaugeMetricFamily(
                "fleetmap_robot_online", "1 while the robot's liveliness token is alive", labels=robot
            ),
            CounterMetricFamily(
                "fleetmap_robot_id_conflicts",
                "Publisher sessions found publishing at once under the robot's id (more than one robot "
                "under one id; see id_conflict in GET /maps/{map_id})",
                labels=robot,
            ),
            GaugeMetricFamily("fleetmap_map_tiles", "Storage tiles allocated", labels=["map"]),
            GaugeMetricFamily(
                "fleetmap_map_memory_bytes",
                "Bytes the map's tiles hold: pools, versions, bookkeeping",
                labels=["map"],
            ),
            GaugeMetricFamily("fleetmap_maps", "Maps held"),
            GaugeMetricFamily("fleetmap_queue_depth", "Scans waiting for integration"),
            GaugeMetricFamily(
                "fleetmap_ingest_backlog_seconds", "Seconds the oldest scan waiting for integration waited"
            ),
            GaugeMetricFamily(
                "fleetmap_storage_ok", "1 while durable storage is healthy (GET /healthz: storage)"
            ),
            GaugeMetricFamily("fleetmap_memory_used_bytes", "Bytes all maps' tiles hold (--max-memory)"),
            GaugeMetricFamily("fleetmap_memory_limit_bytes", "Bytes all maps' tiles may hold (--max-memory)"),
            GaugeMetricFamily(
                "fleetmap_queue_limit",
                "Scans the ingest queue holds at most (all robots); past it new scans are dropped",
            ),
        )


class StorageCollector(Collector):
    """The journal writer's own counters (commits and rows written since start) and its backlog
    (scans applied whose rows wait for their commit, and how long the oldest has waited), read at
    scrape. A disk that stalls shows in the backlog's age alone: with durable storage a scan counts
    as integrated only once its row commits, so commits and scans integrated stop together, and the
    ingest queue stays empty (the workers go on applying scans)."""

    def __init__(self, registry: MapRegistry) -> None:
        self.registry = registry

    def describe(self) -> list[Metric]:
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        commits, rows, failures, waiting, age = self._families()
        durable = self.registry.durable
        if durable is None:
            return
        commits.add_metric([], durable.writer.commits)
        rows.add_metric([], durable.writer.rows)
        pending, oldest = durable.writer.backlog()
        waiting.add_metric([], pending)
        age.add_metric([], oldest)
        counted = dict(durable.failures)  # a copy: the writer and snapshot threads add to it
        # Every operation from the start, at 0 until it fails: `increase()` over a series that
        # appears with its first failure misses that failure.
        for operation in STORAGE_OPERATIONS:
            failures.add_metric([operation], counted.get(operation, 0))
        yield from (commits, rows, failures, waiting, age)

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        return (
            CounterMetricFamily("fleetmap_journal_commits", "Journal transactions committed (group commits)"),
            # A cleared window is a row between the scans (DELETE /maps/{id}/region), so after one
            # the rows are more than the scans integrated.
            CounterMetricFamily(
                "fleetmap_journal_rows",
                "Journal rows committed: scans, and windows cleared (DELETE /maps/{map_id}/region)",
            ),
            CounterMetricFamily(
                "fleetmap_storage_failures",
                "Storage operations that failed (a full or failing disk): journal commits, snapshots, "
                "map creations / deletions",
                labels=["operation"],
            ),
            GaugeMetricFamily(
                "fleetmap_journal_rows_waiting", "Scans applied whose journal rows wait for their commit"
            ),
            GaugeMetricFamily(
                "fleetmap_journal_backlog_seconds",
                "Seconds the oldest scan applied and waiting for its journal commit has waited (a stalled "
                "disk: it grows)",
            ),
        )


class ServiceInfoCollector(Collector):
    """`fleetmap_build_info{version}` (always 1: the version that runs, for upgrades) and, once the
    HTTP server runs, its open connections and their limit (`--max-http-connections`)."""

    def __init__(self) -> None:
        self.version = installed_version()
        self.connections: Callable[[], int] | None = None
        self.max_connections = 0

    def describe(self) -> list[Metric]:
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        info, connections, limit = self._families()
        info.add_metric([self.version], 1)
        yield info
        if self.connections is not None:
            connections.add_metric([], self.connections())
            limit.add_metric([], self.max_connections)
            yield from (connections, limit)

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        return (
            GaugeMetricFamily(
                "fleetmap_build_info", "The fleetmap version running (always 1)", labels=["version"]
            ),
            GaugeMetricFamily(
                "fleetmap_http_connections", "HTTP connections open now (this scrape's included)"
            ),
            GaugeMetricFamily(
                "fleetmap_http_connections_limit", "HTTP connections open at once past which new ones get 503"
            ),
        )


class IngestGateCollector(Collector):
    """HTTP requests held back for ingest (`fleetmap.api.ingest_priority`), read at scrape."""

    def __init__(self, gate: IngestGate) -> None:
        self.gate = gate

    def describe(self) -> list[Metric]:
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        delayed, seconds, timeouts, waiting = self._families()
        delayed.add_metric([], self.gate.delayed)
        seconds.add_metric([], self.gate.delay_seconds)
        timeouts.add_metric([], self.gate.timeouts)
        waiting.add_metric([], self.gate.waiting)
        yield from (delayed, seconds, timeouts, waiting)

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        return (
            CounterMetricFamily(
                "fleetmap_http_delayed_requests", "HTTP requests that waited for the ingest backlog to clear"
            ),
            CounterMetricFamily(
                "fleetmap_http_delay_seconds", "Seconds HTTP requests spent waiting for the ingest backlog"
            ),
            CounterMetricFamily(
                "fleetmap_http_delay_timeouts",
                "Delayed HTTP requests served after the longest wait, with the backlog still there",
            ),
            GaugeMetricFamily("fleetmap_http_requests_waiting", "HTTP requests waiting for ingest now"),
        )


class SlotsCollector(Collector):
    """Requests of a kind in progress (`api.state.Slots`) and those refused at its cap, read at
    scrape: `fleetmap_<name>` and `fleetmap_<name>_refused_total`."""

    def __init__(self, slots: Slots, name: str, what: str) -> None:
        #: `what`: the requests, as the help texts name them ("Event streams (GET ...)").
        self.slots, self.name, self.what = slots, name, what

    def describe(self) -> list[Metric]:
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        in_progress, refused = self._families()
        in_progress.add_metric([], self.slots.open)
        refused.add_metric([], self.slots.refused)
        yield from (in_progress, refused)

    def _families(self) -> tuple[_Family, ...]:
        return (
            GaugeMetricFamily(f"fleetmap_{self.name}", f"{self.what} in progress now"),
            CounterMetricFamily(
                f"fleetmap_{self.name}_refused",
                f"{self.what} refused (503) because the limit of those in progress was reached",
            ),
        )


class TileCacheCollector(Collector):
    """The tile cache's own counters (requests served from the cache, tiles rendered), read at scrape."""

    def __init__(self, cache: TileCache, statuses: dict[int, int]) -> None:
        self.cache = cache
        self.statuses = statuses

    def describe(self) -> list[Metric]:
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        hits, renders, entries, requests = self._families()
        hits.add_metric([], self.cache.hits)
        renders.add_metric([], self.cache.renders)
        entries.add_metric([], len(self.cache))
        for status, count in sorted(dict(self.statuses).items()):  # (a copy: see StatusCounter)
            requests.add_metric([str(status)], count)
        yield from (hits, renders, entries, requests)

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        return (
            CounterMetricFamily(
                "fleetmap_tile_cache_hits",
                "Tile requests served without a render of their own (cached, or another request's render)",
            ),
            CounterMetricFamily("fleetmap_tile_renders", "Tiles rendered (cache misses)"),
            GaugeMetricFamily("fleetmap_tile_cache_entries", "Rendered tiles held in the cache"),
            CounterMetricFamily(
                "fleetmap_tile_requests",
                "Tile requests by the HTTP status answered (200 sent, 304 revalidated, 404, 422, ...)",
                labels=["status"],
            ),
        )


class RuntimeCollector(Collector):
    """The interpreter's garbage collector: collections per generation (a full collection holds the
    GIL while it walks every tracked object) and the objects frozen out of its reach at start-up."""

    def describe(self) -> list[Metric]:
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        collections, frozen = self._families()
        for generation, stats in enumerate(gc.get_stats()):
            collections.add_metric([str(generation)], stats["collections"])
        frozen.add_metric([], gc.get_freeze_count())
        yield from (collections, frozen)

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        return (
            CounterMetricFamily(
                "fleetmap_gc_collections",
                "Garbage collections by generation (2: full)",
                labels=["generation"],
            ),
            GaugeMetricFamily(
                "fleetmap_gc_frozen_objects", "Objects kept out of the garbage collector's walks (gc.freeze)"
            ),
        )


class ZenohCollector(Collector):
    """The service's Zenoh session, from the ingest's `status()` (what `GET /healthz` shows under
    `zenoh`), read at scrape: whether it runs, the routers and peers it is connected to, the robots
    whose liveliness tokens it sees, and its message counters."""

    def __init__(self, status: Callable[[], dict[str, Any]]) -> None:
        self.status = status

    def describe(self) -> list[Metric]:
        return [*self._families(), *self._ros_families()]

    def collect(self) -> Iterator[Metric]:
        families = self._families()
        (up, routers, peers, sessions, max_sessions, alive, received, submitted, invalid, undecodable,
         refused, missed, deferred, refetched) = families  # fmt: skip
        status = self.status()
        up.add_metric([], 1.0 if status.get("running") else 0.0)
        routers.add_metric([], status.get("routers", 0))
        peers.add_metric([], status.get("peers", 0))
        sessions.add_metric([], status.get("sessions", 0))
        if status.get("max_sessions") is not None:
            max_sessions.add_metric([], status["max_sessions"])
        alive.add_metric([], status.get("robots_alive", 0))
        received.add_metric([], status.get("messages_received", 0))
        submitted.add_metric([], status.get("scans_submitted", 0))
        invalid.add_metric([], status.get("invalid_keys", 0))
        undecodable.add_metric([], status.get("decode_errors", 0))
        # The usual reasons from the start, at 0 (see StorageCollector), and any other as it comes.
        counts = dict.fromkeys(ZENOH_REFUSALS, 0) | status.get("rejected", {})
        for reason, count in sorted(counts.items()):
            refused.add_metric([reason], count)
        missed.add_metric([], status.get("unrecoverable", 0))
        deferred.add_metric([], status.get("deferred", 0))
        refetched.add_metric([], status.get("refetched", 0))
        yield from families
        # ROS 2 scans (--ros-scans): at 0 without it, so that alerts need no special case.
        ros_received, ros_submitted, ros_waiting, ros_refused, tf_refused = self._ros_families()
        ros = status.get("ros") or {}
        ros_received.add_metric([], ros.get("scans_received", 0))
        ros_submitted.add_metric([], ros.get("scans_submitted", 0))
        ros_waiting.add_metric([], ros.get("scans_waiting", 0))
        for reason, count in sorted((dict.fromkeys(ROS_REFUSALS, 0) | ros.get("refused", {})).items()):
            ros_refused.add_metric([reason], count)
        tf_refused.add_metric([], ros.get("tf_refused", 0))
        yield from (ros_received, ros_submitted, ros_waiting, ros_refused, tf_refused)

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        return (
            GaugeMetricFamily("fleetmap_zenoh_up", "1 while the service's Zenoh session runs"),
            GaugeMetricFamily(
                "fleetmap_zenoh_routers",
                "Zenoh routers the session is connected to (0 in client mode: the router is unreachable)",
            ),
            GaugeMetricFamily("fleetmap_zenoh_peers", "Zenoh peers the session is connected to"),
            GaugeMetricFamily(
                "fleetmap_zenoh_sessions",
                "Zenoh unicast sessions connected to the service's session (robots; routers and peers too)",
            ),
            GaugeMetricFamily(
                "fleetmap_zenoh_max_sessions",
                "The most Zenoh sessions the service's session accepts (transport/unicast/max_sessions); "
                "robots past it are refused at their handshake",
            ),
            GaugeMetricFamily(
                "fleetmap_zenoh_robots_alive", "Robot liveliness tokens the session sees (every map)"
            ),
            CounterMetricFamily("fleetmap_zenoh_messages_received", "Scan messages received over Zenoh"),
            CounterMetricFamily(
                "fleetmap_zenoh_scans_submitted", "Scans received over Zenoh and queued for integration"
            ),
            CounterMetricFamily(
                "fleetmap_zenoh_invalid_keys",
                "Zenoh messages ignored: an invalid map or robot id in the key (scans; liveliness tokens "
                "as they appear)",
            ),
            # Both kinds: the decoder applies the input limits (codec.decode), and a pose outside
            # the world bound is a robot's fault as much as garbage is.
            CounterMetricFamily(
                "fleetmap_zenoh_decode_errors",
                "Zenoh scan messages refused before they were queued: undecodable, or past the input "
                "limits (a pose outside --world-bound, more than --max-beams beams, ...)",
            ),
            CounterMetricFamily(
                "fleetmap_zenoh_scans_refused",
                "Scans received over Zenoh that the registry refused, by reason (queue_full, duplicate, ...)",
                labels=["reason"],
            ),
            CounterMetricFamily(
                "fleetmap_zenoh_scans_unrecoverable",
                "Scans of advanced publishers (a robot's backlog) that Zenoh could not recover: gone from "
                "the robot's cache before the service could fetch them",
            ),
            CounterMetricFamily(
                "fleetmap_zenoh_scans_deferred",
                "Scans of advanced publishers the full ingest queue deferred, or held back behind a "
                "deferred one, to be fetched again from the robot's cache",
            ),
            CounterMetricFamily(
                "fleetmap_zenoh_scans_refetched",
                "Scans fetched again from robots' caches after the full ingest queue deferred them",
            ),
        )

    @staticmethod
    def _ros_families() -> tuple[_Family, ...]:
        return (
            CounterMetricFamily(
                "fleetmap_ros_scans_received", "ROS 2 LaserScan messages received (--ros-scans)"
            ),
            CounterMetricFamily(
                "fleetmap_ros_scans_submitted", "ROS 2 scans posed by TF and queued for integration"
            ),
            GaugeMetricFamily("fleetmap_ros_scans_waiting", "ROS 2 scans waiting for the TF that poses them"),
            CounterMetricFamily(
                "fleetmap_ros_scans_refused",
                "ROS 2 scans refused, by reason (no_tf, undecodable, tf_error, ...; see docs/ros.md)",
                labels=["reason"],
            ),
            CounterMetricFamily(
                "fleetmap_ros_tf_refused", "ROS 2 TF transforms refused (undecodable, invalid, past a limit)"
            ),
        )


class StatusCounter:
    """ASGI middleware counting HTTP answers by status in `counts`: every answer of the app
    (`fleetmap_http_responses_total{code}`, to alert on 5xx) or, with `only`, those to the paths it
    accepts (tiles: `fleetmap_tile_requests_total{status}`). The status is read from the answer
    itself, so errors raised anywhere (validation, exception handlers) count too; a request whose
    app raised before answering counts as 500. Runs on the event loop only, so `counts` needs no
    lock; a scrape copies it (`dict(counts)`, one C call under the GIL). Answers refused before the
    app (the connection limit, a bad request head) are not the app's and are not counted."""

    def __init__(self, app: Any, counts: dict[int, int], only: Callable[[str], bool] | None = None) -> None:
        self.app = app
        self.counts = counts
        self.only = only

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or (self.only is not None and not self.only(route_path(scope))):
            await self.app(scope, receive, send)
            return
        started = False

        async def counting_send(message: Any) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                status = message["status"]
                self.counts[status] = self.counts.get(status, 0) + 1
            await send(message)

        try:
            await self.app(scope, receive, counting_send)
        except BaseException:
            if not started:
                self.counts[500] = self.counts.get(500, 0) + 1
            raise


class HttpResponsesCollector(Collector):
    """`fleetmap_http_responses_total{code}` from a `StatusCounter`'s counts, read at scrape."""

    def __init__(self, counts: dict[int, int]) -> None:
        self.counts = counts

    def describe(self) -> list[Metric]:
        return list(self._families())

    def collect(self) -> Iterator[Metric]:
        (responses,) = self._families()
        # 500 and 503 from the start, at 0: an alert on `increase()` of 5xx sees the first one.
        counts = {500: 0, 503: 0} | dict(self.counts)  # (a copy: see StatusCounter)
        for status, count in sorted(counts.items()):
            responses.add_metric([str(status)], count)
        yield responses

    @staticmethod
    def _families() -> tuple[_Family, ...]:
        return (
            CounterMetricFamily(
                "fleetmap_http_responses",
                "HTTP answers of the app by status code (every route; 5xx: the service failed)",
                labels=["code"],
            ),
        )


class ServiceMetrics:
    """One app's metrics: its own CollectorRegistry with the registry's counters, the integration
    latencies, the tile cache's counters and the tile render latency (`observe_render` is the tile
    cache's `on_render` hook)."""

    def __init__(
        self, registry: MapRegistry, integration: IntegrationMetrics, robot_idle: float = ROBOT_SERIES_IDLE
    ) -> None:
        """`robot_idle`: see `RegistryCollector`."""
        self.collector_registry = CollectorRegistry()
        self.collector_registry.register(RegistryCollector(registry, robot_idle))
        self.collector_registry.register(StorageCollector(registry))
        self.service_info = ServiceInfoCollector()
        self.collector_registry.register(self.service_info)
        self.collector_registry.register(RuntimeCollector())
        # process_resident_memory_bytes, process_open_fds / process_max_fds, process_cpu_seconds_total,
        # process_start_time_seconds (a restart), from /proc; nothing on systems without it.
        ProcessCollector(registry=self.collector_registry)
        for collector in integration.collectors():
            self.collector_registry.register(collector)
        self.tile_render_seconds = Histogram(
            "fleetmap_tile_render_seconds",
            "Time to render one tile PNG (a cache miss; hits are not rendered)",
            ["layer"],
            buckets=LATENCY_BUCKETS,
            registry=self.collector_registry,
        )
        #: Tile requests by the status of their answer (`StatusCounter` on the tile paths).
        self.tile_statuses: dict[int, int] = {}
        #: Every HTTP answer by its status (`StatusCounter`).
        self.http_statuses: dict[int, int] = {}
        self.collector_registry.register(HttpResponsesCollector(self.http_statuses))

    def observe_render(self, layer: str, z: int, seconds: float) -> None:
        self.tile_render_seconds.labels(layer).observe(seconds)

    def watch_tile_cache(self, cache: TileCache) -> None:
        self.collector_registry.register(TileCacheCollector(cache, self.tile_statuses))

    def watch_gate(self, gate: IngestGate) -> None:
        self.collector_registry.register(IngestGateCollector(gate))

    def watch_http_connections(self, count: Callable[[], int], limit: int) -> None:
        """Report `count()` as the open HTTP connections, out of `limit` (`http_server.make_server`)."""
        self.service_info.max_connections = limit
        self.service_info.connections = count

    def watch_zenoh(self, status: Callable[[], dict[str, Any]]) -> None:
        """Export the Zenoh session's `status()` (`ZenohIngest.status`) as `fleetmap_zenoh_*`."""
        self.collector_registry.register(ZenohCollector(status))

    def watch_slots(self, slots: Slots, name: str, what: str) -> None:
        """Export the requests of a kind in progress and those refused (`SlotsCollector`)."""
        self.collector_registry.register(SlotsCollector(slots, name, what))

    def render(self) -> bytes:
        """The Prometheus text exposition of every metric."""
        return generate_latest(self.collector_registry)


__all__ = [
    "CONTENT_TYPE",
    "ROBOT_SERIES_IDLE",
    "STORAGE_OPERATIONS",
    "HttpResponsesCollector",
    "IngestGateCollector",
    "IntegrationMetrics",
    "RegistryCollector",
    "StatusCounter",
    "RuntimeCollector",
    "ServiceInfoCollector",
    "ServiceMetrics",
    "SlotsCollector",
    "StorageCollector",
    "TileCacheCollector",
    "ZenohCollector",
]
