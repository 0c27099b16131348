"""End to end: a published map's changes go out as `map_msgs/msg/OccupancyGridUpdate`s on
`<topic>_updates`, and its full grid on `<topic>` only when it must (docs/ros.md, "What is
published").

The test acts as RViz's Map display or nav2's static layer with `subscribe_to_updates: true`: a
TRANSIENT_LOCAL subscription of the grid (as tests/test_ros_map_publish.py's, rmw_zenoh's advanced
subscriber with history) and a VOLATILE one of the updates, each update written over the last grid
as both do (`MapDisplay::incomingUpdate`, `StaticLayer::incomingUpdate`), after the bounds check
they make. Messages are decoded by rosbags (Jazzy's definitions, map_msgs added: tests/ros_types.py).
A subscriber may declare its liveliness token as rmw_zenoh does for every subscription, which is
what tells the service a node has joined.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
import zenoh.ext
from ros_types import GRID, GRID_UPDATE, TYPESTORE
from service_process import ServiceProcess, wait_for
from test_ros_map_publish import (
    HASH,
    KEY,
    UPDATES_KEY,
    InProcess,
    Robot,
    client_session,
    export_cells,
    grid_cells,
    in_process,  # noqa: F401 - the fixture
    room_scan,
)

from fleetmap.config import MapConfig
from fleetmap.ros import occupancy_grid
from fleetmap.ros.graph import DURABILITY_TRANSIENT_LOCAL, DURABILITY_VOLATILE, MAP_QOS, Qos, RosNode
from fleetmap.ros.map_publisher import MapTopic, RosMapOptions, RosMapPublisher
from fleetmap.ros.rmw_zenoh import decode_attachment
from fleetmap.scan import Scan

PERIOD = 0.3
#: The big map: a 40 x 40 m room at 0.05 m, 800 x 800 cells (and its walls), over 4 x 4 storage tiles
#: of 256 cells (the default), so that a scan inside one tile changes about a tenth of it.
SIDE = 40.0
#: The centre of storage tile (0, 0) (12.8 m a side): a scan there with short ranges stays in it.
TILE_CENTRE = (6.4, 6.4)


@dataclass
class Message:
    kind: str  # "grid" or "update"
    msg: Any  # rosbags' OccupancyGrid or OccupancyGridUpdate
    size: int  # bytes of the payload
    sequence: int  # the attachment's sequence number


class MapReader:
    """A ROS node reading a map and its updates over rmw_zenoh, as RViz's Map display does."""

    def __init__(
        self,
        endpoint: str,
        token: bool = False,
        key: str = KEY,
        updates_key: str = UPDATES_KEY,
        grid_qos: Qos = MAP_QOS,
    ) -> None:
        self.session = client_session(endpoint)
        self.messages: list[Message] = []
        self._lock = threading.Lock()
        transient_local = grid_qos.durability == DURABILITY_TRANSIENT_LOCAL
        self.subscribers = [
            zenoh.ext.declare_advanced_subscriber(
                self.session,
                key,
                lambda sample: self._on_sample("grid", GRID, sample),
                # TRANSIENT_LOCAL: the publishers' caches asked; VOLATILE: none.
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=grid_qos.depth)
                if transient_local
                else None,
                recovery=zenoh.ext.RecoveryConfig(heartbeat=True) if transient_local else None,
                subscriber_detection=transient_local,
            ),
            # VOLATILE: no history to ask for.
            zenoh.ext.declare_advanced_subscriber(
                self.session, updates_key, lambda sample: self._on_sample("update", GRID_UPDATE, sample)
            ),
        ]
        self.token: Any = None
        if token:  # after the subscriber, as rmw_zenoh's SubscriptionData::init
            node = RosNode(0, str(self.session.zid()), node_id=0, name="rviz")
            topic = "/" + key.split("/")[1]
            token_key = node.subscription_token(
                1, topic, "nav_msgs::msg::dds_::OccupancyGrid_", HASH, grid_qos
            )
            self.token = self.session.liveliness().declare_token(token_key)

    def _on_sample(self, kind: str, ros_type: str, sample: zenoh.Sample) -> None:
        assert sample.attachment is not None  # rmw_zenoh drops samples without one
        attachment = decode_attachment(sample.attachment.to_bytes())
        assert attachment is not None
        payload = sample.payload.to_bytes()
        msg = TYPESTORE.deserialize_cdr(payload, ros_type)
        with self._lock:
            self.messages.append(Message(kind, msg, len(payload), attachment.sequence_number))

    def received(self, kind: str | None = None) -> list[Message]:
        with self._lock:
            return [m for m in self.messages if kind is None or m.kind == kind]

    def map(self) -> np.ndarray | None:
        """The map as RViz shows it: the last grid with every update since written over it (None
        before the first grid: updates before it are dropped, as RViz and nav2 drop them)."""
        cells: np.ndarray | None = None
        frame = ""
        for message in self.received():
            msg = message.msg
            if message.kind == "grid":
                cells, frame = grid_cells(msg).copy(), msg.header.frame_id
                continue
            if cells is None:
                continue
            x, y, width, height = int(msg.x), int(msg.y), int(msg.width), int(msg.height)
            # What both readers check before applying it (nav2 also the frame).
            assert x >= 0 and y >= 0 and x + width <= cells.shape[1] and y + height <= cells.shape[0]
            assert msg.header.frame_id == frame
            cells[y : y + height, x : x + width] = np.asarray(msg.data, dtype=np.int8).reshape(height, width)
        return cells

    def close(self) -> None:
        if self.token is not None:
            self.token.undeclare()
        for subscriber in self.subscribers:
            subscriber.undeclare()
        self.session.close()


