"""rmw_zenoh's key expressions and attachments (fleetmap.ros.rmw_zenoh): the layouts rmw_zenoh_cpp
writes (liveliness_utils.cpp `TopicInfo`, attachment_helpers.cpp), the type hashes as rosbags
computes them, and zenoh-ext's own serializer as an independent encoder of attachments."""

from __future__ import annotations

import struct

import pytest
import zenoh.ext
from hypothesis import given
from hypothesis import strategies as st
from ros_types import TYPESTORE

from fleetmap.ros.rmw_zenoh import (
    TYPE_HASHES,
    Attachment,
    TopicKey,
    dds_type_name,
    decode_attachment,
    encode_attachment,
    parse_topic_key,
    topic_key,
)

LASER_HASH = "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"


def test_type_hashes_are_rosbags_jazzy_hashes() -> None:
    assert set(TYPE_HASHES) == {
        "sensor_msgs/msg/LaserScan",
        "tf2_msgs/msg/TFMessage",
        "nav_msgs/msg/OccupancyGrid",
        "map_msgs/msg/OccupancyGridUpdate",
    }
    for ros_type, type_hash in TYPE_HASHES.items():
        assert TYPESTORE.hash_rihs01(ros_type) == type_hash
    # As `ros2 topic info -v` prints it for RViz's subscription of a costmap's `_updates` topic on Jazzy.
    assert TYPE_HASHES["map_msgs/msg/OccupancyGridUpdate"].startswith("RIHS01_c4095b0be2e4363f")


def test_dds_type_name() -> None:
    assert dds_type_name("sensor_msgs/msg/LaserScan") == "sensor_msgs::msg::dds_::LaserScan_"
    assert dds_type_name("tf2_msgs/msg/TFMessage") == "tf2_msgs::msg::dds_::TFMessage_"
    for bad in ("LaserScan", "sensor_msgs/LaserScan", "a/b/c/d", "a/msg/"):
        with pytest.raises(ValueError):
            dds_type_name(bad)


def test_topic_key_keeps_inner_slashes_and_strips_the_outer_ones() -> None:
    key = topic_key(0, "/robot1/scan", "sensor_msgs/msg/LaserScan", TYPE_HASHES["sensor_msgs/msg/LaserScan"])
    assert key == f"0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/{LASER_HASH}"
    assert topic_key(7, "/tf/", "tf2_msgs/msg/TFMessage", "*") == "7/tf/tf2_msgs::msg::dds_::TFMessage_/*"
    with pytest.raises(ValueError):
        topic_key(0, "/", "sensor_msgs/msg/LaserScan", "*")
    with pytest.raises(ValueError):
        topic_key(-1, "/scan", "sensor_msgs/msg/LaserScan", "*")


def test_parse_topic_key() -> None:
    key = f"0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/{LASER_HASH}"
    assert parse_topic_key(key) == TopicKey(0, "/robot1/scan", "sensor_msgs/msg/LaserScan", LASER_HASH)
    humble = "12/a/b/scan/sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported"
    assert parse_topic_key(humble) == TopicKey(
        12, "/a/b/scan", "sensor_msgs/msg/LaserScan", "TypeHashNotSupported"
    )
    assert parse_topic_key(topic_key(3, "/tf", "tf2_msgs/msg/TFMessage", "h")) == TopicKey(
        3, "/tf", "tf2_msgs/msg/TFMessage", "h"
    )
    highest = topic_key(2**32 - 1, "/scan", "sensor_msgs/msg/LaserScan", "h")  # `--ros-domain`'s largest
    assert parse_topic_key(highest) == TopicKey(2**32 - 1, "/scan", "sensor_msgs/msg/LaserScan", "h")
    for bad in (
        "4294967296/scan/sensor_msgs::msg::dds_::LaserScan_/h",
        "fleetmap/lab/r1/scan",
        "x/scan/sensor_msgs::msg::dds_::LaserScan_/h",
        "0/sensor_msgs::msg::dds_::LaserScan_/h",  # no topic
        "0/scan/LaserScan/h",
        "0/sc*an/sensor_msgs::msg::dds_::LaserScan_/h",
        "0/scan/sensor_msgs::msg::dds_::LaserScan_/@adv",
        "0/scan/sensor_msgs::msg::dds_::LaserScan_/h/@adv/pub/x",
    ):
        assert parse_topic_key(bad) is None, bad


GID = bytes(range(16))


def test_attachment_current_layout_is_zenoh_ext_serialization() -> None:
    a = Attachment(42, 1_700_000_000_123_456_789, GID)
    encoded = encode_attachment(a)
    # rmw_zenoh_cpp serializes int64 seq, int64 stamp, then std::array<uint8_t, 16> gid
    want = zenoh.ext.z_serialize(
        (zenoh.ext.Int64(42), zenoh.ext.Int64(1_700_000_000_123_456_789), GID)
    ).to_bytes()
    assert encoded == want and len(encoded) == 33
    assert decode_attachment(encoded) == a


def test_attachment_older_layout_with_key_strings() -> None:
    old = zenoh.ext.z_serialize(
        ("sequence_number", zenoh.ext.Int64(7), "source_timestamp", zenoh.ext.Int64(-5), "source_gid", GID)
    ).to_bytes()
    assert decode_attachment(old) == Attachment(7, -5, GID)


@given(st.binary(max_size=80))
def test_odd_attachments_are_none_not_errors(data: bytes) -> None:
    got = decode_attachment(data)
    assert got is None or isinstance(got, Attachment)


def test_malformed_attachments() -> None:
    assert decode_attachment(b"") is None
    assert decode_attachment(encode_attachment(Attachment(1, 2, GID))[:-1]) is None  # short gid
    assert decode_attachment(encode_attachment(Attachment(1, 2, GID)) + b"\x00") is None  # trailing byte
    assert decode_attachment(struct.pack("<qqB", 1, 2, 0)) is None  # empty gid
