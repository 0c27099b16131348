"""A robot written from docs/protocol.md alone, against the real service.

Robots need not use fleetmap's Python client: they implement the wire protocol from the doc. This
module is such a robot. Its payloads are packed byte by byte with `struct` and `json` from the
doc's tables (not with `fleetmap.codec`), published over a real Zenoh client session to a real
service process (`python -m fleetmap.server`), and checked over the REST API:

- every form the doc describes (binary version 1 and 2, evenly spaced and explicit angles, JSON with
  angle_min + angle_increment and with angles, NaN / null / Infinity / negative / below range_min /
  at or above range_max readings) gives, layer by layer, exactly the map the project's own encoder
  gives for the same scans, and the binary bytes are what `codec.encode_binary` writes;
- the refusals the doc names come with the doc's reasons, counted on the robot and in /healthz,
  and change nothing in the map.
"""

from __future__ import annotations

import io
import json
import math
import struct
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh
from service_process import ServiceProcess, wait_for
from test_ingest import client_session

from fleetmap import codec
from fleetmap.scan import Scan

LAYERS = ("log_odds", "hits", "misses", "tsdf", "tsdf_weight")
#: The window compared, metres: every scan below stays well inside it.
WINDOW = {"xmin": -10.0, "ymin": -10.0, "xmax": 10.0, "ymax": 10.0}

# -- the robot's own encoder, from docs/protocol.md ------------------------------------------------

#: "Little-endian throughout": magic, version, flags, reserved, seq, stamp, x, y, theta, range_min,
#: range_max, angle_min, angle_increment, n (72 bytes); version 2 then has the session id (u64).
DOC_HEADER = "<4sBBHQddddffdfI"
BINARY = "application/x-fleetmap-scan"
JSON = "application/json"


def doc_binary(
    seq: int, stamp: float, pose: tuple[float, float, float], ranges: list[float], *,
    angle_min: float = 0.0, angle_increment: float = 0.0, angles: list[float] | None = None,
    range_min: float = 0.0, range_max: float = math.inf, session: int | None = None,
) -> bytes:  # fmt: skip
    """The binary encoding as the doc's table lays it out: version 2 when there is a session id,
    flag bit 0 when explicit angles follow (then angle_min and angle_increment are ignored)."""
    version = 1 if session is None else 2
    flags = 0 if angles is None else 1
    header = struct.pack(
        DOC_HEADER, b"FMS1", version, flags, 0, seq, stamp, *pose, range_min, range_max, angle_min,
        angle_increment, len(ranges),
    )  # fmt: skip
    assert len(header) == 72
    if session is not None:
        header += struct.pack("<Q", session)
    body = b"" if angles is None else struct.pack(f"<{len(angles)}f", *angles)
    return header + body + struct.pack(f"<{len(ranges)}f", *ranges)


def doc_json(
    seq: int, stamp: float, pose: tuple[float, float, float], ranges: list[float], *,
    angle_min: float | None = None, angle_increment: float | None = None,
    angles: list[float] | None = None, range_min: float = 0.0, range_max: float = math.inf,
    session: int | None = None,
) -> bytes:  # fmt: skip
    """The JSON message of the doc's field table: no return (+inf) as null, an invalid reading as the
    literal NaN, a negative reading as is; range_max left out for "no maximum"."""
    message: dict[str, object] = {"seq": seq, "stamp": stamp}
    if session is not None:
        message["session"] = session
    message["pose"] = {"x": pose[0], "y": pose[1], "theta": pose[2]}
    if angles is None:
        message["angle_min"], message["angle_increment"] = angle_min, angle_increment
    else:
        message["angles"] = angles
    message["range_min"] = range_min
    if math.isfinite(range_max):
        message["range_max"] = range_max
    message["ranges"] = [None if r == math.inf else r for r in ranges]
    return json.dumps(message).encode()  # Python's json writes NaN as the literal the doc accepts


