"""ROS 2 scans over rmw_zenoh into one map: `RosScanIngest`.

Opt-in (`fleetmap serve --ros-scans MAP_ID`, see docs/ros.md). On the service's own Zenoh session
it subscribes to every `sensor_msgs/msg/LaserScan` and every `tf2_msgs/msg/TFMessage` of one ROS
domain, on the key expressions rmw_zenoh publishes them on (`fleetmap.ros.rmw_zenoh`), whatever the
type hash (Humble's `TypeHashNotSupported` too). TF goes into one `TfBuffer` per namespace: messages
on `/<ns>/tf` and `/<ns>/tf_static` into the tree of `<ns>`, `/tf` and `/tf_static` into the root
tree. A scan on `/<ns>/<name>` is posed in the tree of `<ns>` if that namespace has published TF,
else in that of its nearest parent namespace that has, else in the root tree (a namespace whose
`tf` or `tf_static` publisher the ROS graph shows is waited for instead: its TF is coming): the pose of its
`header.frame_id` in the fixed frame at `header.stamp`, projected onto the map's plane
(`sensor_pose_2d`). It is then handed to `MapRegistry.submit` as the robot `<ns>` (`/` -> `_`;
`robot` without a namespace; `<ns>_<name>` for a topic not named `scan`: `robot_id_for`), exactly
as a native scan.

`/tf_static` is TRANSIENT_LOCAL: rmw_zenoh publishes it with an AdvancedPublisher holding a cache
(rmw_publisher_data.cpp), which an AdvancedSubscriber with history and late-publisher detection
queries, as rmw_zenoh's own subscriptions do (rmw_subscription_data.cpp): so the static TF of robots
that started before the service arrives. Releases before the AdvancedPublisher kept a publication
cache answering plain queries on the topic's key; one query at start covers those.

A robot is shown online (`MapRegistry.set_online`, as native robots by their liveliness tokens)
while at least one of its LaserScan publishers exists: rmw_zenoh declares a graph token for each
publisher (`@ros2_lv/<domain>/.../MP/.../<topic>/sensor_msgs::msg::dds_::LaserScan_/...`,
`fleetmap.ros.graph`), which goes when the publisher is destroyed or its node's session is lost;
a liveliness subscriber with history reports those present at start.

For each LaserScan, `tf` and `tf_static` topic that has a publisher (seen by its graph token), the
service declares the graph token of a subscription of it (node `/fleetmap_scans`; SensorDataQoS for
scans, tf2's listener's QoS for TF), as rmw_zenoh does for each subscription: without it `ros2
topic info` shows no subscriber, and publishers that publish only while a subscription is matched
(`get_subscription_count() > 0`: pointcloud_to_laserscan, lazy bridges) never send fleetmap a scan.
The tokens are declared and undeclared by the `fleetmap-ros` thread.

Threads: the Zenoh callbacks decode and append, never wait. A scan goes on its robot's pending
queue (bounded; the newest refused when full) and the `fleetmap-ros` thread poses it as soon as TF
covers its stamp, in order per robot. A scan whose TF has not come `tf_timeout` seconds after it
arrived is dropped (tf2's MessageFilter does the same), counted on the robot (`scans_rejected`,
`last_error` saying why) and in `status()`. A scan that can never be posed (a tilted laser, a stamp
older than the TF kept, a bad scan) is refused at once the same way, or, while scans of its robot
are queued, when its turn comes: a refusal settles the scan's seq (not lost), which must not
overtake an earlier scan's submission.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext

from fleetmap import codec
from fleetmap.codec import WireScan
from fleetmap.map_entry import IngestRejected
from fleetmap.rate_limited_log import RateLimitedLog
from fleetmap.registry import InvalidId, MapRegistry
from fleetmap.ros import laser_scan, tf_message
from fleetmap.ros.cdr import CdrError
from fleetmap.ros.graph import (
    ADMIN_SPACE,
    PUBLISHER,
    SCAN_SUBSCRIPTION_QOS,
    TF_STATIC_SUBSCRIPTION_QOS,
    TF_SUBSCRIPTION_QOS,
    RosNode,
    publisher_of_token,
    type_hash_of_token,
)
from fleetmap.ros.laser_scan import LaserScanMsg, decode_laser_scan
from fleetmap.ros.rmw_zenoh import TYPE_HASHES, dds_type_name, decode_attachment, parse_topic_key
from fleetmap.ros.tf_message import decode_tf_message
from fleetmap.ros.transforms import TfBuffer, TfError, TfPending, normalize_frame, sensor_pose_2d
from fleetmap.scan import Scan, ScanError
from fleetmap.wire import SESSION_LIMIT, is_valid_id

log = logging.getLogger("fleetmap.ros")

#: Seconds a scan waits for the TF that poses it (tf2's MessageFilter's usual queue time).
TF_TIMEOUT = 0.5
#: Scans held per robot while they wait for TF (20 Hz for 0.5 s is 10).
MAX_PENDING = 50
#: Scans waiting for TF, all robots together: with the beam limit (16 384 by default, 64 KiB of
#: ranges) this bounds what waiting scans hold, about 128 MiB at worst.
MAX_WAITING = 2048
#: Robots (namespaces with LaserScans) and TF trees (namespaces with TF) tracked at most.
MAX_ROBOTS = 1024
MAX_TREES = 64
#: rmw_zenoh graph tokens of LaserScan publishers kept at most (each says a robot is online).
MAX_PUBLISHER_TOKENS = 4096
#: Robot id of a LaserScan topic without a namespace (`/scan`).
ROOT_ROBOT_ID = "robot"
#: The usual name of a robot's LaserScan topic (nav2's default): the robot id is its namespace alone.
SCAN_TOPIC_NAME = "scan"
#: The names of TF's topics (in the root namespace or a robot's).
TF_TOPIC_NAME, TF_STATIC_TOPIC_NAME = "tf", "tf_static"
#: The ROS node fleetmap's LaserScan subscriptions belong to in the ROS graph, and its node id on the
#: service's Zenoh session (the map publisher's node, `/fleetmap`, is 0).
SCAN_NODE_NAME = "fleetmap_scans"
SCAN_NODE_ID = 1
#: The subscriptions' entity ids start past this: apart from the map publisher's (1, 2, ... two a
#: published topic) on the same session, as rmw_zenoh's ids are unique per session.
SCAN_ENTITY_ID_BASE = 1 << 16


def robot_id_for(topic: str) -> str:
    """The robot id of a LaserScan topic: its namespace, `/` turned into `_` (`/robot1/scan` ->
    `robot1`, `/a/b/scan` -> `a_b`), or `robot` without one (`/scan`); then `_<name>` when the
    topic's name is not `scan` (`/robot1/scan_front` -> `robot1_scan_front`, `/scan_rear` ->
    `robot_scan_rear`). May be an invalid fleetmap id (the caller checks).

    The name counts because a robot with two lasers publishes them on two topics of its namespace
    (`scan_front`, `scan_rear`): as one robot id they would be two publisher sessions interleaving,
    which the registry reports as an id conflict (two robots under one id), and its pose and trail
    would jump from laser to laser."""
    namespace, _, name = topic.rpartition("/")
    namespace = namespace.strip("/")
    robot_id = namespace.replace("/", "_") if namespace else ROOT_ROBOT_ID
    return robot_id if name == SCAN_TOPIC_NAME else f"{robot_id}_{name}"


def session_from_gid(gid: bytes) -> int:
    """A fleetmap session id from an rmw_zenoh publisher gid: its first 6 bytes (the gid is a hash
    of the publisher's liveliness token, which holds its Zenoh session id, so a restarted node gets
    a new one), in [1, 2**48]."""
    return int.from_bytes(gid[:6], "big") or 1


@dataclass
class _Pending:
    """A scan on its robot's queue: waiting for the TF that poses it, or (`refusal`: kind, reason)
    refused already, to be counted in its robot's order (`msg` None: it could not be read)."""

    msg: LaserScanMsg | None
    namespace: str
    seq: int
    session: int | None
    deadline: float  # time.monotonic() after which it is dropped if TF still does not cover it
    waited: bool = False  # counted once in `scans_waited_for_tf`
    refusal: tuple[str, str] | None = None

    @property
    def scan_id(self) -> tuple[int, float, int] | None:
        """What settles it when it is refused (`RosScanIngest._refuse`): None without a session (no
        rmw_zenoh attachment), whose seq is not the publisher's."""
        if self.session is None:
            return None
        return (self.seq, 0.0 if self.msg is None else self.msg.stamp, self.session)


