"""LaserScan and TFMessage decoding (fleetmap.ros.laser_scan, tf_message) against rosbags, an
independent CDR encoder: random messages decode to their fields, both byte orders, and truncated or
garbage payloads only ever raise CdrError."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from fleetmap.ros.cdr import CdrError
from fleetmap.ros.laser_scan import LaserScanMsg, decode_laser_scan, encode_laser_scan
from fleetmap.ros.tf_message import TransformStamped, decode_tf_message, encode_tf_message

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
f32 = st.floats(width=32, allow_nan=False)
f64 = st.floats(allow_nan=False, allow_infinity=False)
names = st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=12)
secs = st.integers(-(2**31), 2**31 - 1)
nsecs = st.integers(0, 999_999_999)


def header(sec: int, nanosec: int, frame: str) -> object:
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame
    )


@st.composite
def ros_laser_scans(draw: st.DrawFn) -> object:
    n = draw(st.integers(0, 30))
    return T["sensor_msgs/msg/LaserScan"](
        header=header(draw(secs), draw(nsecs), draw(names)),
        angle_min=draw(f32), angle_max=draw(f32), angle_increment=draw(f32), time_increment=draw(f32),
        scan_time=draw(f32), range_min=draw(f32), range_max=draw(f32),
        ranges=np.array(draw(st.lists(st.floats(width=32), min_size=n, max_size=n)), dtype=np.float32),
        intensities=np.array(draw(st.lists(f32, max_size=n)), dtype=np.float32),
    )  # fmt: skip


@settings(max_examples=100, deadline=None)
@given(ros_laser_scans(), st.booleans())
def test_laser_scan_decodes_what_rosbags_encodes(m: object, little: bool) -> None:
    payload = bytes(TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan", little_endian=little))
    got = decode_laser_scan(payload)
    assert (got.sec, got.nanosec, got.frame_id) == (
        m.header.stamp.sec,
        m.header.stamp.nanosec,
        m.header.frame_id,
    )  # type: ignore[attr-defined]
    for name in (
        "angle_min",
        "angle_max",
        "angle_increment",
        "time_increment",
        "scan_time",
        "range_min",
        "range_max",
    ):
        assert getattr(got, name) == getattr(m, name), name
    np.testing.assert_array_equal(got.ranges, m.ranges)  # type: ignore[attr-defined]
    assert got.ranges.dtype == np.float32
    if little:  # and our encoder writes the same bytes
        assert encode_laser_scan(got, m.intensities) == payload  # type: ignore[attr-defined]


@st.composite
def ros_tf_messages(draw: st.DrawFn) -> object:
    transforms = []
    for _ in range(draw(st.integers(0, 5))):
        transforms.append(
            T["geometry_msgs/msg/TransformStamped"](
                header=header(draw(secs), draw(nsecs), draw(names)),
                child_frame_id=draw(names),
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=draw(f64), y=draw(f64), z=draw(f64)),
                    rotation=T["geometry_msgs/msg/Quaternion"](
                        x=draw(f64), y=draw(f64), z=draw(f64), w=draw(f64)
                    ),
                ),
            )
        )
    return T["tf2_msgs/msg/TFMessage"](transforms=transforms)


@settings(max_examples=100, deadline=None)
@given(ros_tf_messages(), st.booleans())
def test_tf_message_decodes_what_rosbags_encodes(m: object, little: bool) -> None:
    payload = bytes(TS.serialize_cdr(m, "tf2_msgs/msg/TFMessage", little_endian=little))
    got = decode_tf_message(payload)
    assert len(got) == len(m.transforms)  # type: ignore[attr-defined]
    for g, w in zip(got, m.transforms, strict=True):  # type: ignore[attr-defined]
        assert g.stamp == w.header.stamp.sec + w.header.stamp.nanosec * 1e-9
        assert (g.parent, g.child) == (w.header.frame_id, w.child_frame_id)
        tr, rot = w.transform.translation, w.transform.rotation
        assert g.translation == (tr.x, tr.y, tr.z) and g.rotation == (rot.x, rot.y, rot.z, rot.w)


def test_our_tf_encoder_is_what_rosbags_reads() -> None:
    t = TransformStamped(
        1700000000.25, "odom", "base_link", (1.0, -2.0, 0.5), (0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5))
    )
    m = TS.deserialize_cdr(encode_tf_message([t, t]), "tf2_msgs/msg/TFMessage")
    assert len(m.transforms) == 2
    w = m.transforms[1]
    assert (w.header.stamp.sec, w.header.stamp.nanosec) == (1700000000, 250_000_000)
    assert (w.header.frame_id, w.child_frame_id) == ("odom", "base_link")
    assert w.transform.rotation.z == pytest.approx(math.sqrt(0.5))


def test_truncations_and_absurd_counts_are_cdr_errors() -> None:
    scan = LaserScanMsg(1, 2, "laser", -1.0, 1.0, 0.5, 0.0, 0.1, 0.1, 10.0, np.arange(5, dtype=np.float32))
    tf = encode_tf_message([TransformStamped(1.0, "odom", "base", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))])
    for payload, decode in ((encode_laser_scan(scan), decode_laser_scan), (tf, decode_tf_message)):
        for cut in range(len(payload) - 3):
            with pytest.raises(CdrError):
                decode(payload[:cut])
        with pytest.raises(CdrError, match="after the end"):
            decode(payload + bytes(16))
    huge = b"\x00\x01\x00\x00" + (10**6).to_bytes(4, "little") + bytes(100)
    with pytest.raises(CdrError):
        decode_tf_message(huge)
    many = encode_tf_message([TransformStamped(1.0, "a", "b", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))] * 20)
    with pytest.raises(CdrError, match="limit"):
        decode_tf_message(many, max_transforms=10)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_garbage_only_raises_cdr_error(data: bytes) -> None:
    for decode in (decode_laser_scan, decode_tf_message):
        with contextlib.suppress(CdrError):
            decode(b"\x00\x01\x00\x00" + data)
