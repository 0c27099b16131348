"""Scan codecs: round trips of both encodings, and fuzzing that only ever yields DecodeError."""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetmap.codec import (
    HEADER,
    HEADER_V2,
    MAGIC,
    DecodeError,
    InputLimits,
    decode,
    decode_binary,
    decode_json,
    encode_binary,
    encode_json,
)
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING, SESSION_LIMIT, ScanMessage

finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)
ranges = st.lists(
    st.one_of(st.floats(0.0, 100.0), st.just(math.inf), st.just(-math.inf), st.just(math.nan)),
    min_size=1,
    max_size=50,
)


def make_scan(x: float, y: float, th: float, rs: list[float], explicit: bool) -> Scan:
    if explicit:
        angles = np.sort(np.random.default_rng(len(rs)).uniform(-3, 3, len(rs)))
        return Scan.from_angles((x, y, th), angles, rs, 0.05, 60.0)
    return Scan.from_fan((x, y, th), -1.5, 0.01, rs, 0.05, 60.0)


@settings(max_examples=200, deadline=None)
@given(finite, finite, st.floats(-10, 10), ranges, st.booleans(), st.integers(0, 2**63 - 1))
def test_binary_round_trip(x: float, y: float, th: float, rs: list[float], explicit: bool, seq: int) -> None:
    """Binary keeps pose and seq exactly; angles and ranges to float32."""
    scan = make_scan(x, y, th, rs, explicit)
    got = decode(encode_binary(scan, seq, 12.5), BINARY_ENCODING)
    assert got.seq == seq and got.stamp == 12.5
    assert (got.scan.pose.x, got.scan.pose.y, got.scan.pose.theta) == (x, y, th)
    np.testing.assert_allclose(got.scan.angles, scan.angles, atol=1e-6)
    np.testing.assert_array_equal(np.isnan(got.scan.ranges), np.isnan(scan.ranges))
    np.testing.assert_allclose(got.scan.ranges, scan.ranges.astype(np.float32), equal_nan=True)


@settings(max_examples=200, deadline=None)
@given(finite, finite, st.floats(-10, 10), ranges, st.booleans())
def test_json_round_trip(x: float, y: float, th: float, rs: list[float], explicit: bool) -> None:
    """JSON keeps every value exactly; +inf becomes null (no return); NaN beams (invalid readings,
    which JSON cannot hold) and -inf ones (below any range_min) are left out, since no sensor
    model uses them."""
    scan = make_scan(x, y, th, rs, explicit)
    got = decode(encode_json(scan, 7), JSON_ENCODING)
    assert got.seq == 7
    valid = ~np.isnan(scan.ranges) & (scan.ranges != -math.inf)
    np.testing.assert_array_equal(got.scan.angles, scan.angles[valid])
    np.testing.assert_array_equal(got.scan.ranges, scan.ranges[valid])


@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.binary(max_size=400),
    st.sampled_from([BINARY_ENCODING, JSON_ENCODING, "", "zenoh/bytes", "text/plain"]),
)
def test_random_bytes_only_raise_decode_error(data: bytes, encoding: str) -> None:
    with pytest.raises(DecodeError):
        decode(data, encoding)


@settings(max_examples=500, deadline=None)
@given(st.data())
def test_mutated_binary_is_valid_or_refused(data: st.DataObject) -> None:
    """Flip bytes of a valid binary scan: the result decodes to a valid scan or raises DecodeError."""
    session = data.draw(st.sampled_from([None, 1, SESSION_LIMIT - 1]))
    payload = bytearray(
        encode_binary(make_scan(1.0, 2.0, 0.3, [1.0, 2.0, math.inf], False), 3, session=session)
    )
    for _ in range(data.draw(st.integers(1, 6))):
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(payload)))
    try:
        got = decode_binary(bytes(payload[:cut]))
    except DecodeError:
        return
    assert math.isfinite(got.scan.pose.x) and math.isfinite(got.scan.pose.theta)
    assert got.scan.angles.shape == got.scan.ranges.shape
    assert got.session is None or 1 <= got.session < SESSION_LIMIT


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=20,
)