@pytest.fixture
def readers() -> Iterator[Callable[..., MapReader]]:
    opened: list[MapReader] = []

    def open_reader(endpoint: str, **kwargs: Any) -> MapReader:
        opened.append(MapReader(endpoint, **kwargs))
        return opened[-1]

    yield open_reader
    for reader in opened:
        reader.close()


def square_room_scan(x: float, y: float, side: float = SIDE) -> Scan:
    """A 360-degree scan from (x, y) inside a `side` x `side` m room, a beam every 0.25 degree."""
    return room_scan(x, y, side, side, beams=1440, range_max=2 * side)


def pillar_scan(x: float, y: float, distance: float = 1.5) -> Scan:
    """A scan from (x, y) seeing a ring of obstacles `distance` away all round: it changes the cells
    within `distance` of (x, y) only."""
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    return Scan.from_angles((x, y, 0.0), angles, np.full(360, distance), 0.0, 20.0)


def ros_maps(client: httpx.Client, topic: str = "/map") -> dict[str, Any]:
    return dict(client.get("/healthz").json()["zenoh"]["ros_maps"]["topics"][topic])


def published(client: httpx.Client) -> tuple[int, int]:
    """(grids, updates) the service has put on /map and /map_updates."""
    status = ros_maps(client)
    return int(status["grids_published"]), int(status["updates_published"])


def quiet(client: httpx.Client, timeout: float = 30.0) -> tuple[int, int]:
    """Wait until the service has published something and then nothing for 3 periods; the counts."""
    last: tuple[int, int] = (-1, -1)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        counts = published(client)
        if counts == last and counts[0] > 0:
            return counts
        last = counts
        time.sleep(3 * PERIOD)
    raise AssertionError(f"the service still publishes after {timeout} s ({last})")


def big_map(svc: ServiceProcess) -> Robot:
    """Map `lab` made a 40 x 40 m room, published, and the service quiet."""
    robot = Robot(svc)
    for x, y in [(10.0, 10.0), (30.0, 10.0), (10.0, 30.0), (30.0, 30.0), (20.0, 20.0)]:
        robot.post(square_room_scan(x, y))
    quiet(robot.client)
    return robot


