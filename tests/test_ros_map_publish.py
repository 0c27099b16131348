"""End to end: `fleetmap serve --ros-publish-map lab` publishes map `lab` to ROS 2 over rmw_zenoh.

The real service runs as a process and gets scans over its REST API; the test acts as the ROS 2
node (nav2's static layer or AMCL) with its own Zenoh client session. Why a Zenoh session stands in
for a ROS 2 node: ROS 2 with rmw_zenoh cannot be installed on these machines (there is no ROS apt
repository; only Debian, PyPI and npm). So the session does what rmw_zenoh_cpp's subscription does
(rmw_subscription_data.cpp, `SubscriptionData::init`): an advanced subscriber on the exact data key
(type hash included) with history (late publisher detection, one sample) and heartbeat recovery, as
for a TRANSIENT_LOCAL + RELIABLE subscription; it drops samples without an attachment as rmw_zenoh
does, and decodes the payload with rosbags (Jazzy's message definitions) and the attachment with
fleetmap's decoder. The graph is read as rmw_zenoh's graph cache reads it: the liveliness tokens
under `@ros2_lv/<domain>/**`.
"""

from __future__ import annotations

import io
import logging
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
import zenoh.ext
from PIL import Image
from rosbags.typesys import Stores, get_typestore
from service_process import ServiceProcess, free_port, wait_for
from test_ingest import client_session

from fleetmap.codec import JSON_ENCODING, encode_json
from fleetmap.config import MapConfig
from fleetmap.export import Window
from fleetmap.map_entry import MapEntry
from fleetmap.registry import MapRegistry
from fleetmap.ros import occupancy_grid
from fleetmap.ros.map_publisher import MapTopic, RosMapOptions, RosMapPublisher
from fleetmap.ros.rmw_zenoh import Attachment, decode_attachment
from fleetmap.scan import Scan

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
GRID = "nav_msgs/msg/OccupancyGrid"
HASH = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"  # Jazzy's
KEY = f"0/map/nav_msgs::msg::dds_::OccupancyGrid_/{HASH}"
UPDATE_HASH = "RIHS01_c4095b0be2e4363f8978a1570e0293ee093436f1e1c61d99b48502ac317025e8"  # Jazzy's
UPDATES_KEY = f"0/map_updates/map_msgs::msg::dds_::OccupancyGridUpdate_/{UPDATE_HASH}"
PERIOD = 0.3


@dataclass
class Received:
    grid: Any  # rosbags' nav_msgs/msg/OccupancyGrid
    attachment: Attachment
    at: float
    size: int  # bytes of the payload


class RosSubscriber:
    """A TRANSIENT_LOCAL OccupancyGrid subscription as rmw_zenoh makes one, on a Zenoh client session."""

    def __init__(self, endpoint: str, key: str = KEY) -> None:
        self.session = client_session(endpoint)
        self.samples: list[Received] = []
        self.without_attachment = 0
        self._lock = threading.Lock()
        self.subscriber = zenoh.ext.declare_advanced_subscriber(
            self.session,
            key,
            self._on_sample,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            recovery=zenoh.ext.RecoveryConfig(heartbeat=True),
            subscriber_detection=True,
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.attachment is None:  # rmw_zenoh drops it ("Unable to obtain attachment")
            with self._lock:
                self.without_attachment += 1
            return
        attachment = decode_attachment(sample.attachment.to_bytes())
        payload = sample.payload.to_bytes()
        grid = TYPESTORE.deserialize_cdr(payload, GRID)
        assert attachment is not None
        with self._lock:
            self.samples.append(Received(grid, attachment, time.monotonic(), len(payload)))

    def received(self) -> list[Received]:
        with self._lock:
            return list(self.samples)

    def tokens(self) -> list[str]:
        replies = self.session.liveliness().get("@ros2_lv/0/**")
        return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok)

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()


@pytest.fixture
def subscribers() -> Iterator[Callable[[str], RosSubscriber]]:
    opened: list[RosSubscriber] = []

    def open_subscriber(endpoint: str) -> RosSubscriber:
        opened.append(RosSubscriber(endpoint))
        return opened[-1]

    yield open_subscriber
    for sub in opened:
        sub.close()


