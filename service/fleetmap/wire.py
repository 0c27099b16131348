"""The wire schema: one definition of what robots send, the ids that name maps and robots, and the
Zenoh key expressions and settings robots and the service share (and how Zenoh's errors read for
people). (What the REST API answers is in `fleetmap.api_models`.)

`ScanMessage` is the JSON scan robots publish over Zenoh (and POST over REST); the compact binary
encoding of the same message is in `fleetmap.codec`. The REST API, the Python client, the docs and
`openapi/openapi.json` all use these models. A JSON message becomes the engine's `Scan` here, in
`ScanMessage.to_scan`; the binary decoder (`codec.decode_binary`) and the journal's format
(`storage_format.scan_from_blob`) build theirs from the same fields, with the same checks
(`Scan`'s own).
"""

from __future__ import annotations

import math
import re
import secrets
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from fleetmap.scan import MAX_BEAMS, Pose2D, Scan, ScanError
from fleetmap.shown_endpoint import shown_endpoint

#: Map and robot ids: what may stand in a Zenoh key expression and a URL path segment unescaped.
ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
_ID_RE = re.compile(ID_PATTERN)

#: Zenoh key expressions. `<map_id>` and `<robot_id>` match ID_PATTERN.
SCAN_KEY = "fleetmap/{map_id}/{robot_id}/scan"
ALIVE_KEY = "fleetmap/{map_id}/{robot_id}/alive"
SCAN_KEY_WILDCARD = "fleetmap/*/*/scan"
ALIVE_KEY_WILDCARD = "fleetmap/*/*/alive"
#: The Zenoh endpoint the service listens on and robots connect to when neither is told otherwise
#: (`fleetmap.zenoh_ingest.DEFAULT_LISTEN`, `fleetmap_client.zenoh_config.DEFAULT_CONNECT`, `fleetmap demo`):
#: loopback only, Zenoh's usual port.
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: Zenoh's `connect/retry` of robots (`fleetmap_client.zenoh_config.client_config`) and of the
#: service's own session when it connects to a router (`--zenoh-connect`), unless their
#: configuration sets it: 0.1 s after a lost connection, then 0.2, 0.4 and every 0.5 s. Zenoh's
#: default (1 s growing to 4 s) met a restarted service up to 4 s after it listened, and never one
#: that lived less than that (docs/protocol.md). Zenoh takes the block whole.
CONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2.0}
#: The service's queryable that answers what became of a robot's scans (`DeliveryStatus`); the query
#: may name one publisher session (`?session=<id>`, `DELIVERY_SESSION_PARAMETER`).
DELIVERY_KEY = "fleetmap/{map_id}/{robot_id}/delivery"
DELIVERY_KEY_WILDCARD = "fleetmap/*/*/delivery"
DELIVERY_SESSION_PARAMETER = "session"
#: `?fields=2` asks for the reply's fields added after its first version (`DeliveryStatus.
#: last_error`, `SessionDelivery.refused_seqs` and `lost_gaps`). Without it the reply holds the
#: first version's only: clients of that version read it strictly (a field they did not know made
#: their flush fail), and robots are not all upgraded with the service.
DELIVERY_FIELDS_PARAMETER = "fields"
DELIVERY_FIELDS = 2
#: What a reply of the first version leaves out (`DeliveryStatus.model_dump_json(exclude=...)`).
DELIVERY_FIELDS_1_EXCLUDE: dict = {"last_error": True, "sessions": {"__all__": {"refused_seqs", "lost_gaps"}}}
#: The encoding of the service's error replies to a delivery query (a sentence), which tells them
#: from the errors Zenoh itself reports to the querier (a query's timeout).
DELIVERY_ERROR_ENCODING = "text/plain;fleetmap-delivery"

#: Zenoh encodings of the two payload formats.
JSON_ENCODING = "application/json"
BINARY_ENCODING = "application/x-fleetmap-scan"


