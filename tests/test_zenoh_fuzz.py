"""Zenoh fuzzing with real processes: thousands of random and malformed payloads on the scan keys
while a real robot keeps publishing.

The service (`python -m fleetmap.server`, with non-default input limits) runs as a subprocess; a
real robot process (tests/robot_process.py, simulated, 150 binary scans at 30 Hz) publishes to map
`fuzz` as robot `real`. Meanwhile this test opens its own Zenoh session and sends garbage until the
robot is done (at least MIN_GARBAGE messages):

- on the real robot's own key, on dedicated "evil" robots of the same map (one per kind of garbage,
  so each one's `last_error` names its kind), on mixed evil robots and on a map that does not exist;
- kinds: random bytes under every encoding (JSON, binary, unknown, none), truncated and mutated valid
  binary scans, forged binary headers (bad magic / version / flags / length / seq), NaN and infinite
  poses, poses outside the configured world bound, too many beams, angles spanning more than a turn,
  negative ranges, range_min beyond the range limit, payloads above the size limit, valid scans under
  an unknown encoding, JSON of wrong shapes (wrong types, missing and extra fields, deep nesting,
  invalid UTF-8, truncation);
- valid scans and garbage on keys with invalid ids (bad characters, too long), and on wildcard /
  Zenoh-invalid keys.

Every payload sent on a key with valid ids is checked here to be refused by the same decoder and
limits the service uses (`fleetmap.codec.decode`): garbage must be garbage, or "the map is unchanged"
would not be a fair claim. Then: the service is up, the robot's 150 scans are all integrated (none
lost, dropped or duplicated), the map equals cell by cell the engine's map of the same scans as
decoded, every rejection is counted exactly (per robot over REST and in /metrics, globally in
/healthz), no map was created by garbage, and the log holds a handful of rate-limited lines, not
thousands.
"""

from __future__ import annotations

import io
import json
import math
import re
import struct
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
from robot_process import encode, scans_for
from service_process import RobotProcess, ServiceProcess, wait_for
from test_ingest import client_session

from fleetmap import codec
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.rate_limited_log import LOG_INTERVAL
from fleetmap.scan import MAX_BEAMS
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING

MAP_ID = "fuzz"
ROBOT_ID = "real"
GHOST_MAP = "ghost"  # never created: garbage must not create maps
ROBOT_OPTIONS: dict[str, Any] = {"sim": 5, "count": 150, "rate": 30}
#: The service runs with these limits (not the defaults) so the test shows they are configurable.
LIMITS = codec.InputLimits(world_bound=500.0, max_beams=4096, max_range=50.0)
SERVICE_ARGS = ["--in-memory", "--world-bound", "500", "--max-beams", "4096", "--max-range", "50"]
MIN_GARBAGE = 3000
#: Garbage messages per second at most (enough to interleave densely with the robot's 30 Hz).
GARBAGE_RATE = 1500.0
SEED = 20240611
LAYERS = ("log_odds", "hits", "misses", "tsdf", "tsdf_weight")

#: Ids that are valid Zenoh key chunks but not valid fleetmap ids (the service must ignore them).
BAD_IDS = ("a.b", "a b", "robot:1", "r\u00e9bot", "x" * 65, "y" * 300, "ROBOT!", "~", "semi;colon")
#: Keys the service's subscriber may or may not receive (wildcards, verbatim chunks) or that Zenoh
#: refuses locally: not counted exactly.
ODD_KEYS = (
    f"fleetmap/{MAP_ID}/*/scan", f"fleetmap/{MAP_ID}/**/scan", "fleetmap/*/*/scan",
    f"fleetmap/{MAP_ID}/@x/scan",
    f"fleetmap/{MAP_ID}/a#b/scan", f"fleetmap/{MAP_ID}/a?b/scan", f"fleetmap/{MAP_ID}//scan",
    f"fleetmap/{MAP_ID}/$x/scan", f"fleetmap/{MAP_ID}/{ROBOT_ID}/scan/",
)  # fmt: skip
#: Encodings garbage is labelled with (None: the sample carries no encoding, i.e. zenoh/bytes).
ENCODINGS: tuple[str | None, ...] = (
    BINARY_ENCODING, JSON_ENCODING, "application/json;charset=utf-8", "text/json", None,
    "application/octet-stream", "text/plain", "application/x-evil", "image/png",
)  # fmt: skip