FIELDS = [
    "seq",
    "stamp",
    "pose",
    "angle_min",
    "angle_increment",
    "angles",
    "range_min",
    "range_max",
    "ranges",
    "session",
    "x",
]


@settings(max_examples=500, deadline=None)
@given(st.dictionaries(st.sampled_from(FIELDS), json_values, max_size=9))
def test_json_of_any_shape_is_valid_or_refused(message: dict) -> None:
    try:
        got = decode_json(json.dumps(message).encode())
    except DecodeError:
        return
    assert got.scan.pose.is_finite()


@pytest.mark.parametrize(
    ("patch", "reason"),
    [
        ({"pose": {"x": 1e400, "y": 0, "theta": 0}}, "finite"),
        ({"ranges": [1.0, 2.0], "angles": [0.0]}, "angles"),
        ({"range_min": 5.0, "range_max": 1.0}, "greater"),
        ({"seq": -1}, "seq"),
        ({"angle_increment": None}, "required"),
        ({"extra": 1}, "extra"),
        ({"session": 0}, "session"),
        ({"session": 2**53}, "session"),
        ({"session": "abc"}, "session"),
        # Typed strictly: lax parsing read true as seq 1 and "5" as 5, guessing at a sender's mistake.
        ({"seq": True}, "seq.*valid integer"),
        ({"seq": "5"}, "seq.*valid integer"),
        ({"seq": 5.0}, "seq.*valid integer"),
        ({"pose": {"x": "1.5", "y": 0, "theta": 0}}, "pose.x.*valid number"),
        ({"ranges": [1.0, "2.0"]}, r"ranges\.1.*valid number"),
        ({"range_max": False}, "range_max.*valid number"),
    ],
)
def test_json_errors_say_why(patch: dict, reason: str) -> None:
    base = {"seq": 1, "pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": -1.0, "angle_increment": 0.1,
            "range_max": 30.0, "ranges": [1.0, None, 2.0]}  # fmt: skip
    base.update(patch)
    if "angles" in patch:
        base.pop("angle_min")
        base.pop("angle_increment")
    with pytest.raises(DecodeError, match=reason):
        decode_json(json.dumps(base).encode())


@pytest.mark.parametrize(
    ("patch", "detail"),
    [
        ({"angles": [0.0, 0.1], "ranges": [1.0, 2.0, 3.0]}, "invalid JSON scan: 2 angles but 3 ranges"),
        (
            {"angles": [0.0, 0.1, 0.2]},
            "invalid JSON scan: give either angles or angle_min + angle_increment, not both",
        ),
        (
            {"range_min": 5.0, "range_max": 1.0},
            "invalid JSON scan: range_max 1 must be greater than range_min 5",
        ),
        ({"pose": {"x": 0, "y": 0}}, "invalid JSON scan: pose.theta: Field required"),
    ],
)
def test_a_json_refusal_is_one_sentence_without_pydantic_s_words(patch: dict, detail: str) -> None:
    """A check of the whole message read `invalid JSON scan: message: Value error, 2 angles but 3
    ranges`: pydantic's prefix, and a field name that no field has. Robots see this text in their
    flush report, the service's log and `last_error`."""
    base = {"seq": 1, "pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": -1.0, "angle_increment": 0.1,
            "range_max": 30.0, "ranges": [1.0, None, 2.0]}  # fmt: skip
    base.update(patch)
    if "angle_min" not in patch and "angles" in patch and len(patch["angles"]) != len(base["ranges"]):
        base.pop("angle_min")
        base.pop("angle_increment")
    with pytest.raises(DecodeError) as refused:
        decode_json(json.dumps(base).encode())
    assert str(refused.value) == detail


