"""What rmw_zenoh (ROS 2's Zenoh middleware) puts on the wire around a message.

Checked against ros2/rmw_zenoh (rmw_zenoh_cpp/src/detail/liveliness_utils.cpp `TopicInfo`,
rmw_publisher_data.cpp, attachment_helpers.cpp; docs/design.md):

- **Data key expression**: `<domain_id>/<topic>/<dds type name>/<type hash>`, the topic's leading
  and trailing `/` stripped and its inner `/` kept (only liveliness tokens mangle `/` to `%`):
  `0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c1...`. Jazzy and later put the
  type's RIHS01 hash; Humble's backport `TypeHashNotSupported`. Subscribe with `*` for the hash.
- **Payload**: the message in CDR with its 4-byte encapsulation header (`fleetmap.ros.cdr`).
- **Attachment**: zenoh-ext serialization of `(int64 sequence_number, int64 source_timestamp,
  uint8[16] source_gid)`: 8 + 8 bytes little-endian, then the gid as a sequence (LEB128 length
  16, the bytes): 33 bytes. Older releases wrote each value after its name as a string
  (`"sequence_number"`, ...). `decode_attachment` reads both; `encode_attachment` writes the new one.
  The gid is a hash of the publisher's liveliness token, which holds its session's Zenoh id, so a
  restarted node publishes with a new gid.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

#: RIHS01 type hashes of the messages fleetmap reads or writes, as Jazzy (and Kilted, Rolling) put
#: them in key expressions. tests/test_ros_rmw_zenoh.py checks them against rosbags' own hashing.
TYPE_HASHES: dict[str, str] = {
    "sensor_msgs/msg/LaserScan": "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "nav_msgs/msg/OccupancyGrid": "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    "map_msgs/msg/OccupancyGridUpdate": (
        "RIHS01_c4095b0be2e4363f8978a1570e0293ee093436f1e1c61d99b48502ac317025e8"
    ),
}
#: What Humble's rmw_zenoh puts where the type hash goes.
HUMBLE_TYPE_HASH = "TypeHashNotSupported"

_NAME = r"[A-Za-z][A-Za-z0-9_]*"
_ROS_TYPE = re.compile(rf"^({_NAME})/({_NAME})/({_NAME})$")
_DDS_TYPE = re.compile(rf"^({_NAME})::({_NAME})::dds_::({_NAME})_$")
_TOPIC_SEGMENT = re.compile(r"^[A-Za-z0-9_]+$")
_HASH = re.compile(r"^[A-Za-z0-9_]+$")
#: The largest ROS domain id fleetmap takes (`--ros-domain`): its key chunk has up to 10 digits.
MAX_DOMAIN_ID = 2**32 - 1


def dds_type_name(ros_type: str) -> str:
    """`sensor_msgs/msg/LaserScan` -> `sensor_msgs::msg::dds_::LaserScan_` (ValueError if malformed)."""
    m = _ROS_TYPE.match(ros_type)
    if m is None:
        raise ValueError(f"not a ROS type name 'package/msg/Name': {ros_type!r}")
    return f"{m[1]}::{m[2]}::dds_::{m[3]}_"


def ros_type_name(dds_type: str) -> str | None:
    """The inverse of `dds_type_name`, or None if `dds_type` is not one."""
    m = _DDS_TYPE.match(dds_type)
    return None if m is None else f"{m[1]}/{m[2]}/{m[3]}"


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression rmw_zenoh publishes `topic` on (leading/trailing `/` stripped). `type_hash`
    may be `*` to subscribe to every hash (Humble's and later distributions' alike)."""
    if domain_id < 0:
        raise ValueError(f"domain id must be >= 0, got {domain_id}")
    name = topic.strip("/")
    if not name or "//" in name:
        raise ValueError(f"not a ROS topic name: {topic!r}")
    return f"{domain_id}/{name}/{dds_type_name(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class TopicKey:
    """A parsed data key expression: `topic` fully qualified (`/robot1/scan`), `ros_type` as ROS
    writes it (`sensor_msgs/msg/LaserScan`)."""

    domain_id: int
    topic: str
    ros_type: str
    type_hash: str


