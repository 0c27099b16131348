"""ROS 2 robots on rmw_zenoh publishing straight to fleetmap (`fleetmap serve --ros-scans`), end to end.

Why a Zenoh session stands in for a ROS 2 node: ROS 2 with rmw_zenoh cannot be installed on these
machines (no ROS apt repository; only Debian, PyPI and npm are reachable). What fleetmap sees of a
ROS 2 node is only what rmw_zenoh puts on Zenoh, so each emulated robot here is a real Zenoh client
session publishing exactly that: on rmw_zenoh's key expressions (`<domain>/<topic>/<dds type>/<type
hash>`, ros2/rmw_zenoh liveliness_utils.cpp), CDR payloads made by rosbags (an independent ROS 2
serializer), rmw_zenoh's attachment (sequence number, timestamp, gid), and `/tf_static` through an
AdvancedPublisher with a cache, as rmw_zenoh does for TRANSIENT_LOCAL (rmw_publisher_data.cpp).
The robots join a Zenoh router started first (standing in for rmw_zenohd) and publish their static
TF BEFORE the service starts: the service joins that router (`--zenoh-connect`) and must still get it,
from the AdvancedPublishers' caches and from an older rmw_zenoh's publication cache (a queryable).

The real service runs as a process; the map is read back over REST and compared cell by cell.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore
from scipy.ndimage import binary_dilation
from scipy.spatial.transform import Rotation
from service_process import ServiceProcess, free_port, wait_for
from test_e2e import ALL_LAYERS, assert_region_equal, map_stats

from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.ros.rmw_zenoh import TYPE_HASHES, Attachment, encode_attachment, topic_key
from fleetmap.ros.tf_message import decode_tf_message
from fleetmap.ros.transforms import TfBuffer, sensor_pose_2d
from fleetmap.scan import Scan
from fleetmap.sim import SimulatedRobot, generate_floorplan

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
LASER, TF = "sensor_msgs/msg/LaserScan", "tf2_msgs/msg/TFMessage"
PLAN = generate_floorplan(5, width_m=14.0, height_m=10.0)
T0_NS = 1_700_000_000_000_000_000
#: map -> odom (published on /<ns>/tf, as a localizer does) and base_link -> laser (static).
MAP_ODOM = ((1.5, -0.5, 0.0), Rotation.from_euler("z", 0.3))
LASER_UP = ((0.25, 0.0, 0.2), Rotation.identity())
LASER_UPSIDE_DOWN = ((0.1, 0.05, 0.3), Rotation.from_euler("x", math.pi))


def client_session(endpoint: str) -> zenoh.Session:
    """A robot's session. Timestamping on, as rmw_zenoh's default configuration has it (an
    AdvancedPublisher with a cache needs it)."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("timestamping/enabled", "true")
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def router_session(endpoint: str) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def stamp_msg(ns: int) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def tf_payload(stamp_ns: int, edges: list[tuple[str, str, tuple[float, float, float], Rotation]]) -> bytes:
    transforms = []
    for parent, child, xyz, rot in edges:
        q = rot.as_quat()
        transforms.append(
            T["geometry_msgs/msg/TransformStamped"](
                header=T["std_msgs/msg/Header"](stamp=stamp_msg(stamp_ns), frame_id=parent),
                child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
        )
    return bytes(TS.serialize_cdr(T[TF](transforms=transforms), TF))


@dataclass
class LaserData:
    stamp_ns: int
    angle_min: float
    angle_increment: float
    ranges: np.ndarray  # float32
    range_min: float = 0.05
    range_max: float = 12.0

    def payload(self, frame: str) -> bytes:
        n = len(self.ranges)
        msg = T[LASER](
            header=T["std_msgs/msg/Header"](stamp=stamp_msg(self.stamp_ns), frame_id=frame),
            angle_min=self.angle_min, angle_max=self.angle_min + (n - 1) * self.angle_increment,
            angle_increment=self.angle_increment, time_increment=0.0, scan_time=0.1,
            range_min=self.range_min, range_max=self.range_max, ranges=self.ranges,
            intensities=np.zeros(0, dtype=np.float32),
        )  # fmt: skip
        return bytes(TS.serialize_cdr(msg, LASER))

    def engine_scan(self, pose: tuple[float, float, float], sign: float = 1.0) -> Scan:
        """The scan the engine integrates for this LaserScan posed at `pose`: its fields as the message
        carries them (float32), the beams' order reversed (`sign` -1) for a laser mounted upside down."""
        return Scan.from_fan(
            pose,
            sign * float(np.float32(self.angle_min)),
            sign * float(np.float32(self.angle_increment)),
            self.ranges,
            float(np.float32(self.range_min)),
            float(np.float32(self.range_max)),
        )


class RosRobot:
    """What an rmw_zenoh ROS 2 robot in namespace `ns` puts on Zenoh: LaserScan on /<ns>/scan, TF
    on /<ns>/tf, static TF on /<ns>/tf_static (AdvancedPublisher with a cache of 1, as rmw_zenoh
    does for TRANSIENT_LOCAL depth 1). Each publisher has its own gid and sequence numbers from 1."""

    def __init__(self, endpoint: str, ns: str, domain: int = 0) -> None:
        self.ns = ns
        self.session = client_session(endpoint)
        key = lambda name, kind: topic_key(domain, f"/{ns}/{name}", kind, TYPE_HASHES[kind])  # noqa: E731
        self.scan_pub = self.session.declare_publisher(key("scan", LASER))
        self.tf_pub = self.session.declare_publisher(key("tf", TF))
        self.static_pub = zenoh.ext.declare_advanced_publisher(
            self.session, key("tf_static", TF), cache=zenoh.ext.CacheConfig(1), publisher_detection=True
        )
        self._seq: dict[str, int] = {}
        self._gid = {name: os.urandom(16) for name in ("scan", "tf", "tf_static")}

    def _attachment(self, name: str) -> bytes:
        self._seq[name] = self._seq.get(name, 0) + 1
        return encode_attachment(Attachment(self._seq[name], time.time_ns(), self._gid[name]))

    def put_scan(self, payload: bytes) -> None:
        self.scan_pub.put(payload, attachment=self._attachment("scan"))

    def put_tf(self, payload: bytes) -> None:
        self.tf_pub.put(payload, attachment=self._attachment("tf"))

    def put_static(self, payload: bytes) -> None:
        self.static_pub.put(payload, attachment=self._attachment("tf_static"))

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def router() -> Iterator[str]:
    """A Zenoh router the robots join first, standing in for rmw_zenohd."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = router_session(endpoint)
    yield endpoint
    session.close()


def healthz_ros(http: httpx.Client) -> dict[str, Any]:
    ros: dict[str, Any] = http.get("/healthz").json()["zenoh"]["ros"]
    return ros


def sim_laser(robot: SimulatedRobot) -> tuple[tuple[float, float, float], float, float, np.ndarray]:
    """One simulated scan: the sensor pose, and the fan as a LaserScan gives it (float32)."""
    scan = robot.tick()
    angles = scan.angles
    inc = float(np.float32((angles[-1] - angles[0]) / (len(angles) - 1)))
    ranges = np.nan_to_num(scan.ranges, nan=np.inf, posinf=np.inf).astype(np.float32)
    return (scan.pose.x, scan.pose.y, scan.pose.theta), float(np.float32(angles[0])), inc, ranges


def matrix(xyz: tuple[float, float, float], rot: Rotation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rot.as_matrix()
    m[:3, 3] = xyz
    return m


def base_pose_for(sensor: tuple[float, float, float], laser: tuple[Any, Rotation]) -> np.ndarray:
    """odom -> base_link (a level base) such that the laser, mounted by `laser`, has its x axis at
    the simulated sensor's position and heading; upside down, its z axis points down."""
    x, y, theta = sensor
    laser_in_map = matrix((x, y, 0.2), Rotation.from_euler("z", theta) * laser[1])
    base: np.ndarray = np.linalg.inv(matrix(*MAP_ODOM)) @ laser_in_map @ np.linalg.inv(matrix(*laser))
    return base


def rot_of(m: np.ndarray) -> Rotation:
    return Rotation.from_matrix(m[:3, :3])


class Fleet:
    """Two robots publishing, and the expected map: the engine fed with each scan as the service
    must integrate it, posed through a TfBuffer fed with the same payloads (so the map is comparable
    bit for bit), the poses checked independently against scipy's 4x4 matrices."""

    def __init__(self, robots: dict[str, tuple[RosRobot, bool]]) -> None:
        self.robots = robots
        self.expected = GridMap(MapConfig())
        self.buffers = {ns: TfBuffer() for ns in robots}
        self.native = GridMap(MapConfig())  # the simulated scans themselves, for the mirror check

    def static(self, ns: str) -> None:
        robot, upside_down = self.robots[ns]
        payload = tf_payload(
            T0_NS, [("base_link", "laser", *(LASER_UPSIDE_DOWN if upside_down else LASER_UP))]
        )
        robot.put_static(payload)
        for t in decode_tf_message(payload):
            self.buffers[ns].add(t, static=True)

    def tf(self, ns: str, stamp_ns: int, base: np.ndarray) -> None:
        robot, _ = self.robots[ns]
        payload = tf_payload(
            stamp_ns,
            [("map", "odom", *MAP_ODOM), ("odom", "base_link", tuple(base[:3, 3]), rot_of(base))],  # type: ignore[list-item]
        )
        robot.put_tf(payload)
        for t in decode_tf_message(payload):
            self.buffers[ns].add(t, static=False)

    def scan(self, ns: str, stamp_ns: int, sim: SimulatedRobot, tf_delay: float | None = 0.0) -> None:
        """One scan of robot `ns`: TF samples 20 ms either side of its stamp (the same pose), the
        LaserScan; with `tf_delay` > 0 the scan goes first and its TF that much later."""
        robot, upside_down = self.robots[ns]
        sensor, a_min, inc, ranges = sim_laser(sim)
        laser = LASER_UPSIDE_DOWN if upside_down else LASER_UP
        base = base_pose_for(sensor, laser)
        if upside_down:  # the same physical beams, seen by a laser whose angles turn the other way
            data = LaserData(stamp_ns, -(a_min + (len(ranges) - 1) * inc), inc, ranges[::-1].copy())
        else:
            data = LaserData(stamp_ns, a_min, inc, ranges)
        payload = data.payload("laser")
        if tf_delay:
            robot.put_scan(payload)
            time.sleep(tf_delay)
        for dt in (-20_000_000, 20_000_000):
            self.tf(ns, stamp_ns + dt, base)
        if not tf_delay:
            robot.put_scan(payload)
        stamp = stamp_ns // 10**9 + (stamp_ns % 10**9) * 1e-9
        transform = self.buffers[ns].lookup("map", "laser", stamp)
        want = matrix(*MAP_ODOM) @ base @ matrix(*laser)
        np.testing.assert_allclose(
            [*transform.translation[:2]], want[:2, 3], atol=1e-9, err_msg="TfBuffer vs 4x4 matrices"
        )
        pose = sensor_pose_2d(transform)
        assert pose.mirrored == upside_down
        assert math.remainder(pose.theta - sensor[2], math.tau) == pytest.approx(0.0, abs=1e-9)
        sign = -1.0 if pose.mirrored else 1.0
        self.expected.integrate(data.engine_scan((pose.x, pose.y, pose.theta), sign))
        self.native.integrate(
            Scan.from_fan(sensor, a_min, inc, ranges, float(np.float32(0.05)), float(np.float32(12.0)))
        )


def stamp_ns_of(k: int) -> int:
    return T0_NS + k * 100_000_000


def robot_stats(http: httpx.Client, robot_id: str) -> dict[str, Any]:
    """The robot's stats in GET /maps/lab ({} while the map or robot does not exist yet)."""
    response = http.get("/maps/lab")
    if response.status_code == 404:
        return {}
    stats: dict[str, Any] = response.json()["stats"]["robots"].get(robot_id, {})
    return stats


def test_ros_robots_build_the_same_map_as_the_engine(
    router: str, service_factory: Callable[..., ServiceProcess]
) -> None:
    robot1 = RosRobot(router, "robot1")
    robot2 = RosRobot(router, "robot2")
    legacy = client_session(router)
    fleet = Fleet({"robot1": (robot1, False), "robot2": (robot2, True)})
    try:
        # Static TF first, before the service exists: only the publishers' caches hold it then.
        fleet.static("robot1")
        fleet.static("robot2")
        # rmw_zenoh before its AdvancedPublisher: a publication cache, a queryable on the topic's key.
        legacy_key = topic_key(0, "/legacy/tf_static", TF, TYPE_HASHES[TF])
        legacy_tf = tf_payload(T0_NS, [("base_link", "laser", *LASER_UP)])
        _cache = legacy.declare_queryable(  # kept: answers for the whole test
            legacy_key, lambda query: query.reply(legacy_key, legacy_tf)
        )
        time.sleep(0.3)
        service = service_factory("--ros-scans", "lab", "--zenoh-connect", router)
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            wait_for(
                lambda: all(
                    healthz_ros(http)["tf_trees"].get(f"/{ns}", {}).get("frames", 0) >= 2
                    for ns in ("robot1", "robot2", "legacy")
                ),
                timeout=20, what="the static TF published before the service started",
            )  # fmt: skip
            for pub in (robot1.scan_pub, robot2.scan_pub, robot1.tf_pub, robot2.tf_pub):
                wait_for(
                    lambda p=pub: p.matching_status.matching, timeout=20, what="the service's subscribers"
                )
            # Robot 1 (laser level), then robot 2 (laser upside down): one after the other, so the
            # engine's order is the service's (TSDF and clamped log-odds depend on it).
            sim1 = SimulatedRobot(PLAN, 1, num_beams=361, range_max=12.0, scan_rate=5.0)
            for k in range(6):
                fleet.scan("robot1", stamp_ns_of(k), sim1)
            fleet.scan("robot1", stamp_ns_of(6), sim1, tf_delay=0.1)  # its TF 100 ms after it
            wait_for(
                lambda: robot_stats(http, "robot1").get("scans_integrated") == 7,
                timeout=30,
                what="robot1's 7 scans",
            )
            assert healthz_ros(http)["scans_waited_for_tf"] >= 1
            sim2 = SimulatedRobot(PLAN, 2, num_beams=361, range_max=12.0, scan_rate=5.0)
            for k in range(6):
                fleet.scan("robot2", stamp_ns_of(k), sim2)
            wait_for(
                lambda: robot_stats(http, "robot2").get("scans_integrated") == 6,
                timeout=30,
                what="robot2's 6 scans",
            )

            assert_region_equal(http, "lab", fleet.expected, ALL_LAYERS)
            # Independently of the mirroring code: the upside-down robot's walls are where the
            # simulated beams hit them (a wrong mirror puts them elsewhere). Within one cell: the
            # simulated walls lie on cell boundaries, where float32 angles tip an end point across.
            window = fleet.native.known_bounds()
            assert window is not None
            got = binary_dilation(fleet.expected.region("hits", *window) > 0, np.ones((3, 3), bool))
            native = fleet.native.region("hits", *window) > 0
            assert native.sum() > 400
            assert (got & native).sum() >= 0.99 * native.sum()

            # Garbage on robot1's scan topic: counted on robot1, the service carries on.
            robot1.put_scan(b"\x00\x01\x00\x00" + b"\xff" * 40)
            # A scan whose TF never comes: dropped after the wait, counted with its reason.
            robot1.put_scan(
                LaserData(stamp_ns_of(1000), -1.0, 0.01, np.ones(200, np.float32)).payload("laser")
            )
            stats = wait_for(
                lambda: (s := robot_stats(http, "robot1")).get("scans_rejected") == 2 and s,
                timeout=10, what="robot1's two refused scans",
            )  # fmt: skip
            assert "no TF" in stats["last_error"] and "within 0.5 s" in stats["last_error"], stats
            assert stats["scans_integrated"] == 7
            ros = healthz_ros(http)
            assert ros["refused"] == {"undecodable": 1, "no_tf": 1}, ros
            assert ros["scans_submitted"] == 13 and ros["scans_waiting"] == 0
            metrics = http.get("/metrics").text
            for line in (
                'fleetmap_ros_scans_refused_total{reason="no_tf"} 1.0',
                'fleetmap_ros_scans_refused_total{reason="undecodable"} 1.0',
                "fleetmap_ros_scans_submitted_total 13.0",
                'fleetmap_scans_rejected_total{map="lab",robot="robot1"} 2.0',
            ):
                assert line in metrics.splitlines(), line
            assert http.get("/healthz").status_code == 200
            robots = http.get("/maps/lab").json()["stats"]["robots"]
            assert set(robots) == {"robot1", "robot2"}
            assert robots["robot2"]["scans_rejected"] == 0
            # Seqs from rmw_zenoh's sequence numbers (from 1) less 1, sessions from the gids: one per
            # publisher, nothing lost (robot1's two refused scans are seqs 7 and 8, settled as
            # refused), no id conflict.
            assert (robots["robot1"]["last_seq"], robots["robot2"]["last_seq"]) == (8, 5)
            for stats in robots.values():
                assert (stats["lost"], stats["duplicates"], stats["id_conflict"]) == (0, 0, False), stats
            assert map_stats(http, "lab")["scans_integrated"] == 13
        assert service.stop() == 0
        logs = service.logs()
        assert "Traceback" not in logs and "unexpected error" not in logs, logs
        assert "refused a ROS scan of lab/robot1: undecodable LaserScan on /robot1/scan" in logs
    finally:
        legacy.close()
        robot1.close()
        robot2.close()


def test_tilted_laser_and_bad_topics_are_refused_with_reasons(
    service_factory: Callable[..., ServiceProcess], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The fleetmap router itself (robots connect to it), the domain from FLEETMAP_ROS_DOMAIN, a
    root namespace robot (`/scan` -> `robot`, TF on `/tf`), a tilted laser, an invalid robot id."""
    monkeypatch.setenv("FLEETMAP_ROS_DOMAIN", "7")
    service = service_factory("--ros-scans", "lab")
    session = client_session(service.zenoh_endpoint)
    try:
        key = lambda topic, kind: topic_key(7, topic, kind, "TypeHashNotSupported")  # noqa: E731 - Humble's
        scan_pub = session.declare_publisher(key("/scan", LASER))
        tf_pub = session.declare_publisher(key("/tf", TF))
        wait_for(lambda: scan_pub.matching_status.matching, timeout=20, what="the service's subscriber")
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            assert healthz_ros(http)["domain_id"] == 7
            level = Rotation.identity()
            tilt = Rotation.from_euler("y", 20, degrees=True)
            for k, stamp in enumerate((stamp_ns_of(0), stamp_ns_of(1))):
                for dt in (-(10**7), 10**7):
                    edges = [
                        ("map", "base", (float(k), 0.0, 0.0), level),
                        ("base", "laser", (0.0, 0.0, 0.0), level),
                        ("base", "tilted", (0.0, 0.0, 0.0), tilt),
                    ]
                    tf_pub.put(tf_payload(stamp + dt, edges))  # type: ignore[arg-type]
            ranges = np.full(100, 2.0, np.float32)
            scan_pub.put(LaserData(stamp_ns_of(0), -1.0, 0.02, ranges).payload("laser"))
            wait_for(
                lambda: map_stats(http, "lab").get("scans_integrated") == 1, timeout=20, what="the level scan"
            )
            scan_pub.put(LaserData(stamp_ns_of(1), -1.0, 0.02, ranges).payload("tilted"))
            stats = wait_for(
                lambda: (s := robot_stats(http, "robot")).get("scans_rejected") == 1 and s,
                timeout=10, what="the tilted scan refused",
            )  # fmt: skip
            assert "tilted 20.0 degrees" in stats["last_error"], stats
            bad = session.declare_publisher(topic_key(7, "/" + "x" * 70 + "/scan", LASER, "h"))
            bad.put(LaserData(stamp_ns_of(1), -1.0, 0.02, ranges).payload("laser"))
            wait_for(
                lambda: healthz_ros(http)["refused"].get("invalid_topic") == 1, timeout=10, what="bad id"
            )
            assert set(http.get("/maps/lab").json()["stats"]["robots"]) == {"robot"}
        assert service.stop() == 0
        assert "Traceback" not in service.logs()
    finally:
        session.close()


@pytest.mark.parametrize(
    ("args", "env", "message"),
    [
        (["--ros-domain", "3"], {}, "--ros-domain needs --ros-scans MAP_ID or --ros-publish-map MAP_ID"),
        (["--ros-scans", "bad id"], {}, "argument --ros-scans: expected a map id"),
        (["--ros-scans", "lab", "--ros-domain", "-1"], {}, "argument --ros-domain: must be between 0"),
        (
            ["--ros-scans", "lab"],
            {"FLEETMAP_ROS_DOMAIN": "x"},
            "$FLEETMAP_ROS_DOMAIN='x': expected a whole number",
        ),
        (["--ros-scans", "lab"], {"ROS_DOMAIN_ID": "zero"}, "$ROS_DOMAIN_ID='zero': expected a whole number"),
        # A digit to str.isdigit() that int() refuses: it stopped the start with a traceback.
        (["--ros-scans", "lab"], {"ROS_DOMAIN_ID": "\u00b2"}, "$ROS_DOMAIN_ID='\u00b2': expected a whole"),
        (
            ["--ros-scans", "lab", "--ros-fixed-frame", "/"],
            {},
            "argument --ros-fixed-frame: invalid frame id",
        ),
    ],
)
def test_bad_ros_options_stop_with_one_line(args: list[str], env: dict[str, str], message: str) -> None:
    cmd = [sys.executable, "-m", "fleetmap.server", "--in-memory", "--http", "127.0.0.1:0", *args]
    proc = subprocess.run(cmd, env={**os.environ, **env}, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr


def test_the_highest_ros_domain_is_read(service_factory: Callable[..., ServiceProcess]) -> None:
    """`--ros-domain` takes 0 ... 4294967295 (docs/ros.md): the scans and TF of a domain id of ten
    digits are read as any. Before, a key whose domain had more than 9 digits was no rmw_zenoh key:
    every scan was refused as `invalid_topic` and the TF ignored."""
    domain = 2**32 - 1
    service = service_factory("--ros-scans", "lab", "--ros-domain", str(domain))
    session = client_session(service.zenoh_endpoint)
    try:
        key = lambda topic, kind: topic_key(domain, topic, kind, TYPE_HASHES[kind])  # noqa: E731
        scan_pub = session.declare_publisher(key("/robot1/scan", LASER))
        tf_pub = session.declare_publisher(key("/robot1/tf", TF))
        wait_for(lambda: scan_pub.matching_status.matching, timeout=20, what="the service's subscriber")
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            for dt in (-(10**7), 10**7):
                tf_pub.put(
                    tf_payload(stamp_ns_of(0) + dt, [("map", "laser", (1.0, 2.0, 0.0), Rotation.identity())])
                )
            scan_pub.put(
                LaserData(stamp_ns_of(0), -1.0, 0.02, np.full(100, 2.0, np.float32)).payload("laser")
            )
            wait_for(
                lambda: robot_stats(http, "robot1").get("scans_integrated") == 1,
                timeout=10, what="the scan of domain 4294967295 integrated",
            )  # fmt: skip
            ros = healthz_ros(http)
            assert (ros["domain_id"], ros["refused"], ros["tf_refused"]) == (domain, {}, 0), ros
        assert service.stop() == 0
    finally:
        session.close()


def test_a_scan_in_the_fixed_frame_needs_no_tf(service_factory: Callable[..., ServiceProcess]) -> None:
    """A laser whose scans are in the fixed frame itself (a stationary laser mapped in its own frame,
    `--ros-fixed-frame laser`) publishes no TF: tf2 gives the identity from a frame to itself, known
    or not, so the scans are integrated at the origin, as the engine integrates the same beams
    there. Before, each waited for TF that never came and was dropped (`no_tf`)."""
    service = service_factory("--ros-scans", "lab", "--ros-fixed-frame", "laser")
    session = client_session(service.zenoh_endpoint)
    try:
        scan_pub = session.declare_publisher(topic_key(0, "/scan", LASER, TYPE_HASHES[LASER]))
        wait_for(lambda: scan_pub.matching_status.matching, timeout=20, what="the service's subscriber")
        expected = GridMap(MapConfig())
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            for k, frame in enumerate(("laser", "/laser")):  # tf2 drops the leading /
                data = LaserData(stamp_ns_of(k), -1.0, 0.02, np.linspace(1.5, 3.0, 100, dtype=np.float32))
                scan_pub.put(data.payload(frame))
                expected.integrate(data.engine_scan((0.0, 0.0, 0.0)))
                wait_for(
                    lambda k=k: robot_stats(http, "robot").get("scans_integrated") == k + 1,
                    timeout=10, what=f"scan {k} in the fixed frame integrated",
                )  # fmt: skip
            assert healthz_ros(http)["refused"] == {}
            assert_region_equal(http, "lab", expected, ALL_LAYERS)
        assert service.stop() == 0
    finally:
        session.close()


def test_a_scan_stamped_zero_is_posed_at_the_newest_tf(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    """A LaserScan whose `header.stamp` is 0 (unset: `ros2 topic pub`, drivers without a clock) is
    posed, as tf2 poses time 0, at the latest time every edge of its chain has TF for (here the
    newer of two samples of `map -> base_link`), and integrated as the engine integrates the beams
    there. Before, time 0 was taken literally: more than 10 s before the TF kept, the scan waited
    for TF "in case time went back" and was dropped (`no_tf`)."""
    service = service_factory("--ros-scans", "lab")
    session = client_session(service.zenoh_endpoint)
    try:
        key = lambda topic, kind: topic_key(0, topic, kind, TYPE_HASHES[kind])  # noqa: E731
        scan_pub = session.declare_publisher(key("/robot1/scan", LASER))
        tf_pub = session.declare_publisher(key("/robot1/tf", TF))
        static_pub = session.declare_publisher(key("/robot1/tf_static", TF))
        wait_for(lambda: scan_pub.matching_status.matching, timeout=20, what="the service's subscriber")
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            static_pub.put(tf_payload(T0_NS, [("base_link", "laser", (0.5, 0.0, 0.0), Rotation.identity())]))
            turn = Rotation.from_euler("z", 0.4)
            tf_pub.put(tf_payload(stamp_ns_of(0), [("map", "base_link", (1.0, 2.0, 0.0), turn)]))
            tf_pub.put(tf_payload(stamp_ns_of(1), [("map", "base_link", (3.0, 2.0, 0.0), turn)]))
            wait_for(
                lambda: healthz_ros(http)["tf_trees"].get("/robot1", {}).get("samples") == 3,
                timeout=10, what="the robot's TF",
            )  # fmt: skip
            data = LaserData(0, -1.0, 0.02, np.linspace(1.5, 3.0, 100, dtype=np.float32))
            scan_pub.put(data.payload("laser"))
            wait_for(
                lambda: robot_stats(http, "robot1").get("scans_integrated") == 1,
                timeout=10, what="the scan stamped 0 integrated",
            )  # fmt: skip
            assert healthz_ros(http)["refused"] == {}
            expected = GridMap(MapConfig())
            laser_x, laser_y = 3.0 + 0.5 * math.cos(0.4), 2.0 + 0.5 * math.sin(0.4)
            expected.integrate(data.engine_scan((laser_x, laser_y, 0.4)))
            pose = http.get("/maps/lab").json()["stats"]["robots"]["robot1"]["last_pose"]
            assert [pose["x"], pose["y"], pose["theta"]] == pytest.approx([laser_x, laser_y, 0.4], abs=1e-9)
            assert_region_equal(http, "lab", expected, ALL_LAYERS)
        assert service.stop() == 0
    finally:
        session.close()


def test_a_refused_scan_is_not_also_counted_lost(service_factory: Callable[..., ServiceProcess]) -> None:
    """A scan refused (a bad scan, garbage, no TF) reached the service: rmw_zenoh's attachment gives
    its sequence number and publisher, so its seq is settled as refused, as a native scan refused by
    the input limits is (protocol.md), in the robot's order: garbage arriving while an earlier scan
    waits for its TF does not make that scan a duplicate. Before, only `scans_rejected` counted a
    refused scan, and the next scan accepted counted it again in `lost` (scans that never reached
    the service)."""
    service = service_factory("--ros-scans", "lab", "--in-memory")
    robot = RosRobot(service.zenoh_endpoint, "robot1")
    level = Rotation.identity()

    def tf(k: int) -> None:
        for dt in (-(10**7), 10**7):
            robot.put_tf(tf_payload(stamp_ns_of(k) + dt, [("map", "base_link", (1.0, 2.0, 0.0), level)]))

    def scan(k: int, frame: str = "laser", range_min: float = 0.05) -> bytes:
        return LaserData(stamp_ns_of(k), -1.0, 0.02, np.full(100, 2.0, np.float32), range_min).payload(frame)

    try:
        wait_for(lambda: robot.scan_pub.matching_status.matching, timeout=20, what="the service's subscriber")
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            robot.put_static(tf_payload(stamp_ns_of(0), [("base_link", "laser", (0.2, 0.0, 0.3), level)]))
            tf(0)
            robot.put_scan(scan(0))  # seq 0: creates the map, where refusals are counted
            wait_for(
                lambda: robot_stats(http, "robot1").get("scans_integrated") == 1, timeout=10, what="seq 0"
            )
            robot.put_scan(scan(1))  # seq 1 waits for its TF, sent after the next two
            robot.put_scan(b"\x00\x01\x00\x00" + b"\xff" * 40)  # seq 2: undecodable
            robot.put_scan(scan(2, range_min=50.0))  # seq 3: range_min above range_max
            time.sleep(0.1)
            tf(1)
            tf(2)
            robot.put_scan(scan(2, frame="no_such_frame"))  # seq 4: no TF ever
            tf(3)
            robot.put_scan(scan(3))  # seq 5
            stats = wait_for(
                lambda: (s := robot_stats(http, "robot1")).get("scans_integrated") == 3 and s,
                timeout=10, what="seqs 1 and 5 integrated",
            )  # fmt: skip
            assert healthz_ros(http)["refused"] == {"invalid_scan": 1, "undecodable": 1, "no_tf": 1}
            got = {key: stats[key] for key in ("scans_rejected", "lost", "duplicates", "last_seq")}
            assert got == {"scans_rejected": 3, "lost": 0, "duplicates": 0, "last_seq": 5}, stats
        assert service.stop() == 0
    finally:
        robot.close()