def test_angles_in_degrees_are_refused_saying_that_angles_are_radians() -> None:
    """A fan of 360 beams 1 "degree" apart spans 359 rad: the likeliest cause is degrees for radians."""
    degrees = Scan.from_fan((0.0, 0.0, 0.0), -180.0, 1.0, [2.0] * 360, 0.05, 30.0)
    for payload in (encode_binary(degrees, 1), encode_json(degrees, 1)):
        with pytest.raises(DecodeError) as refused:
            decode(payload, "")
        assert str(refused.value) == "beam angles span more than one turn (359 rad; angles are in radians)"


def test_binary_errors_say_why() -> None:
    good = encode_binary(make_scan(0, 0, 0, [1.0, 2.0], False), 1)
    with pytest.raises(DecodeError, match="magic"):
        decode_binary(b"XXXX" + good[4:])
    with pytest.raises(DecodeError, match="must be"):
        decode_binary(good[:-1])
    with pytest.raises(DecodeError, match="version"):
        decode_binary(good[:4] + bytes([9]) + good[5:])
    nan_pose = bytearray(good)
    struct.pack_into("<d", nan_pose, 24, math.nan)
    with pytest.raises(DecodeError, match="finite"):
        decode_binary(bytes(nan_pose))
    assert good[:4] == MAGIC and HEADER.size == 72


@pytest.mark.parametrize("encoding", ["binary", "json"])
def test_the_session_id_round_trips_and_messages_without_one_decode_as_before(encoding: str) -> None:
    """A session id is sent as binary version 2 (an 80-byte header) or a JSON field; without one the
    message is exactly what it was before session ids (binary version 1), and decodes to None."""
    scan = make_scan(1.0, 2.0, 0.3, [1.0, 2.0, math.inf], False)
    encode, kind = (encode_binary, BINARY_ENCODING) if encoding == "binary" else (encode_json, JSON_ENCODING)
    with_session = encode(scan, 3, 1.5, session=SESSION_LIMIT - 1)
    without = encode(scan, 3, 1.5)
    assert decode(with_session, kind).session == SESSION_LIMIT - 1
    assert decode(without, kind).session is None
    assert decode(with_session, kind).scan.ranges.tobytes() == decode(without, kind).scan.ranges.tobytes()
    if encoding == "binary":
        assert (without[4], len(without)) == (1, HEADER.size + 4 * 3)
        assert (with_session[4], len(with_session)) == (2, HEADER_V2.size + 4 * 3)
        assert (
            with_session[:4] + with_session[5:72] == without[:4] + without[5:72]
        )  # the same fields before it
        zero = bytearray(with_session)
        struct.pack_into("<Q", zero, 72, 0)
        with pytest.raises(DecodeError, match="session"):
            decode_binary(bytes(zero))
        with pytest.raises(DecodeError, match="shorter"):
            decode_binary(with_session[:76])
    else:
        assert b"session" not in without


def test_unknown_encoding_is_refused_and_bytes_are_sniffed() -> None:
    scan = make_scan(0, 0, 0, [1.0], False)
    with pytest.raises(DecodeError, match="unknown encoding"):
        decode(encode_json(scan, 1), "text/csv")
    assert decode(encode_binary(scan, 4), "zenoh/bytes").seq == 4
    assert decode(encode_json(scan, 5), "").seq == 5