def parse_topic_key(key: str) -> TopicKey | None:
    """Parse `<domain>/<topic...>/<dds type>/<hash>`; None if `key` is not such a key."""
    parts = key.split("/")
    # Any domain `--ros-domain` takes, 4294967295 (10 digits) too; the length bounds int()'s work.
    if len(parts) < 4 or not (parts[0].isascii() and parts[0].isdigit()) or len(parts[0]) > 10:
        return None
    if int(parts[0]) > MAX_DOMAIN_ID:
        return None
    ros_type = ros_type_name(parts[-2])
    if ros_type is None or not _HASH.match(parts[-1]):
        return None
    segments = parts[1:-2]
    if not all(_TOPIC_SEGMENT.match(s) for s in segments):
        return None
    return TopicKey(int(parts[0]), "/" + "/".join(segments), ros_type, parts[-1])


@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh's per-message metadata: the publisher's sequence number (from 1), its send time in
    ns since the epoch, and its gid (16 bytes, Humble's rmw_zenoh too)."""

    sequence_number: int
    source_timestamp: int
    source_gid: bytes


_MAX_GID = 64  # rmw_zenoh's gids are 16 bytes (Humble's too); anything far beyond is not an attachment


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """A LEB128 length as zenoh-ext writes sequence and string lengths; (value, new pos)."""
    value = shift = 0
    while True:
        if pos >= len(data) or shift > 63:
            raise ValueError("bad length")
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7


def _bytes(data: bytes, pos: int) -> tuple[bytes, int]:
    n, pos = _varint(data, pos)
    if n > _MAX_GID or pos + n > len(data):
        raise ValueError("bad bytes")
    return data[pos : pos + n], pos + n


def _i64(data: bytes, pos: int) -> tuple[int, int]:
    if pos + 8 > len(data):
        raise ValueError("short")
    return struct.unpack_from("<q", data, pos)[0], pos + 8


_KEYS = ("sequence_number", "source_timestamp", "source_gid")


def _decode_keyed(data: bytes) -> Attachment | None:
    values: dict[str, int | bytes] = {}
    pos = 0
    while pos < len(data):
        raw, pos = _bytes(data, pos)
        name = raw.decode("ascii", "replace")
        if name not in _KEYS or name in values:
            return None
        if name == "source_gid":
            values[name], pos = _bytes(data, pos)
        else:
            values[name], pos = _i64(data, pos)
    if set(values) != set(_KEYS):
        return None
    seq, stamp, gid = values["sequence_number"], values["source_timestamp"], values["source_gid"]
    assert isinstance(seq, int) and isinstance(stamp, int) and isinstance(gid, bytes)
    return Attachment(seq, stamp, gid)


def decode_attachment(data: bytes) -> Attachment | None:
    """The attachment of an rmw_zenoh message, in the current layout or the older one with key
    strings; None if `data` is neither (a missing or foreign attachment is not an error)."""
    try:
        if data[:1] == b"\x0f" and data[1:16] == b"sequence_number":
            return _decode_keyed(data)
        seq, pos = _i64(data, 0)
        stamp, pos = _i64(data, pos)
        gid, pos = _bytes(data, pos)
        if pos != len(data) or not gid:
            return None
        return Attachment(seq, stamp, gid)
    except ValueError:
        return None


def encode_attachment(a: Attachment) -> bytes:
    """The current rmw_zenoh layout (33 bytes for a 16-byte gid)."""
    if len(a.source_gid) > 127:
        raise ValueError("gid too long")
    return struct.pack("<qqB", a.sequence_number, a.source_timestamp, len(a.source_gid)) + a.source_gid


__all__ = [
    "HUMBLE_TYPE_HASH",
    "TYPE_HASHES",
    "Attachment",
    "TopicKey",
    "dds_type_name",
    "decode_attachment",
    "encode_attachment",
    "parse_topic_key",
    "ros_type_name",
    "topic_key",
]
