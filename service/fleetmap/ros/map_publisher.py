"""Live maps to ROS 2 navigation stacks: each chosen map published as a `nav_msgs/msg/OccupancyGrid`
over rmw_zenoh, as nav2's map_server publishes `/map`, and its changes between grids as
`map_msgs/msg/OccupancyGridUpdate`s on `<topic>_updates`, as costmap_2d publishes a costmap's, on
the service's own Zenoh session.

    fleetmap serve --ros-publish-map lab --ros-publish-map warehouse=/warehouse/map

What a ROS 2 node with rmw_zenoh sees (the facts and their sources: docs/ros.md):

- Grids on `<domain>/<topic without its leading />/<dds type>/<type hash>`
  (`0/map/nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_8d34...`), the exact key a subscription
  declares, from a Zenoh *advanced* publisher with a one-sample cache, publisher detection and
  sporadic heartbeats (sample miss detection), as rmw_zenoh's publisher for TRANSIENT_LOCAL +
  RELIABLE + KEEP_LAST 1 (`PublisherData::make`): a subscription that starts later asks the cache
  and gets a grid at once, as from map_server.
- Updates on `<domain>/<topic>_updates/map_msgs::msg::dds_::OccupancyGridUpdate_/<type hash>`, from
  a plain advanced publisher (no cache), as rmw_zenoh's for RELIABLE + VOLATILE (`MAP_UPDATES_QOS`,
  the QoS RViz's Map display and nav2's static layer subscribe to updates with).
- Each sample carries rmw_zenoh's attachment (sequence number from 1, source timestamp, gid):
  subscriptions drop samples without one.
- Liveliness tokens for the node (`/fleetmap`) and each publisher (`fleetmap.ros.graph`), so that
  `ros2 node list` and `ros2 topic info -v /map` show them.

Publishing: one thread (`fleetmap-ros-map`) checks every `period` seconds, for each topic, whether
its map changed: one dictionary look-up under the registry's lock and the map's tile clock
(`TileStore.clock`, which every applied scan advances), compared with what it last published. A
map that did not change costs only that. A changed map is published as:

- a **full grid** on `<topic>` when there is none of this map yet, when its observed extent
  (`export.known_window`, the grid's window) changed (the map grew: subscribers resize on a grid),
  when the changed parts would be more than half the window, or when the grid in the publisher's
  cache is behind the map (updates went out since) and either `full_grid_interval` has passed
  since it or a new subscription of `<topic>` appeared, or when a new VOLATILE subscription
  appeared (it asks no cache);
- else **updates** on `<topic>_updates`: the part of the window in the storage tiles changed
  since the last full grid (their versions above the tile clock its cells were read at), one
  update per run of changed tiles side by side in a row of tiles (`export.changed_windows`: apart,
  since the bounding box of two robots' tiles at opposite corners is the whole map; their bounding
  box past `MAX_UPDATES_PER_CHECK` runs, a reader's queue), the cells made
  by the same `occupancy_grid.grid_cells` as a grid's. Since the grid, not since the last updates:
  whoever holds that grid is current after the next check's updates, also when one before them was
  lost (a subscriber that dropped it, or nav2's static
  layer, which loads a grid only at its costmap's next update and so writes over an update that
  came in between).

The cells are read one storage tile at a time, each under the map's lock for its copy only. The
clock is read before the cells, so a scan applied during the read is published at the next check.

Late joiners: a node that subscribes gets the last grid from the cache at once, and updates from
then on. The cached grid lacks the updates sent since it, so fleetmap watches the subscriptions'
liveliness tokens (`@ros2_lv/<domain>/.../MS/.../<topic>/nav_msgs::msg::dds_::OccupancyGrid_/...`,
which rmw_zenoh declares for every subscription) and, when one appears while the cache is behind,
sends a current grid at once (the thread is woken; at most one such grid per update sent). A
VOLATILE subscription (RViz's Map display's default) gets nothing from the cache and drops updates
until it has a grid: its token (whose QoS says so) sends a grid at once whatever the cache holds.
Without a token (or before it arrives), the cache is never more than `full_grid_interval` behind
the map: past that, a full grid goes out at the next check even if the map has not changed since.

A map that is deleted is no longer published: its publishers and tokens are undeclared (a ROS node
starting later gets no stale map from the cache); a map created again, or replaced from a snapshot,
is published again, from publishers declared anew, starting with a full grid (so the old map's grid
is not in the cache even when the new map has nothing to publish yet).
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

from fleetmap.export import Window, bounding_window, changed_windows, known_window, map_source
from fleetmap.map_entry import MapEntry
from fleetmap.rate_limited_log import RateLimitedLog
from fleetmap.registry import MapRegistry
from fleetmap.ros.graph import (
    DURABILITY_TRANSIENT_LOCAL,
    DURABILITY_VOLATILE,
    MAP_QOS,
    MAP_UPDATES_QOS,
    SUBSCRIPTION,
    Qos,
    RosNode,
    durability_of_token,
    endpoints_key,
    entity_gid,
    subscription_of_token,
)
from fleetmap.ros.occupancy_grid import ROS_TYPE, UPDATE_ROS_TYPE, occupancy_grid, occupancy_grid_update
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
#: What the updates' topic adds to a map's topic (`/map` -> `/map_updates`), as RViz's Map display
#: and nav2's static layer (`map_topic + "_updates"`) expect it.
UPDATES_SUFFIX = "_updates"
#: The ROS 2 distributions whose subscribers can be served: Jazzy (and Kilted, Rolling) key topics
#: by the message's RIHS01 hash; Humble's rmw_zenoh (a backport) writes `HUMBLE_TYPE_HASH` in the
#: hash's place. Both have 16-byte gids (`entity_gid`): Humble's rmw_zenoh hard-codes 16 where
#: Humble's RMW_GID_STORAGE_SIZE says 24.
DISTROS = ("jazzy", "humble")
#: The largest window published, in cells: the REST API's bound for an export (16 Mi cells: a
#: 16 MiB grid). A bigger map is not published, and says so in the log.
MAX_GRID_CELLS = 16 * 1024 * 1024
#: rmw_zenoh's heartbeat period for sample miss detection of a RELIABLE + TRANSIENT_LOCAL publisher
#: (SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD, 500 ms), in seconds.
HEARTBEAT_PERIOD = 0.5
#: Seconds, at most, that the grid in a topic's cache stays behind its map (updates sent since it)
#: before a full grid replaces it: what a node that subscribes unnoticed (no token seen) may start
#: from. A full grid of a 4 M-cell map is 3.85 MiB: every 10 s is a tenth of what a grid per second
#: sent.
FULL_GRID_INTERVAL = 10.0
#: Updates whose cells would be more than this share of the window's go as a full grid: hardly
#: bigger, and it also refreshes the cache.
MAX_UPDATE_SHARE = 0.5
#: Updates put in one check at most: a reader's queue loses the oldest of a longer burst, and RViz's
#: Map display queues 5 (`rclcpp::QoS(5)`). More runs of changed tiles go as their bounding box.
MAX_UPDATES_PER_CHECK = 5

_TOPIC_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def type_hash(distro: str, ros_type: str = ROS_TYPE) -> str:
    """The type hash string of `ros_type`'s key expressions (an OccupancyGrid's by default) for a
    ROS 2 distribution."""
    if distro == "humble":
        return HUMBLE_TYPE_HASH
    if distro == "jazzy":
        return TYPE_HASHES[ros_type]
    raise ValueError(f"unknown ROS 2 distribution {distro!r}: expected one of {', '.join(DISTROS)}")


@dataclass(frozen=True)
class MapTopic:
    """One map and the absolute ROS topic it is published on."""

    map_id: str
    topic: str = DEFAULT_TOPIC

    @property
    def updates_topic(self) -> str:
        """The topic of its updates: `/map` -> `/map_updates`."""
        return self.topic + UPDATES_SUFFIX


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


def topic_clash(specs: tuple[MapTopic, ...] | list[MapTopic]) -> str | None:
    """What makes `specs` unpublishable together, or None: two maps on one topic, or a map's topic
    that is another's (or its own other topic's) updates topic (`a=/x/map b=/x/map_updates`), where
    an OccupancyGrid and an OccupancyGridUpdate would share one ROS topic, which ROS tools refuse
    (`ros2 topic echo`: more than one type)."""
    first: dict[str, MapTopic] = {}
    for spec in specs:
        other = first.setdefault(spec.topic, spec)
        if other is spec:
            continue
        if other.map_id == spec.map_id:  # not two maps: one named twice, which the message must say
            return f"map {spec.map_id} is given twice on {spec.topic}; give it once"
        return (
            f"two maps on one ROS topic ({other.map_id} and {spec.map_id} on {spec.topic}); give each "
            "its own (MAP_ID=TOPIC)"
        )
    for spec in specs:
        for other in specs:
            if other.updates_topic == spec.topic:
                return (
                    f"{spec.topic} is map {spec.map_id}'s topic and the updates topic of map "
                    f"{other.map_id}'s {other.topic}; give it another"
                )
    return None


@dataclass(frozen=True)
class RosMapOptions:
    """What `RosMapPublisher` publishes, and how."""

    topics: tuple[MapTopic, ...]
    domain_id: int = 0
    frame_id: str = "map"  # header.frame_id of the grids of a map not in `map_frames`
    #: (map id, frame id): the frame of that map's grids, where it differs from `frame_id` (a map
    #: `--ros-scans` builds in another fixed frame).
    map_frames: tuple[tuple[str, str], ...] = ()
    #: Seconds between two checks of the maps: a changed map is published at most this often (a
    #: new subscriber's grid aside).
    period: float = 1.0
    distro: str = "jazzy"
    node_name: str = "fleetmap"
    max_cells: int = MAX_GRID_CELLS
    full_grid_interval: float = FULL_GRID_INTERVAL


@dataclass
class _Publisher:
    """One rmw_zenoh publisher of a topic: its data key, token and gid, the Zenoh publisher and token
    while declared, and what it sent."""

    topic: str
    key: str
    token_key: str
    gid: bytes
    qos: Qos
    publisher: Any = None  # zenoh.ext.AdvancedPublisher while declared
    token: Any = None  # zenoh.LivelinessToken while declared
    sequence: int = 0  # the last sequence number sent (rmw_zenoh's first is 1)
    published: int = 0  # messages put
    bytes_total: int = 0  # their payloads' bytes
    #: The last message's `bytes`, `build_s` (window, changed tiles, cells, encoding) and `put_s`;
    #: replaced whole.
    last: dict[str, float] = field(default_factory=dict)

    def declare(self, session: zenoh.Session) -> None:
        """The advanced publisher rmw_zenoh declares for `qos`, then the publisher's token (in that
        order, as rmw_zenoh: a node that sees the token can already get the cache)."""
        transient_local = self.qos.durability == DURABILITY_TRANSIENT_LOCAL
        self.publisher = zenoh.ext.declare_advanced_publisher(
            session,
            self.key,
            # TRANSIENT_LOCAL: a cache of `depth` samples, found by late subscribers through
            # publisher detection, and sample miss detection (both RELIABLE here); VOLATILE: none.
            cache=zenoh.ext.CacheConfig(self.qos.depth) if transient_local else None,
            publisher_detection=transient_local,
            sample_miss_detection=zenoh.ext.MissDetectionConfig(
                heartbeat=None, sporadic_heartbeat=HEARTBEAT_PERIOD
            )
            if transient_local
            else None,
            reliability=zenoh.Reliability.RELIABLE,
            # rmw_zenoh drops rather than blocks for KEEP_LAST; a subscriber that misses a grid
            # recovers it from the cache by the heartbeat.
            congestion_control=zenoh.CongestionControl.DROP,
        )
        self.token = session.liveliness().declare_token(self.token_key)

    def undeclare(self) -> None:
        """Undeclare the token, then the publisher (and its cache). Idempotent."""
        token, publisher = self.token, self.publisher
        self.token = self.publisher = None
        for item in (token, publisher):
            if item is not None:
                _undeclare_quietly(item)

    def put(self, payload: bytes, build_s: float) -> None:
        """Put `payload` with rmw_zenoh's attachment, and count it (`build_s`: what making it took)."""
        started = time.perf_counter()
        self.sequence += 1
        attachment = encode_attachment(Attachment(self.sequence, time.time_ns(), self.gid))
        self.publisher.put(payload, attachment=attachment)
        self.published += 1
        self.bytes_total += len(payload)
        self.last = {"bytes": float(len(payload)), "build_s": build_s, "put_s": time.perf_counter() - started}

    def last_status(self) -> dict[str, Any] | None:
        last = self.last
        if not last:
            return None
        return {"bytes": int(last["bytes"]), "build_ms": round(1000 * last["build_s"], 2),
                "put_ms": round(1000 * last["put_s"], 2)}  # fmt: skip