#: Dedicated evil robots: each gets only one kind of garbage; its last_error must match the pattern.
DEDICATED = {
    "evil-bound": r"outside the world bound of \+-500 m",
    "evil-nonfinite": r"finite",
    # The limit in force (--max-beams 4096) is named, whatever n a header claims, never MAX_BEAMS.
    "evil-beams": r"beams is more than the limit of 4096|more items than 4096 beams can have",
    "evil-turn": r"more than one turn",
    "evil-size": r"exceeds the limit of 4194304",
    "evil-encoding": r"unknown encoding",
    "evil-json": r"invalid JSON scan",
    "evil-truncated": r"binary scan of \d+ bytes (is shorter|must be)|must be \d+ bytes",
    "evil-header": (
        r"bad magic|unsupported binary scan version|unknown flags|seq must be below|must be \d+ bytes"
        r"|beams is more than the limit of 4096"
    ),
}
MIXED = [f"evil-mix{i}" for i in range(4)]


# -- garbage ---------------------------------------------------------------------------------------


def raw_binary(
    *, seq: int = 1, stamp: float = 0.0, x: float = 0.0, y: float = 0.0, theta: float = 0.0,
    range_min: float = 0.0, range_max: float = 10.0, angle_min: float = -1.0, increment: float = 0.01,
    ranges: np.ndarray | None = None, angles: np.ndarray | None = None, magic: bytes = codec.MAGIC,
    version: int = codec.VERSION, flags: int | None = None, n: int | None = None,
) -> bytes:  # fmt: skip
    """A binary scan message with any header values, valid or not (layout: fleetmap.codec)."""
    ranges = np.ones(10, dtype=np.float32) if ranges is None else ranges
    if flags is None:
        flags = codec.FLAG_ANGLES if angles is not None else 0
    count = len(ranges) if n is None else n
    header = codec.HEADER.pack(
        magic, version, flags, 0, seq, stamp, x, y, theta, range_min, range_max, angle_min, increment, count
    )
    body = [] if angles is None else [np.asarray(angles, dtype="<f4").tobytes()]
    return header + b"".join(body) + np.asarray(ranges, dtype="<f4").tobytes()


def scan_json(**fields: Any) -> bytes:
    """A JSON scan message, valid unless `fields` say otherwise (a None value removes the field)."""
    message: dict[str, Any] = {
        "seq": 1, "stamp": 0.0, "pose": {"x": 0.0, "y": 0.0, "theta": 0.0},
        "angle_min": -1.0, "angle_increment": 0.01, "range_min": 0.0, "range_max": 10.0,
        "ranges": [1.0] * 10,
    }  # fmt: skip
    for name, value in fields.items():
        if value is None:
            message.pop(name, None)
        else:
            message[name] = value
    return json.dumps(message, allow_nan=True).encode()