def room_scan(
    x: float, y: float, width: float = 6.0, height: float = 4.0, beams: int = 360, range_max: float = 20.0
) -> Scan:
    """A 360-degree scan from (x, y) inside a `width` x `height` m room."""
    angles = np.linspace(-np.pi, np.pi, beams, endpoint=False)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (width - x) / c, np.where(c < 0, -x / c, np.inf))
        ty = np.where(s > 0, (height - y) / s, np.where(s < 0, -y / s, np.inf))
    return Scan.from_angles((x, y, 0.0), angles, np.minimum(tx, ty), 0.0, range_max)


class Robot:
    """Posts scans to map `lab` over REST (the service's native path), one sequence number each."""

    def __init__(self, svc: ServiceProcess) -> None:
        self.client = httpx.Client(base_url=svc.base_url, timeout=30.0)
        self.seq = 0

    def post(self, scan: Scan, map_id: str = "lab") -> None:
        r = self.client.post(
            f"/maps/{map_id}/scans",
            params={"robot_id": "r1"},
            content=encode_json(scan, self.seq),
            headers={"content-type": JSON_ENCODING},
        )
        assert r.status_code == 200, r.text
        self.seq += 1


def export_cells(client: httpx.Client) -> tuple[np.ndarray, tuple[float, float]]:
    """The nav2 export of map `lab` (margin 0) as OccupancyGrid cells (row 0 = lowest y), and its origin."""
    r = client.get("/maps/lab/export", params={"format": "ros", "margin": 0})
    assert r.status_code == 200, r.text
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        pixels = np.array(Image.open(io.BytesIO(zf.read("map.pgm"))))[::-1]
        lines = zf.read("map.yaml").decode().splitlines()
        origin_line = next(line for line in lines if line.startswith("origin"))
    ox, oy, _ = (float(v) for v in origin_line.split("[")[1].rstrip("]").split(","))
    cells = np.select([pixels == 0, pixels == 254, pixels == 205], [100, 0, -1], 99).astype(np.int8)
    return cells, (ox, oy)


def grids_published(client: httpx.Client, topic: str = "/map") -> int:
    """How many grids the service has put on `topic` (GET /healthz)."""
    return int(client.get("/healthz").json()["zenoh"]["ros_maps"]["topics"][topic]["grids_published"])


def settled(client: httpx.Client, timeout: float = 30.0) -> int:
    """Wait until the service has published and then put no grid for 3 periods; the count."""
    last, deadline = -1, time.monotonic() + timeout
    while time.monotonic() < deadline:
        count = grids_published(client)
        if count == last and count > 0:
            return count
        last = count
        time.sleep(3 * PERIOD)
    raise AssertionError(f"the service still publishes after {timeout} s ({last} grids)")


def grid_cells(grid: Any) -> np.ndarray:
    return np.asarray(grid.data, dtype=np.int8).reshape(int(grid.info.height), int(grid.info.width))