#: The Rust source location zenoh appends to its errors (" at /root/.cargo/.../endpoint.rs:615.").
_ZENOH_SOURCE_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?")
#: A configuration error zenoh reports in Rust's debug form of its JSON5 error, alone or after a
#: prefix: `Json5Err(Message { msg: "<the sentence>", location: Some(Location { line: 1, column: 2 }) })`
#: for an endpoint, `JSON error: Message { msg: ..., location: ... }` for a file.
_ZENOH_JSON5_ERROR = re.compile(
    r'(?:Json5Err\()?Message \{ msg: "(?P<msg>(?:[^"\\]|\\.)*)", '
    r"location: (?:None|Some\(Location \{ line: (?P<line>\d+), column: (?P<column>\d+) \}\)) \}\)?"
)


#: A syntax error of a configuration, as zenoh reports it: where (` --> 5:15`), then an excerpt of
#: the file (the line at fault, a caret under the place), then what was expected (`  = expected ...`).
_ZENOH_SYNTAX_ERROR = re.compile(r"-->\s*(?P<line>\d+):(?P<column>\d+)\n(?:[^\n]*\n)*?[ \t]*= ")
#: A configuration value of the wrong type, as zenoh quotes it (`invalid type: integer `4242`,
#: expected a string`, `invalid value: string "x", ...`): the kind is kept, the value left out.
_ZENOH_QUOTED_VALUE = re.compile(
    r"(?P<kind>invalid (?:type|value): [a-z ]*[a-z]) (?:`[^`]*`|\"(?:[^\"\\]|\\.)*\")"
)


#: An endpoint with its own configuration (`tls/host:7447#connect_private_key_base64=...`), as a
#: Zenoh error quotes it: shown without the values (`shown_endpoint`), which may be a private key.
_ENDPOINT_WITH_CONFIG = re.compile(r"[A-Za-z0-9_-]+/[^\s#\"'`,\])]+#[^\s\"'`,\])]+")


def zenoh_error_text(exc: BaseException) -> str:
    """A Zenoh error as one line for people: its sentence, without the Rust source locations and the
    debug wrapper of configuration errors that zenoh adds (`Endpoints must be of the form
    <protocol>/<address>...: 127.0.0.1:7447`, not `Json5Err(Message { msg: "Endpoints must ...`),
    and without what zenoh quotes of a configuration file: it may hold a robot's password
    (`transport/auth/usrpwd`) or a private key inline (`*_base64`), and this text goes to the log.
    A syntax error says where and what was expected (`line 5, column 15: expected array, ...`, not
    the line itself), a value of the wrong type its kind and place (`invalid type: integer, expected
    a string (line 5, column 15)`, not the number)."""
    text = _ZENOH_SOURCE_LOCATION.sub("", str(exc))
    text = _ENDPOINT_WITH_CONFIG.sub(lambda found: shown_endpoint(found[0]), text)
    text = _ZENOH_JSON5_ERROR.sub(_json5_error_sentence, text)
    text = _ZENOH_SYNTAX_ERROR.sub(lambda found: f"line {found['line']}, column {found['column']}: ", text)
    text = _ZENOH_QUOTED_VALUE.sub(lambda found: found["kind"], text)
    return " ".join(text.split())


#: A Zenoh configuration given where its file's path goes: JSON5 itself (an object, or lines).
_INLINE_CONFIG = re.compile(r"^\s*\{|[\r\n]")


def shown_config_path(path: str) -> str:
    """A Zenoh configuration file's `path` as an error names it: as it is, unless it is a
    configuration itself, given where its path goes (as a container's environment tends to be
    filled: `--zenoh-config`, `zenoh_config=`), which may hold a robot's password or a private key
    (`zenoh_error_text`) and was quoted whole as the file that could not be read."""
    if _INLINE_CONFIG.search(path):
        return "(a configuration itself, not shown, where the path of its JSON5 file goes)"
    return path


def _json5_error_sentence(found: re.Match[str]) -> str:
    """The sentence of a `_ZENOH_JSON5_ERROR`; where a value is left out of it
    (`_ZENOH_QUOTED_VALUE`), with the place instead (`(line 5, column 15)`), which is that value's."""
    sentence = found["msg"].replace('\\"', '"')
    if found["line"] is not None and _ZENOH_QUOTED_VALUE.search(sentence):
        sentence += f" (line {found['line']}, column {found['column']})"
    return sentence