class Garbage:
    """Deterministic generators of invalid payloads, by kind. Each returns (payload, encoding)."""

    def __init__(self, rng: np.random.Generator, valid_payloads: list[bytes]) -> None:
        self.rng = rng
        self.valid = valid_payloads  # binary encodings of real scans, to truncate and mutate

    def pick(self, seq: tuple[Any, ...]) -> Any:
        return seq[int(self.rng.integers(len(seq)))]

    def encoding(self) -> str | None:
        return self.pick(ENCODINGS)

    def random_bytes(self) -> tuple[bytes, str | None]:
        size = int(self.rng.choice([0, 1, 4, 71, 72, 73, int(self.rng.integers(0, 3000))]))
        data = self.rng.bytes(size)
        if self.rng.random() < 0.3:  # start like a real message, so the sniffing and parsers go further
            data = self.pick((codec.MAGIC, b"{", b'{"seq":', b"[")) + data
        return data, self.encoding()

    def truncated(self) -> tuple[bytes, str | None]:
        valid = self.pick(tuple(self.valid))
        return valid[: int(self.rng.integers(0, len(valid)))], BINARY_ENCODING

    def mutated(self) -> tuple[bytes, str | None]:
        data = bytearray(self.pick(tuple(self.valid)))
        for _ in range(int(self.rng.integers(1, 6))):
            # Mostly the header: mutated ranges are usually still a valid scan (then not sent).
            at = int(self.rng.integers(0, codec.HEADER.size if self.rng.random() < 0.8 else len(data)))
            data[at] = int(self.rng.integers(0, 256))
        return bytes(data), self.pick((BINARY_ENCODING, None, "application/octet-stream"))

    def header(self) -> tuple[bytes, str | None]:
        kind = int(self.rng.integers(0, 6))
        if kind == 0:
            payload = raw_binary(magic=self.rng.bytes(4))
        elif kind == 1:
            payload = raw_binary(version=int(self.rng.integers(2, 256)))
        elif kind == 2:
            payload = raw_binary(flags=int(self.rng.integers(2, 256)))
        elif kind == 3:
            payload = raw_binary(n=int(self.rng.integers(0, 2**32)))  # length does not match n
        elif kind == 4:
            payload = raw_binary(seq=int(self.rng.integers(2**63, 2**64, dtype=np.uint64)))
        else:
            payload = raw_binary(n=5, ranges=np.ones(7, dtype=np.float32))
        return payload, BINARY_ENCODING

    def nonfinite(self) -> tuple[bytes, str | None]:
        bad = self.pick((math.nan, math.inf, -math.inf))
        where = self.pick(("x", "y", "theta"))
        if self.rng.random() < 0.5:
            return raw_binary(**{where: bad}), self.pick((BINARY_ENCODING, None))
        pose = {"x": 0.0, "y": 0.0, "theta": 0.0, where: bad}
        return scan_json(pose=pose), self.pick((JSON_ENCODING, None))

    def out_of_bound(self) -> tuple[bytes, str | None]:
        far = float(self.rng.uniform(500.5, 1e6)) * self.pick((1.0, -1.0))
        x, y = (far, 0.0) if self.rng.random() < 0.5 else (0.0, far)
        if self.rng.random() < 0.5:
            return raw_binary(x=x, y=y), BINARY_ENCODING
        return scan_json(pose={"x": x, "y": y, "theta": 0.0}), JSON_ENCODING

    def too_many_beams(self) -> tuple[bytes, str | None]:
        n = int(self.pick((4097, 5000, MAX_BEAMS + 1)))
        if self.rng.random() < 0.5:
            return raw_binary(ranges=np.ones(n, dtype=np.float32), increment=1e-4), BINARY_ENCODING
        return scan_json(ranges=[1.0] * n, angle_increment=1e-4), JSON_ENCODING

    def over_a_turn(self) -> tuple[bytes, str | None]:
        kind = int(self.rng.integers(0, 3))
        if kind == 0:  # evenly spaced, too wide an increment
            return raw_binary(ranges=np.ones(361, dtype=np.float32), increment=0.05), BINARY_ENCODING
        angles = np.linspace(-4.0, 4.0, 20)
        if kind == 1:
            return raw_binary(ranges=np.ones(20, dtype=np.float32), angles=angles), BINARY_ENCODING
        message = scan_json(angle_min=None, angle_increment=None, angles=angles.tolist(), ranges=[1.0] * 20)
        return message, JSON_ENCODING

    def too_big(self) -> tuple[bytes, str | None]:
        size = LIMITS.max_payload_bytes + int(self.rng.integers(1, 200_000))
        if self.rng.random() < 0.5:  # a well-formed binary scan of a million beams, just too large
            n = (size - codec.HEADER.size) // 4
            return raw_binary(ranges=np.ones(n, dtype=np.float32), increment=1e-7), BINARY_ENCODING
        return b"{" + b" " * size + b"}", JSON_ENCODING

    def unknown_encoding(self) -> tuple[bytes, str | None]:
        # A perfectly valid scan, labelled with an encoding the service does not know.
        return self.pick(tuple(self.valid)), self.pick(("text/plain", "application/x-evil", "image/png"))

    def bad_json(self) -> tuple[bytes, str | None]:
        r = self.rng
        shapes: list[bytes] = [
            b"[]", b"null", b"42", b'"scan"', b"true", b"{}", b"{", b'{"seq": 1', b"\xff\xfe{}",
            b"[" * 5000 + b"]" * 5000, b'{"a":' * 3000 + b"1" + b"}" * 3000,
            scan_json(seq=-1), scan_json(seq=2**63), scan_json(seq="7"), scan_json(seq=1.5),
            scan_json(pose=None), scan_json(pose=[0, 0, 0]), scan_json(pose={"x": 0, "y": 0}),
            scan_json(ranges=None), scan_json(ranges="1,2,3"), scan_json(ranges=[1, "a"]),
            scan_json(extra_field=1), scan_json(angle_increment=None),
            scan_json(angles=[0.0] * 10), scan_json(angle_min=None, angle_increment=None, angles=[0.0, 0.1]),
            scan_json(range_min=5.0, range_max=1.0), scan_json(range_min=-1.0), scan_json(range_max=0),
            scan_json(stamp="now"), scan_json(stamp=math.inf),
            scan_json(angle_min=math.nan), scan_json(pose={"x": 1e400, "y": 0, "theta": 0}),
            scan_json()[:-1], scan_json() + b"trailing", scan_json().replace(b'"seq"', b'"s\xffq"'),
        ]  # fmt: skip
        payload = shapes[int(r.integers(len(shapes)))]
        return payload, self.pick((JSON_ENCODING, "application/json;charset=utf-8", "text/json"))

    def bad_json_unlabelled(self) -> tuple[bytes, str | None]:
        """Bad JSON without an encoding: the service sniffs it (JSON if it starts with '{')."""
        return self.bad_json()[0], None

    def range_limits(self) -> tuple[bytes, str | None]:
        kind = int(self.rng.integers(0, 4))
        if kind == 0:  # range_min beyond --max-range: nothing trustworthy in it
            return raw_binary(range_min=60.0, range_max=math.inf), BINARY_ENCODING
        if kind == 1:
            return scan_json(range_min=60.0, range_max=None), JSON_ENCODING
        if kind == 2:
            return raw_binary(ranges=-np.ones(10, dtype=np.float32)), BINARY_ENCODING
        return scan_json(ranges=[-1.0, 1.0]), JSON_ENCODING

    def any(self) -> tuple[bytes, str | None]:
        kinds = (
            self.random_bytes, self.truncated, self.mutated, self.header, self.nonfinite, self.out_of_bound,
            self.too_many_beams, self.over_a_turn, self.unknown_encoding, self.bad_json,
            self.bad_json_unlabelled, self.range_limits,
        )  # fmt: skip
        return kinds[int(self.rng.integers(len(kinds)))]()

    def for_robot(self, robot_id: str) -> tuple[bytes, str | None]:
        kind = {
            "evil-bound": self.out_of_bound, "evil-nonfinite": self.nonfinite,
            "evil-beams": self.too_many_beams, "evil-turn": self.over_a_turn, "evil-size": self.too_big,
            "evil-encoding": self.unknown_encoding, "evil-json": self.bad_json,
            "evil-truncated": self.truncated, "evil-header": self.header,
        }.get(robot_id, self.any)  # fmt: skip
        return kind()


