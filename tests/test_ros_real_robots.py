"""`fleetmap serve --ros-scans` against what real ROS 2 robots publish: lasers in sub-namespaces and
several lasers per robot, and rmw_zenoh's graph tokens saying which LaserScan publishers exist.

Why a Zenoh session stands in for a ROS 2 node: ROS 2 with rmw_zenoh cannot be installed on these
machines (no ROS apt repository; only Debian, PyPI and npm are reachable). What fleetmap sees of a
ROS 2 node is only what rmw_zenoh puts on Zenoh, so each emulated node here is a real Zenoh client
session publishing exactly that: data on rmw_zenoh's key expressions (`<domain>/<topic>/<dds
type>/<type hash>`), CDR payloads made by rosbags (`tests/test_ros_ingest.py`'s helpers), rmw_zenoh's
attachment, and for each publisher the liveliness token rmw_zenoh declares for it
(`@ros2_lv/<domain>/<zid>/<nid>/<eid>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>`,
`Entity::Entity` in rmw_zenoh_cpp's liveliness_utils.cpp; `fleetmap.ros.graph` writes the same). The
real service runs as a process and is read back over REST.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import httpx
import numpy as np
import zenoh
from scipy.spatial.transform import Rotation
from service_process import ServiceProcess, free_port, wait_for
from test_ros_ingest import (
    LASER,
    TF,
    LaserData,
    client_session,
    healthz_ros,
    router_session,
    stamp_ns_of,
    tf_payload,
)

from fleetmap.ros.graph import Qos, RosNode
from fleetmap.ros.rmw_zenoh import TYPE_HASHES, Attachment, dds_type_name, encode_attachment, topic_key

LEVEL = Rotation.identity()
#: A LaserScan publisher's QoS as most drivers declare it (SensorDataQoS: best effort, depth 5).
SENSOR_QOS = Qos(reliability=2, depth=5)


class RosNodeEmulation:
    """One ROS 2 node on rmw_zenoh: a Zenoh client session, its publishers with rmw_zenoh's
    attachment, and (with `tokens`) the node's and each publisher's liveliness token."""

    def __init__(self, endpoint: str, name: str, namespace: str = "/", tokens: bool = False) -> None:
        self.session = client_session(endpoint)
        self.node = RosNode(0, str(self.session.zid()), node_id=0, name=name, namespace=namespace)
        self.tokens: list[Any] = []
        if tokens:
            self.tokens.append(self.session.liveliness().declare_token(self.node.node_token()))
        self._publishers: dict[str, tuple[Any, bytes]] = {}
        self._seq: dict[str, int] = {}
        self._with_tokens = tokens

    def publisher(self, topic: str, kind: str) -> Any:
        if topic not in self._publishers:
            pub = self.session.declare_publisher(topic_key(0, topic, kind, TYPE_HASHES[kind]))
            self._publishers[topic] = (pub, os.urandom(16))
            if self._with_tokens:
                eid = len(self._publishers)
                dds_type = dds_type_name(kind)
                key = self.node.publisher_token(eid, topic, dds_type, TYPE_HASHES[kind], SENSOR_QOS)
                self.tokens.append(self.session.liveliness().declare_token(key))
        return self._publishers[topic][0]

    def put(self, topic: str, kind: str, payload: bytes) -> None:
        pub = self.publisher(topic, kind)
        self._seq[topic] = self._seq.get(topic, 0) + 1
        gid = self._publishers[topic][1]
        pub.put(payload, attachment=encode_attachment(Attachment(self._seq[topic], time.time_ns(), gid)))

    def close(self) -> None:
        self.session.close()


def robots(http: httpx.Client, map_id: str = "lab") -> dict[str, Any]:
    response = http.get(f"/maps/{map_id}")
    if response.status_code == 404:
        return {}
    got: dict[str, Any] = response.json()["stats"]["robots"]
    return got


def stamp_ns(k: int, base_ns: int | None) -> int:
    """Scan k's stamp: `stamp_ns_of(k)` (wall-clock-like), or k/10 s after `base_ns` (sim time)."""
    return stamp_ns_of(k) if base_ns is None else base_ns + k * 100_000_000


def publish_robot_tf(
    node: RosNodeEmulation, ns: str, lasers: dict[str, Rotation], k: int, base_ns: int | None = None
) -> None:
    """Static TF of base_link -> each laser frame on `<ns>/tf_static`, and map -> base_link around
    scan k's stamp on `<ns>/tf`."""
    node.put(f"{ns}/tf_static", TF, tf_payload(stamp_ns(0, base_ns), [
        ("base_link", frame, (0.2, 0.0, 0.3), rot) for frame, rot in lasers.items()
    ]))  # fmt: skip
    for dt in (-(10**7), 10**7):
        edge = ("map", "base_link", (1.0, 2.0, 0.0), LEVEL)
        node.put(f"{ns}/tf", TF, tf_payload(stamp_ns(k, base_ns) + dt, [edge]))


