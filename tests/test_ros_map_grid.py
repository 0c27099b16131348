"""A map as a ROS 2 nav_msgs/msg/OccupancyGrid (fleetmap.ros.occupancy_grid), the rmw_zenoh graph
tokens that announce its publisher (fleetmap.ros.graph), and the `serve` options that ask for it.

The grids are decoded by rosbags (an independent CDR implementation with ROS 2 Jazzy's message
definitions), and their cells compared with the nav2 map_server files of fleetmap's own export.
"""

from __future__ import annotations

import io
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import zenoh
from PIL import Image
from ros_types import GRID, TYPESTORE
from test_operations import serve_namespace

from fleetmap import GridMap, MapConfig, Scan
from fleetmap.export import (
    Window,
    bounding_window,
    changed_windows,
    known_window,
    map_state,
    nav2_files,
    tile_blocks,
)
from fleetmap.grid_map import STATE_FREE, STATE_OCCUPIED
from fleetmap.ros import graph
from fleetmap.ros.graph import (
    MAP_QOS,
    TF_STATIC_SUBSCRIPTION_QOS,
    TF_SUBSCRIPTION_QOS,
    Qos,
    RosNode,
    entity_gid,
    mangle,
    qos_keyexpr,
)
from fleetmap.ros.map_publisher import MapTopic, parse_map_topic, type_hash
from fleetmap.ros.occupancy_grid import (
    GridInfo,
    encode_occupancy_grid,
    grid_cells,
    occupancy_grid,
    occupancy_grid_update,
)

UPDATE = "map_msgs/msg/OccupancyGridUpdate"


def decode(payload: bytes):  # noqa: ANN201 - rosbags' generated message class
    return TYPESTORE.deserialize_cdr(payload, GRID)


def room_map(config: MapConfig | None = None) -> GridMap:
    """A map with occupied, free and unknown cells: scans from a few poses inside a 6 x 4 m room,
    repeated so that free space passes the free threshold."""
    gmap = GridMap(config or MapConfig(resolution=0.05))
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    for x, y in [(1.0, 1.0), (3.0, 2.0), (4.5, 1.5)]:
        # Distances to the walls x = 0, x = 6, y = 0, y = 4 along each beam.
        c, s = np.cos(angles), np.sin(angles)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (6.0 - x) / c, np.where(c < 0, -x / c, np.inf))
            ty = np.where(s > 0, (4.0 - y) / s, np.where(s < 0, -y / s, np.inf))
        ranges = np.minimum(tx, ty)
        for _ in range(4):
            gmap.integrate(Scan.from_angles((x, y, 0.0), angles, ranges, 0.0, 20.0))
    return gmap


def pgm_pixels(pgm: bytes) -> np.ndarray:
    return np.array(Image.open(io.BytesIO(pgm)))


# -- the grid ------------------------------------------------------------------------------------------


def test_the_grid_decodes_to_the_nav2_exports_cells_dimensions_origin_and_frame() -> None:
    gmap = room_map()
    window = known_window(gmap)
    assert window is not None
    payload = occupancy_grid(gmap, window, "map", 1_700_000_123_456_789_012)
    assert payload[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    msg = decode(payload)

    assert msg.header.frame_id == "map"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_123, 456_789_012)
    assert (msg.info.map_load_time.sec, msg.info.map_load_time.nanosec) == (1_700_000_123, 456_789_012)
    ny, nx = window.shape
    assert (msg.info.width, msg.info.height) == (nx, ny)
    assert msg.info.resolution == np.float32(0.05)
    ox, oy = window.origin(0.05)
    p, q = msg.info.origin.position, msg.info.origin.orientation
    assert (p.x, p.y, p.z) == (ox, oy, 0.0)
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)

    # The same cells as map_server gets from the nav2 export of the same window (trinary: 0
    # occupied, 254 free, 205 unknown; the image's top row is the highest y).
    files = nav2_files(gmap, window)
    assert b"mode: trinary" in files["map.yaml"]
    pixels = pgm_pixels(files["map.pgm"])[::-1]  # row 0 = lowest y, as OccupancyGrid's data
    expected = np.select([pixels == 0, pixels == 254, pixels == 205], [100, 0, -1], 99).astype(np.int8)
    data = np.asarray(msg.data, dtype=np.int8)
    assert data.shape == (nx * ny,)
    assert np.array_equal(data.reshape(ny, nx), expected)
    assert set(np.unique(data).tolist()) == {-1, 0, 100}  # all three kinds are there to compare