def test_a_small_change_goes_as_an_update_that_brings_the_grid_up_to_date_and_a_grown_map_as_a_grid(
    service_factory: Callable[..., ServiceProcess], readers: Callable[..., MapReader]
) -> None:
    svc = service_factory("--in-memory", "--ros-publish-map", "lab", "--ros-map-period", str(PERIOD))
    robot = big_map(svc)
    reader = readers(svc.zenoh_endpoint)
    grid = wait_for(lambda: reader.received("grid"), timeout=5, what="the grid from the cache")[0]
    assert np.array_equal(grid_cells(grid.msg), export_cells(robot.client)[0])
    grids, updates = published(robot.client)

    # Scans that change a small part of the map: updates, no grid, and what the reader makes of them
    # is exactly the map the service would publish whole now (its nav2 export).
    east = (TILE_CENTRE[0] + 12.8, TILE_CENTRE[1])  # the centre of the next tile east
    for k, (x, y) in enumerate([TILE_CENTRE, (TILE_CENTRE[0] + 2.0, TILE_CENTRE[1] + 1.0), east]):
        robot.post(pillar_scan(x, y))
        wait_for(lambda k=k: len(reader.received("update")) > k, timeout=5, what=f"update {k}")
    # (Read at once: a grid replaces the cached one after it has been behind for 10 s.)
    assert published(robot.client)[0] == grids
    assert quiet(robot.client)[1] == updates + 3
    cells, _ = export_cells(robot.client)
    assert not np.array_equal(grid_cells(grid.msg), cells)  # the updates changed something
    current = reader.map()
    assert current is not None and np.array_equal(current, cells)

    # Each update is the storage tiles changed since the grid: the pillars' tile, 256 x 256 cells, a
    # tenth of the grid's bytes (the whole map sent each time before), then that tile and the next.
    sent = reader.received("update")
    assert [(int(m.msg.width), int(m.msg.height)) for m in sent] == [(256, 256), (256, 256), (512, 256)]
    assert [(int(m.msg.x), int(m.msg.y)) for m in sent] == [(sent[0].msg.x, sent[0].msg.y)] * 3
    assert all(m.size < grid.size / 9 for m in sent[:2]) and sent[2].size < grid.size / 4
    assert [m.sequence for m in sent] == [1, 2, 3]  # the updates' publisher counts from 1
    status = ros_maps(robot.client)
    assert status["updates_key"] == UPDATES_KEY and status["updates_topic"] == "/map_updates"
    assert status["last_update"]["bytes"] == sent[-1].size
    assert status["update_bytes"] == sum(m.size for m in sent)
    assert status["grid_bytes"] >= grid.size and status["last_grid"]["bytes"] == grid.size

    # The map grows (the room's east wall moves out): a full grid of the new window, which the
    # reader takes whole.
    robot.post(square_room_scan(35.0, 20.0, side=SIDE + 5.0))
    grown = wait_for(lambda: reader.received("grid")[1:], timeout=5, what="the grown map's grid")[0]
    assert int(grown.msg.info.width) > int(grid.msg.info.width)
    quiet(robot.client)
    current, (cells, origin) = reader.map(), export_cells(robot.client)
    assert current is not None and np.array_equal(current, cells)
    assert (grown.msg.info.origin.position.x, grown.msg.info.origin.position.y) == origin
    assert svc.stop() == 0
    assert "Traceback" not in svc.logs() and "ERROR" not in svc.logs(), svc.logs()


