"""RosScanIngest's logic without Zenoh: its callbacks' handlers are called directly and its thread's
pass run by hand, against a registry that records what it is given. The robot id and namespace
rules, the wait for TF in order, the timeout, the bounded queue, seq and session from rmw_zenoh's
attachment. (tests/test_ros_ingest.py runs the real service over real Zenoh.)"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import zenoh

from fleetmap.codec import DEFAULT_LIMITS, WireScan
from fleetmap.map_entry import IngestRejected
from fleetmap.registry import MapRegistry
from fleetmap.ros import tf_message
from fleetmap.ros.graph import Qos, RosNode, publisher_of_token, type_hash_of_token
from fleetmap.ros.ingest import MAX_TREES, RosScanIngest, robot_id_for, session_from_gid
from fleetmap.ros.laser_scan import LaserScanMsg, encode_laser_scan
from fleetmap.ros.rmw_zenoh import TYPE_HASHES, Attachment, dds_type_name, encode_attachment, topic_key
from fleetmap.ros.tf_message import TransformStamped, encode_tf_message

IDENTITY = (0.0, 0.0, 0.0, 1.0)


class RecordingRegistry:
    def __init__(self) -> None:
        self.submitted: list[tuple[str, str, WireScan]] = []
        self.rejected: list[tuple[str, str, str]] = []
        self.refuse_next: IngestRejected | None = None
        self.input_limits = DEFAULT_LIMITS

    def submit(self, map_id: str, robot_id: str, wire: WireScan) -> None:
        if self.refuse_next is not None:
            exc, self.refuse_next = self.refuse_next, None
            raise exc
        self.submitted.append((map_id, robot_id, wire))

    def reject(
        self, map_id: str, robot_id: str, reason: str, scan_id: tuple[int, float, int | None] | None = None
    ) -> None:
        self.rejected.append((map_id, robot_id, reason))


def make(**kwargs: Any) -> tuple[RosScanIngest, RecordingRegistry]:
    registry = RecordingRegistry()
    return RosScanIngest(registry, None, "lab", **kwargs), registry  # type: ignore[arg-type]


def scan_key(topic: str) -> str:
    return topic_key(0, topic, "sensor_msgs/msg/LaserScan", TYPE_HASHES["sensor_msgs/msg/LaserScan"])


def tf_key(topic: str) -> str:
    return topic_key(0, topic, "tf2_msgs/msg/TFMessage", "TypeHashNotSupported")


def laser(stamp: float, frame: str = "laser", n: int = 5) -> bytes:
    sec = math.floor(stamp)
    msg = LaserScanMsg(sec, round((stamp - sec) * 1e9), frame, -0.5, 0.5, 0.25, 0.0, 0.1, 0.1, 10.0,
                       np.full(n, 2.0, np.float32))  # fmt: skip
    return encode_laser_scan(msg)


def tf(stamp: float, *edges: tuple[str, str, float]) -> bytes:
    """Edges parent -> child translated by x along the parent's x axis."""
    return encode_tf_message([TransformStamped(stamp, p, c, (x, 0.0, 0.0), IDENTITY) for p, c, x in edges])


def test_robot_ids_and_sessions() -> None:
    assert robot_id_for("/robot1/scan") == "robot1"
    assert robot_id_for("/scan") == "robot"
    assert robot_id_for("/fleet/a/scan") == "fleet_a"
    # A topic not named scan (a robot's second laser) is its own robot: no id conflict.
    assert robot_id_for("/fleet/a/front_scan") == "fleet_a_front_scan"
    assert robot_id_for("/robot1/front/scan") == "robot1_front"
    assert robot_id_for("/scan_rear") == "robot_scan_rear"
    gid = bytes(range(1, 17))
    assert session_from_gid(gid) == int.from_bytes(gid[:6], "big") and session_from_gid(bytes(16)) == 1
    assert session_from_gid(b"\xff" * 16) < 2**53