def test_cells_are_row_major_from_the_origin_cell() -> None:
    """data[row * width + col] is the cell whose lower-left corner is origin + (col, row) * resolution:
    each grid cell is checked against the map's own state at its centre."""
    gmap = room_map()
    window = known_window(gmap)
    assert window is not None
    msg = decode(occupancy_grid(gmap, window, "map", 0))
    res, width = float(msg.info.resolution), int(msg.info.width)
    data = np.asarray(msg.data)
    for value, code in [(100, STATE_OCCUPIED), (0, STATE_FREE)]:
        index = np.flatnonzero(data == value)
        rows, cols = index // width, index % width
        x = msg.info.origin.position.x + (cols + 0.5) * 0.05
        y = msg.info.origin.position.y + (rows + 0.5) * 0.05
        assert np.all(gmap.cells(np.stack([x, y], axis=1))["state"] == code), value
    assert res == np.float32(0.05)
    # Walls: the room's wall y = 0 is in the grid's first rows, y = 4 in its last.
    occupied_rows = np.flatnonzero((data.reshape(-1, width) == 100).any(axis=1))
    assert msg.info.origin.position.y + occupied_rows.min() * 0.05 == pytest.approx(0.0, abs=0.1)
    assert msg.info.origin.position.y + (occupied_rows.max() + 1) * 0.05 == pytest.approx(4.0, abs=0.1)


def test_encoding_puts_each_cell_where_occupancy_grid_says() -> None:
    cells = np.full((3, 4), -1, dtype=np.int8)
    cells[0, 1] = 100  # row 0 = lowest y
    cells[2, 3] = 0
    msg = decode(encode_occupancy_grid(cells, GridInfo("odom", 5, 0.25, (-1.5, 2.0))))
    assert msg.header.frame_id == "odom"
    assert (msg.info.width, msg.info.height) == (4, 3)
    assert msg.info.origin.position.x == -1.5 and msg.info.origin.position.y == 2.0
    assert np.asarray(msg.data).tolist() == [-1, 100, -1, -1] + [-1] * 4 + [-1, -1, -1, 0]


def test_a_counts_only_map_shows_its_count_model_as_the_export_does() -> None:
    gmap = room_map(MapConfig(resolution=0.05, layers=["counts"]))
    window = known_window(gmap)
    assert window is not None
    pixels = pgm_pixels(nav2_files(gmap, window)["map.pgm"])[::-1]
    cells = grid_cells(gmap, window)
    assert np.array_equal(cells == 100, pixels == 0) and np.array_equal(cells == 0, pixels == 254)
    assert (cells == 100).any() and (cells == 0).any()


def test_an_empty_window_is_an_empty_grid() -> None:
    msg = decode(occupancy_grid(GridMap(MapConfig()), Window(0, 0, 0, 0), "map", 0))
    assert (msg.info.width, msg.info.height) == (0, 0) and len(msg.data) == 0