def test_a_late_ros_subscriber_gets_the_map_at_once_then_each_change_and_nothing_else(
    service_factory: Callable[..., ServiceProcess], subscribers: Callable[[str], RosSubscriber]
) -> None:
    svc = service_factory("--in-memory", "--ros-publish-map", "lab", "--ros-map-period", str(PERIOD))
    robot = Robot(svc)
    for x, y in [(1.0, 1.0), (3.0, 2.0), (4.5, 1.5)] * 3:
        robot.post(room_scan(x, y))
    published = settled(robot.client)  # all of it published before the subscriber exists

    # A subscriber that joins after the map was published gets it at once, from the publisher's cache.
    joined = time.monotonic()
    sub = subscribers(svc.zenoh_endpoint)
    first = wait_for(sub.received, timeout=5, interval=0.02, what="the current map")[0]
    assert first.at - joined < 2.0
    grid = first.grid
    assert grid.header.frame_id == "map"
    assert abs(grid.header.stamp.sec + grid.header.stamp.nanosec * 1e-9 - time.time()) < 30
    assert grid.info.resolution == np.float32(0.05)
    cells, origin = export_cells(robot.client)
    assert np.array_equal(grid_cells(grid), cells)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == origin
    assert set(np.unique(cells).tolist()) == {-1, 0, 100}

    # An unchanged map is not sent again (nor put at all, as the service counts).
    time.sleep(5 * PERIOD)
    assert len(sub.received()) == 1
    assert sub.without_attachment == 0
    assert grids_published(robot.client) == published

    # A scan that changes the map: a new grid within the period (and the map's time to integrate).
    robot.post(room_scan(5.5, 3.0, width=8.0))  # the room's east wall moved out: the map grows
    changed_at = time.monotonic()
    second = wait_for(lambda: sub.received()[1:], timeout=5, interval=0.02, what="the changed map")[0]
    assert second.at - changed_at < PERIOD + 1.0
    assert second.attachment.sequence_number > first.attachment.sequence_number
    assert second.attachment.source_gid == first.attachment.source_gid
    assert len(second.attachment.source_gid) == 16
    assert second.attachment.source_timestamp >= first.attachment.source_timestamp
    assert int(second.grid.info.width) > int(grid.info.width)
    assert np.array_equal(grid_cells(second.grid), export_cells(robot.client)[0])
    time.sleep(4 * PERIOD)
    assert len(sub.received()) == 2

    # GET /healthz says what went out.
    status = robot.client.get("/healthz").json()["zenoh"]["ros_maps"]
    assert (status["node"], status["domain_id"], status["distro"]) == ("/fleetmap", 0, "jazzy")
    topic = status["topics"]["/map"]
    assert (topic["map_id"], topic["key"], topic["declared"]) == ("lab", KEY, True)
    # Some before the subscriber joined (it got only the last of those), and the changed one.
    assert topic["grids_published"] >= 2
    assert topic["last_grid"]["bytes"] == second.size

    # The publisher stops with the service: a clean exit, nothing to report.
    assert svc.stop() == 0
    assert "Traceback" not in svc.logs() and "ERROR" not in svc.logs(), svc.logs()
    assert "ROS 2: map 'lab' as nav_msgs/msg/OccupancyGrid on /map (domain 0" in svc.logs()


def test_the_graph_shows_the_node_and_its_publisher_and_a_deleted_map_is_no_longer_published(
    service_factory: Callable[..., ServiceProcess], subscribers: Callable[[str], RosSubscriber]
) -> None:
    svc = service_factory("--in-memory", "--ros-publish-map", "lab", "--ros-map-period", str(PERIOD))
    robot = Robot(svc)
    robot.post(room_scan(1.0, 1.0))
    sub = subscribers(svc.zenoh_endpoint)
    wait_for(sub.received, timeout=5, what="the map")
    zid = svc_zid(robot.client)
    node = f"@ros2_lv/0/{zid}/0/0/NN/%/%/fleetmap"
    publisher = (
        f"@ros2_lv/0/{zid}/0/1/MP/%/%/fleetmap/%map/nav_msgs::msg::dds_::OccupancyGrid_/{HASH}/:1:,1:,:,:,,"
    )
    # The updates' publisher: RELIABLE (the default, empty), VOLATILE (the default, empty), KEEP_LAST 1.
    updates = (
        f"@ros2_lv/0/{zid}/0/2/MP/%/%/fleetmap/%map_updates/map_msgs::msg::dds_::OccupancyGridUpdate_/"
        f"{UPDATE_HASH}/::,1:,:,:,,"
    )
    assert sub.tokens() == [node, publisher, updates]

    snapshot = robot.client.get("/maps/lab/snapshot")
    assert snapshot.status_code == 200
    before = grid_cells(sub.received()[-1].grid)

    # Deleted: the publisher and its token go (the node stays), nothing more is sent, and a
    # subscriber that joins now gets no stale map from a cache.
    assert robot.client.delete("/maps/lab").status_code == 204
    wait_for(lambda: sub.tokens() == [node], timeout=5, what="the publishers' tokens to go")
    assert robot.client.get("/healthz").json()["zenoh"]["ros_maps"]["topics"]["/map"]["declared"] is False
    count = len(sub.received())
    late = subscribers(svc.zenoh_endpoint)
    time.sleep(4 * PERIOD)
    assert late.received() == [] and len(sub.received()) == count

    # Created again by a scan (the same one: the new map's tile clock equals the old one's, so only
    # its being another map tells it apart): published again, to both.
    robot.post(room_scan(1.0, 1.0))
    wait_for(lambda: late.received() and len(sub.received()) > count, timeout=5, what="the new map")
    assert sub.tokens() == [node, publisher, updates]

    # Restored from the snapshot taken before the deletion (the same cells and clock again): that
    # map is published again.
    count = len(sub.received())
    r = robot.client.put(
        "/maps/lab/snapshot", content=snapshot.content, headers={"content-type": "application/zip"}
    )
    assert r.status_code == 200, r.text
    restored = wait_for(lambda: sub.received()[count:], timeout=5, what="the restored map")[-1]
    assert np.array_equal(grid_cells(restored.grid), before)
    sequence = [r.attachment.sequence_number for r in sub.received()]
    assert sequence == sorted(sequence) and len(set(sequence)) == len(sequence)