def test_namespace_tf_first_else_the_root_tree() -> None:
    ingest, registry = make()
    # Root /tf holds robot3's frames, prefixed; robot3 publishes no TF of its own.
    ingest._handle_tf(tf_key("/tf"), tf(1.0, ("map", "robot3/laser", 1.0)))
    ingest._handle_tf(tf_key("/tf"), tf(3.0, ("map", "robot3/laser", 1.0)))
    ingest._handle_scan(scan_key("/robot3/scan"), laser(2.0, "robot3/laser"), None)
    ingest._pass()
    assert [(r, w.scan.pose.x) for _, r, w in registry.submitted] == [("robot3", 1.0)]
    # Once /robot3/tf speaks, robot3's scans are posed in its own tree (x = 5 there).
    ingest._handle_tf(tf_key("/robot3/tf"), tf(1.0, ("map", "robot3/laser", 5.0)))
    ingest._handle_tf(tf_key("/robot3/tf"), tf(3.0, ("map", "robot3/laser", 5.0)))
    ingest._handle_scan(scan_key("/robot3/scan"), laser(2.5, "robot3/laser"), None)
    ingest._pass()
    assert registry.submitted[-1][2].scan.pose.x == 5.0
    # A TFMessage on another topic is not TF.
    ingest._handle_tf(tf_key("/robot3/not_tf"), tf(1.0, ("map", "other", 1.0)))
    assert set(ingest.status()["tf_trees"]) == {"/", "/robot3"}


def test_a_namespace_whose_tf_publisher_exists_waits_for_its_tf_not_the_root_tree() -> None:
    """A robot in a namespace beside one without (a mixed fleet: `/scan` and `/tf` of the first
    robot, `/robot1/scan` and `/robot1/tf` of the second, both naming their frames `map`, `laser`):
    robot1's first scans, which often come before its first TF (its laser driver up before its
    TF publishers), were posed in the root tree, at the other robot's laser, and integrated there.
    rmw_zenoh's graph shows robot1's tf publisher from its start: its scans now wait for its own TF,
    as a tf2 listener in robot1's namespace does. Without such a publisher, the root tree still
    poses them (robots whose frames are prefixed in one tree)."""
    ingest, registry = make()
    ingest._handle_tf(tf_key("/tf"), tf(1.0, ("map", "laser", 9.0)))  # the robot without a namespace
    ingest._handle_tf(tf_key("/tf"), tf(3.0, ("map", "laser", 9.0)))
    node = RosNode(0, "a1b2c3", node_id=0, name="robot_state_publisher", namespace="/robot1")
    ingest._on_tf_token(_tf_publisher(node, 1, "/robot1/tf", True))  # type: ignore[arg-type]
    ingest._handle_scan(scan_key("/robot1/scan"), laser(2.0), None)
    ingest._pass()
    assert registry.submitted == []  # waiting for robot1's own TF
    ingest._handle_tf(tf_key("/robot1/tf"), tf(1.0, ("map", "laser", 2.0)))
    ingest._handle_tf(tf_key("/robot1/tf"), tf(3.0, ("map", "laser", 2.0)))
    ingest._pass()
    assert [(r, w.scan.pose.x) for _, r, w in registry.submitted] == [("robot1", 2.0)]


