"""rmw_zenoh's ROS graph: the liveliness tokens that make a node and its publishers visible.

ROS 2 with rmw_zenoh keeps a graph cache per process from liveliness tokens under
`@ros2_lv/<domain>/**`; `ros2 node list` and `ros2 topic list -v` read it. Data reaches a
subscriber without any token (it subscribes to the topic's data key expression, and drops only
samples without an attachment), so these tokens are what makes fleetmap *visible* as a node
publishing its topics with their QoS, not what makes it heard.

Token key expressions, as rmw_zenoh_cpp builds them (`Entity::Entity` in
rmw_zenoh_cpp/src/detail/liveliness_utils.cpp; the ids in rmw_node_data.cpp and
rmw_publisher_data.cpp):

    @ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>
    @ros2_lv/<domain>/<zid>/<nid>/<eid>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>
    @ros2_lv/<domain>/<zid>/<nid>/<eid>/MS/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>

(`MP` a publisher, `MS` a subscription.)

`<zid>` is the Zenoh session id as Zenoh prints it (`str(session.zid())`), `<nid>` the node's and
`<eid>` the entity's id within the session (rmw_zenoh counts them per context), each name part
mangled (`/` becomes `%`: the root namespace and enclave `/` are `%`, topic `/map` is `%map`), and
`<qos>` the QoS profile written by `qos_keyexpr`. Pure string work: no Zenoh here.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
NODE = "NN"
PUBLISHER = "MP"
SUBSCRIPTION = "MS"

# rmw/types.h enum values, as the QoS part of a token writes them.
RELIABILITY_RELIABLE, RELIABILITY_BEST_EFFORT = 1, 2
DURABILITY_TRANSIENT_LOCAL, DURABILITY_VOLATILE = 1, 2
HISTORY_KEEP_LAST, HISTORY_KEEP_ALL = 1, 2

#: The bytes of an rmw_zenoh gid, in every distribution: Humble's rmw_zenoh too hard-codes 16 where
#: Humble's RMW_GID_STORAGE_SIZE says 24 (ros2/rmw_zenoh#388), and its subscriptions read the
#: attachment's gid as a `std::array<uint8_t, 16>`, which zenoh-cpp's deserializer refuses for a
#: sequence of any other length: every sample with a 24-byte gid was dropped.
GID_SIZE = 16

_HASH_CHUNK = re.compile(r"^[A-Za-z0-9_]{1,128}$")


@dataclass(frozen=True)
class Qos:
    """The QoS policies a token states. Deadline, lifespan and liveliness are always rmw_zenoh's
    defaults here (infinite, infinite, automatic with an infinite lease)."""

    reliability: int = RELIABILITY_RELIABLE
    durability: int = DURABILITY_VOLATILE
    history: int = HISTORY_KEEP_LAST
    depth: int = 42


#: rmw_zenoh's default profile (`QoS::QoS` in rmw_zenoh_cpp/src/detail/qos.cpp): a policy equal to
#: it is left empty in a token.
RMW_ZENOH_DEFAULT_QOS = Qos()

#: What nav2's map_server publishes `/map` with (`rclcpp::QoS(1).transient_local().reliable()`), and
#: so what nav2's static layer and AMCL subscribe with.
MAP_QOS = Qos(RELIABILITY_RELIABLE, DURABILITY_TRANSIENT_LOCAL, HISTORY_KEEP_LAST, 1)
#: What `<map topic>_updates` is published with: RELIABLE and VOLATILE, as its readers subscribe
#: (RViz's Map display `rclcpp::QoS(5)`; nav2's static layer `SystemDefaultsQoS` in Humble and Jazzy,
#: `StandardTopicQoS` (KEEP_LAST 10) later: all reliable and volatile). Not TRANSIENT_LOCAL as
#: costmap_2d's: a node starting later would get the last update with the last grid and might apply
#: it on a newer grid, turning cells back. Depth 1: a volatile rmw_zenoh publisher keeps no cache, so
#: the depth only shows in the graph.
MAP_UPDATES_QOS = Qos(RELIABILITY_RELIABLE, DURABILITY_VOLATILE, HISTORY_KEEP_LAST, 1)
#: What fleetmap's LaserScan subscriptions state (`--ros-scans`): rclcpp's SensorDataQoS (best effort,
#: volatile, keep last 5), as nav2's costmaps and slam_toolbox subscribe to scans. A best-effort
#: volatile subscription is compatible with every publisher's QoS (`rmw_qos_profile_check_compatible`),
#: so rmw_zenoh counts it in every LaserScan publisher's `get_subscription_count()`.
SCAN_SUBSCRIPTION_QOS = Qos(RELIABILITY_BEST_EFFORT, DURABILITY_VOLATILE, HISTORY_KEEP_LAST, 5)
#: What fleetmap's subscriptions of `tf` and `tf_static` state: tf2_ros' TransformListener's
#: (tf2_ros/qos.hpp: DynamicListenerQoS, reliable, volatile, keep last 100; StaticListenerQoS,
#: reliable, transient local, keep last 100), as TF's publishers expect of a listener. Depth 1 is
#: StaticBroadcasterQoS's, the publisher's: a listener keeps the static transforms of every
#: broadcaster, so `ros2 topic info -v /tf_static` showed fleetmap as no listener is.
TF_SUBSCRIPTION_QOS = Qos(RELIABILITY_RELIABLE, DURABILITY_VOLATILE, HISTORY_KEEP_LAST, 100)
TF_STATIC_SUBSCRIPTION_QOS = Qos(RELIABILITY_RELIABLE, DURABILITY_TRANSIENT_LOCAL, HISTORY_KEEP_LAST, 100)


def mangle(name: str) -> str:
    """A ROS name as one key expression chunk: every `/` becomes `%` (`/map` -> `%map`)."""
    return name.replace("/", "%")


def publisher_of_token(token: str) -> tuple[int, str, str] | None:
    """(domain, topic, DDS type name) of a publisher's token (`MP`, see the module doc:
    `@ros2_lv/0/<zid>/0/3/MP/%/%robot1/driver/%robot1%scan/sensor_msgs::msg::dds_::LaserScan_/...` ->
    `(0, "/robot1/scan", "sensor_msgs::msg::dds_::LaserScan_")`); None for any other key (a node's,
    a subscription's, a service's token, or not a token at all)."""
    return _endpoint_of_token(token, PUBLISHER)


def subscription_of_token(token: str) -> tuple[int, str, str] | None:
    """(domain, topic, DDS type name) of a subscription's token (`MS`), as `publisher_of_token` reads
    a publisher's; None for any other key."""
    return _endpoint_of_token(token, SUBSCRIPTION)