def test_a_stored_map_is_published_at_start(
    tmp_path: Path, subscribers: Callable[[str], RosSubscriber]
) -> None:
    data = tmp_path / "data"
    with ServiceProcess(tmp_path, ["--data-dir", str(data)]) as svc:
        robot = Robot(svc)
        for x, y in [(1.0, 1.0), (3.0, 2.0)]:
            robot.post(room_scan(x, y))
        cells, origin = export_cells(robot.client)
    # Started again with the map published: it is there before any scan arrives.
    args = ["--data-dir", str(data), "--ros-publish-map", "lab=/fleet/lab_map", "--ros-map-frame", "world"]
    with ServiceProcess(tmp_path, args) as svc:
        sub = RosSubscriber(svc.zenoh_endpoint, KEY.replace("/map/", "/fleet/lab_map/"))
        try:
            grid = wait_for(sub.received, timeout=10, what="the stored map")[0].grid
        finally:
            sub.close()
    assert grid.header.frame_id == "world"
    assert np.array_equal(grid_cells(grid), cells)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == origin


@dataclass
class InProcess:
    registry: MapRegistry
    router: zenoh.Session
    endpoint: str


@pytest.fixture
def in_process() -> Iterator[InProcess]:
    """A registry (in memory) and a Zenoh router session, for a `RosMapPublisher` run in the test."""
    registry = MapRegistry(MapConfig(resolution=0.05), workers=1)
    registry.start()
    port = free_port()
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(cfg)
    yield InProcess(registry, router, f"tcp/127.0.0.1:{port}")
    router.close()
    registry.close()


def test_humble_subscribers_get_their_key_and_gid_and_unpublishable_maps_are_skipped(
    in_process: InProcess, caplog: pytest.LogCaptureFixture
) -> None:
    """`--ros-distro humble` publishes on Humble's key (no type hash) with 16-byte gids; a TSDF-only
    map and a map past the cell bound are not published, and the log says so.

    Humble's rmw_zenoh hard-codes its gids to 16 bytes, though Humble's RMW_GID_STORAGE_SIZE is 24
    (ros2/rmw_zenoh#388), and reads the attachment's gid as a `std::array<uint8_t, 16>`, which
    zenoh-cpp's deserializer refuses for a sequence of any other length ("Incorrect sequence size",
    ext/serialization.hxx): with the 24-byte gids sent before, a Humble node dropped every grid and
    update, so `--ros-distro humble` reached no Humble subscriber."""
    registry = in_process.registry
    topics = (MapTopic("a", "/a"), MapTopic("tsdf", "/tsdf"), MapTopic("big", "/big"))
    options = RosMapOptions(topics, domain_id=5, period=0.1, distro="humble", max_cells=1000)
    publisher = RosMapPublisher(registry, in_process.router, options)
    humble = "5/a/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported"
    sub = RosSubscriber(in_process.endpoint, humble)
    try:
        assert publisher.topics[0].grid.key == humble
        assert publisher.topics[0].updates.key == (
            "5/a_updates/map_msgs::msg::dds_::OccupancyGridUpdate_/TypeHashNotSupported"
        )
        for map_id, config in [
            ("a", MapConfig(resolution=0.5)),
            ("tsdf", MapConfig(resolution=0.5, layers=["tsdf"])),
            ("big", MapConfig(resolution=0.05)),
        ]:
            registry.create(map_id, config)[0].gmap.integrate(room_scan(1.0, 1.0))
        with caplog.at_level(logging.WARNING, logger="fleetmap.ros"):
            publisher.start()
            received = wait_for(sub.received, timeout=5, what="the grid on Humble's key")
            time.sleep(0.5)
        assert len(received[0].attachment.source_gid) == 16  # what Humble's rmw_zenoh reads, exactly
        assert [t.grid.published for t in publisher.topics] == [1, 0, 0]
        assert "keeps only the TSDF" in caplog.text and "more than the 1000 published" in caplog.text
    finally:
        sub.close()
        publisher.close()


