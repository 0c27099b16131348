"""CDR reader and writer (fleetmap.ros.cdr) against rosbags, an independent CDR implementation:
messages written here are byte for byte what rosbags writes, rosbags' bytes read back field by
field, and truncated or garbage payloads only ever raise CdrError."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from fleetmap.ros.cdr import CdrError, CdrReader, CdrWriter

TS = get_typestore(Stores.ROS2_JAZZY)
LaserScanMsg = TS.types["sensor_msgs/msg/LaserScan"]
Header = TS.types["std_msgs/msg/Header"]
Time = TS.types["builtin_interfaces/msg/Time"]

f32 = st.floats(width=32, allow_nan=False)
names = st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=20)


@st.composite
def laser_scans(draw: st.DrawFn) -> object:
    n = draw(st.integers(0, 40))
    ranges = np.array(draw(st.lists(st.floats(width=32), min_size=n, max_size=n)), dtype=np.float32)
    intens = np.array(draw(st.lists(f32, max_size=5)), dtype=np.float32)
    return LaserScanMsg(
        header=Header(
            stamp=Time(sec=draw(st.integers(-(2**31), 2**31 - 1)), nanosec=draw(st.integers(0, 2**32 - 1))),
            frame_id=draw(names),
        ),
        angle_min=draw(f32), angle_max=draw(f32), angle_increment=draw(f32), time_increment=draw(f32),
        scan_time=draw(f32), range_min=draw(f32), range_max=draw(f32), ranges=ranges, intensities=intens,
    )  # fmt: skip


def write_laser_scan(msg: object) -> bytes:
    w = CdrWriter()
    w.write_int32(msg.header.stamp.sec)  # type: ignore[attr-defined]
    w.write_uint32(msg.header.stamp.nanosec)  # type: ignore[attr-defined]
    w.write_string(msg.header.frame_id)  # type: ignore[attr-defined]
    for name in (
        "angle_min",
        "angle_max",
        "angle_increment",
        "time_increment",
        "scan_time",
        "range_min",
        "range_max",
    ):
        w.write_float32(getattr(msg, name))
    w.write_sequence_float32(msg.ranges)  # type: ignore[attr-defined]
    w.write_sequence_float32(msg.intensities)  # type: ignore[attr-defined]
    return w.getvalue()


def same_f32(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


@settings(max_examples=150, deadline=None)
@given(laser_scans())
def test_writer_matches_rosbags_and_reader_reads_rosbags(msg: object) -> None:
    want = bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))
    assert write_laser_scan(msg) == want
    for payload in (want, bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/LaserScan", little_endian=False))):
        r = CdrReader(payload)
        assert (r.int32(), r.uint32(), r.string()) == (
            msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id,  # type: ignore[attr-defined]
        )  # fmt: skip
        for name in ("angle_min", "angle_max", "angle_increment", "time_increment", "scan_time"):
            assert same_f32(r.float32(), getattr(msg, name))
        assert same_f32(r.float32(), msg.range_min)  # type: ignore[attr-defined]
        assert same_f32(r.float32(), msg.range_max)  # type: ignore[attr-defined]
        np.testing.assert_array_equal(r.sequence_float32(), msg.ranges)  # type: ignore[attr-defined]
        np.testing.assert_array_equal(r.sequence_float32(), msg.intensities)  # type: ignore[attr-defined]
        assert r.remaining == 0


def test_every_primitive_round_trips_with_cdr_alignment() -> None:
    w = CdrWriter()
    w.write_uint8(255)
    w.write_int64(-(2**63))  # 7 bytes of padding before it
    w.write_int8(-128)
    w.write_uint16(65535)  # 1 byte of padding
    w.write_int16(-32768)
    w.write_uint64(2**64 - 1)  # 2 bytes of padding (offset 14 -> 16)
    w.write_float64(math.pi)
    w.write_uint32(7)
    w.write_float64_array([1.0, 2.0])  # 4 bytes of padding
    w.write_float32_array([0.5])
    w.write_sequence_int8(np.array([-1, 2], dtype=np.int8))
    w.write_sequence_uint8(b"\x00\xff")
    w.write_string("")
    payload = w.getvalue()
    assert payload[:4] == b"\x00\x01\x00\x00"
    assert payload[4:5] == b"\xff" and payload[5:12] == b"\x00" * 7  # offsets count from the header's end
    r = CdrReader(payload)
    assert r.uint8() == 255 and r.int64() == -(2**63) and r.int8() == -128
    assert r.uint16() == 65535 and r.int16() == -32768 and r.uint64() == 2**64 - 1
    assert r.float64() == math.pi and r.uint32() == 7
    assert r.float64_array(2).tolist() == [1.0, 2.0] and r.float32_array(1).tolist() == [0.5]
    seq = r.sequence_int8()
    assert seq.dtype == np.int8 and seq.tolist() == [-1, 2]
    assert r.sequence_uint8() == b"\x00\xff" and r.string() == "" and r.remaining == 0


def test_every_truncation_of_a_message_is_a_cdr_error() -> None:
    msg = LaserScanMsg(
        header=Header(stamp=Time(sec=5, nanosec=6), frame_id="laser_frame"), angle_min=-1.0, angle_max=1.0,
        angle_increment=0.5, time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=10.0,
        ranges=np.arange(5, dtype=np.float32), intensities=np.arange(2, dtype=np.float32),
    )  # fmt: skip
    payload = bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))

    def read_all(p: bytes) -> None:
        r = CdrReader(p)
        r.int32(), r.uint32(), r.string()
        for _ in range(7):
            r.float32()
        r.sequence_float32(), r.sequence_float32()

    read_all(payload)
    for cut in range(len(payload)):
        with pytest.raises(CdrError):
            read_all(payload[:cut])


def test_a_huge_length_is_refused_before_allocating() -> None:
    payload = b"\x00\x01\x00\x00" + struct.pack("<I", 0xFFFFFFFF) + b"\x00" * 8
    for method in ("sequence_float32", "sequence_int8", "sequence_uint8", "string"):
        with pytest.raises(CdrError, match="left"):
            getattr(CdrReader(payload), method)()
    with pytest.raises(CdrError):
        CdrReader(payload).float64_array(2**40)


@pytest.mark.parametrize(
    "payload",
    [b"", b"\x00\x01", b"\x00\x07\x00\x00" + bytes(16), b"\x01\x01\x00\x00" + bytes(16), b"FMS1" + bytes(16)],
)
def test_unsupported_headers_are_refused(payload: bytes) -> None:
    with pytest.raises(CdrError):
        CdrReader(payload)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_garbage_only_raises_cdr_error(data: bytes) -> None:
    try:
        r = CdrReader(data)
        r.string()
        r.sequence_float32()
        r.float64()
        r.sequence_uint8()
    except CdrError:
        pass


def test_non_utf8_and_unterminated_strings_are_refused() -> None:
    with pytest.raises(CdrError, match="UTF-8"):
        CdrReader(b"\x00\x01\x00\x00" + struct.pack("<I", 2) + b"\xff\x00").string()
    with pytest.raises(CdrError, match="NUL"):
        CdrReader(b"\x00\x01\x00\x00" + struct.pack("<I", 2) + b"ab").string()
