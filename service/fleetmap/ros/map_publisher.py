"""Live maps to ROS 2 navigation stacks: each chosen map published as a `nav_msgs/msg/OccupancyGrid`
over rmw_zenoh, as nav2's map_server publishes `/map`, on the service's own Zenoh session.

    fleetmap serve --ros-publish-map lab --ros-publish-map warehouse=/warehouse/map

What a ROS 2 node with rmw_zenoh sees (the facts and their sources: docs/ros.md):

- Data on `<domain>/<topic without its leading />/<dds type>/<type hash>`
  (`0/map/nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_8d34...`), the exact key a subscription
  declares, from a Zenoh *advanced* publisher with a one-sample cache, publisher detection and
  sporadic heartbeats (sample miss detection), as rmw_zenoh's publisher for TRANSIENT_LOCAL +
  RELIABLE + KEEP_LAST 1 (`PublisherData::make`): a subscription that starts later asks the cache
  and gets the current map at once, as from map_server.
- Each sample carries rmw_zenoh's attachment (sequence number from 1, source timestamp, gid):
  subscriptions drop samples without one.
- Liveliness tokens for the node (`/fleetmap`) and each publisher (`fleetmap.ros.graph`), so that
  `ros2 node list` and `ros2 topic info -v /map` show them.

Publishing: one thread (`fleetmap-ros-map`) checks every `period` seconds, for each topic, whether
its map changed: one dictionary look-up under the registry's lock and the map's tile clock
(`TileStore.clock`, which every applied scan advances), compared with what it last published. A
map that did not change costs only that. A changed map is published whole: the observed extent
(`export.known_window`), classified as the nav2 export does (`occupancy_grid.grid_cells`, which
reads the map one storage tile at a time, each under the map's lock for its copy only), CDR-encoded
and put. The clock is read before the cells, so a scan applied during the read is published at the
next check.
A map that is deleted is no longer published: its publisher and token are undeclared (a ROS node
starting later gets no stale map from the cache); a map created again, or replaced from a snapshot,
is published again, from a publisher declared anew (so the old map's grid is not in its cache even
when the new map has nothing to publish yet).
"""

from __future__ import annotations

import contextlib
import logging
import re
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh
import zenoh.ext

from fleetmap.export import known_window, map_source
from fleetmap.rate_limited_log import RateLimitedLog
from fleetmap.registry import MapEntry, MapRegistry
from fleetmap.ros.graph import MAP_QOS, RosNode, entity_gid
from fleetmap.ros.occupancy_grid import ROS_TYPE, occupancy_grid
from fleetmap.ros.rmw_zenoh import (
    HUMBLE_TYPE_HASH,
    TYPE_HASHES,
    Attachment,
    dds_type_name,
    encode_attachment,
    topic_key,
)
from fleetmap.wire import is_valid_id

log = logging.getLogger("fleetmap.ros")

DEFAULT_TOPIC = "/map"
#: The ROS 2 distributions whose subscribers can be served: Jazzy (and Kilted, Rolling) key topics
#: by the message's RIHS01 hash and have 16-byte gids; Humble's rmw_zenoh (a backport) writes
#: `HUMBLE_TYPE_HASH` in the hash's place and has 24-byte gids (RMW_GID_STORAGE_SIZE), which its
#: subscribers read from the attachment as a fixed-size array.
DISTROS = ("jazzy", "humble")
GID_SIZES = {"jazzy": 16, "humble": 24}
#: The largest window published, in cells: the REST API's bound for an export (16 Mi cells: a
#: 16 MiB grid). A bigger map is not published, and says so in the log.
MAX_GRID_CELLS = 16 * 1024 * 1024
#: rmw_zenoh's heartbeat period for sample miss detection of a RELIABLE + TRANSIENT_LOCAL publisher
#: (SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD, 500 ms), in seconds.
HEARTBEAT_PERIOD = 0.5