def test_another_map_of_the_same_id_and_tile_clock_is_published(in_process: InProcess) -> None:
    """A map deleted and made again between two checks, by the same scan, has the same tile clock:
    it is told apart by being another map (its generation), and published."""
    registry, scan = in_process.registry, room_scan(1.0, 1.0)
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions((MapTopic("a"),), period=3600.0))
    try:
        first = registry.create("a", MapConfig(resolution=0.5))[0]
        first.gmap.integrate(scan)
        publisher.start()  # its first check publishes; the next would be an hour later
        wait_for(lambda: publisher.topics[0].grid.published == 1, timeout=5, what="the first grid")
        assert publisher.publish_changed() == 0
        registry.delete("a", wait=True)
        second = registry.create("a", MapConfig(resolution=0.5))[0]
        second.gmap.integrate(scan)
        assert second.gmap.store.clock == first.gmap.store.clock
        assert publisher.publish_changed() == 1
    finally:
        publisher.close()


def test_a_map_replaced_by_one_with_nothing_to_publish_leaves_no_stale_grid(in_process: InProcess) -> None:
    """A map deleted and made again between two checks, the new one with no observed cell yet: the
    old map's grid does not stay in the publisher's cache, where a ROS node starting later would get
    a map that no longer exists (as after a deletion the publisher noticed)."""
    registry = in_process.registry
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions((MapTopic("a"),), period=3600.0))
    try:
        registry.create("a", MapConfig(resolution=0.5))[0].gmap.integrate(room_scan(1.0, 1.0))
        publisher.start()  # its first check publishes; the next would be an hour later
        wait_for(lambda: publisher.topics[0].grid.published == 1, timeout=5, what="the first grid")
        registry.delete("a", wait=True)
        registry.create("a", MapConfig(resolution=0.5))
        assert publisher.publish_changed() == 0  # nothing observed: nothing to publish
        assert publisher.topics[0].declared  # the map exists: still declared
        assert_a_late_subscriber_gets_no_grid(in_process.endpoint)
    finally:
        publisher.close()


def publish_a_room(registry: MapRegistry, publisher: RosMapPublisher) -> MapEntry:
    """Map `a` (0.5 m cells) of a room scanned once, and `publisher` started on it: its first grid
    published. Returns the map."""
    entry = registry.create("a", MapConfig(resolution=0.5))[0]
    entry.gmap.integrate(room_scan(1.0, 1.0))
    publisher.start()  # its first check publishes; the next would be an hour later
    wait_for(lambda: publisher.topics[0].grid.published == 1, timeout=5, what="the first grid")
    return entry


def assert_a_late_subscriber_gets_no_grid(endpoint: str) -> None:
    """A ROS node starting now gets no grid from the publisher's cache."""
    late = RosSubscriber(endpoint)
    try:
        time.sleep(1.5)  # the cache is queried at once, and the heartbeat comes every 0.5 s
        assert late.received() == []
    finally:
        late.close()