def test_scans_wait_for_tf_in_order_and_are_dropped_after_the_timeout() -> None:
    ingest, registry = make(tf_timeout=0.2)
    ingest._handle_tf(tf_key("/r/tf"), tf(1.0, ("map", "laser", 0.0)))
    ingest._handle_tf(tf_key("/r/tf"), tf(1.5, ("map", "laser", 1.0)))
    for stamp in (1.25, 2.0, 1.4):  # the third is covered, but must not overtake the second
        ingest._handle_scan(
            scan_key("/r/scan"), laser(stamp), encode_attachment(Attachment(10, 0, b"g" * 16))
        )
    timeout = ingest._pass()
    assert [w.stamp for _, _, w in registry.submitted] == [1.25]
    assert registry.submitted[0][2].scan.pose.x == pytest.approx(0.5)  # interpolated
    assert timeout is not None and 0 < timeout <= 0.2
    ingest._handle_tf(tf_key("/r/tf"), tf(2.5, ("map", "laser", 2.0)))
    ingest._pass()
    assert [w.stamp for _, _, w in registry.submitted] == [1.25, 2.0, 1.4]
    assert ingest.status()["scans_waited_for_tf"] == 1  # the third waited for order, not for its TF
    # A scan TF never covers: dropped once its time is up, counted on the robot with the reason.
    ingest._handle_scan(scan_key("/r/scan"), laser(9.0), None)
    assert ingest._pass() is not None and not registry.rejected
    time.sleep(0.25)
    assert ingest._pass() is None
    ((map_id, robot_id, reason),) = registry.rejected
    assert (map_id, robot_id) == ("lab", "r") and "no TF for the scan at 9.000" in reason
    assert "within 0.2 s" in reason and "map -> laser" in reason
    assert ingest.status()["refused"] == {"no_tf": 1}


def test_seq_and_session_from_the_attachment_else_a_counter() -> None:
    ingest, registry = make()
    ingest._handle_tf(tf_key("/tf_static"), tf(0.0, ("map", "laser", 0.0)))
    gid = bytes(range(16))
    ingest._handle_scan(scan_key("/a/scan"), laser(1.0), encode_attachment(Attachment(41, 5, gid)))
    ingest._handle_scan(scan_key("/b/scan"), laser(1.0), None)
    ingest._handle_scan(scan_key("/b/scan"), laser(1.1), b"not an attachment")
    ingest._pass()
    got = [(r, w.seq, w.session) for _, r, w in registry.submitted]
    assert got == [("a", 40, session_from_gid(gid)), ("b", 0, None), ("b", 1, None)]  # 41 counted from 1


def test_refusals_are_counted_with_their_reasons() -> None:
    ingest, registry = make(max_pending=2)
    ingest._handle_tf(tf_key("/tf_static"), tf(0.0, ("map", "base", 0.0)))
    ingest._handle_scan(scan_key("/r/scan"), b"\x00\x01\x00\x00garbage", None)
    ingest._handle_scan(scan_key("/" + "x" * 65 + "/scan"), laser(1.0), None)
    ingest._handle_scan("fleetmap/lab/r/scan", laser(1.0), None)
    ingest._handle_scan(scan_key("/r/scan"), laser(1.0, frame="x" * 300), None)
    ingest._handle_scan(scan_key("/r/scan"), laser(1.0, n=20000), None)  # refused before it waits
    for _ in range(3):  # "laser" is in no tree: they wait; the third does not fit
        ingest._handle_scan(scan_key("/r/scan"), laser(1.0), None)
    registry.refuse_next = IngestRejected("duplicate", 200)
    ingest._handle_tf(tf_key("/tf_static"), tf(0.0, ("base", "laser", 0.0)))
    ingest._pass()
    assert ingest.status()["refused"] == {
        "undecodable": 1, "invalid_topic": 2, "tf_error": 1, "invalid_scan": 1, "pending_full": 1,
        "duplicate": 1,
    }  # fmt: skip
    reasons = [reason for _, robot, reason in registry.rejected if robot == "r"]
    assert "undecodable LaserScan on /r/scan" in reasons[0]
    assert "invalid frame id" in reasons[1] and len(reasons[1]) < 300
    assert "2 scans of the robot (2048 of all robots) already wait for TF" in reasons[3]
    assert "20000 beams is more than the limit of 16384" in reasons[2]
    assert len(registry.submitted) == 1