def wait_subscribed(node: RosNodeEmulation, topic: str, what: str = "the service's scan subscriber") -> None:
    """Until the service's LaserScan subscriber matches `node`'s publisher of `topic` (a scan put
    before would go nowhere)."""
    wait_for(lambda: node.publisher(topic, LASER).matching_status.matching, timeout=20, what=what)


def laser(k: int, frame: str, base_ns: int | None = None) -> bytes:
    return LaserData(stamp_ns(k, base_ns), -1.0, 0.02, np.full(100, 2.0, np.float32)).payload(frame)


def test_a_laser_in_a_sub_namespace_is_posed_by_its_robots_tf(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    """A laser driver launched in a sub-namespace of its robot (`/robot1/front/scan`, the robot's TF
    on `/robot1/tf`, as `ros2 launch ... namespace:=robot1` with the driver's own `front` namespace)
    is posed in `/robot1`'s TF tree. Before, only `/robot1/front/tf` or the root `/tf` were looked
    at: every scan waited 0.5 s and was dropped (`no_tf`)."""
    service = service_factory("--ros-scans", "lab")
    node = RosNodeEmulation(service.zenoh_endpoint, "robot")
    try:
        wait_subscribed(node, "/robot1/front/scan")
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            for k in range(3):
                publish_robot_tf(node, "/robot1", {"front_laser": LEVEL}, k)
                node.put("/robot1/front/scan", LASER, laser(k, "front_laser"))
            wait_for(
                lambda: robots(http).get("robot1_front", {}).get("scans_integrated") == 3,
                timeout=20, what="the three scans of /robot1/front/scan integrated",
            )  # fmt: skip
            assert healthz_ros(http)["refused"] == {}
        assert service.stop() == 0
    finally:
        node.close()


def test_a_robot_with_two_lasers_is_two_fleetmap_robots_without_an_id_conflict(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    """A robot with a front and a rear laser (`/robot1/scan_front`, `/robot1/scan_rear`, one TF
    tree on `/robot1/tf`), each driver its own publisher: two fleetmap robots, one per laser, each
    posed by its own frame. Before, both were robot `robot1`: two publisher sessions interleaving,
    shown as `id_conflict` ("robot id conflict" in the log) and a pose jumping from laser to
    laser."""
    service = service_factory("--ros-scans", "lab")
    front = RosNodeEmulation(service.zenoh_endpoint, "front_driver", "/robot1")
    rear = RosNodeEmulation(service.zenoh_endpoint, "rear_driver", "/robot1")
    tf = RosNodeEmulation(service.zenoh_endpoint, "robot_state_publisher", "/robot1")
    lasers = {"front_laser": LEVEL, "rear_laser": Rotation.from_euler("z", 180, degrees=True)}
    try:
        for node, topic in ((front, "/robot1/scan_front"), (rear, "/robot1/scan_rear")):
            wait_subscribed(node, topic)
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            for k in range(4):
                publish_robot_tf(tf, "/robot1", lasers, k)
                front.put("/robot1/scan_front", LASER, laser(k, "front_laser"))
                rear.put("/robot1/scan_rear", LASER, laser(k, "rear_laser"))
            want = {"robot1_scan_front", "robot1_scan_rear"}
            got = wait_for(
                lambda: (r := robots(http)) and all(r.get(i, {}).get("scans_integrated") == 4 for i in want)
                and r,
                timeout=20, what="each laser's four scans integrated",
            )  # fmt: skip
            assert set(got) == want, got
            for stats in got.values():
                assert (stats["id_conflict"], stats["lost"], stats["duplicates"]) == (False, 0, 0), stats
            # Each laser posed by its own frame: the rear one looks backwards.
            theta = {rid: got[rid]["last_pose"]["theta"] for rid in want}
            assert abs(abs(theta["robot1_scan_rear"] - theta["robot1_scan_front"]) - np.pi) < 1e-3, theta
        assert service.stop() == 0
        assert "robot id conflict" not in service.logs()
    finally:
        for node in (front, rear, tf):
            node.close()


def subscriptions(session: zenoh.Session, ros_type: str = LASER) -> list[tuple[str, str, str, str]]:
    """The subscriptions of `ros_type` in the ROS graph, as rmw_zenoh's graph cache reads them from
    the liveliness tokens: (node, topic, type hash, QoS) of each."""
    replies = session.liveliness().get(f"@ros2_lv/0/*/*/*/MS/*/*/*/*/{dds_type_name(ros_type)}/**")
    found = []
    for reply in replies:
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            found.append((parts[8], parts[9].replace("%", "/"), parts[11], parts[12]))
    return sorted(found)


def test_ros_robots_are_online_while_their_laserscan_publisher_exists(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    """A ROS robot is shown online in `GET /maps/{id}` (and so in the viewer) while rmw_zenoh's
    graph token of its LaserScan publisher exists, offline once it goes (here its node's session
    closes, as when the robot is switched off or its network lost), as native robots are by their
    `alive` tokens. A publisher that existed before the service started counts (the liveliness
    subscriber has history); other graph tokens (a node's, another type's publisher) do not. Before,
    a ROS robot was never online.

    While the topic has a publisher, the graph shows the service's subscription of it (node
    `/fleetmap_scans`, SensorDataQoS: best effort, depth 5), gone with the last publisher, and so for
    a TF topic (with tf2's listener's QoS). rmw_zenoh counts subscription tokens in a publisher's
    `get_subscription_count()`, which lazy publishers (pointcloud_to_laserscan, lazy bridges) wait
    for before they publish anything. Before, the service declared none: `ros2 topic info` showed
    no subscriber, and such a robot never sent a scan."""
    router = f"tcp/127.0.0.1:{free_port()}"
    router_session_ = router_session(router)  # rmw_zenohd: the robot is up before the service
    robot2 = RosNodeEmulation(router, "driver", "/robot2", tokens=True)
    other = RosNodeEmulation(router, "camera", "/robot3", tokens=True)
    try:
        robot2.publisher("/robot2/scan", LASER)  # declared, its token with it; nothing published yet
        other.publisher("/robot3/tf", TF)  # a graph token of another type: no robot
        other.publisher("/robot3/tf_static", TF)
        other.publisher("/robot3/not_tf", TF)  # a TFMessage on another topic is not TF: not read
        service = service_factory("--ros-scans", "lab", "--zenoh-connect", router)
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            wait_for(
                lambda: robots(http).get("robot2", {}).get("online") is True,
                timeout=20, what="robot2 online from its LaserScan publisher's token",
            )  # fmt: skip
            subscription = ("fleetmap_scans", "/robot2/scan", TYPE_HASHES[LASER], "2::,5:,:,:,,")
            wait_for(
                lambda: subscriptions(router_session_) == [subscription],
                timeout=10, what="the service's subscription of /robot2/scan in the ROS graph",
            )  # fmt: skip
            tf_subscriptions = [
                ("fleetmap_scans", "/robot3/tf", TYPE_HASHES[TF], "::,100:,:,:,,"),
                ("fleetmap_scans", "/robot3/tf_static", TYPE_HASHES[TF], ":1:,100:,:,:,,"),
            ]
            wait_for(
                lambda: subscriptions(router_session_, TF) == tf_subscriptions,
                timeout=10, what="the service's subscription of /robot3/tf in the ROS graph",
            )  # fmt: skip
            for k in range(2):
                publish_robot_tf(robot2, "/robot2", {"laser": LEVEL}, k)
                robot2.put("/robot2/scan", LASER, laser(k, "laser"))
            stats = wait_for(
                lambda: (s := robots(http).get("robot2", {})).get("scans_integrated") == 2 and s,
                timeout=20, what="robot2's scans",
            )  # fmt: skip
            assert stats["online"] is True
            assert set(robots(http)) == {"robot2"}
            ros = healthz_ros(http)
            assert (ros["laser_publishers"], ros["robots_online"]) == (1, 1), ros
            listed = http.get("/maps").json()
            summary = next(m for m in listed.get("maps", listed) if m["id"] == "lab")
            assert summary["robots_online"] == 1, summary
            robot2.close()  # the robot goes: its session, and so its tokens
            wait_for(
                lambda: robots(http)["robot2"]["online"] is False,
                timeout=20, what="robot2 offline once its publisher is gone",
            )  # fmt: skip
            assert healthz_ros(http)["robots_online"] == 0
            wait_for(
                lambda: subscriptions(router_session_) == [],
                timeout=10, what="the subscription gone with the topic's last publisher",
            )  # fmt: skip
        assert service.stop() == 0
        logs = service.logs()
        assert "Traceback" not in logs
        assert "ROS robot lab/robot2 is online (LaserScan publisher on /robot2/scan)" in logs
        assert "ROS robot lab/robot2 is offline" in logs and "robot3" not in logs
    finally:
        robot2.close()
        other.close()
        router_session_.close()


def test_a_simulation_restarted_under_use_sim_time_is_posed_again(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    """A simulated robot (`use_sim_time`: stamps from Gazebo's `/clock`) maps for a while, then the
    simulation is restarted: its clock starts again from 0, its nodes are new publishers. Its scans
    and TF must be integrated again, as tf2 clears its buffer on a jump back in time (the same comes
    of a bag replayed again, or a robot's clock stepped back), also when a scan comes before its TF.
    Before, every new TF sample was older than the 10 s kept behind the tree's newest one and silently
    dropped, and a scan that far back was refused at once: each later scan was refused (`tf_error`,
    "older than the TF kept") until the service restarted."""
    service = service_factory("--ros-scans", "lab")
    first = RosNodeEmulation(service.zenoh_endpoint, "gazebo", "/sim1")
    try:
        wait_subscribed(first, "/sim1/scan")
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            for k in range(3):  # sim time 300 s on: a run of five minutes
                publish_robot_tf(first, "/sim1", {"laser": LEVEL}, k, base_ns=300 * 10**9)
                first.put("/sim1/scan", LASER, laser(k, "laser", base_ns=300 * 10**9))
            wait_for(
                lambda: robots(http).get("sim1", {}).get("scans_integrated") == 3,
                timeout=20, what="the first run's scans",
            )  # fmt: skip
            first.close()  # the simulation stops; restarted, its clock starts from 0 again
            second = RosNodeEmulation(service.zenoh_endpoint, "gazebo", "/sim1")
            try:
                wait_subscribed(second, "/sim1/scan", "the restarted robot's scan publisher matched")
                for k in range(3):  # sim time 2 s on; each scan before its TF, as TF often comes
                    second.put("/sim1/scan", LASER, laser(k, "laser", base_ns=2 * 10**9))
                    time.sleep(0.05)
                    publish_robot_tf(second, "/sim1", {"laser": LEVEL}, k, base_ns=2 * 10**9)
                stats = wait_for(
                    lambda: (s := robots(http).get("sim1", {})).get("scans_integrated", 0)
                    + s.get("scans_rejected", 0) >= 6 and s,
                    timeout=20, what="the restarted run's scans handled",
                )  # fmt: skip
                assert (stats["scans_integrated"], stats["scans_rejected"]) == (6, 0), (
                    stats["last_error"],
                    healthz_ros(http)["refused"],
                )
            finally:
                second.close()
        assert service.stop() == 0
    finally:
        first.close()


def test_a_tf_tree_at_its_sample_limit_keeps_up_with_time(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    """A robot whose TF has many fast edges (a mobile manipulator: robot_state_publisher sends each
    moving joint at the joint_states rate; or a fleet's prefixed frames in one root tree) fills its
    tree's 20 000 samples before its edges' 10 s of history. Here 41 edges at 100 Hz, 24 600 samples
    in 6 s: the tree keeps every edge moving, its fullest edges' oldest samples making room, and a
    scan stamped at the end is posed. Before, every sample past the limit was refused: the tree froze
    for good (an edge drops old samples only when it takes a new one) and every later scan was
    dropped (`no_tf`)."""
    service = service_factory("--ros-scans", "lab")
    node = RosNodeEmulation(service.zenoh_endpoint, "robot")
    try:
        wait_subscribed(node, "/robot1/scan")
        # Blocking, not dropping, when the link is busy: every TF message must arrive.
        static_pub, tf_pub = (
            node.session.declare_publisher(
                topic_key(0, topic, TF, TYPE_HASHES[TF]), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for topic in ("/robot1/tf_static", "/robot1/tf")
        )
        static_pub.put(tf_payload(stamp_ns_of(0), [("base_link", "laser", (0.2, 0.0, 0.3), LEVEL)]))
        with httpx.Client(base_url=service.base_url, timeout=20.0) as http:
            joints = [("base_link", f"joint{j}", (0.1 * j, 0.0, 0.5), LEVEL) for j in range(40)]
            for k in range(600):  # 10 ms apart: 100 Hz
                stamp = stamp_ns_of(0) + k * 10_000_000
                tf_pub.put(tf_payload(stamp, [("map", "base_link", (1.0, 2.0, 0.0), LEVEL), *joints]))
            wait_for(
                lambda: healthz_ros(http)["tf_messages"] == 601, timeout=20, what="the TF messages handled"
            )
            assert healthz_ros(http)["tf_trees"]["/robot1"]["samples"] == 20_000
            node.put(
                "/robot1/scan",
                LASER,
                LaserData(stamp_ns_of(0) + 5_985_000_000, -1.0, 0.02, np.full(100, 2.0, np.float32)).payload(
                    "laser"
                ),
            )
            wait_for(
                lambda: robots(http).get("robot1", {}).get("scans_integrated") == 1,
                timeout=10, what="the scan at the end of the TF integrated",
            )  # fmt: skip
            ros = healthz_ros(http)
            assert (ros["refused"], ros["tf_refused"]) == ({}, 0), ros
        assert service.stop() == 0
    finally:
        node.close()