def test_input_limits_refuse_what_is_out_of_bounds_and_cap_the_range() -> None:
    limits = InputLimits(world_bound=100.0, max_beams=10, max_range=50.0)
    within = decode(encode_binary(make_scan(150.0, 0, 0, [1.0], False), 1), BINARY_ENCODING)
    assert within.scan.pose.x == 150.0  # the default limits take it: the limits given decide
    with pytest.raises(DecodeError, match="world bound"):
        decode(encode_binary(make_scan(150.0, 0, 0, [1.0], False), 1), BINARY_ENCODING, limits)
    with pytest.raises(DecodeError, match="limit of 10"):
        decode(encode_json(make_scan(0, 0, 0, [1.0] * 11, False), 1), JSON_ENCODING, limits)
    wide = Scan.from_angles((0, 0, 0), [0.0, 7.0], [1.0, 1.0], 0.0, 30.0)
    with pytest.raises(DecodeError, match="one turn"):
        decode(encode_binary(wide, 1), BINARY_ENCODING, limits)
    far = Scan.from_fan((0, 0, 0), 0.0, 0.1, [10.0, 60.0, 5000.0], 0.0, 1e6)
    got = decode(encode_binary(far, 1), BINARY_ENCODING, limits).scan
    assert got.range_max == 50.0
    assert got.returns_mask().tolist() == [True, False, False]  # beyond the cap: no return


def test_rejection_reasons_cannot_inject_log_lines() -> None:
    """Field names come from the sender: a newline in one must not reach the reason (and the log)."""
    evil = {"seq": 1, "pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": 0.0, "angle_increment": 0.1,
            "ranges": [1.0], "x\nERROR fake log line" + "y" * 500: 1}  # fmt: skip
    with pytest.raises(DecodeError) as refused:
        decode_json(json.dumps(evil).encode())
    reason = str(refused.value)
    assert "\n" not in reason and len(reason) < 400


def test_a_json_nan_range_is_an_invalid_reading_like_binary_nan() -> None:
    """The non-standard JSON literal NaN in `ranges` is accepted and means what a binary NaN means,
    an invalid reading the engine ignores; and the published schema says so (it used to call NaN
    binary-only while the decoder accepted it)."""
    body = b'{"seq": 3, "pose": {"x": 1, "y": 2, "theta": 0}, "angle_min": -0.25, "angle_increment": 0.25, '
    body += b'"range_max": 30, "ranges": [1.0, NaN, 2.0]}'
    got = decode(body, JSON_ENCODING)
    binary = decode_binary(
        encode_binary(Scan.from_fan((1.0, 2.0, 0.0), -0.25, 0.25, [1.0, math.nan, 2.0], 0, 30), 3)
    )
    assert np.isnan(got.scan.ranges[1]) and np.isnan(binary.scan.ranges[1])
    np.testing.assert_array_equal(got.scan.ranges, binary.scan.ranges)
    np.testing.assert_array_equal(got.scan.angles, binary.scan.angles)
    schema = ScanMessage.model_json_schema()
    described = (schema["description"] + schema["properties"]["ranges"].get("description", "")).lower()
    assert "binary encoding only" not in described
    assert "nan: an invalid reading, ignored" in described


@pytest.mark.parametrize("encode", [encode_binary, encode_json])
def test_a_reading_of_minus_infinity_is_ignored_in_both_encodings_not_made_a_no_return(
    encode: Callable[[Scan, int], bytes],
) -> None:
    """-inf is below any range_min (ROS drivers report "too close to measure" so, REP 117): every
    sensor model ignores it. The JSON encoding wrote it as null, which means +inf, no return, so a
    map with no_return_range > 0 cleared the beam as free space, through the obstacle right in front
    of the sensor: a robot publishing JSON, or `post_scan` with its default JSON, got another map
    than the engine's of the same scan."""
    config = {"no_return_range": 2.0}
    scan = Scan.from_fan((0.0, 0.0, 0.0), -0.2, 0.1, [-math.inf, 3.0, -math.inf, 3.0, -math.inf], 0.05, 10.0)
    decoded = decode(encode(scan, 1), BINARY_ENCODING if encode is encode_binary else JSON_ENCODING).scan
    assert not decoded.no_return_mask().any()
    engine, service = GridMap(config), GridMap(config)
    engine.integrate(scan)
    service.integrate(decoded)
    window = (-40, -40, 80, 80)
    np.testing.assert_array_equal(service.region("log_odds", *window), engine.region("log_odds", *window))