def wire_encoding(encoding: str | None) -> str:
    """The encoding string the service's callback sees for a sample put with `encoding`."""
    return str(zenoh.Encoding(encoding)) if encoding else str(zenoh.Encoding.ZENOH_BYTES)


def refused_here(payload: bytes, encoding: str | None) -> bool:
    """True when the service's decoder and limits refuse it."""
    try:
        codec.decode(payload, wire_encoding(encoding), LIMITS)
    except codec.DecodeError:
        return True
    return False


@dataclass
class Tally:
    """What the garbage sender sent, by destination."""

    per_robot: Counter[str] = field(default_factory=Counter)  # map `fuzz`, valid ids
    ghost: int = 0  # map that does not exist, valid ids
    invalid_keys: int = 0  # keys with invalid ids the subscriber receives
    odd_sent: int = 0  # ODD_KEYS that Zenoh accepted locally (the service may or may not see them)
    odd_refused: int = 0  # ODD_KEYS Zenoh refused locally
    skipped_valid: int = 0  # generated payloads that turned out valid: not sent
    before_robot_done: int = 0  # sent while the robot was still publishing

    @property
    def on_valid_keys(self) -> int:
        return sum(self.per_robot.values()) + self.ghost

    @property
    def counted(self) -> int:
        """Messages the service must have received exactly."""
        return self.on_valid_keys + self.invalid_keys