def test_a_map_grown_past_the_cell_bound_leaves_no_stale_grid(in_process: InProcess) -> None:
    """A published map whose window grows past the cells published (`max_cells`) is no longer
    published, and its last grid does not stay in the publisher's cache either: a ROS node starting
    later would get, as the current map, one that lacks everything seen since, for as long as the
    map stays that big (the cache is otherwise never more than `full_grid_interval` behind)."""
    registry = in_process.registry
    options = RosMapOptions((MapTopic("a"),), period=3600.0, max_cells=1000)
    publisher = RosMapPublisher(registry, in_process.router, options)
    try:
        entry = publish_a_room(registry, publisher)
        entry.gmap.integrate(Scan.from_fan((40.0, 40.0, 0.0), 0.0, 0.1, [1.0] * 10))  # 80 x 80 cells
        assert publisher.publish_changed() == 0  # past the bound: not published
        assert publisher.topics[0].declared  # the map exists: still declared
        assert_a_late_subscriber_gets_no_grid(in_process.endpoint)
    finally:
        publisher.close()


def test_a_map_whose_every_cell_was_cleared_is_published_unknown(in_process: InProcess) -> None:
    """`DELETE /maps/{id}/region` over the whole map leaves no observed cell: subscribers get that
    change, and so does the grid's cache once a full grid is due. Before, a map with no observed cell
    was taken for one not observed yet: nothing was published, and nav2 (and any node starting
    later) kept the old obstacles."""
    registry = in_process.registry
    options = RosMapOptions((MapTopic("a"),), period=3600.0, full_grid_interval=0.0)
    publisher = RosMapPublisher(registry, in_process.router, options)
    try:
        entry = publish_a_room(registry, publisher)
        first = RosSubscriber(in_process.endpoint)
        try:
            old = grid_cells(wait_for(first.received, timeout=5, what="the cached grid")[0].grid)
        finally:
            first.close()
        assert (old != -1).sum() > 30
        assert registry.clear_window(entry, Window(-1000, -1000, 1000, 1000)).cells >= (old != -1).sum()
        assert entry.gmap.known_bounds() is None
        assert publisher.publish_changed() == 1  # an update (a full grid is due at once here)
        late = RosSubscriber(in_process.endpoint)
        try:
            grid = grid_cells(wait_for(late.received, timeout=5, what="the cached grid")[-1].grid)
        finally:
            late.close()
        assert grid.shape == old.shape and (grid == -1).all()
    finally:
        publisher.close()


def test_each_map_is_published_in_its_own_frame(in_process: InProcess) -> None:
    """`map_frames` labels a map's grids (the map `--ros-scans` builds in `world`); the others keep
    `frame_id` (a native robots' map is not in that frame)."""
    registry = in_process.registry
    topics = (MapTopic("lab", "/lab/map"), MapTopic("wh", "/wh/map"))
    options = RosMapOptions(topics, frame_id="map", map_frames=(("lab", "world"), ("wh", "map")), period=0.1)
    publisher = RosMapPublisher(registry, in_process.router, options)
    subs = [RosSubscriber(in_process.endpoint, topic.grid.key) for topic in publisher.topics]
    try:
        for map_id in ("lab", "wh"):
            registry.create(map_id, MapConfig(resolution=0.5))[0].gmap.integrate(room_scan(1.0, 1.0))
        publisher.start()
        frames = [wait_for(sub.received, timeout=5, what="a grid")[0].grid.header.frame_id for sub in subs]
        assert frames == ["world", "map"]
    finally:
        for sub in subs:
            sub.close()
        publisher.close()