def test_a_scan_message_serialized_by_pydantic_decodes_to_the_same_scan() -> None:
    """`ScanMessage` is the wire schema, and `model_dump_json` the natural way to put one on the
    wire from Python without `ScanPublisher`. Pydantic wrote NaN and infinities as null: a message
    with the default range_max (no maximum) was refused ("range_max: Input should be a valid
    number"), and NaN readings (invalid) and -inf ones (below range_min) became no returns, as
    `from_scan` also made -inf. Now they travel as the literals the decoders read."""
    scan = Scan.from_fan((1.0, 2.0, 0.5), -0.2, 0.1, [math.nan, -math.inf, math.inf, 1.5, 0.01], 0.05)
    message = ScanMessage.from_scan(scan, seq=4, stamp=2.5, session=9)
    for payload in (message.model_dump_json(), message.model_dump_json(exclude_none=True)):
        got = decode(payload.encode(), JSON_ENCODING)
        assert (got.seq, got.stamp, got.session) == (4, 2.5, 9)
        np.testing.assert_array_equal(got.scan.ranges, scan.ranges)
        np.testing.assert_array_equal(got.scan.no_return_mask(), [False, False, True, False, False])
        assert got.scan.range_max == InputLimits().max_range  # no maximum: the service's cap
    np.testing.assert_array_equal(message.to_scan().ranges, scan.ranges)


def test_a_json_list_too_long_for_any_scan_is_refused_before_it_is_parsed() -> None:
    """2 million ranges in 4 MB took 110-140 ms to parse before pydantic refused the list, on the
    Zenoh thread all robots share; the items are counted first. The largest valid scan still
    decodes."""
    beams = InputLimits().max_beams

    head = b'{"seq": 1, "pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": 0, "angle_increment": 1e-5, '
    flood = head + b'"ranges": [' + b",".join([b"1"] * 2_000_000) + b"]}"
    with pytest.raises(DecodeError, match=f"more items than {beams} beams can have"):
        decode(flood, JSON_ENCODING)
    largest = json.dumps(
        {"seq": 1, "pose": {"x": 0, "y": 0, "theta": 0}, "angles": [k * 1e-4 for k in range(beams)],
         "ranges": [1.0] * beams, "range_min": 0.0, "range_max": 30.0, "stamp": 1.0}
    ).encode()  # fmt: skip
    assert decode(largest, JSON_ENCODING).scan.num_beams == beams


@pytest.mark.parametrize(
    "repeat",
    [
        lambda text: text.replace("{", '{"seq": 1, ', 1),
        lambda text: text.replace("{", '{"\\u0073eq": 1, ', 1),  # the same key, spelled otherwise
        lambda text: text.replace('"x"', '"x": 7, "x"', 1),  # in the pose
        lambda text: text.replace("{", '{"angles": null, "angles": null, ', 1),  # even with equal values
    ],
)
def test_a_json_scan_holding_a_key_twice_is_refused(repeat: Callable[[str], str]) -> None:
    """The JSON parser keeps a repeated key's last value silently; which one the robot meant is a
    guess. The quick test that spares valid scans a second parse must not let any form through."""
    scan = Scan.from_fan((1.0, 2.0, 0.3), -1.0, 0.01, [1.0] * 200, 0.05, 30.0)
    text = encode_json(scan, 5).decode()
    assert decode_json(text.encode()).seq == 5
    with pytest.raises(DecodeError, match="appears twice in an object"):
        decode_json(repeat(text).encode())