def garbage_stream(
    rng: np.random.Generator, garbage: Garbage
) -> Iterator[tuple[str, str, bytes, str | None]]:
    """An endless, interleaved stream of (destination kind, key, payload, encoding)."""
    huge_every = 700  # a few payloads above the size limit, not thousands of megabytes
    robots = [ROBOT_ID, *DEDICATED, *MIXED]
    k = 0
    while True:
        k += 1
        roll = rng.random()
        if k % huge_every == 0:
            payload, encoding = garbage.too_big()
            yield "robot", f"fleetmap/{MAP_ID}/evil-size/scan", payload, encoding
        elif roll < 0.80:
            robot_id = robots[int(rng.integers(len(robots)))]
            if robot_id == "evil-size":
                robot_id = "evil-mix0"  # evil-size only gets the periodic huge payloads
            payload, encoding = garbage.for_robot(robot_id)
            yield "robot", f"fleetmap/{MAP_ID}/{robot_id}/scan", payload, encoding
        elif roll < 0.86:
            payload, encoding = garbage.any()
            yield "ghost", f"fleetmap/{GHOST_MAP}/evil/scan", payload, encoding
        elif roll < 0.98:
            # Invalid ids, with garbage or with perfectly valid scans: ignored either way.
            bad = BAD_IDS[int(rng.integers(len(BAD_IDS)))]
            key = f"fleetmap/{MAP_ID}/{bad}/scan" if rng.random() < 0.7 else f"fleetmap/{bad}/{ROBOT_ID}/scan"
            payload, encoding = (
                (garbage.pick(tuple(garbage.valid)), BINARY_ENCODING) if rng.random() < 0.5 else garbage.any()
            )
            yield "invalid", key, payload, encoding
        else:
            payload, encoding = (garbage.pick(tuple(garbage.valid)), BINARY_ENCODING)
            yield "odd", ODD_KEYS[int(rng.integers(len(ODD_KEYS)))], payload, encoding


def send_garbage(session: zenoh.Session, robot: RobotProcess, tally: Tally, stop: threading.Event) -> None:
    """Send garbage until the robot is done publishing and at least MIN_GARBAGE were sent (or `stop`).
    Every payload on a key with valid ids is refused by the local decoder before it is sent."""
    rng = np.random.default_rng(SEED)
    valid = [encode(scan, seq, "binary") for seq, scan in enumerate(scans_for(sim=99, count=8))]
    garbage = Garbage(rng, valid)
    block = zenoh.CongestionControl.BLOCK  # garbage must arrive, or the exact counts mean nothing
    started = time.monotonic()
    sent = 0
    robot_done = False
    for kind, key, payload, encoding in garbage_stream(rng, garbage):
        if stop.is_set() or (robot_done and sent >= MIN_GARBAGE) or sent > 50 * MIN_GARBAGE:
            return
        if kind in ("robot", "ghost") and not refused_here(payload, encoding):
            tally.skipped_valid += 1
            continue
        try:
            session.put(key, payload, encoding=encoding, congestion_control=block)
        except zenoh.ZError:
            assert kind == "odd", f"Zenoh refused {key!r}"
            tally.odd_refused += 1
            continue
        sent += 1
        if kind == "robot":
            tally.per_robot[key.split("/")[2]] += 1
        elif kind == "ghost":
            tally.ghost += 1
        elif kind == "invalid":
            tally.invalid_keys += 1
        else:
            tally.odd_sent += 1
        if sent % 50 == 0:
            robot_done = robot_done or "published" in robot.logs()
            if not robot_done:
                tally.before_robot_done = sent
            # Pace: at most GARBAGE_RATE messages per second.
            time.sleep(max(0.0, started + sent / GARBAGE_RATE - time.monotonic()))


# -- the map's reference -----------------------------------------------------------------------------


def reference_map() -> tuple[GridMap, int]:
    """The engine's map of the robot's scans, each decoded from the bytes the robot sends."""
    gmap = GridMap(MapConfig())
    scans = scans_for(sim=ROBOT_OPTIONS["sim"], count=ROBOT_OPTIONS["count"])
    for seq, scan in enumerate(scans):
        gmap.integrate(codec.decode(encode(scan, seq, "binary"), BINARY_ENCODING, LIMITS).scan)
    return gmap, len(scans)