def test_a_node_that_subscribes_after_updates_gets_a_current_grid_at_once(
    service_factory: Callable[..., ServiceProcess], readers: Callable[..., MapReader]
) -> None:
    """The grid in the cache lacks the updates sent since it: a node that subscribes then would
    start from an old map. Its subscription's token makes the service send a current grid at once."""
    svc = service_factory("--in-memory", "--ros-publish-map", "lab", "--ros-map-period", str(PERIOD))
    robot = big_map(svc)
    robot.post(pillar_scan(*TILE_CENTRE))
    wait_for(lambda: published(robot.client)[1] == 1, timeout=5, what="the update")
    grids = quiet(robot.client)[0]
    cells, _ = export_cells(robot.client)

    joined = time.monotonic()
    late = readers(svc.zenoh_endpoint, token=True)
    # The cache's grid lacks the update; a current one follows it (or, should it overtake the
    # cache's reply, takes its place).
    wait_for(
        lambda: [m for m in late.received("grid") if np.array_equal(grid_cells(m.msg), cells)],
        timeout=5,
        what="a current grid",
    )
    assert time.monotonic() - joined < 2.0
    current = late.map()
    assert current is not None and np.array_equal(current, cells)
    status = ros_maps(robot.client)
    assert status["grids_published"] == grids + 1 and status["new_subscribers"] == 1

    # Another node joins: the cache is current now, so it gets that grid and nothing is sent again.
    other = readers(svc.zenoh_endpoint, token=True)
    wait_for(lambda: other.received("grid"), timeout=5, what="the cached grid")
    time.sleep(4 * PERIOD)
    assert np.array_equal(grid_cells(other.received("grid")[0].msg), cells)
    assert published(robot.client)[0] == grids + 1 and len(other.received()) == 1
    assert ros_maps(robot.client)["new_subscribers"] == 2


def test_the_cached_grid_is_replaced_when_it_has_been_behind_the_map_for_full_grid_interval(
    in_process: InProcess,  # noqa: F811 - the fixture
    readers: Callable[..., MapReader],
) -> None:
    """A node whose subscription's token the service does not see (none, or not yet) starts from the
    cache: the grid there is at most `full_grid_interval` behind the map, even when the map stopped
    changing after an update."""
    registry = in_process.registry
    options = RosMapOptions((MapTopic("a"),), period=0.1, full_grid_interval=1.0)
    publisher = RosMapPublisher(registry, in_process.router, options)
    try:
        registry.create("a", MapConfig(resolution=0.05))[0].gmap.integrate(square_room_scan(20.0, 20.0))
        publisher.start()
        topic = publisher.topics[0]
        wait_for(lambda: topic.grid.published == 1, timeout=5, what="the first grid")
        registry.get("a").gmap.integrate(pillar_scan(*TILE_CENTRE))
        wait_for(lambda: topic.updates.published == 1, timeout=5, what="the update")
        assert topic.grid.published == 1
        wait_for(lambda: topic.grid.published == 2, timeout=3, what="the grid again after 1 s")
        time.sleep(1.5)
        assert (topic.grid.published, topic.updates.published) == (2, 1)  # behind no more: nothing
        late = readers(in_process.endpoint)  # no token
        cached = wait_for(lambda: late.received("grid"), timeout=5, what="the cached grid")[0]
        assert topic.window is not None
        expected = occupancy_grid.grid_cells(registry.get("a").gmap, topic.window)
        assert np.array_equal(grid_cells(cached.msg), expected)
    finally:
        publisher.close()


def test_a_change_over_half_the_window_goes_as_a_grid(in_process: InProcess) -> None:  # noqa: F811
    """An update of most of the window would be hardly smaller than a grid: a grid goes instead."""
    registry = in_process.registry
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions((MapTopic("a"),), period=3600.0))
    try:
        gmap = registry.create("a", MapConfig(resolution=0.05))[0].gmap
        gmap.integrate(square_room_scan(20.0, 20.0))
        assert publisher.publish_changed() == 1  # declared on the way: the first grid
        topic = publisher.topics[0]
        gmap.integrate(pillar_scan(*TILE_CENTRE))
        assert publisher.publish_changed() == 1 and topic.updates.published == 1
        gmap.integrate(square_room_scan(19.0, 21.0))  # every tile of the room changes
        assert publisher.publish_changed() == 1
        assert (topic.grid.published, topic.updates.published) == (2, 1)
        assert publisher.publish_changed() == 0
    finally:
        publisher.close()