def test_a_bad_scan_behind_a_full_queue_is_refused_for_what_it_is() -> None:
    """A scan refused before it waits (garbage here) while its robot's queue is full of scans
    waiting for TF: it was counted as `pending_full`, its reason asking whether TF is published for
    frame ''. It is refused for what it is, and still not settled (its turn never comes)."""
    ingest, registry = make(max_pending=2)
    for stamp in (1.0, 1.1):  # no TF: they wait
        ingest._handle_scan(scan_key("/r/scan"), laser(stamp), None)
    ingest._handle_scan(scan_key("/r/scan"), b"\x00\x01\x00\x00garbage", None)
    assert ingest.status()["refused"] == {"undecodable": 1}
    ((_, robot_id, reason),) = registry.rejected
    assert robot_id == "r" and "undecodable LaserScan on /r/scan" in reason


def test_tf_floods_and_bad_transforms_are_counted_not_kept() -> None:
    ingest, _ = make()
    bad = encode_tf_message([TransformStamped(0.0, "a", "b", (math.nan, 0.0, 0.0), IDENTITY)])
    ingest._handle_tf(tf_key("/tf"), bad)
    ingest._handle_tf(tf_key("/tf"), b"\x00\x01\x00\x00\xff\xff\xff\xff")
    for i in range(300):  # more frames than a tree may hold
        ingest._handle_tf(tf_key("/tf_static"), tf(0.0, ("map", f"f{i}", 0.0)))
    status = ingest.status()
    assert status["tf_trees"]["/"]["frames"] == 256
    assert status["tf_refused"] == 1 + 1 + (300 - 255)


def test_laserscan_publisher_tokens_name_their_topic() -> None:
    """rmw_zenoh's publisher token (as `fleetmap.ros.graph` writes one, the format of
    liveliness_utils.cpp) gives back its domain, topic and type; other tokens give None."""
    node = RosNode(3, "a1b2c3", node_id=0, name="driver", namespace="/robot1")
    token = node.publisher_token(
        2, "/robot1/scan_front", "sensor_msgs::msg::dds_::LaserScan_", "RIHS01_x", Qos()
    )
    assert publisher_of_token(token) == (3, "/robot1/scan_front", "sensor_msgs::msg::dds_::LaserScan_")
    assert publisher_of_token(node.node_token()) is None
    assert publisher_of_token(token.replace("/MP/", "/MS/")) is None  # a subscription
    assert publisher_of_token("fleetmap/lab/r1/alive") is None
    # The type hash fleetmap's subscription of the topic states: the publisher's (Humble's too).
    assert type_hash_of_token(token) == "RIHS01_x"
    humble = node.publisher_token(
        3, "/robot1/scan", "sensor_msgs::msg::dds_::LaserScan_", "TypeHashNotSupported", Qos()
    )
    assert type_hash_of_token(humble) == "TypeHashNotSupported"
    assert type_hash_of_token(node.node_token()) is None


def test_a_map_deleted_after_a_scan_is_not_made_again_by_showing_its_robot_online() -> None:
    """After a submitted scan, a robot whose LaserScan publisher lives is shown online if its map
    exists. It looked the map up (`registry.get`, which lets go of the registry's lock) and then
    called `set_online`, which makes a map for a token: a DELETE landing in between made the
    deleted map again, empty. The check and the update are now one hold of the registry's lock
    (`MapRegistry.mark_online`, which the native ingest uses too) and never create a map."""
    registry = MapRegistry(workers=1)
    ingest = RosScanIngest(registry, None, "lab")  # type: ignore[arg-type]
    entry, _ = registry.create("lab")
    ingest._alive["robot1"] = 1  # its publisher's token is present
    ingest._mark_online("robot1")
    assert entry.robots["robot1"].online
    entry.robots["robot1"].online = False
    real_get = registry.get

    def deleted_after_the_look_up(map_id: str) -> Any:
        found = real_get(map_id)
        registry.delete(map_id)  # the DELETE lands where the lock was let go
        return found

    registry.get = deleted_after_the_look_up  # type: ignore[method-assign]
    ingest._mark_online("robot1")
    assert registry.maps.get("lab") in (None, entry), "the deleted map was made again"
    registry.get = real_get  # type: ignore[method-assign]
    registry.delete("lab")
    ingest._mark_online("robot1")  # its map gone: nothing to show, nothing made
    assert "lab" not in registry.maps