def region_npy(http: httpx.Client, layer: str, window: tuple[int, int, int, int], res: float) -> np.ndarray:
    i0, j0, i1, j1 = window
    params = {
        "xmin": (i0 + 0.5) * res, "ymin": (j0 + 0.5) * res,
        "xmax": (i1 + 0.5) * res, "ymax": (j1 + 0.5) * res,
        "layer": layer, "format": "npy",
    }  # fmt: skip
    response = http.get(f"/maps/{MAP_ID}/region", params=params)
    assert response.status_code == 200, response.text
    return np.load(io.BytesIO(response.content), allow_pickle=False)


def rejected_metrics(text: str) -> dict[tuple[str, str], float]:
    """fleetmap_scans_rejected_total by (map, robot) from the Prometheus exposition."""
    out = {}
    for labels, value in re.findall(r"^fleetmap_scans_rejected_total\{([^}]*)\} (\S+)$", text, flags=re.M):
        pairs = dict(re.findall(r'(\w+)="([^"]*)"', labels))
        out[(pairs["map"], pairs["robot"])] = float(value)
    return out


# -- the test ------------------------------------------------------------------------------------------


def test_garbage_flood_leaves_the_real_robots_map_exact(tmp_path: Path) -> None:
    svc = ServiceProcess(tmp_path, SERVICE_ARGS).start()
    robot: RobotProcess | None = None
    stop = threading.Event()
    session: zenoh.Session | None = None
    try:
        http = httpx.Client(base_url=svc.base_url, timeout=30.0)
        response = http.put(f"/maps/{MAP_ID}", json=MapConfig().model_dump(mode="json"))
        assert response.status_code in (200, 201), response.text

        session = client_session(svc.zenoh_endpoint)
        # Wait until the service's subscriber is known here, so nothing is sent into the void.
        probe = session.declare_publisher(f"fleetmap/{MAP_ID}/evil-mix0/scan")
        wait_for(lambda: probe.matching_status.matching, timeout=20, what="the service's subscriber")
        probe.undeclare()

        robot = RobotProcess(svc.zenoh_endpoint, MAP_ID, ROBOT_ID, log_dir=tmp_path, **ROBOT_OPTIONS).start()

        def robot_integrated() -> int:
            robots = http.get(f"/maps/{MAP_ID}").json()["stats"]["robots"]
            return robots.get(ROBOT_ID, {}).get("scans_integrated", 0)

        wait_for(robot_integrated, timeout=60, what="the robot's first scan integrated")
        assert "published" not in robot.logs(), "the robot finished before the garbage started"

        tally = Tally()
        errors: list[BaseException] = []

        def sender() -> None:
            try:
                send_garbage(session, robot, tally, stop)
            except BaseException as exc:  # re-raised in the test thread
                errors.append(exc)

        garbage_started = time.monotonic()
        thread = threading.Thread(target=sender, name="garbage", daemon=True)
        thread.start()
        robot.wait(timeout=120)
        thread.join(timeout=120)
        assert not thread.is_alive(), "the garbage sender did not finish"
        if errors:
            raise errors[0]
        sent = tally.counted + tally.odd_sent

        # -- accounting: the service saw every message, and refused all the garbage ----------------
        expected_scans = ROBOT_OPTIONS["count"]

        def received() -> int:
            return http.get("/healthz").json()["zenoh"]["messages_received"]

        wait_for(lambda: received() >= expected_scans + tally.counted, timeout=60,
                 what=f"{expected_scans + tally.counted} messages received")  # fmt: skip
        wait_for(lambda: robot_integrated() >= expected_scans, timeout=60, what="all the robot's scans")
        time.sleep(0.5)  # let any late message land before the exact counts are read
        garbage_done = time.monotonic()

        assert svc.alive(), svc.logs()
        health = http.get("/healthz")
        assert health.status_code == 200
        zstatus = health.json()["zenoh"]
        assert sent >= MIN_GARBAGE
        assert tally.before_robot_done >= 300, f"garbage did not overlap the robot's publishing: {tally}"
        assert expected_scans + tally.counted <= zstatus["messages_received"] <= expected_scans + sent
        assert tally.invalid_keys <= zstatus["invalid_keys"] <= tally.invalid_keys + tally.odd_sent
        assert zstatus["decode_errors"] == tally.on_valid_keys, (zstatus, tally)
        assert zstatus["scans_submitted"] == expected_scans
        assert zstatus["rejected"] == {}, zstatus  # no duplicates, no queue overflow

        # Garbage created no map (not the ghost map, not a map named by an invalid key).
        assert [m["id"] for m in http.get("/maps").json()["maps"]] == [MAP_ID]

        stats = http.get(f"/maps/{MAP_ID}").json()["stats"]
        real = stats["robots"][ROBOT_ID]
        assert real["scans_integrated"] == expected_scans
        assert (real["lost"], real["dropped"], real["duplicates"]) == (0, 0, 0), real
        assert real["last_seq"] == expected_scans - 1
        assert real["scans_rejected"] == tally.per_robot[ROBOT_ID] > 0, (real, tally)
        assert stats["scans_integrated"] == expected_scans
        assert stats["scans_rejected"] == sum(tally.per_robot.values())
        assert set(stats["robots"]) == {ROBOT_ID, *tally.per_robot}, "a robot with an invalid id was recorded"
        for robot_id, count in tally.per_robot.items():
            state = stats["robots"][robot_id]
            assert state["scans_rejected"] == count, (robot_id, state)
            assert state["last_error"], (robot_id, state)
            if robot_id != ROBOT_ID:
                assert state["scans_integrated"] == 0 and state["last_seq"] is None, (robot_id, state)
            if robot_id in DEDICATED:
                assert re.search(DEDICATED[robot_id], state["last_error"]), (robot_id, state["last_error"])
        assert set(DEDICATED) <= set(tally.per_robot), tally.per_robot
        metrics = rejected_metrics(http.get("/metrics").text)
        for robot_id, count in tally.per_robot.items():
            assert metrics[(MAP_ID, robot_id)] == count, robot_id

        # -- the map is exactly the engine's map of the robot's scans -------------------------------
        want, n = reference_map()
        assert n == expected_scans
        window = want.known_bounds()
        assert window is not None
        assert stats["bounds"] == pytest.approx([v * want.resolution for v in window])
        for layer in LAYERS:
            got = region_npy(http, layer, window, want.resolution)
            expected = want.region(layer, *window)
            assert got.shape == expected.shape and got.dtype == expected.dtype, layer
            np.testing.assert_array_equal(got, expected, err_msg=f"layer {layer} differs after the garbage")

        # -- the log is rate-limited ---------------------------------------------------------------
        logs = svc.logs()
        lines = [line for line in logs.splitlines() if "rejected a scan" in line or "ignored a scan" in line]
        # One category per robot of map fuzz, one for the ghost map's robot, one for invalid keys.
        categories = len(tally.per_robot) + 2
        periods = math.ceil((garbage_done - garbage_started) / LOG_INTERVAL) + 1
        assert 0 < len(lines) <= categories * periods, f"{len(lines)} log lines for {sent} bad messages"
        assert len(lines) * 20 < sent
        assert "Traceback" not in logs and "unexpected error" not in logs, logs
    finally:
        stop.set()
        if robot is not None:
            robot.stop()
        if session is not None:
            session.close()
        code = svc.stop()
    assert code == 0, f"service exited with {code}:\n{svc.logs()}"