#: The largest TCP or UDP port.
MAX_PORT = 65535
#: Zenoh's link protocols whose address is HOST:PORT (not a path, as `unixsock-stream`'s).
_PORTED_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})


def check_endpoint_form(endpoint: str) -> None:
    """Raise ValueError if `endpoint` is written as a URL (`tcp://127.0.0.1:7447`) rather than as
    the Zenoh endpoint `PROTOCOL/ADDRESS` (`tcp/127.0.0.1:7447`): Zenoh takes the URL for protocol
    `tcp:` and address `/127.0.0.1:7447`, so a robot given one waited for the service for ever and
    the service failed to listen with "Unicast not supported for tcp: protocol"; or one of a
    protocol of host and port (`tcp`, `udp`, ...) without its port, or with one past `MAX_PORT`.
    Other mistakes are Zenoh's own to report (`zenoh_error_text`)."""
    protocol, slash, rest = endpoint.partition("/")
    if slash and protocol.endswith(":") and rest.startswith("/"):
        raise ValueError(
            f"{shown_endpoint(endpoint)!r} is written as a URL: a Zenoh endpoint is PROTOCOL/ADDRESS, "
            f"{shown_endpoint(protocol[:-1] + '/' + rest[1:])}"
        )
    # Without its port (`tcp/127.0.0.1`), Zenoh says only "invalid socket address", naming no
    # endpoint, and the service said so only once it had loaded every map.
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not (slash and protocol in _PORTED_PROTOCOLS):
        return
    port = re.search(r":(\d+)$", address)
    if port is None:
        raise ValueError(
            f"{shown_endpoint(endpoint)!r} has no port: a Zenoh {protocol} endpoint is {protocol}/HOST:PORT, "
            f"e.g. {protocol}/{address.rstrip(':') or '127.0.0.1'}:7447"
        )
    # Nor past the last port: Zenoh says only "invalid port value", as late.
    if int(port.group(1)) > MAX_PORT:
        raise ValueError(
            f"{shown_endpoint(endpoint)!r} has port {int(port.group(1))}: a port is at most {MAX_PORT}"
        )


def is_valid_id(value: str) -> bool:
    """Whether `value` is a valid map or robot id (`ID_PATTERN`: 1 to 64 of A-Z a-z 0-9 _ -)."""
    # The whole of it: `match` also took an id followed by a newline (`$` matches before a last
    # one), and a Zenoh key `fleetmap/m\n/r/scan` made a map that no URL can name, nor delete.
    return _ID_RE.fullmatch(value) is not None


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise ValueError("must be a finite number")
    return value


Finite = Annotated[float, AfterValidator(_finite)]


class PoseMessage(BaseModel):
    """The SENSOR pose in the map frame: metres, radians counter-clockwise."""

    model_config = ConfigDict(extra="forbid")

    x: Finite
    y: Finite
    theta: Finite


#: Sequence numbers are below this (they travel as a signed 64-bit integer in SQLite's journal).
SEQ_LIMIT = 2**63
#: Session ids are in [1, SESSION_LIMIT): 53 bits, so that every JSON parser (JavaScript's numbers
#: included) reads them exactly, and two publishers that pick one at random share it with a chance of
#: about 1 in 9e15. (0 is "no session" in the binary encoding and the journal.)
SESSION_LIMIT = 2**53


def new_session_id() -> int:
    """A random session id for a publisher that starts (or starts its seq again)."""
    return secrets.randbelow(SESSION_LIMIT - 1) + 1