def _tf_publisher(node: RosNode, entity_id: int, topic: str, present: bool) -> SimpleNamespace:
    """What the graph's liveliness subscriber hands `_on_tf_token`: a TFMessage publisher's token of
    `topic` appearing (`present`) or going."""
    token = node.publisher_token(
        entity_id, topic, dds_type_name(tf_message.ROS_TYPE), "TypeHashNotSupported", Qos()
    )
    return SimpleNamespace(key_expr=token, kind=zenoh.SampleKind.PUT if present else zenoh.SampleKind.DELETE)


def test_tf_trees_of_robots_gone_make_room_for_new_robots() -> None:
    """The ingest keeps at most 64 TF trees, one per namespace publishing TF, and kept each for the
    service's whole life: a fleet whose robots come and go under new namespaces (renamed, replaced,
    simulated) had every later robot's TF refused ("already 64 TF namespaces") once 64 namespaces
    had ever published, and its scans refused for want of TF, for good. A new namespace now takes the
    place of the tree heard from least recently of a namespace whose tf and tf_static publishers are
    all gone; while every tree has a publisher alive, a new one is still refused."""
    ingest, registry = make()
    node = RosNode(0, "a1b2c3", node_id=0, name="robot_state_publisher", namespace="/")
    for i in range(MAX_TREES):
        ingest._on_tf_token(_tf_publisher(node, i, f"/old{i}/tf", True))  # type: ignore[arg-type]
        ingest._handle_tf(tf_key(f"/old{i}/tf"), tf(1.0, ("map", "laser", 0.0)))
    ingest._handle_tf(tf_key("/new0/tf"), tf(1.0, ("map", "laser", 0.0)))
    assert "/new0" not in ingest.status()["tf_trees"]  # every robot still publishes TF
    assert ingest.status()["tf_refused"] == 1
    # Two robots leave (their nodes end: their publishers' tokens go); old1 was heard last of them.
    ingest._handle_tf(tf_key("/old0/tf"), tf(2.0, ("map", "laser", 0.0)))
    for i in (1, 0):
        ingest._on_tf_token(_tf_publisher(node, i, f"/old{i}/tf", False))  # type: ignore[arg-type]
    # Two new robots come, each in its own namespace: their TF is kept and poses their scans.
    for i, x in ((1, 3.0), (2, 4.0)):
        ingest._on_tf_token(_tf_publisher(node, 100 + i, f"/new{i}/tf", True))  # type: ignore[arg-type]
        ingest._handle_tf(tf_key(f"/new{i}/tf"), tf(1.0, ("map", "laser", x)))
        ingest._handle_tf(tf_key(f"/new{i}/tf"), tf(3.0, ("map", "laser", x)))
        ingest._handle_scan(scan_key(f"/new{i}/scan"), laser(2.0), None)
    ingest._pass()
    assert [(r, w.scan.pose.x) for _, r, w in registry.submitted] == [("new1", 3.0), ("new2", 4.0)]
    trees = set(ingest.status()["tf_trees"])
    assert len(trees) == MAX_TREES and {"/new1", "/new2"} <= trees
    assert not {"/old0", "/old1"} & trees  # the robots gone, old1 first (heard from least recently)
    # Full again, every tree's publisher alive: the next one is refused.
    ingest._handle_tf(tf_key("/new3/tf"), tf(1.0, ("map", "laser", 0.0)))
    assert "/new3" not in ingest.status()["tf_trees"]