_TOPIC_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def type_hash(distro: str) -> str:
    """The type hash string of an OccupancyGrid's key expression for a ROS 2 distribution."""
    if distro == "humble":
        return HUMBLE_TYPE_HASH
    if distro == "jazzy":
        return TYPE_HASHES[ROS_TYPE]
    raise ValueError(f"unknown ROS 2 distribution {distro!r}: expected one of {', '.join(DISTROS)}")


@dataclass(frozen=True)
class MapTopic:
    """One map and the absolute ROS topic it is published on."""

    map_id: str
    topic: str = DEFAULT_TOPIC


def parse_map_topic(text: str) -> MapTopic:
    """`MAP_ID[=TOPIC]` (`lab`, `lab=/lab/map`, `lab=map`) as a `MapTopic`; a relative topic is taken
    from the root namespace. Raises ValueError saying what is wrong."""
    map_id, sep, topic = text.strip().partition("=")
    if not is_valid_id(map_id):
        raise ValueError(f"{text!r}: expected MAP_ID[=TOPIC] with a map id of 1 to 64 of A-Z a-z 0-9 _ -")
    if not sep:
        return MapTopic(map_id)
    topic = topic if topic.startswith("/") else "/" + topic
    if not _TOPIC_RE.match(topic):
        raise ValueError(
            f"{text!r}: {topic!r} is not a ROS topic name (names of letters, digits and _, not starting "
            "with a digit, separated by /)"
        )
    return MapTopic(map_id, topic)


@dataclass(frozen=True)
class RosMapOptions:
    """What `RosMapPublisher` publishes, and how."""

    topics: tuple[MapTopic, ...]
    domain_id: int = 0
    frame_id: str = "map"  # header.frame_id of the grids of a map not in `map_frames`
    #: (map id, frame id): the frame of that map's grids, where it differs from `frame_id` (a map
    #: `--ros-scans` builds in another fixed frame).
    map_frames: tuple[tuple[str, str], ...] = ()
    period: float = 1.0  # seconds, at least, between two grids of one map
    distro: str = "jazzy"
    node_name: str = "fleetmap"
    max_cells: int = MAX_GRID_CELLS


@dataclass
class _Topic:
    """One published map: its Zenoh publisher and token while the map exists, and what it sent."""

    spec: MapTopic
    key: str
    entity_id: int
    token_key: str
    gid: bytes
    publisher: Any = None  # zenoh.ext.AdvancedPublisher while declared
    token: Any = None  # zenoh.LivelinessToken while declared
    sequence: int = 0  # the last sequence number sent (rmw_zenoh's first is 1)
    #: (generation, tile clock) of the map as last published or found empty / unpublishable.
    seen: tuple[int, int] | None = None
    published: int = 0  # grids put
    #: The last grid's `bytes`, `build_s` (window, cells, encoding) and `put_s`; replaced whole.
    last_build: dict[str, float] = field(default_factory=dict)