def test_every_dedicated_kind_is_refused_by_the_decoder() -> None:
    """The generators produce what their names say: each dedicated kind yields payloads that the
    decoder refuses for the expected reason (checked here so the end-to-end test's per-robot
    last_error assertions rest on the generators, not on luck)."""
    rng = np.random.default_rng(SEED + 1)
    valid = [encode(scan, seq, "binary") for seq, scan in enumerate(scans_for(sim=99, count=4))]
    garbage = Garbage(rng, valid)
    for robot_id, pattern in DEDICATED.items():
        for _ in range(3 if robot_id == "evil-size" else 40):
            payload, encoding = garbage.for_robot(robot_id)
            with pytest.raises(codec.DecodeError, match=pattern):
                codec.decode(payload, wire_encoding(encoding), LIMITS)
    # And the valid material really is valid, under both labels a robot may use.
    for payload in valid:
        assert codec.decode(payload, BINARY_ENCODING, LIMITS).scan.num_beams == 361
        assert codec.decode(payload, "zenoh/bytes", LIMITS).seq >= 0
    assert struct.unpack_from("<4s", valid[0])[0] == codec.MAGIC


def test_liveliness_token_flood_writes_a_bounded_log(tmp_path: Path) -> None:
    """Any Zenoh peer can declare and drop liveliness tokens as fast as it likes, each under another
    robot id: the service logs robots coming online and going offline, and wrote one line per token
    event (13000 lines a second, unbounded). Now those lines are rate-limited like refusals: a few
    per robot and state, at most 100 per interval in all, the rest counted as suppressed."""
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc:
        session = client_session(svc.zenoh_endpoint)
        try:
            first = session.liveliness().declare_token("fleetmap/flood/first/alive")
            wait_for(lambda: "robot flood/first is online" in svc.logs(), timeout=20, what="the first token")
            first.undeclare()
            declared = 0
            started = time.monotonic()
            while time.monotonic() - started < 2.0:  # well within one LOG_INTERVAL
                token = session.liveliness().declare_token(f"fleetmap/flood/r{declared}/alive")
                token.undeclare()
                declared += 1

            def events() -> int:
                return int(httpx.get(f"{svc.base_url}/healthz").json()["zenoh"]["liveliness_events"])

            wait_for(lambda: events() >= 2 * declared, timeout=30, what="every token event handled")
            handled = time.monotonic()
        finally:
            session.close()
        assert declared >= 1000, f"only {declared} tokens declared: no flood"
        alive_line = re.compile(r"robot flood/\S+ is (online|offline)")
        lines = [line for line in svc.logs().splitlines() if alive_line.search(line)]
        # The first token's lines, then at most 100 per interval the handling spanned: one or two on
        # a quiet machine; a loaded one (CI beside other work) took longer than 2 intervals to handle
        # 17,526 events, and logged 100 lines in each.
        periods = math.ceil((handled - started) / LOG_INTERVAL) + 1
        assert len(lines) <= 2 + periods * 100, f"{len(lines)} lines for {2 * declared} token events"