def test_robots_at_opposite_corners_send_updates_of_their_tiles_not_grids(
    in_process: InProcess,  # noqa: F811 - the fixture
    readers: Callable[..., MapReader],
) -> None:
    """Two robots each in a corner tile of a big map change two tiles, whose bounding box is the
    whole map: they go as an update per tile, not as a full grid every period (as when the update
    was that bounding box, which docs/ros.md's cost of robots "in a few tiles" did not hold for a
    fleet spread over a site), and a reader writing them over the grid holds the map; more tiles
    apart than a reader's queue holds go as one message."""
    registry = in_process.registry
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions((MapTopic("lab"),), period=3600.0))
    reader = readers(in_process.endpoint)
    try:
        gmap = registry.create("lab", MapConfig(resolution=0.05))[0].gmap
        for x, y in [(10.0, 10.0), (30.0, 10.0), (10.0, 30.0), (30.0, 30.0), (20.0, 20.0)]:
            gmap.integrate(square_room_scan(x, y))
        assert publisher.publish_changed() == 1  # declared on the way: the first grid
        wait_for(lambda: reader.received("grid"), timeout=10, what="the first grid")
        topic = publisher.topics[0]
        window = topic.window
        assert window is not None and window.shape[1] > 3 * gmap.store.tile_size
        for k in range(3):
            gmap.integrate(pillar_scan(*TILE_CENTRE, distance=1.0 + 0.2 * k))
            gmap.integrate(pillar_scan(SIDE - TILE_CENTRE[0], SIDE - TILE_CENTRE[1], distance=1.0 + 0.2 * k))
            assert publisher.publish_changed() == 2  # one update per robot's tile
        assert (topic.grid.published, topic.updates.published) == (1, 6)
        assert topic.updates.last["bytes"] < 1.1 * gmap.store.tile_size**2  # a tile, not the map
        # Six tiles apart: more updates in one burst than RViz's queue of 5 holds. One message.
        side = gmap.store.tile_size * 0.05
        for ti, tj in [(0, 0), (2, 0), (1, 1), (3, 1), (0, 2), (2, 2)]:
            gmap.integrate(pillar_scan(ti * side + 1.0, tj * side + 1.0, distance=0.5))
        assert publisher.publish_changed() == 1
        assert topic.window == window  # inside the room: the map did not grow
        expected = occupancy_grid.grid_cells(gmap, window)

        def current() -> bool:
            cells = reader.map()
            return cells is not None and np.array_equal(cells, expected)

        try:
            wait_for(current, timeout=10, what="the reader's map, the grid with the updates written over it")
        except AssertionError as exc:
            received = [(m.kind, m.sequence) for m in reader.received()]
            raise AssertionError(f"{exc}; the reader received (kind, sequence) {received}") from None
    finally:
        publisher.close()


class StaticLayer:
    """nav2's static layer with `subscribe_to_updates` (`StaticLayer::incomingMap`, `incomingUpdate`,
    `updateBounds` in nav2_costmap_2d/plugins/static_layer.cpp, Humble to Rolling): the first grid
    is taken at once, a later one is only buffered (`map_buffer_`) until the costmap's next
    `updateBounds` loads it whole; an update is written over the costmap at once."""

    def __init__(self) -> None:
        self.cells: np.ndarray | None = None
        self.buffered: Any = None

    def incoming(self, message: Message) -> None:
        msg = message.msg
        if message.kind == "grid":
            if self.cells is None:
                self.cells = grid_cells(msg).copy()
            else:
                self.buffered = msg
            return
        assert self.cells is not None
        x, y, width, height = int(msg.x), int(msg.y), int(msg.width), int(msg.height)
        assert x >= 0 and y >= 0 and x + width <= self.cells.shape[1] and y + height <= self.cells.shape[0]
        self.cells[y : y + height, x : x + width] = np.asarray(msg.data, dtype=np.int8).reshape(height, width)

    def update_bounds(self) -> None:
        if self.buffered is not None:
            self.cells, self.buffered = grid_cells(self.buffered).copy(), None


