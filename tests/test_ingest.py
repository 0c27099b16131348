"""Zenoh ingest with real Zenoh sessions in this process: the service's `ZenohIngest` feeding a real
`MapRegistry`, and robots as Zenoh client sessions connected to it over loopback TCP."""

from __future__ import annotations

import json
import logging
import threading
import time
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh
from fleetmap_client.publisher import ScanPublisher
from registry_idle import wait_idle
from service_process import FreezableProxy, ServiceProcess, free_port, wait_for

from fleetmap import codec
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.rate_limited_log import RateLimitedLog
from fleetmap.registry import MapRegistry
from fleetmap.scan import Scan
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap.wire import ALIVE_KEY, BINARY_ENCODING, JSON_ENCODING, SCAN_KEY
from fleetmap.zenoh_ingest import DEFAULT_LISTEN, IngestStartError, ZenohIngest, parse_key

PLAN = generate_floorplan(3, width_m=16.0, height_m=12.0)


def sim_scans(seed: int, count: int, beams: int = 181) -> list[Scan]:
    robot = SimulatedRobot(PLAN, seed, num_beams=beams, range_max=10.0, scan_rate=5.0)
    return [robot.tick() for _ in range(count)]


def client_session(endpoint: str) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def scan_publisher(session: zenoh.Session, map_id: str, robot_id: str, encoding: str) -> zenoh.Publisher:
    """A BLOCK publisher for the robot's scan key, returned once the service's subscriber matches
    (samples published before that could be dropped)."""
    pub = session.declare_publisher(
        SCAN_KEY.format(map_id=map_id, robot_id=robot_id),
        encoding=zenoh.Encoding(encoding),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    wait_for(lambda: pub.matching_status.matching, timeout=10, interval=0.01, what="a matching subscriber")
    return pub


def engine_map(payloads: list[tuple[bytes, str]], config: MapConfig | None = None) -> GridMap:
    """The engine's map of exactly what was sent: each payload decoded as the service decodes it
    (binary ranges are float32), integrated in order."""
    gmap = GridMap(config or MapConfig())
    for payload, encoding in payloads:
        gmap.integrate(codec.decode(payload, encoding).scan)
    return gmap


def assert_same_map(got: GridMap, want: GridMap) -> None:
    bounds = want.known_bounds()
    assert bounds is not None
    assert got.known_bounds() == bounds
    for layer in ("log_odds", "hits", "misses", "tsdf", "tsdf_weight"):
        np.testing.assert_array_equal(got.region(layer, *bounds), want.region(layer, *bounds), err_msg=layer)


@pytest.fixture
def registry() -> Iterator[MapRegistry]:
    reg = MapRegistry(workers=2)
    reg.start()
    yield reg
    reg.close()


@pytest.fixture
def ingest(registry: MapRegistry) -> Iterator[ZenohIngest]:
    ing = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    ing.start()
    yield ing
    ing.close()


@pytest.fixture
def robot(ingest: ZenohIngest) -> Iterator[zenoh.Session]:
    session = client_session(ingest.listen[0])
    yield session
    session.close()


def integrated(registry: MapRegistry, map_id: str, robot_id: str) -> int:
    try:
        entry = registry.get(map_id)
    except KeyError:
        return 0
    with registry.lock:
        state = entry.robots.get(robot_id)
        return state.scans_integrated if state else 0


def test_json_and_binary_scans_integrate_exactly_like_the_engine(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session
) -> None:
    """Two robots, one per encoding and map: each map equals the engine's map of the same messages."""
    sent: dict[str, list[tuple[bytes, str]]] = {"mj": [], "mb": []}
    pub_j = scan_publisher(robot, "mj", "r1", JSON_ENCODING)
    pub_b = scan_publisher(robot, "mb", "r1", BINARY_ENCODING)
    for seq, (sj, sb) in enumerate(zip(sim_scans(1, 25), sim_scans(2, 25), strict=True)):
        pj, pb = codec.encode_json(sj, seq, stamp=seq * 0.2), codec.encode_binary(sb, seq, stamp=seq * 0.2)
        pub_j.put(pj)
        pub_b.put(pb)
        sent["mj"].append((pj, JSON_ENCODING))
        sent["mb"].append((pb, BINARY_ENCODING))
    for map_id in sent:
        wait_for(lambda m=map_id: integrated(registry, m, "r1") == 25, what=f"25 scans on {map_id}")
    assert wait_idle(registry)
    for map_id, payloads in sent.items():
        entry = registry.get(map_id)
        assert_same_map(entry.gmap, engine_map(payloads))
        state = entry.robots["r1"]
        assert (state.last_seq, state.lost, state.duplicates, state.scans_rejected) == (24, 0, 0, 0)
        assert state.last_stamp == pytest.approx(24 * 0.2)
    status = ingest.status()
    assert status["messages_received"] == 50 and status["scans_submitted"] == 50
    assert status["decode_errors"] == 0 and status["invalid_keys"] == 0


def test_bad_payloads_are_counted_per_robot_with_reasons_and_change_nothing(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session
) -> None:
    good = sim_scans(4, 3)
    pub = scan_publisher(robot, "m", "r1", BINARY_ENCODING)
    for seq, scan in enumerate(good):
        pub.put(codec.encode_binary(scan, seq))
    wait_for(lambda: integrated(registry, "m", "r1") == 3, what="the good scans")
    entry = registry.get("m")
    before = (entry.gmap.store.clock, entry.gmap.region("log_odds", *entry.gmap.known_bounds()))

    valid_json = json.loads(codec.encode_json(good[0], 10))
    binary = codec.encode_binary(good[0], 11)
    bad: list[tuple[bytes, str, str]] = [  # (payload, encoding, a word the reason must contain)
        (b"not json at all", JSON_ENCODING, "invalid JSON"),
        (json.dumps({k: v for k, v in valid_json.items() if k != "pose"}).encode(), JSON_ENCODING, "pose"),
        (json.dumps({**valid_json, "range_min": -1.0}).encode(), JSON_ENCODING, "range_min"),
        (b"XXXX" + binary[4:], BINARY_ENCODING, "magic"),
        (binary[:-4], BINARY_ENCODING, "bytes"),
        (binary[:40], BINARY_ENCODING, "header"),
        (binary, "text/plain", "unknown encoding"),
    ]  # fmt: skip
    state = entry.robots["r1"]
    for k, (payload, encoding, reason) in enumerate(bad):
        robot.put(SCAN_KEY.format(map_id="m", robot_id="r1"), payload, encoding=zenoh.Encoding(encoding),
                  congestion_control=zenoh.CongestionControl.BLOCK)  # fmt: skip
        # Checked one by one: last_error holds only the latest reason.
        wait_for(lambda n=k + 1: ingest.status()["decode_errors"] == n, what=f"decode error {k}")
        assert reason in (state.last_error or ""), (reason, state.last_error)
    wait_for(lambda: ingest.status()["decode_errors"] == len(bad), what="every bad payload")
    assert state.scans_rejected == len(bad) and entry.scans_rejected == len(bad)
    assert "unknown encoding" in (state.last_error or "")
    assert wait_idle(registry)
    assert entry.gmap.store.clock == before[0]  # no tile was written
    np.testing.assert_array_equal(entry.gmap.region("log_odds", *entry.gmap.known_bounds()), before[1])
    assert state.scans_integrated == 3 and state.last_seq == 2  # refused messages do not move seq


@pytest.mark.parametrize(
    ("payload", "encoding", "reason"),
    [
        (b"{}", JSON_ENCODING, "seq"),
        (b'{"seq": 1, "pose": {"x": 0, "y": 0, "theta": 0}, "ranges": [1.0]}', JSON_ENCODING, "angle_min"),
        (b"FMS1" + bytes(68), BINARY_ENCODING, "version"),
        (b"", BINARY_ENCODING, "header"),
        # Payloads whose start is wrong were refused as "unknown encoding 'zenoh/bytes'" (an encoding
        # docs/protocol.md accepts) or "expected value at line 1 column 1" (a byte order mark).
        (b"", "zenoh/bytes", "neither a binary scan (magic b'FMS1') nor a JSON object"),
        (b'\n{"seq": 1}', "application/octet-stream", "payload starting b'\\n{\"seq\":'"),
        (b'\xef\xbb\xbf{"seq": 1}', JSON_ENCODING, "starts with a byte order mark"),
        (b'\xef\xbb\xbf{"seq": 1}', "zenoh/bytes", "starts with a byte order mark"),
    ],
)
def test_each_decode_error_reason_reaches_the_robot(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session, payload: bytes, encoding: str,
    reason: str,
) -> None:  # fmt: skip
    registry.create("m")
    robot.put(SCAN_KEY.format(map_id="m", robot_id="r9"), payload, encoding=zenoh.Encoding(encoding))
    wait_for(lambda: ingest.status()["decode_errors"] == 1, what="the decode error")
    state = registry.get("m").robots["r9"]
    assert state.scans_rejected == 1 and reason in (state.last_error or "")
    assert state.scans_integrated == 0 and state.last_seq is None


def test_an_oversized_payload_is_refused_before_it_is_copied(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session
) -> None:
    """A payload over the limit (4 MiB) is refused by its size before it is copied out of Zenoh's
    buffer: Zenoh takes messages of up to 1 GiB, and one copied whole into Python to be refused held
    its size again (170 MB more for a 200 MB put). Python's allocations are traced meanwhile."""
    registry.create("m")
    size = 64 << 20
    tracemalloc.start()
    try:
        robot.put(
            SCAN_KEY.format(map_id="m", robot_id="r9"), bytes(size), encoding=zenoh.Encoding(BINARY_ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,  # a message this big is dropped otherwise
        )  # fmt: skip
        tracemalloc.reset_peak()  # the test's own 64 MB payload is not the service's
        wait_for(lambda: ingest.status()["decode_errors"] == 1, what="the refusal", timeout=60)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    state = registry.get("m").robots["r9"]
    assert state.scans_rejected == 1 and f"payload of {size} bytes exceeds the limit" in (
        state.last_error or ""
    )
    assert peak < size // 4, f"{peak} bytes allocated by Python while a {size}-byte payload was refused"


def test_invalid_keys_are_counted_globally_and_create_nothing(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session
) -> None:
    """Also an id followed by a newline, which Zenoh keys may hold: it was taken as valid (`$`
    matches before a last newline), and made a map `m\n` that no URL names (nor deletes), its robot
    in /metrics under an escaped label and its id breaking log lines."""
    payload = codec.encode_binary(sim_scans(5, 1)[0], 0)
    keys = (
        "fleetmap/bad.id/r1/scan", f"fleetmap/{'x' * 65}/r1/scan", "fleetmap/m/r~1/scan",
        "fleetmap/m\n/r1/scan", "fleetmap/m/r1\n/scan",
    )  # fmt: skip
    for key in keys:
        robot.put(key, payload, encoding=zenoh.Encoding(BINARY_ENCODING))
    token = robot.liveliness().declare_token("fleetmap/m\n/r1\n/alive")
    try:
        wait_for(lambda: ingest.status()["invalid_keys"] == 6, what="six invalid keys")
        assert registry.list() == []
        assert ingest.status()["scans_submitted"] == 0
    finally:
        token.undeclare()
    # The invalid token's disappearance is not a second message ignored: it was counted again, so
    # `invalid_keys` grew by two for each token. A valid token after it, seen in order on the same
    # subscriber, shows that the disappearance was handled.
    valid = robot.liveliness().declare_token("fleetmap/m/r2/alive")
    try:
        wait_for(lambda: ingest.status()["robots_alive"] == 1, what="the valid token")
        assert ingest.status()["invalid_keys"] == 6
    finally:
        valid.undeclare()


def test_an_invalid_key_is_logged_cut_short(
    ingest: ZenohIngest, robot: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A key is the sender's to make as long as a Zenoh message holds (some 60 KB): its warning
    wrote it whole, a 60 KB log line every 5 s from one peer (a scan's field names are cut short in
    its reason; the ROS ingest cuts keys to 200 characters)."""
    payload = codec.encode_binary(sim_scans(5, 1)[0], 0)
    long_id = "x" * 30_000
    with caplog.at_level(logging.WARNING, logger="fleetmap.ingest"):
        robot.put(f"fleetmap/{long_id}/r1/scan", payload, encoding=zenoh.Encoding(BINARY_ENCODING))
        token = robot.liveliness().declare_token(f"fleetmap/m/{long_id}/alive")
        try:
            wait_for(lambda: ingest.status()["invalid_keys"] == 2, what="both invalid keys")
            wait_for(lambda: len(caplog.records) == 2, what="a line for each")
        finally:
            token.undeclare()
    for record in caplog.records:
        line = record.getMessage()
        assert len(line) < 500, line[:300]
        # Both keys, fleetmap/<id>/r1/scan and fleetmap/m/<id>/alive, are 30017 characters long.
        assert "invalid key 'fleetmap/" in line and "... (30017 characters)" in line, line[:300]
    assert {"scan", "liveliness"} == {
        "scan" if " scan " in r.getMessage() else "liveliness" for r in caplog.records
    }


def test_a_scan_refused_at_integration_is_logged_with_its_reason(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A robot's scan refused by its map (past `max_tiles`, or the memory budget) was counted on the
    robot and nowhere in the log, where every other refusal of a Zenoh scan is (rate-limited): the
    robot is told nothing, and an operator reading the log saw none of its scans refused."""
    registry.create("tiny", MapConfig(tile_size=16, max_tiles=1))
    far = Scan.from_fan((0.4, 0.4, 0.0), -1.0, 0.1, [20.0] * 20, 0.05, 30.0)
    with caplog.at_level(logging.WARNING, logger="fleetmap.registry"):
        robot.put(
            SCAN_KEY.format(map_id="tiny", robot_id="r1"),
            codec.encode_binary(far, 7, session=5),
            encoding=zenoh.Encoding(BINARY_ENCODING),
        )
        wait_for(lambda: "r1" in registry.get("tiny").robots, what="the robot")
        state = wait_for(
            lambda: (s := registry.get("tiny").robots["r1"]).scans_rejected and s, what="the refusal"
        )
        wait_for(lambda: caplog.records, what="a log line")
    assert state.last_error is not None and "max_tiles" in state.last_error
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "scan seq 7 from tiny/r1 refused" in lines[0], lines
    assert state.last_error in lines[0]


def test_a_scan_refused_at_the_input_limits_is_logged_with_its_seq_as_a_field(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A log line about a scan carries its `seq` as a field beside `map_id` and `robot_id` (docs/
    security.md, "What is logged": a JSON log pipeline filters on it), as the lines of the scans the
    registry refuses do; a well-formed scan refused at the input limits (a pose outside the world
    bound), whose seq the line's text names, had no such field."""
    far = Scan.from_fan((1e9, 0.0, 0.0), -1.0, 0.1, [2.0] * 10, 0.05, 30.0)
    with caplog.at_level(logging.WARNING, logger="fleetmap.ingest"):
        robot.put(
            SCAN_KEY.format(map_id="m", robot_id="far"),
            codec.encode_binary(far, 7, session=5),
            encoding=zenoh.Encoding(BINARY_ENCODING),
        )
        wait_for(lambda: caplog.records, what="a log line")
    (record,) = caplog.records
    assert "scan seq 7 refused" in record.getMessage(), record.getMessage()
    assert (record.map_id, record.robot_id, record.seq) == ("m", "far", 7)  # type: ignore[attr-defined]


def test_parse_key() -> None:
    assert parse_key("fleetmap/m-1/r_2/scan", "scan") == ("m-1", "r_2")
    assert parse_key("fleetmap/m/r/alive", "scan") is None
    assert parse_key("fleetmap/m/r/x/scan", "scan") is None
    assert parse_key("other/m/r/scan", "scan") is None
    assert parse_key("fleetmap/m/r:1/scan", "scan") is None
    assert parse_key("fleetmap/m\n/r/scan", "scan") is None
    assert parse_key("fleetmap/m/r\n/scan", "scan") is None


def test_seq_gaps_duplicates_and_restart_are_accounted(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session
) -> None:
    scans = sim_scans(6, 10)
    pub = scan_publisher(robot, "m", "r1", BINARY_ENCODING)
    seqs = [0, 1, 2, 2, 5, 6, 1, 0, 1]  # dup 2; 3-4 lost; stale 1 is a duplicate; 0 restarts
    for k, seq in enumerate(seqs):
        pub.put(codec.encode_binary(scans[k], seq))
    wait_for(lambda: ingest.status()["messages_received"] == len(seqs), what="every message")
    assert wait_idle(registry)
    state = registry.get("m").robots["r1"]
    assert (state.scans_integrated, state.duplicates, state.lost, state.last_seq) == (7, 2, 2, 1)
    assert ingest.status()["rejected"] == {"duplicate": 2}


def test_full_queue_refuses_the_newest_without_blocking_the_callback() -> None:
    """While the map is locked, integration stalls; the Zenoh callback keeps accepting (it never
    waits), the per-robot queue fills, and the newest scans are refused and counted as dropped.
    The scans that do get integrated are the oldest ones, in order.

    The first scan is published alone and the test waits until the worker has taken it off the
    queue (it then waits for the lock): otherwise the first scans can fill the queue before the
    worker takes one, and the slot it frees then goes to whichever scan comes next, a race that
    decides which scans are kept (a clean CI run once kept seqs 0, 1 and 3)."""
    registry = MapRegistry(workers=1, queue_per_robot=2)
    registry.start()
    ingest = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    ingest.start()
    session = client_session(ingest.listen[0])
    try:
        entry, _ = registry.create("m")
        scans = sim_scans(7, 12)
        pub = scan_publisher(session, "m", "r1", BINARY_ENCODING)
        payloads = [codec.encode_binary(s, k) for k, s in enumerate(scans)]
        with entry.gmap.lock:
            pub.put(payloads[0])
            wait_for(lambda: ingest.status()["scans_submitted"] == 1, what="the first scan queued")
            wait_for(lambda: registry.backlog()[0] == 0, what="the worker to take the first scan")
            for p in payloads[1:]:
                pub.put(p)
            wait_for(lambda: ingest.status()["messages_received"] == 12, what="all 12 delivered while locked")
        assert wait_idle(registry)
        state = entry.robots["r1"]
        assert state.dropped == 12 - 3  # one in flight and two queued got through
        assert state.scans_integrated == 3
        assert ingest.status()["rejected"] == {"queue_full": state.dropped}
        kept = state.scans_integrated
        assert_same_map(entry.gmap, engine_map([(p, BINARY_ENCODING) for p in payloads[:kept]]))
    finally:
        session.close()
        ingest.close()
        registry.close()


def test_a_map_full_of_robots_that_left_makes_room_for_new_ones() -> None:
    """Robots come and go over a map's life (replaced, renamed, a fleet of short missions). Once a
    map had seen `max_robots_per_map` (1024) robot ids, every new robot was refused for good (429),
    although the earlier ones had all left. Now the offline robot heard from least recently is
    forgotten to make room; an online robot never is, however long ago it last sent a scan."""
    registry = MapRegistry(max_robots_per_map=3)
    registry.start()
    ingest = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    ingest.start()
    endpoint = ingest.listen[0]
    scans = sim_scans(9, 2)

    def online(robot_id: str) -> bool | None:
        with registry.lock:
            state = registry.get("m").robots.get(robot_id)
            return None if state is None else state.online

    try:
        with ScanPublisher("m", "stays", connect=endpoint) as stays:
            assert stays.wait_connected(10) and stays.publish(scans[0])
            wait_for(lambda: integrated(registry, "m", "stays") == 1, timeout=10, what="its scan")
            for robot_id in ("left-1", "left-2", "left-3", "left-4"):
                with ScanPublisher("m", robot_id, connect=endpoint) as pub:
                    assert pub.wait_connected(10)
                    assert all(pub.publish(scan) for scan in scans)
                    wait_for(lambda r=robot_id: integrated(registry, "m", r) == 2, timeout=5, what=robot_id)
                wait_for(lambda r=robot_id: online(r) is False, timeout=10, what=f"{robot_id} offline")
            entry = registry.get("m")
            with registry.lock:
                assert sorted(entry.robots) == ["left-3", "left-4", "stays"]
            assert entry.scans_integrated == 9 and entry.scans_rejected == 0
            assert ingest.status()["rejected"] == {}
    finally:
        ingest.close()
        registry.close()


def test_liveliness_online_offline_including_tokens_older_than_the_service(registry: MapRegistry) -> None:
    port = free_port()
    # A router already up with a robot online before the service joins: history=True reports it.
    router_cfg = zenoh.Config()
    router_cfg.insert_json5("mode", '"router"')
    router_cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    router_cfg.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(router_cfg)
    early = client_session(f"tcp/127.0.0.1:{port}")
    early_token = early.liveliness().declare_token(ALIVE_KEY.format(map_id="m", robot_id="early"))
    ingest = ZenohIngest(registry, connect=[f"tcp/127.0.0.1:{port}"])  # joins as a client
    try:
        ingest.start()
        assert ingest.mode == "client"

        def online(robot_id: str) -> bool | None:
            try:
                state = registry.get("m").robots.get(robot_id)
            except KeyError:
                return None
            return state.online if state else None

        wait_for(lambda: online("early") is True, what="the early robot online")
        late = client_session(f"tcp/127.0.0.1:{port}")
        late_token = late.liveliness().declare_token(ALIVE_KEY.format(map_id="m", robot_id="late"))
        wait_for(lambda: online("late") is True, what="the late robot online")
        late_token.undeclare()
        wait_for(lambda: online("late") is False, what="the late robot offline after undeclare")
        assert online("early") is True
        early.close()  # the session goes away, and its token with it
        del early_token
        wait_for(lambda: online("early") is False, what="the early robot offline after its session closed")
        late.close()
        assert ingest.status()["liveliness_events"] == 4
    finally:
        ingest.close()
        router.close()


def test_a_token_its_map_cannot_show_is_not_logged_as_a_robot_online(tmp_path: Path) -> None:
    """A liveliness token for a robot its map has no room for (every robot it holds online) was
    logged "robot full/b is online", and its going "offline", though GET /maps/{id} and /metrics
    listed no such robot. The line now says the robot is not on its map, and why; a robot the map
    shows keeps its plain line."""
    with ServiceProcess(tmp_path, ["--in-memory", "--max-robots-per-map", "1"]) as svc:
        session = client_session(svc.zenoh_endpoint)
        try:
            a = session.liveliness().declare_token(ALIVE_KEY.format(map_id="full", robot_id="a"))
            wait_for(lambda: "robot full/a is online" in svc.logs(), timeout=20, what="a's token")
            b = session.liveliness().declare_token(ALIVE_KEY.format(map_id="full", robot_id="b"))
            wait_for(lambda: "robot full/b is online" in svc.logs(), timeout=20, what="b's token")
            robots = httpx.get(f"{svc.base_url}/maps/full", timeout=10).json()["stats"]["robots"]
            assert sorted(robots) == ["a"] and robots["a"]["online"] is True
            assert 'robot="b"' not in httpx.get(f"{svc.base_url}/metrics", timeout=10).text
            lines = {line.split(": ", 1)[1] for line in svc.logs().splitlines() if "robot full/" in line}
            assert "robot full/a is online" in lines, lines
            assert (
                "robot full/b is online (its liveliness token), but not on its map: map 'full' already "
                "has 1 robots, the most it may have, every one online or with scans waiting"
            ) in lines, lines
            b.undeclare()
            a.undeclare()
            wait_for(lambda: "robot full/a is offline" in svc.logs(), timeout=20, what="a offline")
        finally:
            session.close()


def test_robot_online_again_after_its_map_is_recreated(
    registry: MapRegistry, ingest: ZenohIngest, robot: zenoh.Session
) -> None:
    """A deleted map comes back (auto-create) with its robot still online: the token is still there."""
    token = robot.liveliness().declare_token(ALIVE_KEY.format(map_id="m", robot_id="r1"))
    wait_for(lambda: "m" in registry.maps and registry.get("m").robots["r1"].online, what="online")
    registry.delete("m")
    pub = scan_publisher(robot, "m", "r1", BINARY_ENCODING)
    pub.put(codec.encode_binary(sim_scans(8, 1)[0], 0))
    wait_for(lambda: integrated(registry, "m", "r1") == 1, what="the scan on the new map")
    assert registry.get("m").robots["r1"].online is True
    token.undeclare()


def test_joining_an_existing_network_as_a_peer(registry: MapRegistry) -> None:
    """With connect AND listen endpoints the service is a peer: robots reach it both through the
    existing router and directly."""
    router_port, own_port = free_port(), free_port()
    router_cfg = zenoh.Config()
    router_cfg.insert_json5("mode", '"router"')
    router_cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{router_port}"]))
    router_cfg.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(router_cfg)
    ingest = ZenohIngest(
        registry, connect=[f"tcp/127.0.0.1:{router_port}"], listen=[f"tcp/127.0.0.1:{own_port}"]
    )
    sessions: list[zenoh.Session] = []
    try:
        ingest.start()
        assert ingest.mode == "peer"
        for robot_id, port in (("via-router", router_port), ("direct", own_port)):
            session = client_session(f"tcp/127.0.0.1:{port}")
            sessions.append(session)
            pub = scan_publisher(session, "m", robot_id, BINARY_ENCODING)
            pub.put(codec.encode_binary(sim_scans(9, 1)[0], 0))
        for robot_id in ("via-router", "direct"):
            wait_for(lambda r=robot_id: integrated(registry, "m", r) == 1, what=f"{robot_id}'s scan")
    finally:
        for session in sessions:
            session.close()
        ingest.close()
        router.close()


@pytest.mark.parametrize("mode", ["client", "peer"])
def test_the_service_meets_a_restarted_router_within_a_second_of_it_listening(
    registry: MapRegistry, mode: str
) -> None:
    """The router the service joined (`--zenoh-connect`) goes away for 6 s and comes back: the
    service is connected to it again within 2 s of it becoming reachable (its retry is 0.5 s at
    most, `CONNECT_RETRY`). The proxy refuses connections until just after one of the service's
    attempts failed, so the time measured is the wait for its next attempt. With Zenoh's default
    `connect/retry` (1 s growing to 4 s) it was about 4 s, in both modes."""
    router_port = free_port()
    router_cfg = zenoh.Config()
    router_cfg.insert_json5("mode", '"router"')
    router_cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{router_port}"]))
    router_cfg.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(router_cfg)
    proxy = FreezableProxy(router_port)
    listen = [f"tcp/127.0.0.1:{free_port()}"] if mode == "peer" else []
    ingest = ZenohIngest(registry, connect=[proxy.endpoint], listen=listen)

    def routers() -> int:
        return int(ingest.status().get("routers", 0))

    try:
        ingest.start()
        assert ingest.mode == mode
        wait_for(lambda: routers() == 1, 10, 0.01, "the service to join the router")
        router.close()
        proxy.cut()  # refused from now on, and counted: the service's attempts
        away = time.monotonic()
        wait_for(lambda: routers() == 0, 15, 0.01, "the service to notice the router left")
        router = zenoh.open(router_cfg)
        # Past the backoff's first steps (Zenoh's default tries again 1, 3, 7, 11 s after the loss).
        time.sleep(max(0.0, away + 6.0 - time.monotonic()))
        attempts = len(proxy.refused)
        try:
            wait_for(lambda: len(proxy.refused) > attempts, 10, 0.002, "a connection attempt")
        except AssertionError:
            tries = [round(t - away, 2) for t in proxy.refused]
            raise AssertionError(
                f"no connection attempt of the service 6 to 16 s after the router left; attempts at "
                f"{tries}; ingest status {ingest.status()}"
            ) from None
        proxy.restore()
        reachable = time.monotonic()
        wait_for(lambda: routers() == 1, 20, 0.01, "the service to join the router again")
        took = time.monotonic() - reachable
        tries = [round(t - away, 2) for t in proxy.refused]
        assert took < 2.0, f"joined {took:.2f} s after the router was reachable; attempts at {tries}"
    finally:
        ingest.close()
        proxy.close()
        router.close()


def test_config_file_is_loaded_first_and_arguments_apply_on_top(registry: MapRegistry, tmp_path) -> None:  # noqa: ANN001
    port_file, port_arg = free_port(), free_port()
    path = tmp_path / "zenoh.json5"
    path.write_text(
        "{\n  // a JSON5 comment\n  mode: 'peer',\n"
        f"  listen: {{ endpoints: ['tcp/127.0.0.1:{port_file}'] }},\n}}\n"
    )
    from_file = ZenohIngest(registry, config_file=path)
    cfg = from_file.build_config()
    assert from_file.mode == "peer" and from_file.listen == [f"tcp/127.0.0.1:{port_file}"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    overridden = ZenohIngest(registry, config_file=path, listen=[f"tcp/127.0.0.1:{port_arg}"], mode="router")
    overridden.start()
    try:
        status = overridden.status()
        assert status["mode"] == "router" and status["endpoints"] == [f"tcp/127.0.0.1:{port_arg}"]
        session = client_session(f"tcp/127.0.0.1:{port_arg}")  # really listening there
        session.close()
    finally:
        overridden.close()


def test_a_config_file_giving_listen_endpoints_per_mode_listens_on_the_services_modes(
    registry: MapRegistry, tmp_path: Path
) -> None:
    """Zenoh takes `listen/endpoints` per mode too (`{router: [...], peer: [...]}`), and the
    service took such a file's endpoints for none: it listened on loopback alone, robots on other
    machines kept out without a word. It listens on its mode's now; a file that repeats Zenoh's own
    default per-mode endpoints still gets the service's default, loopback."""
    router_port, peer_port = free_port(), free_port()
    path = tmp_path / "zenoh.json5"
    path.write_text(
        f"{{ listen: {{ endpoints: {{ router: ['tcp/127.0.0.1:{router_port}'], "
        f"peer: ['tcp/127.0.0.1:{peer_port}'] }} }} }}"
    )
    as_router = ZenohIngest(registry, config_file=path)
    as_router.build_config()
    assert as_router.mode == "router" and as_router.listen == [f"tcp/127.0.0.1:{router_port}"]
    as_peer = ZenohIngest(registry, config_file=path, mode="peer")
    as_peer.build_config()
    assert as_peer.listen == [f"tcp/127.0.0.1:{peer_port}"]
    default = json.loads(zenoh.Config().get_json("listen/endpoints"))
    path.write_text(json.dumps({"listen": {"endpoints": default}}))
    copied = ZenohIngest(registry, config_file=path)
    copied.build_config()
    assert copied.listen == list(DEFAULT_LISTEN)


@pytest.mark.parametrize(
    ("setting", "stamps", "warns"),
    [("{ peer: false }", False, False), ("{ router: true }", True, True), ("true", True, True)],
)
def test_a_config_file_timestamps_only_when_it_says_so_for_the_services_mode(
    registry: MapRegistry,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    setting: str,
    stamps: bool,
    warns: bool,
) -> None:
    """`timestamping/enabled` set per mode for other modes than the service's (a router here) left
    the service's own at Zenoh's default, which is on for a router: its session stamped every sample,
    silently (no warning), and the advanced subscriber dropped plain publishers' scans. Unset for
    the service's mode, it is switched off; set on for it, it stays on with a warning. Checked on a
    real session: does a sample a client puts reach the service's session with a timestamp?"""
    path = tmp_path / "zenoh.json5"
    path.write_text(f"{{ timestamping: {{ enabled: {setting} }} }}\n")
    ingest = ZenohIngest(registry, config_file=path, listen=[f"tcp/127.0.0.1:{free_port()}"])
    with caplog.at_level(logging.WARNING, logger="fleetmap.ingest"):
        session = zenoh.open(ingest.build_config())
    assert ingest.mode == "router"
    assert ("sets timestamping/enabled" in caplog.text) is warns
    got: list[zenoh.Timestamp | None] = []
    sub = session.declare_subscriber("ts/check", lambda sample: got.append(sample.timestamp))
    client = client_session(ingest.listen[0])
    try:
        wait_for(lambda: client.info.routers_zid(), 10, 0.02, "the client to connect")
        client.put("ts/check", b"x")
        wait_for(lambda: got, 10, 0.02, "the sample")
        assert (got[0] is not None) is stamps
    finally:
        client.close()
        sub.undeclare()
        session.close()


def test_default_mode_is_a_router_on_the_default_endpoint(registry: MapRegistry) -> None:
    ing = ZenohIngest(registry)
    cfg = ing.build_config()
    assert ing.mode == "router" and ing.listen == ["tcp/127.0.0.1:7447"]
    assert json.loads(cfg.get_json("mode")) == "router"
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False  # Zenoh's default: true
    assert json.loads(cfg.get_json("connect/retry"))["period_max_ms"] == 500  # Zenoh's default: 4000


def test_a_router_subscribes_as_soon_as_it_listens(registry: MapRegistry, tmp_path: Path) -> None:
    """The service's router accepts robots from the moment it listens; `zenoh.open` then waited
    Zenoh's `scouting/delay` (0.5 s) before the scan subscriber could be declared. Robots waiting for
    a restarted service connected in that time, and the subscriber's history then fetched their
    caches twice at once (its first query, and one per publisher it detects), which lost part of a
    robot's cache: 6 to 450 scans, in about half of tests/test_crash_exactly_once.py's runs of 10
    restarts. A router that connects to no one waits for nothing now; with connect endpoints, or
    when its configuration file sets the delay, Zenoh's is kept."""
    ingest = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    assert json.loads(ingest.build_config().get_json("scouting/delay")) == 0
    started = time.monotonic()
    ingest.start()
    try:
        assert time.monotonic() - started < 0.25  # was 0.5 s and more
    finally:
        ingest.close()
    joined = ZenohIngest(registry, listen=[], connect=[f"tcp/127.0.0.1:{free_port()}"], mode="peer")
    assert json.loads(joined.build_config().get_json("scouting/delay")) is None
    path = tmp_path / "zenoh.json5"
    path.write_text("{ scouting: { delay: 200 } }")
    from_file = ZenohIngest(registry, config_file=path).build_config()
    assert json.loads(from_file.get_json("scouting/delay")) == 200


def test_shared_memory_only_when_asked(registry: MapRegistry, tmp_path) -> None:  # noqa: ANN001
    """Shared memory stays off even when a config file switches it on, unless the service is told
    (`--zenoh-shared-memory`)."""
    path = tmp_path / "zenoh.json5"
    path.write_text("{ transport: { shared_memory: { enabled: true } } }")
    cfg = ZenohIngest(registry, config_file=path).build_config()
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    port = free_port()
    ing = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{port}"], shared_memory=True)
    assert json.loads(ing.build_config().get_json("transport/shared_memory/enabled")) is True


def test_start_errors_are_readable(registry: MapRegistry, tmp_path) -> None:  # noqa: ANN001
    port = free_port()
    first = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{port}"])
    first.start()
    try:
        with pytest.raises(IngestStartError, match="in use") as info:
            ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{port}"]).start()
        assert ".rs:" not in str(info.value)  # no Rust source locations
    finally:
        first.close()
    with pytest.raises(IngestStartError, match="endpoint"):
        ZenohIngest(registry, listen=["nonsense"]).start()
    with pytest.raises(IngestStartError, match="cannot load Zenoh config"):
        ZenohIngest(registry, config_file=tmp_path / "missing.json5").start()
    with pytest.raises(IngestStartError, match="cannot open"):
        ZenohIngest(registry, connect=[f"tcp/127.0.0.1:{free_port()}"]).start()  # a client, nobody there
    with pytest.raises(ValueError, match="mode"):
        ZenohIngest(registry, mode="satellite")


def test_a_listen_endpoint_given_twice_is_refused_as_such(registry: MapRegistry, tmp_path: Path) -> None:
    """`--zenoh-listen tcp/127.0.0.1:7447 tcp/127.0.0.1:7447` (or the endpoint in the config file and
    on the command line, now that a list option given twice takes both) failed with Zenoh's
    "Address already in use", which sent the user after another process that was not there.
    Two `:0` endpoints are two free ports (`with_free_port`), not one endpoint twice."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(IngestStartError, match=f"listen endpoint {endpoint} is given twice"):
        ZenohIngest(registry, listen=[endpoint, f"tcp/127.0.0.1:{free_port()}", endpoint]).build_config()
    path = tmp_path / "zenoh.json5"
    path.write_text(f"{{ listen: {{ endpoints: ['{endpoint}', '{endpoint}'] }} }}\n")
    with pytest.raises(IngestStartError, match="given twice"):
        ZenohIngest(registry, config_file=path).build_config()
    ZenohIngest(registry, listen=["tcp/127.0.0.1:0", "tcp/127.0.0.1:0"]).build_config()


def test_close_is_idempotent_and_stops_ingest(registry: MapRegistry) -> None:
    ing = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    ing.start()
    endpoint = ing.listen[0]
    ing.close()
    ing.close()
    assert ing.status()["running"] is False
    with pytest.raises(zenoh.ZError):
        client_session(endpoint)  # nothing listens any more


def test_rate_limited_log_holds_back_repeats(caplog: pytest.LogCaptureFixture) -> None:
    limited = RateLimitedLog(logging.getLogger("test.ratelimit"), interval=0.2)
    with caplog.at_level(logging.WARNING, logger="test.ratelimit"):
        results = [limited.warning("a", f"message {k}") for k in range(100)]
        assert limited.warning("b", "other category")
        time.sleep(0.25)
        assert limited.warning("a", "after the interval")
    assert results.count(True) == 1
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["message 0", "other category", "after the interval (99 similar messages suppressed)"]


def test_rate_limited_log_bounds_lines_and_memory_across_categories(caplog: pytest.LogCaptureFixture) -> None:
    """20,000 bad messages under 20,000 robot ids wrote 20,000 lines, and the held-back counts of
    categories never logged again stayed in memory for good."""
    limited = RateLimitedLog(logging.getLogger("test.ratelimit"), interval=60.0, max_lines=20)
    with caplog.at_level(logging.WARNING, logger="test.ratelimit"):
        for k in range(20_000):
            limited.warning(f"decode:m/r{k}", f"message {k}")
            limited.warning(f"decode:m/r{k}", f"again {k}")
    assert len(caplog.records) == 20
    assert len(limited._held) <= 10_001 and len(limited._last) <= 10_001
    limited._window -= 61.0  # the next interval: the budget is back, and says what it held
    assert limited.warning("decode:m/later", "later")
    assert caplog.records[-1].getMessage().startswith("later (") and "other messages suppressed" in (
        caplog.records[-1].getMessage()
    )


def test_a_map_created_by_a_refused_zenoh_scan_is_removed_again() -> None:
    """Over Zenoh too, a scan that auto-creates its map and is then refused (past max_tiles) leaves
    no map behind; a robot whose liveliness token is up keeps its map (the token creates it)."""
    registry = MapRegistry(default_config=MapConfig(max_tiles=1, tile_size=16, resolution=0.1))
    registry.start()
    ingest = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    ingest.start()
    session = client_session(ingest.listen[0])
    try:
        token = session.liveliness().declare_token(ALIVE_KEY.format(map_id="tokened", robot_id="r1"))
        wait_for(lambda: "tokened" in registry.maps, what="the token's map")
        too_big = codec.encode_binary(Scan.from_fan((0.0, 0.0, 0.0), -0.5, 0.05, [20.0] * 20, 0.0, 30.0), 0)
        for map_id in ("fresh", "tokened"):
            scan_publisher(session, map_id, "r1", BINARY_ENCODING).put(too_big)
        wait_for(lambda: ingest.status()["scans_submitted"] == 2, what="both scans submitted")
        assert wait_idle(registry)
        assert list(registry.maps) == ["tokened"]
        assert "max_tiles" in registry.get("tokened").robots["r1"].last_error
        token.undeclare()
    finally:
        session.close()
        ingest.close()
        registry.close()


def test_plain_publishers_publishing_at_once_lose_no_sample(registry: MapRegistry) -> None:
    """The scan subscriber is zenoh-ext's advanced subscriber, which orders samples without a
    sequence number (plain publishers') by their timestamps and drops one older than the last it
    delivered. A Zenoh router timestamps every sample by default, with one clock, on several
    receiving threads: 6 robots publishing 2000 samples each at once lost 7 to 21 each. The service's
    session does not timestamp, so none is lost."""
    ingest = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    ingest.start()
    assert json.loads(ingest.build_config().get_json("timestamping/enabled")) is False
    robots, count = 6, 1000
    sessions = [client_session(ingest.endpoints[0]) for _ in range(robots)]
    try:
        pubs = [scan_publisher(s, "burst", f"r{k}", BINARY_ENCODING) for k, s in enumerate(sessions)]

        def publish(pub: zenoh.Publisher) -> None:
            for _ in range(count):
                pub.put(b"x")  # undecodable: counted, never queued, so nothing but delivery is measured

        threads = [threading.Thread(target=publish, args=(pub,)) for pub in pubs]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wait_for(lambda: ingest.status()["messages_received"] >= robots * count, 10, 0.05, "every sample")
        time.sleep(0.2)
        assert ingest.status()["messages_received"] == robots * count
    finally:
        for s in sessions:
            s.close()
        ingest.close()


def test_the_services_zenoh_callback_threads_are_waited_for_at_exit_and_end_with_close(
    registry: MapRegistry,
) -> None:
    """zenoh-python runs each Python callback on a thread of its own ("pyo3-closure"), a daemon when
    the declaring thread is one. `fleetmap serve` declares its callbacks (the scan ingest's, and
    with `--ros-scans` and `--ros-publish-map` the ROS ones) from the main thread: their threads are
    not daemons, so none is left running, unjoined, into the interpreter's finalization (a daemon
    one coming back from Zenoh then aborts the process: "FATAL: exception not rethrown"). The
    interpreter waits for such threads at exit: each ends when its declaration goes, in `close`,
    or `fleetmap serve` would hang after it stopped."""
    from fleetmap.ros.ingest import RosScanIngest
    from fleetmap.ros.map_publisher import MapTopic, RosMapOptions, RosMapPublisher

    def callback_threads() -> set[threading.Thread]:
        return {t for t in threading.enumerate() if "pyo3-closure" in t.name}

    before = callback_threads()
    ingest = ZenohIngest(registry, listen=[f"tcp/127.0.0.1:{free_port()}"])
    ingest.start()
    assert ingest.session is not None
    ros = RosScanIngest(registry, ingest.session, "lab")
    ros.start()
    ros_maps = RosMapPublisher(registry, ingest.session, RosMapOptions((MapTopic("lab"),), period=3600.0))
    ros_maps.start()
    started = callback_threads() - before
    assert started and not any(t.daemon for t in started), started
    ros_maps.close()  # in the order of `fleetmap serve`'s shutdown
    ros.close()
    ingest.close()
    for thread in started:
        thread.join(10)
    assert not any(t.is_alive() for t in started), started


def test_a_listen_endpoint_on_port_0_says_the_port_robots_reach(registry: MapRegistry) -> None:
    """`fleetmap serve --zenoh-listen tcp/127.0.0.1:0` listened on a port Zenoh picked and reports
    nowhere, and its start-up line, ready line and /healthz all said `tcp/127.0.0.1:0`: no robot
    could be pointed at it. The service picks the free port itself, as `--http HOST:0` does, and
    says that one: a robot connecting there has its scans integrated."""
    ingest = ZenohIngest(registry, listen=["tcp/127.0.0.1:0", f"tcp/127.0.0.1:{free_port()}"])
    ingest.start()
    try:
        endpoint = ingest.listen[0]
        host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
        assert host == "127.0.0.1" and int(port) > 0, endpoint
        assert ingest.status()["listen"] == ingest.listen and ingest.status()["endpoints"][0] == endpoint
        session = client_session(endpoint)
        try:
            pub = scan_publisher(session, "m", "r1", BINARY_ENCODING)
            pub.put(codec.encode_binary(sim_scans(3, 1)[0], 0))
            wait_for(lambda: integrated(registry, "m", "r1") == 1, what="the scan sent to the port said")
        finally:
            session.close()
    finally:
        ingest.close()