def test_scans_creating_maps_they_lose_again_write_a_bounded_log(tmp_path: Path) -> None:
    """A valid scan to a new map id creates the map, and when the scan is refused later (here: it
    needs more tiles than `max_tiles`) the map is removed again. Both were logged, two lines a scan:
    any Zenoh peer could write hundreds of lines a second with 1 KB scans under made-up map ids. Now
    those lines are rate-limited, and no map stays."""
    beams = 64  # 999 m in every direction: about 78 tiles a beam, over the 4096 a map may hold
    scan = {
        "seq": 0, "pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -math.pi,
        "angle_increment": 2 * math.pi / beams, "range_max": 999.5, "ranges": [999.0] * beams,
    }  # fmt: skip
    payload = json.dumps(scan).encode()
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc:
        session = client_session(svc.zenoh_endpoint)
        try:
            probe = session.declare_publisher("fleetmap/probe/r/scan")
            wait_for(lambda: probe.matching_status.matching, timeout=20, what="the service's subscriber")
            probe.undeclare()
            sent = 0
            started = time.monotonic()
            while time.monotonic() - started < 2.0:
                session.put(f"fleetmap/made-up-{sent}/r/scan", payload, encoding=JSON_ENCODING)
                sent += 1
                time.sleep(0.002)

            def settled() -> bool:
                health = httpx.get(f"{svc.base_url}/healthz").json()
                return bool(health["zenoh"]["messages_received"] >= sent and health["queue_depth"] == 0)

            wait_for(settled, timeout=60, what="every scan handled")
            wait_for(
                lambda: httpx.get(f"{svc.base_url}/maps").json()["maps"] == [], timeout=30, what="no map"
            )
            elapsed = time.monotonic() - started
        finally:
            session.close()
        assert sent >= 200, f"only {sent} scans sent: no flood"
        map_line = re.compile(r"(created|removed) map made-up-")
        lines = [line for line in svc.logs().splitlines() if map_line.search(line)]
        assert lines, "no map was created and removed: the scans did not reach the case tested"
        # At most 20 lines per 5 s interval, over as many intervals as the flood and its integration
        # took: a few on a quiet machine, more on a loaded one (a fixed 80 failed at 100 lines there).
        # Unlimited, it is two lines a scan.
        bound = 20 * (math.floor(elapsed / LOG_INTERVAL) + 1)
        assert len(lines) <= min(bound, sent), f"{len(lines)} lines for {sent} scans in {elapsed:.1f} s"