def test_an_update_overwritten_by_a_grid_nav2_loads_late_is_made_good_by_the_next_update(
    in_process: InProcess,  # noqa: F811 - the fixture
    readers: Callable[..., MapReader],
) -> None:
    """nav2's static layer loads a grid after its first only at the costmap's next update (1 Hz for
    nav2's global costmap) and writes an update at once: an update that arrives in between is
    overwritten by that grid. The next updates must bring the costmap up to date, so each check's
    updates carry everything changed since the last grid, not only since the last updates."""
    registry = in_process.registry
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions((MapTopic("a"),), period=3600.0))
    reader = readers(in_process.endpoint)
    nav2 = StaticLayer()
    taken = 0

    def publish(kind: str, count: int = 1) -> None:
        """One check, which puts `count` messages of `kind` (an update per changed tile apart)."""
        nonlocal taken
        assert publisher.publish_changed() == count
        wait_for(lambda: len(reader.received()) >= taken + count, timeout=5, what=f"the {kind}")
        for message in reader.received()[taken : taken + count]:
            assert message.kind == kind
            nav2.incoming(message)
        taken += count

    try:
        gmap = registry.create("a", MapConfig(resolution=0.05))[0].gmap
        gmap.integrate(square_room_scan(20.0, 20.0))
        publish("grid")
        topic = publisher.topics[0]
        gmap.integrate(pillar_scan(*TILE_CENTRE))
        publish("update")
        topic.new_subscriber = True  # a node joins: every subscriber gets a current grid
        publish("grid")
        gmap.integrate(pillar_scan(TILE_CENTRE[0] + 12.8, TILE_CENTRE[1]))  # the next tile east
        publish("update")  # before the costmap's next update: overwritten by the buffered grid
        nav2.update_bounds()
        gmap.integrate(pillar_scan(TILE_CENTRE[0], TILE_CENTRE[1] + 12.8))  # the next tile north
        publish("update", count=2)  # the east tile's again, and the north tile's
        nav2.update_bounds()
        assert topic.window is not None
        assert nav2.cells is not None
        assert np.array_equal(nav2.cells, occupancy_grid.grid_cells(gmap, topic.window))
    finally:
        publisher.close()


def test_a_volatile_subscriber_such_as_rviz_by_default_gets_a_grid_at_once(
    in_process: InProcess,  # noqa: F811 - the fixture
    readers: Callable[..., MapReader],
) -> None:
    """RViz's Map display subscribes to the map with `rclcpp::QoS(5)` unless told otherwise
    (`_RosTopicDisplay::qos_profile`, rviz_common/ros_topic_display.hpp): VOLATILE, so it asks no
    cache and drops updates until it has a grid (`MapDisplay::incomingUpdate`). Its token says so;
    the service sends it a grid at once, even though the cache is current."""
    registry = in_process.registry
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions((MapTopic("a"),), period=3600.0))
    try:
        registry.create("a", MapConfig(resolution=0.05))[0].gmap.integrate(square_room_scan(20.0, 20.0))
        publisher.start()  # the first check at once, the next in an hour
        topic = publisher.topics[0]
        wait_for(lambda: topic.grid.published == 1, timeout=5, what="the first grid")
        rviz = readers(in_process.endpoint, token=True, grid_qos=Qos(durability=DURABILITY_VOLATILE, depth=5))
        # "At once" against the hour of the publisher's period: 20 s, since the subscriber's token
        # must be discovered first (CI, loaded, once took over 5 s).
        grid = wait_for(lambda: rviz.received("grid"), timeout=20, what="a grid for the volatile subscriber")[
            0
        ]
        assert topic.window is not None
        assert np.array_equal(
            grid_cells(grid.msg), occupancy_grid.grid_cells(registry.get("a").gmap, topic.window)
        )
        # A TRANSIENT_LOCAL subscriber then has the cache's grid, which is current: nothing more is sent.
        nav2 = readers(in_process.endpoint, token=True)
        wait_for(lambda: nav2.received("grid"), timeout=5, what="the cached grid")
        time.sleep(1.0)
        assert topic.grid.published == 2 and topic.subscribers_seen == 2
    finally:
        publisher.close()