def type_hash_of_token(token: str) -> str | None:
    """The type hash a publisher's or subscription's token states (its twelfth chunk: a RIHS01 hash,
    or Humble's `TypeHashNotSupported`), None if it has none that could stand in a key expression of
    fleetmap's own (letters, digits and `_` only)."""
    parts = token.split("/")
    if len(parts) < 13 or not _HASH_CHUNK.match(parts[11]):
        return None
    return parts[11]


def durability_of_token(token: str) -> int:
    """The durability a publisher's or subscription's token states (the second field of its QoS
    part, see `qos_keyexpr`): `DURABILITY_TRANSIENT_LOCAL`, or `DURABILITY_VOLATILE` (rmw_zenoh's
    default, written empty) for anything else."""
    qos = token.split("/")[12:13]
    fields = qos[0].split(":") if qos else []
    durability = fields[1] if len(fields) > 1 else ""
    return (
        DURABILITY_TRANSIENT_LOCAL if durability == str(DURABILITY_TRANSIENT_LOCAL) else DURABILITY_VOLATILE
    )


def endpoints_key(domain_id: int, kind: str, dds_type: str, topic: str | None = None) -> str:
    """The key expression of the tokens of every `kind` (`PUBLISHER`, `SUBSCRIPTION`) of `dds_type`
    in a domain, whatever their session, node and QoS: of `topic` only when given (absolute), else
    of every topic."""
    topic_chunk = "*" if topic is None else mangle(topic)
    return f"{ADMIN_SPACE}/{domain_id}/*/*/*/{kind}/*/*/*/{topic_chunk}/{mangle(dds_type)}/**"