class ScanMessage(BaseModel):
    """One laser scan with the sensor's pose.

    Beam i points at `angle_min + i * angle_increment` relative to the sensor heading, or at
    `angles[i]` when `angles` is given. `ranges[i]` is a number in metres or null; null, inf or a
    value >= `range_max` means "no return", NaN an invalid reading, ignored: the same as a binary NaN
    and the engine's NaN. (Strict JSON has no NaN, but the non-standard literal `NaN`, which Python's
    `json` and many ROS bridges write, is accepted rather than refusing the whole scan.)
    """

    # `model_dump_json` writes NaN and infinities as the literals NaN, Infinity and -Infinity, which
    # the decoders read (docs/protocol.md). Pydantic's default wrote them as null: a NaN reading
    # (invalid) became null (no return), -inf (below range_min) too, and the default range_max
    # (inf, no maximum) null, which the service refuses ("range_max: Input should be a valid number").
    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    seq: int = Field(ge=0, lt=SEQ_LIMIT, description="per-robot sequence number, +1 per scan")
    stamp: Finite = Field(default=0.0, description="acquisition time, seconds (any epoch)")
    session: int | None = Field(
        default=None,
        ge=1,
        lt=SESSION_LIMIT,
        description="the publisher's session id: picked at random when it starts (or starts its seq "
        "again), the same in each of its scans; tells a restarted robot and robots sharing one id apart "
        "(docs/protocol.md, Sessions). Without it, restarts are recognised by the stamps",
    )
    pose: PoseMessage
    angle_min: Finite | None = None
    angle_increment: Finite | None = None
    angles: list[Finite] | None = Field(default=None, max_length=MAX_BEAMS)
    range_min: Finite = Field(default=0.0, ge=0)
    range_max: float = Field(default=math.inf, gt=0, description="metres; may be omitted for 'no maximum'")
    ranges: list[float | None] = Field(
        max_length=MAX_BEAMS,
        description="metres; null, Infinity or >= range_max: no return; NaN: an invalid reading, ignored",
    )

    @model_validator(mode="after")
    def _check_angles(self) -> ScanMessage:
        if self.angles is not None:
            if self.angle_min is not None or self.angle_increment is not None:
                raise ValueError("give either angles or angle_min + angle_increment, not both")
            if len(self.angles) != len(self.ranges):
                raise ValueError(f"{len(self.angles)} angles but {len(self.ranges)} ranges")
        elif self.angle_min is None or self.angle_increment is None:
            raise ValueError("angle_min and angle_increment are required when angles is absent")
        if math.isnan(self.range_max):
            raise ValueError("range_max must be a number")
        if self.range_max <= self.range_min:
            raise ValueError(
                f"range_max {self.range_max:g} must be greater than range_min {self.range_min:g}"
            )
        return self

    def to_scan(self) -> Scan:
        """The engine's `Scan`; raises `ScanError` for content the engine refuses."""
        pose = Pose2D(self.pose.x, self.pose.y, self.pose.theta)
        if self.angles is not None:
            return Scan.from_angles(pose, self.angles, self.ranges, self.range_min, self.range_max)
        assert self.angle_min is not None and self.angle_increment is not None
        return Scan.from_fan(
            pose, self.angle_min, self.angle_increment, self.ranges, self.range_min, self.range_max
        )

    @classmethod
    def from_scan(cls, scan: Scan, seq: int, stamp: float = 0.0, session: int | None = None) -> ScanMessage:
        """The message for an engine scan (explicit angles; +inf ranges become null, no return; NaN
        and -inf stay, both ignored: null would make them no returns)."""
        return cls(
            seq=seq,
            stamp=stamp,
            session=session,
            pose=PoseMessage(x=scan.pose.x, y=scan.pose.y, theta=scan.pose.theta),
            angles=scan.angles.tolist(),
            range_min=scan.range_min,
            range_max=scan.range_max,
            ranges=[None if r == math.inf else r for r in scan.ranges.tolist()],
        )