def test_an_update_carries_the_cells_of_its_part_at_their_offset_in_the_grid() -> None:
    """Written over the grid of the window at (x, y), the update's cells make the grid of the map as
    it is now: the same cells as a grid of the whole window (one classification)."""
    gmap = room_map(MapConfig(resolution=0.05, tile_size=16))
    window = known_window(gmap)
    assert window is not None and (window.i0, window.j0) != (0, 0)  # offsets differ from cell indices
    before = decode(occupancy_grid(gmap, window, "map", 0))
    clock = gmap.store.clock
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    gmap.integrate(Scan.from_angles((2.0, 2.0, 0.0), angles, np.full(90, 0.3), 0.0, 20.0))  # a pillar
    parts = changed_windows(gmap, clock, window)
    assert parts
    part = bounding_window(parts)  # the update of them all in one
    # The tiles (16 cells) the pillar's 0.3 m touch: a few, not the window.
    assert part.shape[0] * part.shape[1] <= 9 * 16 * 16 < window.shape[0] * window.shape[1] // 4
    msg = TYPESTORE.deserialize_cdr(occupancy_grid_update(gmap, window, part, "odom", 5_000_000_123), UPDATE)
    assert msg.header.frame_id == "odom" and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (5, 123)
    assert (msg.x, msg.y, msg.width, msg.height) == (
        part.i0 - window.i0, part.j0 - window.j0, part.shape[1], part.shape[0]
    )  # fmt: skip
    cells = np.asarray(before.data, dtype=np.int8).reshape(window.shape).copy()
    cells[msg.y : msg.y + msg.height, msg.x : msg.x + msg.width] = np.asarray(msg.data).reshape(part.shape)
    after = np.asarray(decode(occupancy_grid(gmap, window, "map", 0)).data).reshape(window.shape)
    assert np.array_equal(cells, after) and not np.array_equal(
        cells, np.asarray(before.data).reshape(window.shape)
    )
    # Nothing changed since: no part; a part outside the window is refused.
    assert changed_windows(gmap, gmap.store.clock, window) == []
    with pytest.raises(ValueError):
        occupancy_grid_update(gmap, window, Window(window.i0 - 1, part.j0, part.i1, part.j1), "map", 0)


class CountingLock:
    """A map's lock that counts its outermost acquisitions (each a hold integration may wait for)."""

    def __init__(self, lock: object) -> None:
        self.lock, self.holds, self.depth = lock, 0, 0

    def __enter__(self) -> None:
        self.lock.__enter__()  # type: ignore[attr-defined]
        self.depth += 1
        self.holds += self.depth == 1

    def __exit__(self, *exc: object) -> None:
        self.depth -= 1
        self.lock.__exit__(*exc)  # type: ignore[attr-defined]