def test_angle_min_and_increment_are_ignored_with_explicit_angles() -> None:
    """docs/protocol.md: angle_min and angle_increment are "ignored with flag bit 0". They were
    still required to be finite, so a robot that wrote NaN there ("not given") had every scan refused
    with `angle_min must be finite`. Without the flag they are the beams' bearings and still checked."""
    scan = Scan.from_angles((0.5, 0.25, 0.3), [-0.5, 0.0, 0.75], [1.0, 2.0, 3.0], 0.05, 30.0)
    good = encode_binary(scan, 7, 1.5, explicit_angles=True)
    assert good[5] == 1  # flag bit 0: explicit angles
    for angle_min, increment in ((math.nan, math.nan), (math.inf, -math.inf), (math.nan, 0.25)):
        header = bytearray(good)
        struct.pack_into("<d", header, 56, angle_min)
        struct.pack_into("<f", header, 64, increment)
        got = decode_binary(bytes(header))
        np.testing.assert_array_equal(got.scan.angles, decode_binary(good).scan.angles)
        np.testing.assert_array_equal(got.scan.ranges, scan.ranges)
    fan = bytearray(encode_binary(Scan.from_fan((0, 0, 0), -0.5, 0.25, [1.0, 2.0], 0.05, 30.0), 7))
    assert fan[5] == 0
    struct.pack_into("<d", fan, 56, math.nan)
    with pytest.raises(DecodeError, match="angle_min must be finite"):
        decode_binary(bytes(fan))


def test_a_binary_header_over_the_beam_limit_names_the_limit_in_force() -> None:
    """A header whose n is over `--max-beams` (16384 by default) is refused before its length is
    checked. The reason named the engine's ceiling (100000) instead, so a robot sending 20000 beams
    read 'more than the limit of 100000' for one past 16384, or a length error."""
    header = bytearray(encode_binary(make_scan(0, 0, 0, [1.0], False), 1))
    for n in (16_385, 200_000):
        struct.pack_into("<I", header, 68, n)
        with pytest.raises(DecodeError, match=f"^{n} beams is more than the limit of 16384$"):
            decode_binary(bytes(header))
    struct.pack_into("<I", header, 68, 11)
    with pytest.raises(DecodeError, match="^11 beams is more than the limit of 10$"):
        decode_binary(bytes(header), InputLimits(max_beams=10))


@pytest.mark.parametrize(
    ("changes", "scan_id"),
    [
        ({"angles": [0.0, 0.1]}, (7, 2.5, 42)),  # 2 angles but 3 ranges: refused with its identity
        ({"range_min": -1.0}, (7, 2.5, 42)),
        ({"session": None, "range_min": -1.0}, (7, 2.5, None)),
        ({"ranges": [1.0] * 40_000}, (7, 2.5, 42)),  # past the beam limit, refused unparsed
        ({"stamp": "2.5", "range_min": -1.0}, None),  # an identity not as ScanMessage takes it
        ({"session": 0, "range_min": -1.0}, None),
        ({"seq": 7.0, "range_min": -1.0}, None),
        ({"seq": -7, "range_min": -1.0}, None),
    ],
)
def test_a_refused_json_scan_carries_its_identity_when_it_can_be_read(
    changes: dict[str, object], scan_id: tuple[int, float, int | None] | None
) -> None:
    """A JSON scan refused for its body keeps its (seq, stamp, session), so the service settles it
    as refused rather than count its seq as lost (tests/test_delivery.py); one whose identity is not
    valid has none."""
    pose = {"x": 0, "y": 0, "theta": 0}
    message: dict[str, object] = {"seq": 7, "stamp": 2.5, "session": 42, "pose": pose, "angle_min": 0.0,
                                  "angle_increment": 0.1, "ranges": [1.0, 2.0, 3.0]}  # fmt: skip
    if "angles" in changes:
        del message["angle_min"], message["angle_increment"]
    payload = json.dumps({k: v for k, v in (message | changes).items() if v is not None}).encode()
    with pytest.raises(DecodeError) as refused:
        decode(payload, JSON_ENCODING)
    assert refused.value.scan_id == scan_id
    repeated = payload.replace(b'{"seq": 7', b'{"seq": 7, "seq": 8', 1)
    with pytest.raises(DecodeError) as refused:
        decode(repeated, JSON_ENCODING)
    assert refused.value.scan_id is None  # which seq the robot meant is a guess