def test_a_map_on_several_topics_is_built_once_a_check(
    in_process: InProcess, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One map on each namespaced nav2 stack's topic (`lab=/robot1/map lab=/robot2/map`): each check
    builds its grid once and puts it on every topic (building it per topic cost 15 ms a topic for
    a 2000 x 2000 map)."""
    from fleetmap.ros import map_publisher

    builds: list[int] = []
    real = map_publisher.occupancy_grid

    def counted(*args: Any, **kwargs: Any) -> bytes:
        builds.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(map_publisher, "occupancy_grid", counted)
    registry = in_process.registry
    topics = (MapTopic("lab", "/robot1/map"), MapTopic("lab", "/robot2/map"))
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions(topics, period=3600.0))
    subs = [RosSubscriber(in_process.endpoint, topic.grid.key) for topic in publisher.topics]
    try:
        registry.create("lab", MapConfig(resolution=0.5))[0].gmap.integrate(room_scan(1.0, 1.0))
        assert publisher.publish_changed() == 2
        assert len(builds) == 1
        grids = [wait_for(sub.received, timeout=5, what="a grid")[0].grid for sub in subs]
        assert grids[0].data.tobytes() == grids[1].data.tobytes() and len(grids[0].data) > 0
    finally:
        for sub in subs:
            sub.close()
        publisher.close()


def svc_zid(client: httpx.Client) -> str:
    """The service's Zenoh session id, as its health answer reports it."""
    return str(client.get("/healthz").json()["zenoh"]["zid"])


def test_ros_robots_scans_in_and_the_nav2_map_out_through_the_robots_router(
    service_factory: Callable[..., ServiceProcess], subscribers: Callable[[str], RosSubscriber]
) -> None:
    """Both directions at once, as a ROS 2 fleet would use them: a robot's LaserScans and TF (as
    rmw_zenoh puts them on Zenoh: tests/test_ros_ingest.py's emulated robot) reach the service
    through the robots' router (standing in for rmw_zenohd), `--ros-scans` builds the map, and
    `--ros-publish-map` sends it back to a ROS node on that router as the OccupancyGrid nav2 reads."""
    from test_ros_ingest import PLAN, Fleet, RosRobot, healthz_ros, robot_stats, router_session, stamp_ns_of

    from fleetmap.sim import SimulatedRobot

    router = f"tcp/127.0.0.1:{free_port()}"
    router_zenoh = router_session(router)
    robot = RosRobot(router, "robot1")
    try:
        fleet = Fleet({"robot1": (robot, False)})
        fleet.static("robot1")
        svc = service_factory(
            "--in-memory", "--zenoh-connect", router, "--ros-scans", "lab",
            "--ros-publish-map", "lab", "--ros-map-period", str(PERIOD),
        )  # fmt: skip
        nav2 = subscribers(router)
        http = Robot(svc).client
        wait_for(lambda: healthz_ros(http)["tf_trees"].get("/robot1", {}).get("frames", 0) >= 2, timeout=20)
        for pub in (robot.scan_pub, robot.tf_pub):
            wait_for(lambda p=pub: p.matching_status.matching, timeout=20, what="the service's subscribers")
        sim = SimulatedRobot(PLAN, 1, num_beams=361, range_max=12.0, scan_rate=5.0)
        for k in range(8):
            fleet.scan("robot1", stamp_ns_of(k), sim)
        wait_for(lambda: robot_stats(http, "robot1").get("scans_integrated") == 8, timeout=30, what="8 scans")
        cells, origin = export_cells(http)
        latest = wait_for(
            lambda: [r for r in nav2.received() if np.array_equal(grid_cells(r.grid), cells)],
            timeout=10,
            what="the grid of all 8 scans on the robots' router",
        )[-1]
        assert (latest.grid.info.origin.position.x, latest.grid.info.origin.position.y) == origin
        assert set(np.unique(cells).tolist()) == {-1, 0, 100}
    finally:
        robot.close()
        router_zenoh.close()


def test_one_map_on_each_robots_namespaced_map_topic(service_factory: Callable[..., ServiceProcess]) -> None:
    """Several robots' nav2 stacks, each in its namespace, read the map on their own relative `map`
    topic (`/robot1/map`, `/robot2/map`): one fleetmap map is published on each, the same grid, and
    the graph shows one publisher per topic."""
    svc = service_factory(
        "--in-memory",
        "--ros-publish-map",
        "lab=/robot1/map",
        "lab=/robot2/map",
        "--ros-map-period",
        str(PERIOD),
    )
    robot = Robot(svc)
    subs = [
        RosSubscriber(svc.zenoh_endpoint, KEY.replace("0/map/", f"0/{ns}/map/"))
        for ns in ("robot1", "robot2")
    ]
    try:
        robot.post(room_scan(2.0, 2.0))
        grids = [
            wait_for(sub.received, timeout=10, what=f"the map on sub {n}")[-1] for n, sub in enumerate(subs)
        ]
        wait_for(
            lambda: all(grids_published(robot.client, t) >= 1 for t in ("/robot1/map", "/robot2/map")),
            timeout=10,
        )
        time.sleep(3 * PERIOD)
        grids = [sub.received()[-1].grid for sub in subs]
        cells, origin = export_cells(robot.client)
        for grid in grids:
            assert np.array_equal(grid_cells(grid), cells)
            assert (grid.info.origin.position.x, grid.info.origin.position.y) == origin
        tokens = subs[0].tokens()
        for ns in ("robot1", "robot2"):
            assert (
                sum(f"/MP/%/%/fleetmap/%{ns}%map/nav_msgs::msg::dds_::OccupancyGrid_/" in t for t in tokens)
                == 1
            )
    finally:
        for sub in subs:
            sub.close()
        robot.client.close()
    assert svc.stop() == 0


def test_the_grid_is_in_the_frame_the_ros_scans_map_is_built_in(
    service_factory: Callable[..., ServiceProcess], subscribers: Callable[[str], RosSubscriber]
) -> None:
    """`--ros-scans lab --ros-fixed-frame world --ros-publish-map lab`: the map is built in TF frame
    `world`, so its grid says `world` (nav2 places a grid by its frame). Before, the grid said `map`
    unless `--ros-map-frame world` was also given: a map built in one frame published as another."""
    svc = service_factory(
        "--in-memory", "--ros-scans", "lab", "--ros-fixed-frame", "world", "--ros-publish-map", "lab",
        "--ros-map-period", str(PERIOD),
    )  # fmt: skip
    robot = Robot(svc)
    try:
        robot.post(room_scan(2.0, 2.0))
        sub = subscribers(svc.zenoh_endpoint)
        grid = wait_for(sub.received, timeout=10, what="the map")[-1].grid
        assert grid.header.frame_id == "world"
    finally:
        robot.client.close()
    assert svc.stop() == 0


def test_a_map_grown_while_its_topics_are_checked_gets_each_topic_the_grid_of_its_own_window(
    in_process: InProcess, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One map on two topics, and a scan that grows it after the second topic read the tile clock
    but before it read the map's window: the first topic's grid (same clock, the window before the
    scan) is not the second's. Reused for it, the second topic's subscribers held a grid of the old
    window while the publisher took them to hold the new one, so its next updates were offsets in a
    window they did not have (cells misplaced, or refused as out of bounds)."""
    from fleetmap.ros import map_publisher

    registry = in_process.registry
    entry = registry.create("lab", MapConfig(resolution=0.5))[0]
    entry.gmap.integrate(room_scan(1.0, 1.0))
    real, calls = map_publisher.known_window, []

    def racing(gmap: Any, *args: Any) -> Any:
        calls.append(1)
        if len(calls) == 2:  # the second topic's window: a scan far off lands first
            gmap.integrate(room_scan(1.0, 1.0, width=30.0, height=20.0))
        return real(gmap, *args)

    monkeypatch.setattr(map_publisher, "known_window", racing)
    topics = (MapTopic("lab", "/robot1/map"), MapTopic("lab", "/robot2/map"))
    publisher = RosMapPublisher(registry, in_process.router, RosMapOptions(topics, period=3600.0))
    subs = [RosSubscriber(in_process.endpoint, topic.grid.key) for topic in publisher.topics]
    try:
        assert publisher.publish_changed() == 2
        grids = [wait_for(sub.received, timeout=5, what="a grid")[0].grid for sub in subs]
        for topic, grid in zip(publisher.topics, grids, strict=True):
            assert topic.window is not None
            assert (int(grid.info.height), int(grid.info.width)) == topic.window.shape
        window = publisher.topics[1].window
        assert window is not None
        assert np.array_equal(grid_cells(grids[1]), occupancy_grid.grid_cells(entry.gmap, window))
        assert publisher.topics[0].window != publisher.topics[1].window  # the race did happen
    finally:
        for sub in subs:
            sub.close()
        publisher.close()