def test_a_volatile_subscription_that_appears_while_an_earlier_ones_flag_is_cleared_still_gets_a_grid(
    in_process: InProcess,  # noqa: F811 - the fixture
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """`_check` reads a topic's new-subscriber flags and clears them when the cache serves the
    subscriptions they stand for; Zenoh's thread sets them. A VOLATILE subscription (RViz's) whose
    token arrives between that read and the clear was wiped with the earlier TRANSIENT_LOCAL one's
    flag, and got no grid until the map next changed: the hand-over is now under a lock. The
    interleaving is forced: the token is handed to `_on_subscription` (from another thread, as
    Zenoh's) just after `_check` has read the VOLATILE flag."""
    registry = in_process.registry
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions((MapTopic("a"),), period=3600.0))
    try:
        registry.create("a", MapConfig(resolution=0.05))[0].gmap.integrate(square_room_scan(20.0, 20.0))
        assert publisher.publish_changed() == 1  # the first grid: the cache is current
        topic = publisher.topics[0]
        topic.new_subscriber = True  # an earlier TRANSIENT_LOCAL subscription, which the cache serves
        rviz = RosNode(0, "1f", node_id=0, name="rviz").subscription_token(
            1,
            "/map",
            "nav_msgs::msg::dds_::OccupancyGrid_",
            HASH,
            Qos(durability=DURABILITY_VOLATILE, depth=5),
        )
        sample = SimpleNamespace(kind=zenoh.SampleKind.PUT, key_expr=rviz)
        # Set when Zenoh's thread waits for the lock `_check` holds, or has handed the token over.
        arrived = threading.Event()
        monkeypatch.setattr(
            publisher, "_subscribers_lock", _SignallingLock(publisher._subscribers_lock, arrived)
        )
        zenoh_thread = threading.Thread(target=lambda: (publisher._on_subscription(sample), arrived.set()))

        class Interleaved(type(topic)):  # type: ignore[misc]
            def __getattribute__(self, name: str) -> Any:
                value = super().__getattribute__(name)
                if name == "new_volatile_subscriber" and not zenoh_thread.is_alive() and not arrived.is_set():
                    # The token arrives just after `_check` read the flag, before it acts on it.
                    zenoh_thread.start()
                    assert arrived.wait(timeout=30)
                return value

        topic.__class__ = Interleaved
        assert publisher.publish_changed() == 0  # the map has not changed
        zenoh_thread.join(timeout=30)
        topic.__class__ = Interleaved.__mro__[1]
        assert topic.subscribers_seen == 1 and topic.new_volatile_subscriber
        assert publisher.publish_changed(new_subscribers_only=True) == 1  # RViz's grid
        assert topic.grid.published == 2
    finally:
        publisher.close()


class _SignallingLock:
    """A lock that sets `waiting` before it waits to be acquired: how a test knows another thread
    is blocked on it."""

    def __init__(self, lock: Any, waiting: threading.Event) -> None:
        self._lock, self._waiting = lock, waiting

    def __enter__(self) -> bool:
        if threading.current_thread() is not threading.main_thread():
            self._waiting.set()
        return bool(self._lock.__enter__())

    def __exit__(self, *exc: object) -> None:
        self._lock.__exit__(*exc)