def _endpoint_of_token(token: str, kind: str) -> tuple[int, str, str] | None:
    parts = token.split("/")
    if len(parts) < 12 or parts[0] != ADMIN_SPACE or parts[5] != kind or not parts[1].isdigit():
        return None
    topic = parts[9].replace("%", "/")
    if not topic.startswith("/"):
        return None
    return int(parts[1]), topic, parts[10]


def qos_keyexpr(qos: Qos) -> str:
    """The QoS part of a token, `<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:
    <lifespan s>,<ns>:<liveliness>,<lease s>,<ns>`, each value left empty when it is rmw_zenoh's
    default (`qos_to_keyexpr`): `MAP_QOS` is `:1:,1:,:,:,,`."""
    default = RMW_ZENOH_DEFAULT_QOS

    def part(value: int, default_value: int) -> str:
        return "" if value == default_value else str(value)

    reliability = part(qos.reliability, default.reliability)
    durability = part(qos.durability, default.durability)
    history = f"{part(qos.history, default.history)},{part(qos.depth, default.depth)}"
    # Deadline, lifespan (sec,nsec) and liveliness (kind,sec,nsec): all defaults, all empty.
    return f"{reliability}:{durability}:{history}:,:,:,,"


@dataclass(frozen=True)
class RosNode:
    """A ROS node on one Zenoh session: what every token of it starts with."""

    domain_id: int
    zid: str  # str(session.zid())
    node_id: int
    name: str = "fleetmap"
    namespace: str = "/"
    enclave: str = "/"

    def _prefix(self, entity_id: int, kind: str) -> str:
        return "/".join(
            [
                ADMIN_SPACE, str(self.domain_id), self.zid, str(self.node_id), str(entity_id), kind,
                mangle(self.enclave), mangle(self.namespace), mangle(self.name),
            ]
        )  # fmt: skip

    def node_token(self) -> str:
        """The node's token (`NN`; its entity id is its node id, as in rmw_node_data.cpp)."""
        return self._prefix(self.node_id, NODE)

    def publisher_token(self, entity_id: int, topic: str, dds_type: str, type_hash: str, qos: Qos) -> str:
        """The token of this node's publisher `entity_id` of `topic` (absolute, `/map`), whose type is
        `dds_type` (`nav_msgs::msg::dds_::OccupancyGrid_`) with `type_hash`, published with `qos`."""
        return self._endpoint_token(PUBLISHER, entity_id, topic, dds_type, type_hash, qos)

    def subscription_token(self, entity_id: int, topic: str, dds_type: str, type_hash: str, qos: Qos) -> str:
        """The token of this node's subscription `entity_id`, as `publisher_token` for a publisher."""
        return self._endpoint_token(SUBSCRIPTION, entity_id, topic, dds_type, type_hash, qos)

    def _endpoint_token(
        self, kind: str, entity_id: int, topic: str, dds_type: str, type_hash: str, qos: Qos
    ) -> str:
        parts = [mangle(topic), mangle(dds_type), mangle(type_hash), qos_keyexpr(qos)]
        return "/".join([self._prefix(entity_id, kind), *parts])


def entity_gid(token: str) -> bytes:
    """The gid (`GID_SIZE` bytes) a publisher puts in each sample's attachment (`source_gid`),
    derived from its token so that it is stable and unique. rmw_zenoh hashes the token with
    XXH3-128; this uses BLAKE2b (hashlib: no dependency). A subscriber passes it on to the
    application (`rmw_message_info_t.publisher_gid`), where rclcpp compares it only with its own
    process's publishers (intra-process delivery), which a gid of fleetmap never equals; the graph
    cache computes its own gids from the tokens."""
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()