class RosMapPublisher:
    """Publishes `options.topics` on `session` from `registry`'s maps (see the module doc).

    `start` declares the node's token and starts the thread; `close` stops it and undeclares
    everything (call it before the session closes). The thread never raises: a failing grid is
    logged (rate-limited) and tried again when the map next changes."""

    def __init__(self, registry: MapRegistry, session: zenoh.Session, options: RosMapOptions) -> None:
        self.registry = registry
        self.session = session
        self.options = options
        type_hash_text = type_hash(options.distro)
        self.node = RosNode(options.domain_id, str(session.zid()), node_id=0, name=options.node_name)
        dds_type = dds_type_name(ROS_TYPE)
        self.topics: list[_Topic] = []
        for n, spec in enumerate(options.topics, start=1):
            token_key = self.node.publisher_token(n, spec.topic, dds_type, type_hash_text, MAP_QOS)
            key = topic_key(options.domain_id, spec.topic, ROS_TYPE, type_hash_text)
            gid = entity_gid(token_key, GID_SIZES[options.distro])
            self.topics.append(_Topic(spec, key, n, token_key, gid))
        self._node_token: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._warnings = RateLimitedLog(log)

    def start(self) -> None:
        """Declare the node's token and start publishing (the first check runs at once)."""
        if self._thread is not None:
            return
        self._node_token = self.session.liveliness().declare_token(self.node.node_token())
        for topic in self.topics:
            log.info(
                "ROS 2: map %r as %s on %s (domain %d, node /%s, key %s), at most every %g s",
                topic.spec.map_id, ROS_TYPE, topic.spec.topic, self.options.domain_id,
                self.options.node_name, topic.key, self.options.period,
                extra={"map_id": topic.spec.map_id},
            )  # fmt: skip
        self._thread = threading.Thread(target=self._run, name="fleetmap-ros-map", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 10.0) -> None:
        """Stop the thread (a grid being built is finished first), then undeclare the publishers and
        tokens. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        for topic in self.topics:
            self._undeclare(topic)
        if self._node_token is not None:
            token, self._node_token = self._node_token, None
            _undeclare_quietly(token)

    def status(self) -> dict[str, Any]:
        """A JSON-able summary for `GET /healthz` (`zenoh.ros_maps`): the node, and per topic its map,
        key, whether its publisher is declared (its map exists), the grids put, and the last one's
        size and times. Read without a lock: each field is one value the thread replaces whole."""
        topics = {}
        for topic in self.topics:
            last = topic.last_build
            topics[topic.spec.topic] = {
                "map_id": topic.spec.map_id,
                "key": topic.key,
                "declared": topic.publisher is not None,
                "grids_published": topic.published,
                "last_grid": {"bytes": int(last["bytes"]), "build_ms": round(1000 * last["build_s"], 2),
                              "put_ms": round(1000 * last["put_s"], 2)} if last else None,
            }  # fmt: skip
        return {
            "node": f"/{self.options.node_name}",
            "domain_id": self.options.domain_id,
            "distro": self.options.distro,
            "period": self.options.period,
            "topics": topics,
        }

    def _run(self) -> None:
        while True:
            self.publish_changed()
            if self._stop.wait(self.options.period):
                return

    def publish_changed(self) -> int:
        """One check of every topic: publish each map that changed since it was last published.
        Returns how many grids were put."""
        put = 0
        # A map published on several topics (one per robot's nav2 namespace) is built once a check.
        grids: dict[tuple[str, int, int], bytes] = {}
        for topic in self.topics:
            if self._stop.is_set():
                break
            try:
                put += self._check(topic, grids)
            except Exception as exc:  # noqa: BLE001 - the thread must go on; the next change retries
                self._warnings.error(
                    f"grid {topic.spec.map_id}",
                    f"ROS 2: publishing map {topic.spec.map_id!r} on {topic.spec.topic} failed: {exc}",
                    exc_info=exc,
                    map_id=topic.spec.map_id,
                )
        return put

    def _check(self, topic: _Topic, grids: dict[tuple[str, int, int], bytes]) -> int:
        with self.registry.lock:
            entry = self.registry.maps.get(topic.spec.map_id)
        if entry is None:
            if topic.publisher is not None:
                log.info(
                    "ROS 2: map %r is gone: no longer published on %s", topic.spec.map_id, topic.spec.topic,
                    extra={"map_id": topic.spec.map_id},
                )  # fmt: skip
            self._undeclare(topic)
            topic.seen = None
            return 0
        if topic.publisher is not None and topic.seen is not None and topic.seen[0] != entry.generation:
            # Another map of the id since the last check (deleted and created again within a
            # period, or replaced by an upload): the old map's grid leaves the publisher's cache
            # now, even if the new map has nothing to publish (no observed cell yet, TSDF only, too
            # big), or a ROS node starting later would get a map that no longer exists.
            self._undeclare(topic)
        if topic.publisher is None:
            self._declare(topic)
        # Before the cells: a scan applied while they are read advances the clock past this, so the
        # next check publishes again.
        seen = (entry.generation, entry.gmap.store.clock)
        if seen == topic.seen:
            return 0
        topic.seen = seen
        return self._publish(topic, entry, grids)

    def _publish(self, topic: _Topic, entry: MapEntry, grids: dict[tuple[str, int, int], bytes]) -> int:
        """Put `entry`'s grid on `topic`; `grids` holds those built in this check, by map id and
        `topic.seen`, so that another topic of the same map state reuses the one built."""
        gmap, spec = entry.gmap, topic.spec
        if map_source(gmap) is None:
            self._warnings.warning(
                f"tsdf {spec.map_id}",
                f"ROS 2: map {spec.map_id!r} keeps only the TSDF, which has no occupancy to publish",
                map_id=spec.map_id,
            )
            return 0
        started = time.perf_counter()
        window = known_window(gmap)
        if window is None:
            return 0  # no observed cell yet: published once it has one
        ny, nx = window.shape
        if nx * ny > self.options.max_cells:
            self._warnings.warning(
                f"size {spec.map_id}",
                f"ROS 2: map {spec.map_id!r} spans {nx} x {ny} cells, more than the {self.options.max_cells} "
                f"published: not published on {spec.topic}",
                map_id=spec.map_id,
            )
            return 0
        frame_id = dict(self.options.map_frames).get(spec.map_id, self.options.frame_id)
        assert topic.seen is not None
        built_as = (spec.map_id, *topic.seen)
        payload = grids.get(built_as)
        if payload is None:
            payload = grids[built_as] = occupancy_grid(gmap, window, frame_id, time.time_ns())
        built = time.perf_counter()
        topic.sequence += 1
        attachment = encode_attachment(Attachment(topic.sequence, time.time_ns(), topic.gid))
        topic.publisher.put(payload, attachment=attachment)
        done = time.perf_counter()
        topic.published += 1
        topic.last_build = {"build_s": built - started, "put_s": done - built, "bytes": float(len(payload))}
        log.debug(
            "ROS 2: map %r published on %s: %d x %d cells, %d bytes, built in %.1f ms, put in %.1f ms",
            spec.map_id, spec.topic, nx, ny, len(payload), 1000 * (built - started), 1000 * (done - built),
            extra={"map_id": spec.map_id},
        )  # fmt: skip
        return 1

    def _declare(self, topic: _Topic) -> None:
        """The advanced publisher rmw_zenoh declares for TRANSIENT_LOCAL + RELIABLE + KEEP_LAST 1,
        then the publisher's token (in that order, as rmw_zenoh: a node that sees the token can
        already get the cache)."""
        topic.publisher = zenoh.ext.declare_advanced_publisher(
            self.session,
            topic.key,
            cache=zenoh.ext.CacheConfig(MAP_QOS.depth),
            publisher_detection=True,
            sample_miss_detection=zenoh.ext.MissDetectionConfig(
                heartbeat=None, sporadic_heartbeat=HEARTBEAT_PERIOD
            ),
            reliability=zenoh.Reliability.RELIABLE,
            # rmw_zenoh drops rather than blocks for KEEP_LAST; a subscriber that misses the sample
            # recovers it from the cache by the heartbeat.
            congestion_control=zenoh.CongestionControl.DROP,
        )
        topic.token = self.session.liveliness().declare_token(topic.token_key)

    def _undeclare(self, topic: _Topic) -> None:
        token, publisher = topic.token, topic.publisher
        topic.token = topic.publisher = None
        for item in (token, publisher):
            if item is not None:
                _undeclare_quietly(item)


def _undeclare_quietly(item: Any) -> None:
    """Undeclare a Zenoh entity; one whose session is already closed has nothing left to undo."""
    with contextlib.suppress(zenoh.ZError):
        item.undeclare()