@dataclass
class _Topic:
    """One published map: its grid and updates publishers, and what their subscribers hold."""

    spec: MapTopic
    grid: _Publisher
    updates: _Publisher
    #: (generation, tile clock) of the map as last published or found empty / unpublishable.
    seen: tuple[int, int] | None = None
    #: The window of the last full grid (None: no grid since the publishers were declared, or the
    #: map could not be published since): updates are offsets in it.
    window: Window | None = None
    #: The tile clock read before the cells of the last full grid: tiles with a newer version may
    #: differ from it, and each update carries all of them (see the module doc).
    grid_clock: int = 0
    grid_at: float = 0.0  # time.monotonic() of the last full grid
    #: Updates went out since the last full grid: the grid in the cache is behind the map.
    behind: bool = False
    #: A subscription of the grid's topic appeared since the last full grid (set by Zenoh's thread;
    #: this and the next under `RosMapPublisher._subscribers_lock`).
    new_subscriber: bool = False
    #: One of them is VOLATILE: it asks no cache, so only a grid sent now reaches it.
    new_volatile_subscriber: bool = False
    subscribers_seen: int = 0  # subscription tokens seen appear

    @property
    def declared(self) -> bool:
        return self.grid.publisher is not None


class RosMapPublisher:
    """Publishes `options.topics` on `session` from `registry`'s maps (see the module doc).

    `start` declares the node's token and starts the thread; `close` stops it and undeclares
    everything (call it before the session closes). The thread never raises: a failing grid is
    logged (rate-limited) and tried again when the map next changes."""

    def __init__(self, registry: MapRegistry, session: zenoh.Session, options: RosMapOptions) -> None:
        self.registry = registry
        self.session = session
        self.options = options
        self.node = RosNode(options.domain_id, str(session.zid()), node_id=0, name=options.node_name)
        self.topics: list[_Topic] = []
        for n, spec in enumerate(options.topics):
            # Entity ids from 1 (the node's is 0), two a topic: its grid's publisher, then its updates'.
            grid = self._publisher(2 * n + 1, spec.topic, ROS_TYPE, MAP_QOS)
            updates = self._publisher(2 * n + 2, spec.updates_topic, UPDATE_ROS_TYPE, MAP_UPDATES_QOS)
            self.topics.append(_Topic(spec, grid, updates))
        self._node_token: Any = None
        self._subscriptions: Any = None  # the liveliness subscriber of the grids' subscriptions
        self._stop = threading.Event()
        self._wake = threading.Event()  # set by a new subscription (and by close)
        #: Guards the topics' new-subscriber flags, which Zenoh's thread sets and `_check` reads and
        #: clears: a subscription that appears between that read and the clear would be cleared
        #: with the earlier ones, and a VOLATILE one then gets no grid until the map next changes.
        self._subscribers_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._warnings = RateLimitedLog(log)

    def _publisher(self, entity_id: int, topic: str, ros_type: str, qos: Qos) -> _Publisher:
        hash_text = type_hash(self.options.distro, ros_type)
        token_key = self.node.publisher_token(entity_id, topic, dds_type_name(ros_type), hash_text, qos)
        key = topic_key(self.options.domain_id, topic, ros_type, hash_text)
        return _Publisher(topic, key, token_key, entity_gid(token_key), qos)

    def start(self) -> None:
        """Declare the node's token, watch the grids' subscriptions, and start publishing (the first
        check runs at once)."""
        if self._thread is not None:
            return
        self._node_token = self.session.liveliness().declare_token(self.node.node_token())
        # Every OccupancyGrid subscription of the domain: one subscriber for all the topics. Only
        # those that appear from now on matter (the first grid goes to those already there).
        self._subscriptions = self.session.liveliness().declare_subscriber(
            endpoints_key(self.options.domain_id, SUBSCRIPTION, dds_type_name(ROS_TYPE)),
            self._on_subscription,
        )
        for topic in self.topics:
            log.info(
                "ROS 2: map %r as %s on %s (domain %d, node /%s, key %s), its changes as %s on %s, at most "
                "every %g s",
                topic.spec.map_id, ROS_TYPE, topic.spec.topic, self.options.domain_id, self.options.node_name,
                topic.grid.key, UPDATE_ROS_TYPE, topic.updates.topic, self.options.period,
                extra={"map_id": topic.spec.map_id},
            )  # fmt: skip
        self._thread = threading.Thread(target=self._run, name="fleetmap-ros-map", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 10.0) -> None:
        """Stop the thread (a grid being built is finished first), then undeclare the publishers and
        tokens. Idempotent."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        if self._subscriptions is not None:
            subscriptions, self._subscriptions = self._subscriptions, None
            _undeclare_quietly(subscriptions)
        for topic in self.topics:
            self._undeclare(topic)
        if self._node_token is not None:
            token, self._node_token = self._node_token, None
            _undeclare_quietly(token)

    def status(self) -> dict[str, Any]:
        """A JSON-able summary for `GET /healthz` (`zenoh.ros_maps`): the node, and per topic its map,
        keys, whether its publishers are declared (its map exists), the grids and updates put, their
        bytes, and the last one's size and times. Read without a lock: each field is one value the
        thread replaces whole."""
        topics = {}
        for topic in self.topics:
            grid, updates = topic.grid, topic.updates
            topics[topic.spec.topic] = {
                "map_id": topic.spec.map_id,
                "key": grid.key,
                "declared": topic.declared,
                "grids_published": grid.published,
                "grid_bytes": grid.bytes_total,
                "last_grid": grid.last_status(),
                "updates_topic": updates.topic,
                "updates_key": updates.key,
                "updates_published": updates.published,
                "update_bytes": updates.bytes_total,
                "last_update": updates.last_status(),
                "new_subscribers": topic.subscribers_seen,
            }
        return {
            "node": f"/{self.options.node_name}",
            "domain_id": self.options.domain_id,
            "distro": self.options.distro,
            "period": self.options.period,
            "full_grid_interval": self.options.full_grid_interval,
            "topics": topics,
        }

    def _on_subscription(self, sample: zenoh.Sample) -> None:
        """Zenoh's callback for a subscription token: a new subscription of a published topic is
        flagged (a VOLATILE one as such), and the thread woken to send it a current grid (see
        `_check`)."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        token = str(sample.key_expr)
        parsed = subscription_of_token(token)
        if parsed is None:
            return
        volatile = durability_of_token(token) == DURABILITY_VOLATILE
        for topic in self.topics:
            if topic.spec.topic == parsed[1]:
                with self._subscribers_lock:
                    topic.subscribers_seen += 1
                    if volatile:
                        topic.new_volatile_subscriber = True
                    topic.new_subscriber = True
                self._wake.set()

    def _run(self) -> None:
        next_check = time.monotonic()
        while not self._stop.is_set():
            # Cleared before the topics' flags are read: a subscription that appears during the
            # check wakes the next wait at once.
            self._wake.clear()
            if time.monotonic() >= next_check:
                self.publish_changed()
                next_check = time.monotonic() + self.options.period
            else:
                # Woken by a new subscription between two checks: only the grids it needs.
                self.publish_changed(new_subscribers_only=True)
            self._wake.wait(max(0.0, next_check - time.monotonic()))

    def publish_changed(self, new_subscribers_only: bool = False) -> int:
        """One check of every topic: publish each map that changed since it was last published (a
        grid or an update), and a grid where the cache's is due to be replaced. With
        `new_subscribers_only`, only the grids new subscriptions need. Returns how many grids and
        updates were put."""
        put = 0
        # A map published on several topics (one per robot's nav2 namespace) is built once a check.
        built: dict[tuple[Any, ...], bytes] = {}
        for topic in self.topics:
            if self._stop.is_set():
                break
            if new_subscribers_only and not topic.new_subscriber:
                continue
            try:
                put += self._check(topic, built, new_subscribers_only)
            except Exception as exc:  # noqa: BLE001 - the thread must go on; the next change retries
                topic.window = None  # what subscribers hold is unknown: the next publication is whole
                self._warnings.error(
                    f"grid {topic.spec.map_id}",
                    f"ROS 2: publishing map {topic.spec.map_id!r} on {topic.spec.topic} failed: {exc}",
                    exc_info=exc,
                    map_id=topic.spec.map_id,
                )
        return put

    def _check(self, topic: _Topic, built: dict[tuple[Any, ...], bytes], new_subscribers_only: bool) -> int:
        with self.registry.lock:
            entry = self.registry.maps.get(topic.spec.map_id)
        if entry is None:
            if topic.declared:
                log.info(
                    "ROS 2: map %r is gone: no longer published on %s", topic.spec.map_id, topic.spec.topic,
                    extra={"map_id": topic.spec.map_id},
                )  # fmt: skip
            self._undeclare(topic)
            topic.seen = None
            return 0
        if topic.declared and topic.seen is not None and topic.seen[0] != entry.generation:
            # Another map of the id since the last check (deleted and created again within a
            # period, or replaced by an upload): the old map's grid leaves the publisher's cache
            # now, even if the new map has nothing to publish (no observed cell yet, TSDF only, too
            # big), or a ROS node starting later would get a map that no longer exists.
            self._undeclare(topic)
        if not topic.declared:
            self._declare(topic)
        with self._subscribers_lock:  # read and cleared as one (see `_subscribers_lock`)
            if topic.new_subscriber and (
                topic.window is None or not (topic.behind or topic.new_volatile_subscriber)
            ):
                # No grid sent yet (the first goes to it too), or the cache's grid is current and the
                # new node asks for it: it has what it needs.
                topic.new_subscriber = topic.new_volatile_subscriber = False
            new_subscriber = topic.new_subscriber
        # A grid is due for a new subscription the cache does not serve (behind the map, or the
        # subscription VOLATILE), and when the cache's grid has been behind the map for long.
        since_grid = time.monotonic() - topic.grid_at
        grid_due = new_subscriber or (topic.behind and since_grid >= self.options.full_grid_interval)
        if new_subscribers_only and not grid_due:
            return 0
        # Before the cells: a scan applied while they are read advances the clock past this, so the
        # next check publishes again.
        seen = (entry.generation, entry.gmap.store.clock)
        if seen == topic.seen and not grid_due:
            return 0
        topic.seen = seen
        return self._publish(topic, entry, built, grid_due)

    def _publish(
        self, topic: _Topic, entry: MapEntry, built: dict[tuple[Any, ...], bytes], grid_due: bool
    ) -> int:
        """Put `entry`'s grid, or the update since the last grid, on `topic`; `built` holds the
        messages made in this check, by what they show, so that another topic of the same map state
        reuses the one made."""
        gmap, spec = entry.gmap, topic.spec
        if map_source(gmap) is None:
            self._unpublishable(topic)
            self._warnings.warning(
                f"tsdf {spec.map_id}",
                f"ROS 2: map {spec.map_id!r} keeps only the TSDF, which has no occupancy to publish",
                map_id=spec.map_id,
            )
            return 0
        started = time.perf_counter()
        window = known_window(gmap)
        if window is None:
            if topic.window is None:
                return 0  # no observed cell yet: published once it has one
            # Every cell cleared since (`DELETE .../region`): the last grid's window, unknown now,
            # so that subscribers and the grid's cache do not keep the old cells.
            window = topic.window
        ny, nx = window.shape
        if nx * ny > self.options.max_cells:
            self._unpublishable(topic)
            self._warnings.warning(
                f"size {spec.map_id}",
                f"ROS 2: map {spec.map_id!r} spans {nx} x {ny} cells, more than the {self.options.max_cells} "
                f"published: not published on {spec.topic}",
                map_id=spec.map_id,
            )
            return 0
        frame_id = dict(self.options.map_frames).get(spec.map_id, self.options.frame_id)
        assert topic.seen is not None
        generation, clock = topic.seen
        parts: list[Window] | None = None
        if window == topic.window and not grid_due:
            # The changed tiles as rectangles apart, not their bounding box: robots at opposite
            # corners of a map change a tile each, whose bounding box is the whole map.
            parts = changed_windows(gmap, topic.grid_clock, window)
            if not parts:
                topic.grid_clock = clock  # nothing the grid shows changed (a tile touched outside it)
                return 0
            if len(parts) > MAX_UPDATES_PER_CHECK:
                parts = [bounding_window(parts)]
            if sum(part.cells for part in parts) > MAX_UPDATE_SHARE * nx * ny:
                parts = None
        if parts is None:
            # Cleared before the cells are read: a subscription that appears meanwhile gets another.
            with self._subscribers_lock:
                topic.new_subscriber = topic.new_volatile_subscriber = False
            # The window too: read after the clock, it may differ between two topics of one clock
            # (a scan that grew the map in between), and a grid is only good for its own window.
            key: tuple[Any, ...] = ("grid", spec.map_id, generation, clock, window)
            payload = built.get(key)
            if payload is None:
                payload = built[key] = occupancy_grid(gmap, window, frame_id, time.time_ns())
            topic.grid.put(payload, time.perf_counter() - started)
            topic.window, topic.grid_at, topic.behind = window, time.monotonic(), False
            topic.grid_clock = clock
            log.debug(
                "ROS 2: map %r published on %s: a grid of %d x %d cells, %d bytes",
                spec.map_id, spec.topic, nx, ny, len(payload), extra={"map_id": spec.map_id},
            )  # fmt: skip
            return 1
        # One update per rectangle: together they bring the last grid up to date (module doc).
        for part in parts:
            key = ("update", spec.map_id, generation, clock, window, part)
            payload = built.get(key)
            if payload is None:
                payload = built[key] = occupancy_grid_update(gmap, window, part, frame_id, time.time_ns())
            topic.updates.put(payload, time.perf_counter() - started)
            started = time.perf_counter()
        topic.behind = True
        log.debug(
            "ROS 2: map %r published on %s: %d update(s), %d of %d x %d cells",
            spec.map_id, spec.topic, len(parts), sum(part.cells for part in parts), nx, ny,
            extra={"map_id": spec.map_id},
        )  # fmt: skip
        return len(parts)

    def _unpublishable(self, topic: _Topic) -> None:
        """`topic`'s map cannot be published (its window past `max_cells`, or no occupancy to show):
        nothing more is sent until it can, and a grid already sent leaves the grid publisher's cache,
        which is dropped with the publishers, declared anew. Kept, the cache handed every ROS node
        starting later that grid as the current map, however far behind the map it fell (a map
        grown past the bound stays that big), where it is otherwise never more than
        `full_grid_interval` behind."""
        if topic.window is not None:
            self._undeclare(topic)
            self._declare(topic)
        topic.window = None

    def _declare(self, topic: _Topic) -> None:
        topic.grid.declare(self.session)
        topic.updates.declare(self.session)

    def _undeclare(self, topic: _Topic) -> None:
        topic.grid.undeclare()
        topic.updates.undeclare()
        # What the next publishers' subscribers will hold starts again from a full grid.
        topic.window, topic.behind = None, False
        topic.new_subscriber = topic.new_volatile_subscriber = False


def _undeclare_quietly(item: Any) -> None:
    """Undeclare a Zenoh entity; one whose session is already closed has nothing left to undo."""
    with contextlib.suppress(zenoh.ZError):
        item.undeclare()