def test_the_grid_is_read_one_storage_tile_per_hold_of_the_maps_lock() -> None:
    """Publishing must not keep integration waiting: the window's bounds and its cells are read with
    the map's lock held for one storage tile at a time (16-cell tiles here: the room spans many)."""
    gmap = room_map(MapConfig(resolution=0.05, tile_size=16))
    window = known_window(gmap)
    assert window is not None
    tiles = len(gmap.store.slots)
    blocks = list(tile_blocks(window, 16))
    assert all(b.i0 // 16 == (b.i1 - 1) // 16 and b.j0 // 16 == (b.j1 - 1) // 16 for b in blocks)
    assert sum(b.shape[0] * b.shape[1] for b in blocks) == window.shape[0] * window.shape[1]
    expected = map_state(gmap, window)

    lock = gmap.lock = CountingLock(gmap.lock)  # type: ignore[assignment]
    assert np.array_equal(map_state(gmap, window), expected)
    # A hold a tile, and two short ones: the version clock before, the tiles changed since after.
    assert lock.holds == len(blocks) + 2 > 52
    # Bounds: one hold to find the tiles changed since the last call, one per such tile, one to
    # combine them; then, with nothing changed, one hold that answers at once.
    gmap._bounds_version[:] = -1
    gmap._bounds_answer = ((-1, -1), None)
    lock.holds = 0
    assert known_window(gmap) == window
    assert lock.holds == 2 + tiles
    lock.holds = 0
    assert known_window(gmap) == window
    assert lock.holds == 1


# -- graph tokens --------------------------------------------------------------------------------------


def test_qos_is_written_as_rmw_zenoh_writes_it_defaults_left_empty() -> None:
    # nav2's map QoS: RELIABLE (the default), TRANSIENT_LOCAL (1), KEEP_LAST (the default), depth 1.
    assert qos_keyexpr(MAP_QOS) == ":1:,1:,:,:,,"
    assert qos_keyexpr(Qos()) == "::,:,:,:,,"
    assert qos_keyexpr(Qos(reliability=2, durability=2, history=1, depth=10)) == "2::,10:,:,:,,"
    # tf2_ros' TransformListener's (tf2_ros/qos.hpp): DynamicListenerQoS and StaticListenerQoS are
    # both keep last 100, the static one transient local (depth 1 is StaticBroadcasterQoS's, the
    # publisher's side).
    assert qos_keyexpr(TF_SUBSCRIPTION_QOS) == "::,100:,:,:,,"
    assert qos_keyexpr(TF_STATIC_SUBSCRIPTION_QOS) == ":1:,100:,:,:,,"


def test_node_and_publisher_tokens() -> None:
    node = RosNode(7, "48de7eee5f15711b55ea5f4e4ac55fb1", node_id=0)
    assert node.node_token() == "@ros2_lv/7/48de7eee5f15711b55ea5f4e4ac55fb1/0/0/NN/%/%/fleetmap"
    token = node.publisher_token(
        1, "/wh/map", "nav_msgs::msg::dds_::OccupancyGrid_", type_hash("jazzy"), MAP_QOS
    )
    assert token == (
        "@ros2_lv/7/48de7eee5f15711b55ea5f4e4ac55fb1/0/1/MP/%/%/fleetmap/%wh%map/"
        "nav_msgs::msg::dds_::OccupancyGrid_/"
        "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7/:1:,1:,:,:,,"
    )
    assert mangle("/") == "%"
    # A subscription's token, as rmw_zenoh declares one for RViz's Map display (KEEP_LAST 5,
    # VOLATILE): what tells the publisher a node has joined.
    subscription = node.subscription_token(
        3, "/wh/map", "nav_msgs::msg::dds_::OccupancyGrid_", type_hash("jazzy"), Qos(depth=5)
    )
    assert subscription == token.replace("/0/1/MP/", "/0/3/MS/").replace(":1:,1:,:,:,,", "::,5:,:,:,,")
    assert graph.subscription_of_token(subscription) == (7, "/wh/map", "nav_msgs::msg::dds_::OccupancyGrid_")
    assert graph.subscription_of_token(token) is None and graph.publisher_of_token(subscription) is None
    # Its durability (VOLATILE: no cache asked, so it needs a grid sent for it) and the publisher's.
    assert graph.durability_of_token(subscription) == graph.DURABILITY_VOLATILE
    assert graph.durability_of_token(token) == graph.DURABILITY_TRANSIENT_LOCAL
    watched = graph.endpoints_key(7, graph.SUBSCRIPTION, "nav_msgs::msg::dds_::OccupancyGrid_")
    assert zenoh.KeyExpr(watched).intersects(zenoh.KeyExpr(subscription))
    assert not zenoh.KeyExpr(watched).intersects(zenoh.KeyExpr(token))
    assert qos_keyexpr(graph.MAP_UPDATES_QOS) == "::,1:,:,:,,"  # RELIABLE, VOLATILE: the defaults, left empty
    assert len(entity_gid(token)) == 16 and entity_gid(token) == entity_gid(token) != entity_gid(token + "x")


def test_type_hash_per_distribution_matches_rosbags() -> None:
    assert type_hash("jazzy") == TYPESTORE.hash_rihs01(GRID)
    assert type_hash("humble") == "TypeHashNotSupported"
    with pytest.raises(ValueError):
        type_hash("foxy")


# -- options -------------------------------------------------------------------------------------------


def test_parse_map_topic() -> None:
    assert parse_map_topic("lab") == MapTopic("lab", "/map")
    assert parse_map_topic("lab=/lab/map") == MapTopic("lab", "/lab/map")
    assert parse_map_topic("lab=floor_2") == MapTopic("lab", "/floor_2")
    for bad in ["", "=x", "bad id", "lab=/", "lab=/a//b", "lab=/2map", "lab=/a b", "lab=/map/"]:
        with pytest.raises(ValueError):
            parse_map_topic(bad)


def test_ros_options_repeat_come_from_the_environment_and_the_command_line_wins(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    defaults = serve_namespace([], {}, monkeypatch)
    assert defaults.ros_publish_map == [] and defaults.ros_domain is None  # $ROS_DOMAIN_ID, else 0
    assert (defaults.ros_map_frame, defaults.ros_map_period, defaults.ros_distro) == (None, 1.0, "jazzy")
    from fleetmap.serve_ros import ros_map_frame

    # The grids' frame: --ros-map-frame, else for the map --ros-scans builds the frame it builds it
    # in, else map. Another map (native robots') is not in --ros-fixed-frame: before, it was
    # labelled with it all the same, and nav2 placed it in a frame it is not in.
    assert ros_map_frame(defaults, "lab") == "map"
    scans_in_world = [
        "--ros-scans",
        "lab",
        "--ros-fixed-frame",
        "/world",
        "--ros-publish-map",
        "lab",
        "wh=/wh/map",
    ]
    args = serve_namespace(scans_in_world, {}, monkeypatch)
    assert (ros_map_frame(args, "lab"), ros_map_frame(args, "wh")) == ("world", "map")
    args = serve_namespace([*scans_in_world, "--ros-map-frame", "odom"], {}, monkeypatch)
    assert (ros_map_frame(args, "lab"), ros_map_frame(args, "wh")) == ("odom", "odom")
    argv = ["--ros-publish-map", "lab", "--ros-publish-map", "wh=/wh/map", "b=/b"]
    expected = [MapTopic("lab"), MapTopic("wh", "/wh/map"), MapTopic("b", "/b")]
    assert serve_namespace(argv, {}, monkeypatch).ros_publish_map == expected
    # The domain of both directions: --ros-domain, else ROS's own variable, else 0; it may be given
    # with --ros-publish-map alone.
    from fleetmap.serve_ros import ros_domain, ros_options

    options = serve_namespace([*argv, "--ros-domain", "4"], {}, monkeypatch)
    assert ros_options(options) is None and ros_domain(options, {"ROS_DOMAIN_ID": "7"}) == 4
    options = serve_namespace(argv, {}, monkeypatch)
    assert ros_domain(options, {"ROS_DOMAIN_ID": "7"}) == 7 and ros_domain(options, {}) == 0
    env = {"FLEETMAP_ROS_PUBLISH_MAP": "lab wh=/wh/map b=/b", "FLEETMAP_ROS_DOMAIN": "3"}
    options = serve_namespace([], env, monkeypatch)
    assert options.ros_publish_map == expected and options.ros_domain == 3
    # The command line's maps replace the variable's, rather than adding to them.
    options = serve_namespace(["--ros-publish-map", "x", "--ros-publish-map", "y=/y"], env, monkeypatch)
    assert options.ros_publish_map == [MapTopic("x"), MapTopic("y", "/y")]


def test_bad_ros_options_are_refused(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    for argv in (["--ros-publish-map", "lab=/a b"], ["--ros-domain", "-1"], ["--ros-map-frame", ""]):
        with pytest.raises(SystemExit):
            serve_namespace(argv, {}, monkeypatch)
        assert "error" in capsys.readouterr().err, argv


NEED_MAPS = "--ros-map-frame, --ros-map-period and --ros-distro need --ros-publish-map MAP_ID"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--ros-map-period", "2"], NEED_MAPS),
        (["--ros-distro", "humble"], NEED_MAPS),
        (
            ["--ros-publish-map", "a", "b=/map"],
            "--ros-publish-map: two maps on one ROS topic (a and b on /map)",
        ),
        # One map named twice: the message said "two maps on one ROS topic".
        (
            ["--ros-publish-map", "a", "a=/map"],
            "--ros-publish-map: map a is given twice on /map; give it once",
        ),
        (
            ["--ros-publish-map", "a=/x/map", "b=/x/map_updates"],
            "--ros-publish-map: /x/map_updates is map b's topic and the updates topic of map a's /x/map",
        ),
        (
            ["--ros-publish-map", "a=/map_updates", "a=/map"],
            "--ros-publish-map: /map_updates is map a's topic and the updates topic of map a's /map",
        ),
        (["--ros-publish-map", "a"], "$ROS_DOMAIN_ID='one': expected a whole number"),
    ],
)
def test_ros_map_options_that_cannot_work_stop_the_start_with_one_line(argv: list[str], message: str) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETMAP_")} | {"ROS_DOMAIN_ID": "one"}
    done = subprocess.run(
        [sys.executable, "-m", "fleetmap.server", "--in-memory", "--http", "127.0.0.1:0", *argv],
        capture_output=True, text=True, env=env, timeout=60,
    )  # fmt: skip
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and message in lines[0], done.stderr