class SessionDelivery(BaseModel):
    """What became of the scans of one publisher session of a robot, as the service counted them
    (saved with the map: a durable service counts across its restarts; docs/protocol.md, "Delivery
    confirmation").

    A scan is SETTLED once its fate is final: integrated into the map (with durable storage: its
    journal row committed), or not integrated (refused, dropped by the full ingest queue, its map
    deleted or replaced first). A robot's scans are settled in order, so `settled` is one seq: that
    scan and every scan of the session accepted before it are settled."""

    model_config = ConfigDict(extra="ignore")  # a newer service may add fields: see DeliveryStatus

    session: int = Field(description="the publisher's session id; 0: scans that carry none")
    first_seq: int = Field(description="seq of its first scan the service counted")
    last_accepted: int = Field(description="seq of its last scan accepted (queued for integration)")
    settled: int | None = Field(
        description="seq S: S and every scan accepted before it are settled; null: none yet"
    )
    integrated: int = Field(description="its scans integrated (durable, with storage)")
    refused: int = Field(
        description="its scans settled without being integrated (refused, dropped, map gone)"
    )
    lost: int = Field(description="seqs it skipped after first_seq: scans that never arrived")
    duplicates: int = Field(description="its scans ignored because their seq was accepted already")
    refused_seqs: list[int] | None = Field(
        default=None,
        description="the seqs of its scans refused, one by one, so that a reader counts those through a "
        "seq of its own; null: not known (counted before the service's last start, or more than 64)",
    )
    lost_gaps: list[tuple[int, int]] | None = Field(
        default=None,
        description="[seq, n]: the n seqs just before seq were lost (skipped), one gap each; null: not "
        "known, as for refused_seqs",
    )


class BuriedSession(BaseModel):
    """A publisher session of the robot whose scans through `last_seq` went with a map of this id
    that was deleted or replaced by an upload (the service's tombstones: docs/protocol.md,
    "Delivery guarantees"): they are in no map now."""

    model_config = ConfigDict(extra="ignore")  # a newer service may add fields: see DeliveryStatus

    session: int = Field(description="the publisher's session id")
    last_seq: int = Field(description="the last seq the service had of it when the map went")
    deleted_at: float = Field(description="when the map was deleted or replaced (Unix time)")


class DeliveryStatus(BaseModel):
    """The service's answer on `DELIVERY_KEY`: what it knows of one robot's scans. `status` says
    whether there is such a map and robot; the counts are the robot's on the map (all its sessions,
    as `GET /maps/{id}` shows them), `sessions` its recent publisher sessions (or the one asked for).

    Readers ignore fields they do not know (as the models of its entries do): robots run the client
    they were built with for years, and a service that adds a field must not make every robot's
    `flush` take its answer for something else than fleetmap's."""

    model_config = ConfigDict(extra="ignore")  # a newer service may add fields: see DeliveryStatus

    map_id: str
    robot_id: str
    status: Literal["ok", "no_map", "no_robot"]
    unsettled: int = Field(default=0, description="the robot's scans accepted and not settled yet")
    scans_integrated: int = 0
    lost: int = 0
    dropped: int = 0
    duplicates: int = 0
    sessions: list[SessionDelivery] = Field(default_factory=list)
    buried: list[BuriedSession] = Field(
        default_factory=list,
        description="its sessions whose scans went with a deleted or replaced map of this id",
    )
    last_error: str | None = Field(
        default=None,
        description="why the robot's last scan refused or dropped was so (`last_error` in GET /maps/{id})",
    )

    def session(self, session_id: int | None) -> SessionDelivery | None:
        """The entry of publisher session `session_id` (None: scans without one), if listed."""
        key = 0 if session_id is None else session_id
        return next((entry for entry in self.sessions if entry.session == key), None)

    def buried_session(self, session_id: int | None) -> BuriedSession | None:
        """The `buried` entry of publisher session `session_id`, if listed."""
        return next((entry for entry in self.buried if entry.session == session_id), None)


__all__ = [
    "CONNECT_RETRY",
    "DEFAULT_ENDPOINT",
    "ALIVE_KEY",
    "ALIVE_KEY_WILDCARD",
    "BINARY_ENCODING",
    "BuriedSession",
    "DELIVERY_KEY",
    "DELIVERY_ERROR_ENCODING",
    "DELIVERY_KEY_WILDCARD",
    "DELIVERY_FIELDS",
    "DELIVERY_FIELDS_1_EXCLUDE",
    "DELIVERY_FIELDS_PARAMETER",
    "DELIVERY_SESSION_PARAMETER",
    "DeliveryStatus",
    "ID_PATTERN",
    "JSON_ENCODING",
    "SCAN_KEY",
    "SCAN_KEY_WILDCARD",
    "SEQ_LIMIT",
    "SESSION_LIMIT",
    "PoseMessage",
    "ScanError",
    "ScanMessage",
    "SessionDelivery",
    "is_valid_id",
    "new_session_id",
    "zenoh_error_text",
]