class _Robot:
    __slots__ = ("counters", "pending")

    def __init__(self) -> None:
        self.pending: deque[_Pending] = deque()
        self.counters: dict[str, int] = {}  # seq counter per topic, for messages without attachment


class RosScanIngest:
    """LaserScans and TF of one ROS domain, over an open Zenoh session, into map `map_id`.

    Contract: after `start()`, every LaserScan sample of the domain is either submitted to the
    registry with the sensor pose TF gives at its stamp, or counted (in `status()`, and on its robot
    through `MapRegistry.reject` when the map exists) with a rate-limited log line saying why.
    `close()` undeclares the subscribers and stops the thread (scans still waiting are dropped);
    call it before closing the session. Both are idempotent."""

    def __init__(
        self,
        registry: MapRegistry,
        session: zenoh.Session,
        map_id: str,
        *,
        domain_id: int = 0,
        fixed_frame: str = "map",
        tf_timeout: float = TF_TIMEOUT,
        max_pending: int = MAX_PENDING,
    ) -> None:
        if not is_valid_id(map_id):
            raise ValueError(f"map id must match [A-Za-z0-9_-]{{1,64}}, got {map_id!r}")
        self.registry = registry
        self.session = session
        self.map_id = map_id
        self.domain_id = domain_id
        self.fixed_frame = fixed_frame
        self.tf_timeout = tf_timeout
        self.max_pending = max_pending
        self.scan_key = f"{domain_id}/**/{dds_type_name(laser_scan.ROS_TYPE)}/*"
        self.tf_key = f"{domain_id}/**/{dds_type_name(tf_message.ROS_TYPE)}/*"
        #: rmw_zenoh's graph tokens of the domain's LaserScan publishers (`fleetmap.ros.graph`).
        self.token_key = (
            f"{ADMIN_SPACE}/{domain_id}/*/*/*/{PUBLISHER}/*/*/*/*/{dds_type_name(laser_scan.ROS_TYPE)}/**"
        )
        #: Their TF publishers' (of every TFMessage topic: `_on_tf_token` keeps tf and tf_static).
        self.tf_token_key = (
            f"{ADMIN_SPACE}/{domain_id}/*/*/*/{PUBLISHER}/*/*/*/*/{dds_type_name(tf_message.ROS_TYPE)}/**"
        )
        self._subscribers: list[Any] = []
        self._lock = threading.Lock()  # guards _robots, the counters
        self._tf_lock = threading.Lock()  # guards _trees
        self._robots: dict[str, _Robot] = {}
        #: By namespace ('' for /tf), in the order they were last heard (`_forget_a_tree`).
        self._trees: dict[str, TfBuffer] = {}
        self._waiting = 0  # scans in all robots' pending queues
        self._publisher_tokens: dict[str, str] = {}  # token key -> robot id, LaserScan publishers alive
        self._tf_publisher_tokens: set[str] = set()  # token keys of the tf and tf_static publishers alive
        #: (LaserScan or TF topic, its ROS type) -> (its publishers alive, the type hash of the first
        #: one's token): the topics the graph should show a subscription of (`_count_publisher`).
        self._graph_topics: dict[tuple[str, str], tuple[int, str]] = {}
        #: A topic got its first publisher or lost its last since the thread last looked (its passes
        #: run at every TF message: they look at `_graph_topics` only then).
        self._graph_changed = False
        #: What the thread declared: the node's token, and per (topic, type) its subscription's token.
        self._node_token: Any = None
        self._subscription_tokens: dict[tuple[str, str], Any] = {}
        self._next_entity_id = SCAN_ENTITY_ID_BASE
        self._graph_node: RosNode | None = None
        self._alive: Counter[str] = Counter()  # robot id -> its LaserScan publishers alive (> 0)
        self._wake = threading.Event()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._log = RateLimitedLog(log)
        self._alive_log = RateLimitedLog(log, max_lines=100)
        self.scans_received = 0
        self.scans_submitted = 0
        self.scans_waited_for_tf = 0
        self.tf_messages = 0
        self.tf_refused = 0  # transforms (not messages) refused: bad values, limits
        self.refused: Counter[str] = Counter()  # scans refused, by kind

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> None:
        """Declare the subscribers, query old-style publication caches, start the thread. Raises
        zenoh.ZError (nothing left declared) if the session refuses."""
        if self._thread is not None:
            return
        try:
            self._subscribers.append(self.session.declare_subscriber(self.scan_key, self._on_scan))
            self._subscribers.append(
                zenoh.ext.declare_advanced_subscriber(
                    self.session,
                    self.tf_key,
                    self._on_tf,
                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
                    subscriber_detection=True,
                )
            )
            # rmw_zenoh before its AdvancedPublisher: a publication cache answering queries on the key.
            self.session.get(self.tf_key, self._on_reply)
            self._graph_node = RosNode(
                self.domain_id, str(self.session.zid()), node_id=SCAN_NODE_ID, name=SCAN_NODE_NAME
            )
            self._node_token = self.session.liveliness().declare_token(self._graph_node.node_token())
            # With history: the publishers that exist already are reported at once.
            self._subscribers.append(
                self.session.liveliness().declare_subscriber(self.token_key, self._on_token, history=True)
            )
            self._subscribers.append(
                self.session.liveliness().declare_subscriber(
                    self.tf_token_key, self._on_tf_token, history=True
                )
            )
        except zenoh.ZError:
            self.close()
            raise
        # Scans the callbacks queued meanwhile wait for it; the first pass takes them.
        self._thread = threading.Thread(target=self._run, name="fleetmap-ros", daemon=True)
        self._thread.start()
        log.info(
            "ROS 2 scans of domain %d go into map %s, posed in frame %s (keys %s, %s)",
            self.domain_id, self.map_id, self.fixed_frame, self.scan_key, self.tf_key,
        )  # fmt: skip

    def close(self) -> None:
        """Undeclare the subscribers and stop the thread. Idempotent."""
        subscribers, self._subscribers = self._subscribers, []
        for sub in subscribers:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()
        self._stop = True
        self._wake.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=5)
        # After the thread, which declares the subscriptions' tokens: none is declared after this.
        tokens = [*self._subscription_tokens.values(), self._node_token]
        self._subscription_tokens, self._node_token = {}, None
        for token in tokens:
            if token is not None:
                with contextlib.suppress(zenoh.ZError):
                    token.undeclare()

    # -- Zenoh callbacks (Zenoh threads: never block) --------------------------------------------

    def _on_scan(self, sample: zenoh.Sample) -> None:
        try:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            self._handle_scan(str(sample.key_expr), sample.payload.to_bytes(), attachment)
        except Exception:  # an exception must not escape into Zenoh's thread; a bug is logged
            log.exception("unexpected error handling a ROS scan sample on %s", sample.key_expr)

    def _refuse(
        self, kind: str, robot_id: str | None, reason: str, scan_id: tuple[int, float, int] | None = None
    ) -> None:
        """Count a refused scan (on its robot when there is one) and log it, rate-limited. `scan_id`:
        its (seq, stamp, session) when its publisher's attachment gave them (`_Pending.scan_id`),
        which settles its seq as refused, as `MapRegistry.reject` does a native scan's: it reached the
        service, and is not to be counted as lost when the next one arrives."""
        with self._lock:
            self.refused[kind] += 1
        if robot_id is not None:
            self.registry.reject(self.map_id, robot_id, reason, scan_id)
        who = f"{self.map_id}/{robot_id}" if robot_id else "ROS"
        self._log.warning(
            f"ros-{kind}:{robot_id}", f"refused a ROS scan of {who}: {reason}", map_id=self.map_id,
            robot_id=robot_id,
        )  # fmt: skip

    def _handle_scan(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        with self._lock:
            self.scans_received += 1
        topic_key = parse_topic_key(key)
        if topic_key is None or topic_key.ros_type != laser_scan.ROS_TYPE:
            self._refuse("invalid_topic", None, f"not an rmw_zenoh LaserScan key: {key[:200]!r}")
            return
        topic = topic_key.topic
        robot_id = robot_id_for(topic)
        if not is_valid_id(robot_id):
            reason = f"topic {topic[:200]!r} gives robot id {robot_id[:80]!r}, not [A-Za-z0-9_-]{{1,64}}"
            self._refuse("invalid_topic", None, reason)
            return
        msg, refusal = self._decode(topic, payload)
        meta = decode_attachment(attachment) if attachment is not None else None
        namespace = topic.rsplit("/", 1)[0]
        with self._lock:
            robot = self._robots.get(robot_id)
            if robot is None and self._room_for_robot():
                robot = self._robots[robot_id] = _Robot()
            if robot is not None:
                if meta is not None and 1 <= meta.sequence_number < 2**63:
                    # rmw_zenoh counts from 1, fleetmap from 0: a restarted node's first scan is then
                    # not one "lost" scan (protocol.md, "Sequence numbers").
                    seq, session = meta.sequence_number - 1, session_from_gid(meta.source_gid)
                else:  # no rmw_zenoh attachment: count per topic; the stamps tell restarts
                    seq = robot.counters.get(topic, -1) + 1
                    if topic in robot.counters or len(robot.counters) < 16:
                        robot.counters[topic] = seq
                    session = None
                assert session is None or 1 <= session < SESSION_LIMIT
                item = _Pending(
                    msg, namespace, seq, session, time.monotonic() + self.tf_timeout, refusal=refusal
                )
                # A refused scan is refused at once, unless scans of its robot are queued (waiting
                # for TF, or being handed on by the thread): then it queues behind them, to be refused
                # in the robot's order, since settling its seq (`_refuse`) before an earlier scan is
                # submitted would make that one a duplicate.
                refuse_now = refusal is not None and not robot.pending
                full = not refuse_now and (
                    len(robot.pending) >= self.max_pending or self._waiting >= MAX_WAITING
                )
                if not (refuse_now or full):
                    self._waiting += 1
                    robot.pending.append(item)
        if robot is None:
            self._refuse("too_many_robots", None, f"already {MAX_ROBOTS} ROS robots; {robot_id!r} ignored")
            return
        if refuse_now:
            assert refusal is not None
            self._refuse(refusal[0], robot_id, refusal[1], item.scan_id)
            return
        if full and refusal is not None:
            # Refused for what it is (garbage, too many beams, a bad frame id), not for the queue it
            # could not join; unsettled all the same, as any scan refused while its robot's queue is
            # full (see above).
            self._refuse(refusal[0], robot_id, refusal[1])
            return
        if full:  # not settled (see above): its seq counts as lost once a later one is accepted
            frame = "" if msg is None else msg.frame_id
            reason = (
                f"{self.max_pending} scans of the robot ({MAX_WAITING} of all robots) already wait for TF "
                f"(is TF published for {frame!r}?)"
            )
            self._refuse("pending_full", robot_id, reason)
            return
        self._wake.set()

    def _decode(self, topic: str, payload: bytes) -> tuple[LaserScanMsg | None, tuple[str, str] | None]:
        """The LaserScan of `payload`, or (None, (kind, reason)) if it is refused before it waits for
        TF: garbage, more beams than the limit, an invalid frame id (so that it holds no memory while
        queued, and no reason or log line carries a huge id)."""
        limit = self.registry.input_limits.max_payload_bytes
        if len(payload) > limit:
            return None, ("undecodable", f"LaserScan of {len(payload)} bytes exceeds the limit of {limit}")
        try:
            msg = decode_laser_scan(payload)
        except CdrError as exc:
            return None, ("undecodable", f"undecodable LaserScan on {topic}: {exc}")
        max_beams = self.registry.input_limits.max_beams
        if len(msg.ranges) > max_beams:
            reason = f"LaserScan of {len(msg.ranges)} beams is more than the limit of {max_beams}"
            return None, ("invalid_scan", reason)
        try:
            normalize_frame(msg.frame_id)
        except TfError as exc:
            return None, ("tf_error", f"LaserScan on {topic}: {exc}")
        return msg, None

    def _room_for_robot(self) -> bool:
        """Whether another robot may be tracked (caller holds `_lock`): below MAX_ROBOTS, or after
        forgetting one with no scan waiting (all it holds is its seq counters for messages without
        an attachment), so robots that came and went do not lock new ones out."""
        if len(self._robots) < MAX_ROBOTS:
            return True
        idle = next((rid for rid, r in self._robots.items() if not r.pending), None)
        if idle is None:
            return False
        del self._robots[idle]
        return True

    def _on_token(self, sample: zenoh.Sample) -> None:
        """A LaserScan publisher's graph token appeared (PUT) or went (DELETE: undeclared, or its
        node's Zenoh session gone): its robot is online while it has one."""
        try:
            key = str(sample.key_expr)
            parsed = publisher_of_token(key)
            if parsed is None or parsed[0] != self.domain_id:
                return
            robot_id = robot_id_for(parsed[1])
            if not is_valid_id(robot_id):
                return  # its scans are refused as invalid_topic
            present = sample.kind == zenoh.SampleKind.PUT
            with self._lock:  # held across set_online: a robot's PUT and DELETE reach it in order
                if present:
                    if key in self._publisher_tokens or len(self._publisher_tokens) >= MAX_PUBLISHER_TOKENS:
                        return
                    self._publisher_tokens[key] = robot_id
                    self._alive[robot_id] += 1
                    changed = self._alive[robot_id] == 1
                else:
                    if self._publisher_tokens.pop(key, None) is None:
                        return
                    self._alive[robot_id] -= 1
                    changed = self._alive[robot_id] == 0
                    if changed:
                        del self._alive[robot_id]
                self._count_publisher(parsed[1], laser_scan.ROS_TYPE, key, present)
                unshown = self.registry.set_online(self.map_id, robot_id, present) if changed else None
            if changed:  # any peer can declare tokens: rate-limited, as the native ingest's
                state = "online" if present else "offline"
                shown = f", but not on its map: {unshown}" if unshown else ""  # as the native ingest's
                publisher = f"LaserScan publisher on {parsed[1]}"
                self._alive_log.log(
                    logging.INFO, f"{state}:{robot_id}",
                    f"ROS robot {self.map_id}/{robot_id} is {state} ({publisher}){shown}",
                    map_id=self.map_id, robot_id=robot_id,
                )  # fmt: skip
        except Exception:
            log.exception("unexpected error handling a ROS graph token %s", sample.key_expr)

    def _on_tf_token(self, sample: zenoh.Sample) -> None:
        """A TFMessage publisher's graph token appeared or went: counted for the subscription of its
        topic the graph shows (`tf` and `tf_static` topics only: others are not TF)."""
        try:
            key = str(sample.key_expr)
            parsed = publisher_of_token(key)
            if parsed is None or parsed[0] != self.domain_id:
                return
            if parsed[1].rpartition("/")[2] not in (TF_TOPIC_NAME, TF_STATIC_TOPIC_NAME):
                return
            present = sample.kind == zenoh.SampleKind.PUT
            with self._lock:
                if present:
                    if (
                        key in self._tf_publisher_tokens
                        or len(self._tf_publisher_tokens) >= MAX_PUBLISHER_TOKENS
                    ):
                        return
                    self._tf_publisher_tokens.add(key)
                elif key in self._tf_publisher_tokens:
                    self._tf_publisher_tokens.discard(key)
                else:
                    return
                self._count_publisher(parsed[1], tf_message.ROS_TYPE, key, present)
        except Exception:
            log.exception("unexpected error handling a ROS graph token %s", sample.key_expr)

    def _count_publisher(self, topic: str, ros_type: str, token: str, present: bool) -> None:
        """Count a publisher of `topic` (of `ros_type`) come (`present`) or gone, for the subscription
        of the topic the graph shows while it has one; wakes the thread, which declares and undeclares
        those tokens, when its first came or its last went (caller holds `_lock`)."""
        publishers, type_hash = self._graph_topics.get((topic, ros_type), (0, ""))
        if present:
            type_hash = type_hash or type_hash_of_token(token) or TYPE_HASHES[ros_type]
            self._graph_topics[topic, ros_type] = (publishers + 1, type_hash)
        elif publishers > 1:
            self._graph_topics[topic, ros_type] = (publishers - 1, type_hash)
        else:
            self._graph_topics.pop((topic, ros_type), None)
        if publishers == 0 or (not present and publishers == 1):
            self._graph_changed = True
            self._wake.set()

    def _mark_online(self, robot_id: str) -> None:
        """After a scan of `robot_id` was submitted: if a publisher of it is alive, make sure the
        robot shows online (its map, or its robot state, may have been created after the token
        appeared, as the native ingest does)."""
        with self._lock:  # held: a token DELETE cannot slip in between
            if robot_id in self._alive:
                self.registry.mark_online(self.map_id, robot_id)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        with contextlib.suppress(Exception):  # an error reply (no cache) is no TF
            sample = reply.ok
            if sample is not None:
                self._on_tf(sample)

    def _on_tf(self, sample: zenoh.Sample) -> None:
        try:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            self._handle_tf(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:
            log.exception("unexpected error handling a ROS TF sample on %s", sample.key_expr)

    def _handle_tf(self, key: str, payload: bytes) -> None:
        topic_key = parse_topic_key(key)
        if topic_key is None or topic_key.ros_type != tf_message.ROS_TYPE:
            return
        namespace, _, name = topic_key.topic.rpartition("/")
        if name not in (TF_TOPIC_NAME, TF_STATIC_TOPIC_NAME):
            return  # a TFMessage on another topic is not TF
        try:
            transforms = decode_tf_message(payload)
        except CdrError as exc:
            with self._lock:
                self.tf_refused += 1
            self._log.warning(
                f"ros-tf:{namespace}", f"undecodable TFMessage on {topic_key.topic[:200]}: {exc}"
            )
            return
        refused: list[str] = []
        with self._tf_lock:
            tree = self._trees.pop(namespace, None)
            if tree is None:
                if len(self._trees) >= MAX_TREES and not self._forget_a_tree():
                    refused.append(
                        f"already {MAX_TREES} TF namespaces, each with a tf or tf_static publisher "
                        f"alive; {namespace[:80]!r} ignored"
                    )
                else:
                    tree = TfBuffer()
            if tree is not None:
                self._trees[namespace] = tree  # (last: the trees in the order they were last heard)
                for t in transforms:
                    try:
                        tree.add(t, static=name == TF_STATIC_TOPIC_NAME)
                    except TfError as exc:
                        refused.append(str(exc))
        with self._lock:
            self.tf_messages += 1
            self.tf_refused += len(refused) if tree is not None else len(transforms)
        if refused:
            self._log.warning(
                f"ros-tf:{namespace}",
                f"refused {len(refused)} transform(s) on {topic_key.topic}: {refused[0]}",
            )
        self._wake.set()

    def _forget_a_tree(self) -> bool:
        """Make room for one more TF tree: forget the tree heard from least recently of a namespace
        none of whose `tf` and `tf_static` publishers is alive (its robot gone, renamed or replaced);
        False when every tree has one. Robots come and go under new namespaces for the service's
        whole life: kept for good, the trees of those gone refused every later robot's TF once 64
        namespaces had ever published. (Caller holds `_tf_lock`; `_lock` is taken inside it, the
        one order they nest in.)"""
        with self._lock:
            publishing = {
                topic.rpartition("/")[0]
                for topic, ros_type in self._graph_topics
                if ros_type == tf_message.ROS_TYPE
            }
        gone = next((namespace for namespace in self._trees if namespace not in publishing), None)
        if gone is None:
            return False
        del self._trees[gone]
        return True

    # -- the fleetmap-ros thread -----------------------------------------------------------------

    def _run(self) -> None:
        timeout: float | None = None
        while True:
            self._wake.wait(timeout)
            self._wake.clear()  # before the pass: a wake-up during it makes another pass
            if self._stop:
                return
            try:
                timeout = self._pass()
                self._sync_subscription_tokens()
            except Exception:  # a bug must not end the thread: every later scan would wait forever
                log.exception("unexpected error posing ROS scans")
                timeout = 0.1

    def _sync_subscription_tokens(self) -> None:
        """Declare the graph token of a subscription of each LaserScan, `tf` and `tf_static` topic
        that has a publisher, and undeclare those of topics whose publishers are all gone (on the
        `fleetmap-ros` thread: a declaration may wait on the session, which Zenoh's callbacks must
        not)."""
        node = self._graph_node
        if node is None:
            return
        with self._lock:
            if not self._graph_changed:
                return
            self._graph_changed = False
            wanted = dict(self._graph_topics)
        for gone in [t for t in self._subscription_tokens if t not in wanted]:
            with contextlib.suppress(zenoh.ZError):
                self._subscription_tokens.pop(gone).undeclare()
        for (topic, ros_type), (_, type_hash) in wanted.items():
            if (topic, ros_type) in self._subscription_tokens or self._stop:
                continue
            if ros_type == laser_scan.ROS_TYPE:
                qos = SCAN_SUBSCRIPTION_QOS
            elif topic.rpartition("/")[2] == TF_STATIC_TOPIC_NAME:
                qos = TF_STATIC_SUBSCRIPTION_QOS
            else:
                qos = TF_SUBSCRIPTION_QOS
            self._next_entity_id += 1
            key = node.subscription_token(
                self._next_entity_id, topic, dds_type_name(ros_type), type_hash, qos
            )
            with contextlib.suppress(zenoh.ZError):  # the session closing: nothing to show any more
                self._subscription_tokens[topic, ros_type] = self.session.liveliness().declare_token(key)

    def _pass(self) -> float | None:
        """Pose, submit or drop what each robot's queue holds, in order; the seconds until the
        earliest deadline of a scan still waiting (None: nothing waits)."""
        with self._lock:
            robots = [(rid, r) for rid, r in self._robots.items() if r.pending]
        next_deadline: float | None = None
        for robot_id, robot in robots:
            while True:
                with self._lock:
                    if not robot.pending:
                        break
                    item = robot.pending[0]
                # Handed on (submitted or refused) before it leaves the queue: while the robot's queue
                # is not empty, a refusal in `_handle_scan` queues behind it (see there).
                if item.refusal is not None:
                    kind, reason = item.refusal
                    self._refuse(kind, robot_id, reason, item.scan_id)
                    self._pop(robot)
                    continue
                msg = item.msg
                assert msg is not None  # only a refused scan has none
                now = time.monotonic()
                try:
                    wire = self._pose(item)
                except TfPending as exc:
                    if now < item.deadline:
                        if not item.waited:
                            item.waited = True
                            with self._lock:
                                self.scans_waited_for_tf += 1
                        if next_deadline is None or item.deadline < next_deadline:
                            next_deadline = item.deadline
                        break
                    reason = (
                        f"no TF for the scan at {msg.stamp:.3f} ({self.fixed_frame} -> "
                        f"{msg.frame_id}) within {self.tf_timeout:g} s: {exc}"
                    )
                    self._refuse("no_tf", robot_id, reason, item.scan_id)
                except TfError as exc:
                    reason = f"scan at {msg.stamp:.3f} not posed: {exc}"
                    self._refuse("tf_error", robot_id, reason, item.scan_id)
                except (ScanError, codec.DecodeError) as exc:
                    self._refuse("invalid_scan", robot_id, f"invalid LaserScan: {exc}", item.scan_id)
                except Exception as exc:  # a bug: drop the scan, or it would block its robot for good
                    self._log.error(
                        f"ros-bug:{type(exc).__name__}", "unexpected error posing a ROS scan", exc
                    )
                    reason = f"not posed: internal error {type(exc).__name__}"
                    self._refuse("invalid_scan", robot_id, reason, item.scan_id)
                else:
                    self._submit(robot_id, wire)
                self._pop(robot)
        return None if next_deadline is None else max(0.0, next_deadline - time.monotonic())

    def _pop(self, robot: _Robot) -> None:
        with self._lock:
            robot.pending.popleft()
            self._waiting -= 1

    def _pose(self, item: _Pending) -> WireScan:
        """The scan as fleetmap integrates it, posed by TF; raises TfPending, TfError, ScanError,
        DecodeError."""
        msg = item.msg
        assert msg is not None  # only a refused scan has none
        with self._tf_lock:
            tree, announced = self._tree_for(item.namespace)
            if tree is None and normalize_frame(msg.frame_id) == normalize_frame(self.fixed_frame):
                tree = TfBuffer()  # a scan in the fixed frame needs no TF: the identity (`lookup`)
            if tree is None and announced is not None:
                raise TfPending(
                    f"no TF received yet on {announced}/tf or {announced}/tf_static, whose publisher the "
                    "ROS graph shows"
                )
            if tree is None:
                where = f"{item.namespace}/tf" if item.namespace else "/tf"
                raise TfPending(f"no TF received on {where}, a parent namespace's tf or /tf")
            transform = tree.lookup(self.fixed_frame, msg.frame_id, msg.stamp)
        pose = sensor_pose_2d(transform)
        sign = -1.0 if pose.mirrored else 1.0  # upside down: beam i at -(angle_min + i * increment)
        scan = Scan.from_fan(
            (pose.x, pose.y, pose.theta),
            sign * msg.angle_min,
            sign * msg.angle_increment,
            msg.ranges,
            msg.range_min,
            msg.range_max,
        )
        return self.registry.input_limits.check(WireScan(item.seq, msg.stamp, scan, item.session))

    def _tree_for(self, namespace: str) -> tuple[TfBuffer | None, str | None]:
        """The TF tree a scan of `namespace` (`/robot1/front`, or '' for the root) is posed in
        (caller holds `_tf_lock`): that of the namespace itself or, failing that, of its nearest
        parent that published TF (`/robot1/front/scan` posed by `/robot1/tf`: a robot's lasers in
        sub-namespaces share its tree), else the root tree; None when there is none yet. Also None
        when, on the way up, a namespace that has no tree yet has a `tf` or `tf_static` publisher in
        the ROS graph (`_graph_topics`): its TF is coming, and its robot's scans wait for it (the
        second value names that namespace, else None). A laser driver often sends scans before its
        robot's TF publishers send anything, and a parent's or the root tree is another robot's
        there: in a fleet where a robot without a namespace names its frames as the namespaced ones
        do (`map`, `laser` on `/tf`), the root tree posed a namespaced robot's first scans at that
        robot's laser, and they were integrated there."""
        level = namespace
        while level:
            tree = self._trees.get(level)
            if tree is not None:
                return tree, None
            if self._publishes_tf(level):
                return None, level
            level = level.rpartition("/")[0]
        return self._trees.get(""), None

    def _publishes_tf(self, namespace: str) -> bool:
        """Whether the ROS graph shows a publisher of `namespace`'s `tf` or `tf_static` topic (the
        caller holds `_tf_lock`: `_lock` is taken inside it, the one order they nest in)."""
        with self._lock:
            return any(
                (f"{namespace}/{name}", tf_message.ROS_TYPE) in self._graph_topics
                for name in (TF_TOPIC_NAME, TF_STATIC_TOPIC_NAME)
            )

    def _submit(self, robot_id: str, wire: WireScan) -> None:
        try:
            self.registry.submit(self.map_id, robot_id, wire)
        except IngestRejected as exc:
            kind = exc.kind
            with self._lock:
                self.refused[kind] += 1
            message = f"ROS scan seq {wire.seq} of {self.map_id}/{robot_id}: {exc.reason}"
            self._log.warning(
                f"ros-{kind}:{robot_id}", message, map_id=self.map_id, robot_id=robot_id, seq=wire.seq
            )
            return
        except InvalidId:  # robot_id_for's ids are checked; kept for safety
            return
        with self._lock:
            self.scans_submitted += 1
        self._mark_online(robot_id)

    # -- reporting -------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """A JSON-able summary for `GET /healthz` (`zenoh.ros`)."""
        with self._tf_lock:
            trees = {ns or "/": {"frames": t.frames, "samples": t.samples} for ns, t in self._trees.items()}
        with self._lock:
            return {
                "map_id": self.map_id,
                "domain_id": self.domain_id,
                "fixed_frame": self.fixed_frame,
                "scans_received": self.scans_received,
                "scans_submitted": self.scans_submitted,
                "scans_waited_for_tf": self.scans_waited_for_tf,
                "scans_waiting": self._waiting,
                "refused": dict(self.refused),
                "laser_publishers": len(self._publisher_tokens),
                "robots_online": len(self._alive),
                "tf_messages": self.tf_messages,
                "tf_refused": self.tf_refused,
                "tf_trees": dict(list(trees.items())[:MAX_TREES]),
            }


__all__ = ["MAX_PENDING", "TF_TIMEOUT", "RosScanIngest", "robot_id_for", "session_from_gid"]