def f32(value: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


# -- the scans -------------------------------------------------------------------------------------

#: Beam i at -1 + i/64 rad: exact in float32, so explicit angles and the fan give the same bearings
#: and every encoding below must give the same map bit for bit.
ANGLE_MIN, INCREMENT, BEAMS = -1.0, 1.0 / 64, 129
RANGE_MIN, RANGE_MAX = 0.125, 8.0
POSES = [(1.0, 2.0, 0.7), (1.3, 2.1, 0.75), (-0.4, 0.3, -2.0)]


def ranges_for(seed: int) -> list[float]:
    """Returns (float32 values) mixed with every kind of reading the doc names."""
    rng = np.random.default_rng(seed)
    out = [f32(float(r)) for r in rng.uniform(0.3, 7.5, BEAMS)]
    specials = [math.inf, math.nan, -1.0, 0.0625, RANGE_MAX, 9.0, RANGE_MIN]  # RANGE_MIN: a return
    for k, value in enumerate(specials * 3):
        out[(7 * k + seed) % BEAMS] = value
    return out


SCANS = [(seq, 10.0 + seq, pose, ranges_for(seq)) for seq, pose in enumerate(POSES)]
ANGLES = [ANGLE_MIN + i * INCREMENT for i in range(BEAMS)]
FAN = {"angle_min": ANGLE_MIN, "angle_increment": INCREMENT}
WINDOW_ARGS = {"range_min": RANGE_MIN, "range_max": RANGE_MAX}
SESSION = 6020155262712573

#: Each form the doc describes: (encoding, payload of one scan).
FORMS = {
    "bin-v1": lambda s, t, p, r: (BINARY, doc_binary(s, t, p, r, **FAN, **WINDOW_ARGS)),
    "bin-v2": lambda s, t, p, r: (BINARY, doc_binary(s, t, p, r, **FAN, **WINDOW_ARGS, session=SESSION)),
    "bin-angles": lambda s, t, p, r: (BINARY, doc_binary(s, t, p, r, angles=ANGLES, **WINDOW_ARGS)),
    # "ignored with flag bit 0": a robot may leave them NaN when it sends explicit angles
    "bin-angles-nan-fan": lambda s, t, p, r: (
        BINARY,
        doc_binary(s, t, p, r, angles=ANGLES, angle_min=math.nan, angle_increment=math.nan, **WINDOW_ARGS),
    ),
    "bin-unlabelled": lambda s, t, p, r: ("zenoh/bytes", doc_binary(s, t, p, r, **FAN, **WINDOW_ARGS)),
    "json-fan": lambda s, t, p, r: (JSON, doc_json(s, t, p, r, **FAN, **WINDOW_ARGS)),
    "json-angles": lambda s, t, p, r: (
        "application/json;schema=doc",
        doc_json(s, t, p, r, angles=ANGLES, session=SESSION, **WINDOW_ARGS),
    ),
    "json-unlabelled": lambda s, t, p, r: (None, doc_json(s, t, p, r, **FAN, **WINDOW_ARGS)),
}


def project_payloads(
    seq: int, stamp: float, pose: tuple[float, float, float], ranges: list[float]
) -> dict[str, bytes]:
    """The project's own encoder's payloads of the same scan (the reference)."""
    scan = Scan.from_fan(pose, ANGLE_MIN, INCREMENT, ranges, RANGE_MIN, RANGE_MAX)
    return {
        "bin-v1": codec.encode_binary(scan, seq, stamp),
        "bin-v2": codec.encode_binary(scan, seq, stamp, session=SESSION),
        "bin-angles": codec.encode_binary(scan, seq, stamp, explicit_angles=True),
        "json": codec.encode_json(scan, seq, stamp),
    }


# -- the service and the robot's session ---------------------------------------------------------


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    svc = ServiceProcess(tmp_path_factory.mktemp("protocol-robot"), ["--in-memory"])
    with svc:
        yield svc


@pytest.fixture(scope="module")
def robot(service: ServiceProcess) -> Iterator[zenoh.Session]:
    session = client_session(service.zenoh_endpoint)
    yield session
    session.close()


@pytest.fixture(scope="module")
def http(service: ServiceProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=service.base_url, timeout=30.0) as client:
        yield client


def publish(session: zenoh.Session, map_id: str, robot_id: str, encoding: str | None, payload: bytes) -> None:
    """Put one sample as a robot following the doc does: a BLOCK publisher, once it matches."""
    options = {} if encoding is None else {"encoding": zenoh.Encoding(encoding)}
    pub = session.declare_publisher(
        f"fleetmap/{map_id}/{robot_id}/scan", congestion_control=zenoh.CongestionControl.BLOCK, **options
    )
    try:
        wait_for(lambda: pub.matching_status.matching, timeout=10, interval=0.01, what="the service")
        pub.put(payload)
    finally:
        pub.undeclare()


def robot_state(http: httpx.Client, map_id: str, robot_id: str) -> dict:
    answer = http.get(f"/maps/{map_id}")
    return answer.json()["stats"]["robots"].get(robot_id, {}) if answer.status_code == 200 else {}


def layers(http: httpx.Client, map_id: str) -> dict[str, np.ndarray]:
    out = {}
    for layer in LAYERS:
        answer = http.get(f"/maps/{map_id}/region", params={**WINDOW, "layer": layer, "format": "npy"})
        assert answer.status_code == 200, answer.text
        out[layer] = np.load(io.BytesIO(answer.content))
    return out


# -- tests -----------------------------------------------------------------------------------------


def test_the_doc_encoders_bytes_are_the_projects() -> None:
    """The doc says its hexdump is what `codec.encode_binary` writes; so is every binary form here."""
    for seq, stamp, pose, ranges in SCANS:
        ours = project_payloads(seq, stamp, pose, ranges)
        assert FORMS["bin-v1"](seq, stamp, pose, ranges)[1] == ours["bin-v1"]
        assert FORMS["bin-v2"](seq, stamp, pose, ranges)[1] == ours["bin-v2"]
        # With explicit angles the project fills the ignored angle_min and increment in from them.
        explicit = doc_binary(seq, stamp, pose, ranges, angles=ANGLES, **FAN, **WINDOW_ARGS)
        assert explicit == ours["bin-angles"]


def test_every_form_the_doc_describes_maps_exactly_as_the_projects_encoder(
    robot: zenoh.Session, http: httpx.Client
) -> None:
    """Each form on its own map, the project's binary and JSON on two more: all maps are equal,
    layer by layer and cell by cell, and each robot has its three scans integrated, none refused."""
    maps: dict[str, str] = {}
    for form, make in FORMS.items():
        for seq, stamp, pose, ranges in SCANS:
            encoding, payload = make(seq, stamp, pose, ranges)
            publish(robot, f"doc-{form}", "r1", encoding, payload)
        maps[form] = f"doc-{form}"
    for seq, stamp, pose, ranges in SCANS:
        ours = project_payloads(seq, stamp, pose, ranges)
        publish(robot, "lib-bin", "r1", BINARY, ours["bin-v1"])
        publish(robot, "lib-json", "r1", JSON, ours["json"])
    maps.update({"lib-bin": "lib-bin", "lib-json": "lib-json"})
    for name, map_id in maps.items():
        state = wait_for(
            lambda m=map_id: (s := robot_state(http, m, "r1")) and s["scans_integrated"] == 3 and s,
            timeout=30, what=f"3 scans integrated on {map_id}",
        )  # fmt: skip
        assert (state["scans_rejected"], state["last_error"], state["duplicates"]) == (0, None, 0), name
        assert (state["last_seq"], state["last_stamp"], state["lost"]) == (2, 12.0, 0), name
        assert state["last_pose"] == {"x": -0.4, "y": 0.3, "theta": -2.0}, name
    reference = layers(http, "lib-bin")
    assert np.count_nonzero(reference["hits"]) > 100 and np.count_nonzero(reference["misses"]) > 1000
    for name, map_id in maps.items():
        got = layers(http, map_id)
        for layer in LAYERS:
            np.testing.assert_array_equal(got[layer], reference[layer], err_msg=f"{name}: {layer}")


#: A valid scan of 3 beams, the doc's example, for the refusals below.
EXAMPLE = doc_binary(42, 1700000000.25, (1.5, -2.25, 0.5), [1.0, math.inf, math.nan],
                     angle_min=-0.25, angle_increment=0.25, range_min=0.05, range_max=30.0)  # fmt: skip
EXAMPLE_JSON = json.loads(
    doc_json(42, 1.0, (1.5, -2.25, 0.5), [1.0, 2.5], angle_min=-0.25, angle_increment=0.25)
)


def patched(offset: int, fmt: str, value: object) -> bytes:
    data = bytearray(EXAMPLE)
    struct.pack_into(fmt, data, offset, value)
    return bytes(data)


def example_json(drop: str = "", **changes: object) -> bytes:
    """The JSON example without the field `drop` and with `changes`."""
    return json.dumps({k: v for k, v in {**EXAMPLE_JSON, **changes}.items() if k != drop}).encode()


#: (robot id, encoding, payload, the reason the doc names).
REFUSALS = [
    ("magic", BINARY, b"FMS2" + EXAMPLE[4:], "bad magic"),
    ("version", BINARY, patched(4, "<B", 3), "unsupported binary scan version"),
    ("flags", BINARY, patched(5, "<B", 2), "unknown flags"),
    ("length", BINARY, EXAMPLE[:80], "binary scan of 3 beams must be 84 bytes, got 80"),
    ("header", BINARY, EXAMPLE[:60], "shorter than its 72-byte header"),
    ("stamp", BINARY, patched(16, "<d", math.nan), "stamp must be finite"),
    ("seq", BINARY, patched(8, "<Q", 2**63), "seq must be below 2**63"),
    ("pose", BINARY, patched(24, "<d", math.nan), "pose must be finite"),
    ("bound", BINARY, patched(32, "<d", 2e5), "outside the world bound of +-100000 m"),
    ("fan-nan", BINARY, patched(56, "<d", math.nan), "angle_min must be finite"),
    # Each finite, their sum is not: no direction for its beams.
    (
        "heading",
        BINARY,
        doc_binary(1, 0.0, (0.0, 0.0, 1e308), [1.0, 2.0], angle_min=1e308, angle_increment=0.25),
        "the sensor heading plus its beam angles must be finite",
    ),
    ("beams", BINARY, patched(68, "<I", 16_385), "16385 beams is more than the limit of 16384"),
    ("session", BINARY, doc_binary(1, 0.0, (0, 0, 0), [1.0], session=0), "session must be in [1, 2**53)"),
    ("encoding", "text/plain", EXAMPLE, "unknown encoding"),
    ("sniffed", None, b"hello", "is neither a binary scan (magic b'FMS1') nor a JSON object"),
    ("extra", JSON, example_json(sesion=1), "sesion: Extra inputs are not permitted"),
    ("twice", JSON, b'{"seq": 1, ' + example_json()[1:], "the key 'seq' appears twice in an object"),
    ("bom", JSON, b"\xef\xbb\xbf" + example_json(), "it starts with a byte order mark"),
    ("seq-float", JSON, example_json(seq=5.0), "seq: Input should be a valid integer"),
    ("no-pose", JSON, example_json(drop="pose"), "invalid JSON scan: pose: Field required"),
    # Checks of the whole message: the sentence alone (it read "message: Value error, 1 angles ...").
    (
        "lengths",
        JSON,
        example_json(drop="angle_min", angle_increment=None, angles=[0.0]),
        "invalid JSON scan: 1 angles but 2 ranges",
    ),
    (
        "degrees",
        JSON,
        example_json(angle_min=-180.0, angle_increment=1.0, ranges=[1.0] * 360),
        "beam angles span more than one turn (359 rad; angles are in radians)",
    ),
]


def test_the_refusals_the_doc_names_are_counted_with_its_reasons_and_change_nothing(
    robot: zenoh.Session, http: httpx.Client
) -> None:
    publish(robot, "refusals", "good", BINARY, EXAMPLE)
    wait_for(lambda: robot_state(http, "refusals", "good").get("scans_integrated") == 1, what="the good scan")
    before = layers(http, "refusals")
    errors_before = http.get("/healthz").json()["zenoh"]["decode_errors"]
    for robot_id, encoding, payload, _ in REFUSALS:
        publish(robot, "refusals", robot_id, encoding, payload)
    for robot_id, _, _, reason in REFUSALS:
        state = wait_for(
            lambda r=robot_id: (s := robot_state(http, "refusals", r)) and s["scans_rejected"] and s,
            timeout=30, what=f"{robot_id}'s refusal",
        )  # fmt: skip
        assert state["scans_rejected"] == 1 and state["scans_integrated"] == 0, robot_id
        assert reason in state["last_error"], (robot_id, state["last_error"])
    assert http.get("/healthz").json()["zenoh"]["decode_errors"] == errors_before + len(REFUSALS)
    after = layers(http, "refusals")
    for layer in LAYERS:
        np.testing.assert_array_equal(after[layer], before[layer], err_msg=layer)


def test_the_module_names_a_layout_the_doc_has() -> None:
    """This robot's header format is the doc's table, read from the doc itself."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text()
    assert struct.calcsize(DOC_HEADER) == 72 and "A 72-byte header (version 1), or an 80-byte one" in doc


def test_a_zenoh_delete_on_a_scan_key_is_no_refused_scan(robot: zenoh.Session, http: httpx.Client) -> None:
    """A scan is a put ("one scan per sample (put)"). A Zenoh DELETE on the key (`publisher.delete()`,
    `session.delete(key)`) carries no payload: it was decoded as one, counted as the robot's refused
    scan with "a payload starting b'' is neither a binary scan ... nor a JSON object" as its
    `last_error`, which hid the robot's real last refusal. It is ignored, as the ROS ingest ignores one."""
    publish(robot, "deletes", "r1", BINARY, doc_binary(0, 1.0, (0.0, 0.0, 0.0), [1.0, 2.0], session=7))
    publish(robot, "deletes", "r1", BINARY, patched(32, "<d", 2e5))  # a refusal: its reason stays
    wait_for(lambda: robot_state(http, "deletes", "r1").get("scans_rejected") == 1, what="the refusal")
    errors_before = http.get("/healthz").json()["zenoh"]["decode_errors"]
    key = "fleetmap/deletes/r1/scan"
    pub = robot.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        wait_for(lambda: pub.matching_status.matching, timeout=10, interval=0.01, what="the service")
        pub.delete()
        robot.delete(key, congestion_control=zenoh.CongestionControl.BLOCK)
        # Samples of one session arrive in order: once this scan is in, the deletes were handled.
        pub.put(doc_binary(1, 2.0, (0.0, 0.0, 0.0), [1.0, 2.0], session=7))
    finally:
        pub.undeclare()
    state = wait_for(
        lambda: (s := robot_state(http, "deletes", "r1")) and s["scans_integrated"] == 2 and s,
        timeout=30, what="the scan after the deletes",
    )  # fmt: skip
    assert state["scans_rejected"] == 1 and state["lost"] == 0, state
    assert "outside the world bound" in state["last_error"], state["last_error"]
    assert http.get("/healthz").json()["zenoh"]["decode_errors"] == errors_before


def test_a_payload_past_the_size_limit_is_undecodable_as_the_doc_says(
    robot: zenoh.Session, http: httpx.Client
) -> None:
    """The doc's limits table lists the payload size, and it said of every scan breaking a limit
    that with a session id its seq counts as accepted and it is settled at once as refused. One past
    the size limit is refused before any of it is read (a Zenoh message may be 1 GiB): its seq is
    not known, so the next scan counts it as lost and a flush waits for it. The doc says so now."""
    small = doc_json(0, 1.0, (0.0, 0.0, 0.0), [1.0, 2.0], angle_min=0.0, angle_increment=0.1, session=9)
    publish(robot, "oversized", "r1", JSON, small)
    big = small[:-1] + b" " * (4 * 1024 * 1024) + b"}"
    publish(robot, "oversized", "r1", JSON, big.replace(b'"seq": 0', b'"seq": 1'))
    publish(robot, "oversized", "r1", JSON, small.replace(b'"seq": 0', b'"seq": 2'))
    state = wait_for(
        lambda: (s := robot_state(http, "oversized", "r1")) and s["scans_integrated"] == 2 and s,
        timeout=30, what="the scans around the oversized one",
    )  # fmt: skip
    assert state["scans_rejected"] == 1 and "exceeds the limit of 4194304" in state["last_error"]
    replies = list(robot.get("fleetmap/oversized/r1/delivery?session=9", timeout=10))
    session = json.loads(replies[0].ok.payload.to_string())["sessions"][0]
    assert (session["refused"], session["lost"], session["settled"]) == (0, 1, 2), session
    doc = " ".join((Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text().split())
    assert "Not so a payload past the size limit, refused before any of it is read" in doc
