"""Scan payload codecs: bytes on the wire <-> `WireScan` (a sequence number, a stamp, the publisher's
session id if it sends one, and an engine `Scan`).

Two encodings, chosen by the Zenoh sample's encoding (`fleetmap.wire`): JSON (`ScanMessage`) and
the compact little-endian binary layout below, documented byte by byte in docs/protocol.md. Every
decode either returns a fully valid `WireScan` or raises `DecodeError` with a reason.

Binary layout (little-endian), header of `HEADER.size` = 72 bytes (version 1) or
`HEADER_V2.size` = 80 bytes (version 2), then the arrays:

    offset size type    field
    0      4    bytes   magic b"FMS1"
    4      1    u8      version (1: no session id; 2: with one)
    5      1    u8      flags: bit 0 = explicit angles follow (else angle_min/increment are used)
    6      2    u16     reserved, 0
    8      8    u64     seq
    16     8    f64     stamp (s)
    24     8    f64     pose x (m)
    32     8    f64     pose y (m)
    40     8    f64     pose theta (rad)
    48     4    f32     range_min (m)
    52     4    f32     range_max (m; +inf = no maximum)
    56     8    f64     angle_min (rad; ignored, not checked, with flag bit 0)
    64     4    f32     angle_increment (rad; ignored, not checked, with flag bit 0)
    68     4    u32     n, the number of beams
    72     8    u64     session id, in [1, 2**53) (version 2 only)
    72/80  4*n  f32     angles (only with flag bit 0)
    ...    4*n  f32     ranges (NaN = invalid, +inf or >= range_max = no return)

A scan without a session id is encoded as version 1, which services before version 2 read too.
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import ValidationError

from fleetmap.scan import MAX_BEAMS, Pose2D, Scan, ScanError
from fleetmap.wire import BINARY_ENCODING, JSON_ENCODING, SEQ_LIMIT, SESSION_LIMIT, ScanMessage

MAGIC = b"FMS1"
#: The header without a session id (version 1) and with one (version 2, the session id after it).
VERSION, VERSION_SESSION = 1, 2
FLAG_ANGLES = 1
HEADER = struct.Struct("<4sBBHQddddffdfI")
HEADER_V2 = struct.Struct("<4sBBHQddddffdfIQ")
assert HEADER.size == 72 and HEADER_V2.size == 80, "the layout documented above and in docs/protocol.md"
#: The largest finite float32, the binary encoding's type for ranges, range_min, range_max, the angle
#: increment and explicit angles.
F32_MAX = float(np.finfo(np.float32).max)
#: The largest scan payload accepted by default, over Zenoh and REST alike (about 16 K beams as JSON
#: with explicit angles). Over REST it is stricter than the HTTP body limit (`ApiSettings.max_body_bytes`).
MAX_PAYLOAD_BYTES_DEFAULT = 4 * 1024 * 1024


class DecodeError(ValueError):
    """A payload that is not a valid scan message. The message says why.

    `scan_id` is the message's (seq, stamp, session) when it was read that far: a well-formed scan
    that the engine's checks or the input limits refuse (a pose outside the world bound, ...). The
    service then settles that scan of its session as refused (`MapRegistry.reject`), rather than
    count its seq as lost when the next one arrives, or never settle it when it was the last."""

    def __init__(self, message: str, scan_id: tuple[int, float, int | None] | None = None) -> None:
        super().__init__(message)
        self.scan_id = scan_id


class PayloadTooLarge(DecodeError):
    """A payload over `InputLimits.max_payload_bytes`, refused before decoding. Still a DecodeError,
    so Zenoh ingest counts it as rejected like any bad payload; REST answers it 413, not 422."""


class UnknownEncoding(DecodeError):
    """A payload labelled with an encoding the codec does not read (`text/plain`). Still a
    DecodeError, so Zenoh ingest counts it as rejected like any bad payload; REST answers it 415
    (Unsupported Media Type), naming the types it reads, not 422: the scan was not looked at."""


@dataclass(frozen=True)
class InputLimits:
    """What the service accepts from robots, beyond well-formedness. Checked on every decoded scan,
    whichever way it came (Zenoh or REST), before it can touch a map.

    - `world_bound`: |x| and |y| of the sensor pose, metres;
    - `max_beams`: beams per scan;
    - `max_range`: the longest range trusted, metres: readings at or beyond it (or the message's own
      range_max, whichever is smaller) are "no return", never a return kilometres away;
    - angles must be finite and span at most one turn (plus a rounding margin);
    - `max_payload_bytes`: the size of the encoded message, checked by `decode` before it decodes
      (`PayloadTooLarge`).
    """

    world_bound: float = 100_000.0
    max_beams: int = 16_384
    max_range: float = 1_000.0
    max_payload_bytes: int = MAX_PAYLOAD_BYTES_DEFAULT

    def check(self, wire: WireScan) -> WireScan:
        """`wire`, with range_max capped at max_range; raises DecodeError if it breaks a limit."""
        scan = wire.scan
        pose = scan.pose
        scan_id = (wire.seq, wire.stamp, wire.session)
        if abs(pose.x) > self.world_bound or abs(pose.y) > self.world_bound:
            raise DecodeError(
                f"pose ({pose.x:.6g}, {pose.y:.6g}) is outside the world bound of +-{self.world_bound:g} m",
                scan_id,
            )
        if scan.num_beams > self.max_beams:
            raise DecodeError(f"{scan.num_beams} beams is more than the limit of {self.max_beams}", scan_id)
        if scan.num_beams > 1 and (span := float(np.ptp(scan.angles))) > 2 * math.pi + 1e-3:
            # Most likely degrees where radians were meant (an increment of 1 for 1 degree): say so.
            raise DecodeError(
                f"beam angles span more than one turn ({span:.6g} rad; angles are in radians)", scan_id
            )
        if scan.range_max > self.max_range:
            if scan.range_min >= self.max_range:
                raise DecodeError(
                    f"range_min {scan.range_min:g} m is beyond the limit of {self.max_range:g} m", scan_id
                )
            capped = Scan(pose, scan.angles, scan.ranges, scan.range_min, self.max_range)
            return WireScan(wire.seq, wire.stamp, capped, wire.session)
        return wire


#: The limits when none are given: `fleetmap serve`'s defaults. The service's own (its options) are
#: `MapRegistry.input_limits`, which every way in (Zenoh, REST, ROS 2) passes to the decoders.
DEFAULT_LIMITS = InputLimits()


@dataclass(frozen=True)
class WireScan:
    """A decoded scan message: what the service integrates. `session` is the publisher's session id
    (`ScanMessage.session`), None from a publisher that sends none."""

    seq: int
    stamp: float
    scan: Scan
    session: int | None = None


def check_payload_size(size: int, limits: InputLimits = DEFAULT_LIMITS) -> None:
    """Raise `PayloadTooLarge` if a payload of `size` bytes is over `limits.max_payload_bytes`: what
    `decode` checks first, and what a transport can check before it copies the payload out."""
    if size > limits.max_payload_bytes:
        raise PayloadTooLarge(f"payload of {size} bytes exceeds the limit of {limits.max_payload_bytes}")


def decode(
    payload: bytes | bytearray | memoryview, encoding: str, limits: InputLimits = DEFAULT_LIMITS
) -> WireScan:
    """Decode a payload by its encoding, held to `limits`; an empty or unspecific encoding is sniffed
    (JSON object or binary magic). Raises `DecodeError` (`PayloadTooLarge` past the payload limit,
    `UnknownEncoding` for an encoding it does not read)."""
    check_payload_size(len(payload), limits)
    data = bytes(payload)
    # Media types are case-insensitive (RFC 9110, 8.3.1), as the REST API's other JSON bodies take them.
    kind = encoding.split(";", 1)[0].strip().lower()
    if kind in SNIFFED_ENCODINGS:
        kind = _sniff(data)
    if kind == JSON_ENCODING or kind == "text/json":
        return decode_json(data, limits)
    if kind == BINARY_ENCODING:
        return decode_binary(data, limits)
    raise UnknownEncoding(f"unknown encoding {encoding!r}; use {JSON_ENCODING} or {BINARY_ENCODING}")


#: Encodings that say nothing of the payload (Zenoh's default among them): it is told by its start.
SNIFFED_ENCODINGS = ("", "zenoh/bytes", "application/octet-stream")
#: What some Windows tools write before UTF-8 text; JSON forbids it (RFC 8259, 8.1).
UTF8_BOM = b"\xef\xbb\xbf"


def _sniff(data: bytes) -> str:
    """The encoding of a payload labelled with one of SNIFFED_ENCODINGS: binary if it starts
    with the magic, JSON if with `{` (after a byte order mark too, which `decode_json` then refuses by
    name). Anything else raises a DecodeError that says so: "unknown encoding 'zenoh/bytes'" told the
    sender that an encoding docs/protocol.md accepts was not known."""
    if data[:4] == MAGIC:
        return BINARY_ENCODING
    if data[:1] == b"{" or data[:4] == UTF8_BOM + b"{":
        return JSON_ENCODING
    raise DecodeError(
        f"a payload starting {data[:8]!r} is neither a binary scan (magic {MAGIC!r}) nor a JSON object "
        f"('{{'); label it {JSON_ENCODING} or {BINARY_ENCODING}"
    )


#: Items a JSON scan holds besides its two lists (`angles`, `ranges`).
JSON_SCAN_FIELDS = 64


#: `"seq": 7`, `"stamp": 1.5`, `"session": 42` (or null) in a JSON scan's bytes (`_json_scan_id`),
#: and those keys whatever their value.
_JSON_SCAN_ID_FIELD = re.compile(rb'"(seq|stamp|session)"\s*:\s*(null|-?[0-9][0-9.eE+-]*)')
_JSON_SCAN_ID_KEY = re.compile(rb'"(?:seq|stamp|session)"\s*:')


def _json_scan_id(data: bytes) -> tuple[int, float, int | None] | None:
    """The (seq, stamp, session) of a JSON scan that `decode_json` refuses, unparsed (too many items
    for the beam limit) or invalid, read from the bytes (a pass at C speed, as the count of commas):
    each of the three at most once, seq present, each valid as `ScanMessage` takes it. A scan's only
    strings are its keys, so in a scan as a client writes it they are these fields. None when not
    so (the message is refused as undecodable: its seq is not recorded)."""
    found: dict[bytes, bytes] = {}
    for match in _JSON_SCAN_ID_FIELD.finditer(data):
        key, value = match.groups()
        if key in found:
            return None
        found[key] = value
    if len(_JSON_SCAN_ID_KEY.findall(data)) != len(found):  # one with another value: "stamp": "1"
        return None
    try:
        seq = int(found[b"seq"])  # int(b"7.0") raises: a seq must be an integer, as strict parsing says
        stamp = float(found.get(b"stamp", b"0"))
        session = None if found.get(b"session", b"null") == b"null" else int(found[b"session"])
    except (KeyError, ValueError):
        return None
    if not (0 <= seq < SEQ_LIMIT and math.isfinite(stamp)):
        return None
    if session is not None and not 1 <= session < SESSION_LIMIT:
        return None
    return seq, stamp, session


def decode_json(data: bytes, limits: InputLimits = DEFAULT_LIMITS) -> WireScan:
    if data.startswith(UTF8_BOM):  # the parser's "expected value at line 1 column 1" did not say why
        raise DecodeError("invalid JSON scan: it starts with a byte order mark; send UTF-8 without one")
    # A JSON scan's only lists are `angles` and `ranges`, at most `max_beams` items each, and JSON
    # separates items by commas: a payload with more cannot be a scan within the limits. Counting
    # them (at C speed, about 1 ms for 4 MB) refuses it unparsed: a 4 MB list of 2 million numbers
    # took 110-140 ms to parse, on the Zenoh thread that every robot's scans pass through.
    if data.count(b",") > 2 * limits.max_beams + JSON_SCAN_FIELDS:
        # Refused as a scan past the beam limit, as binary's header check and `InputLimits.check`
        # refuse one, when its seq can be read (`_json_scan_id`): without it the service counted its
        # seq as lost too, and its robot's flush, never told, waited for it when it was the last.
        raise DecodeError(
            f"invalid JSON scan: more items than {limits.max_beams} beams can have", _json_scan_id(data)
        )
    try:
        # Strict: "5" or true for a number, or 5.0 for the seq, is a sender's mistake to name, not to
        # guess at (lax mode read true as seq 1).
        message = ScanMessage.model_validate_json(data, strict=True)
    except ValidationError as exc:
        # With its seq when that can be read (`_json_scan_id`): a scan refused for its body (2 angles
        # but 3 ranges, a negative range_min) was counted lost as well as rejected, and its robot's
        # flush waited for it when it was the last, as for the binary scans `from_message` refuses.
        raise DecodeError(f"invalid JSON scan: {_first_error(exc)}", _json_scan_id(data)) from None
    _refuse_repeated_keys(data, message)
    return from_message(message, limits)


def repeated_key(pairs: list[tuple[str, Any]]) -> str | None:
    """The first key given twice among one JSON object's `pairs` (`json.loads`' `object_pairs_hook`
    gets them), None when each is there once."""
    seen: set[str] = set()
    for key, _ in pairs:
        if key in seen:
            return key
        seen.add(key)
    return None


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    repeated = repeated_key(pairs)
    if repeated is not None:
        raise DecodeError(f"invalid JSON scan: the key {repeated!r} appears twice in an object")
    return dict(pairs)


def _refuse_repeated_keys(data: bytes, message: ScanMessage) -> None:
    """Refuse a scan that holds a key twice (`{"seq": 1, "seq": 7}`): the parser above keeps the
    last silently, and which one the robot meant is a guess; the REST API's other JSON bodies are
    refused so too (`api.strict_requests`). Called on a scan already valid, whose only strings are
    its keys (`ScanMessage` and `PoseMessage` forbid other keys and hold no string values): with
    each key once, the quotes are two per field it set. Counting them is one pass over the bytes
    (about 10 µs a 1081-beam scan); the second parse, made only when the count is off, took 0.32 ms,
    twice what decoding the scan takes."""
    keys = len(message.model_fields_set) + len(message.pose.model_fields_set)
    if data.count(b'"') != 2 * keys:
        json.loads(data, object_pairs_hook=_unique_pairs)


def from_message(message: ScanMessage, limits: InputLimits = DEFAULT_LIMITS) -> WireScan:
    """A validated `ScanMessage` as a `WireScan` within `limits`; raises `DecodeError` if the engine
    or the limits refuse it."""
    try:
        return limits.check(WireScan(message.seq, message.stamp, message.to_scan(), message.session))
    except ScanError as exc:
        raise DecodeError(str(exc), (message.seq, message.stamp, message.session)) from None


def decode_binary(data: bytes, limits: InputLimits = DEFAULT_LIMITS) -> WireScan:
    if len(data) < HEADER.size:
        raise DecodeError(f"binary scan of {len(data)} bytes is shorter than its {HEADER.size}-byte header")
    (magic, version, flags, _reserved, seq, stamp, x, y, theta, range_min, range_max, angle_min,
     angle_increment, n) = HEADER.unpack_from(data)  # fmt: skip
    if magic != MAGIC:
        raise DecodeError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version not in (VERSION, VERSION_SESSION):
        raise DecodeError(f"unsupported binary scan version {version}")
    header = HEADER if version == VERSION else HEADER_V2
    session = None
    if version == VERSION_SESSION:
        if len(data) < header.size:
            raise DecodeError(
                f"binary scan of {len(data)} bytes is shorter than its {header.size}-byte header"
            )
        session = header.unpack_from(data)[-1]
        if not 1 <= session < SESSION_LIMIT:
            raise DecodeError("session must be in [1, 2**53)")
    if flags & ~FLAG_ANGLES:
        raise DecodeError(f"unknown flags {flags:#x}")
    # Refused before the length is checked or anything allocated, against the limit in force
    # (`--max-beams`, 16384 by default) rather than the engine's MAX_BEAMS, so the reason names the
    # limit the robot broke, as `InputLimits.check` does for a scan of the right length.
    beam_limit = min(limits.max_beams, MAX_BEAMS)
    if n > beam_limit:
        # A well-formed header: the scan is refused, as `InputLimits.check` refuses one (`scan_id`).
        known = seq < SEQ_LIMIT and math.isfinite(stamp)
        raise DecodeError(
            f"{n} beams is more than the limit of {beam_limit}", (seq, stamp, session) if known else None
        )
    arrays = 2 if flags & FLAG_ANGLES else 1
    expected = header.size + 4 * n * arrays
    if len(data) != expected:
        raise DecodeError(f"binary scan of {n} beams must be {expected} bytes, got {len(data)}")
    if seq >= SEQ_LIMIT:
        raise DecodeError("seq must be below 2**63")
    # With explicit angles (flag bit 0) angle_min and angle_increment are not used, so not checked:
    # docs/protocol.md says they are ignored, and a robot may leave them NaN there ("not given").
    checked = [("stamp", stamp), ("range_min", range_min)]
    if not flags & FLAG_ANGLES:
        checked += [("angle_min", angle_min), ("angle_increment", angle_increment)]
    for name, value in checked:
        if not math.isfinite(value):
            # With a finite stamp (checked first) the scan's identity is known: refused as a scan, as
            # `decode_json` refuses a non-finite range_min (counted lost too without it).
            raise DecodeError(
                f"{name} must be finite", None if name == "stamp" else (int(seq), float(stamp), session)
            )
    body = np.frombuffer(data, dtype="<f4", offset=header.size)
    # Any 32-bit pattern may arrive, signalling NaNs included: widening them is fine (they stay NaN,
    # an invalid reading), so numpy's warning about it is noise.
    with np.errstate(invalid="ignore"):
        if flags & FLAG_ANGLES:
            angles = body[:n].astype(np.float64)
            ranges = body[n:].astype(np.float64)
        else:
            angles = angle_min + angle_increment * np.arange(n, dtype=np.float64)
            ranges = body.astype(np.float64)
    try:
        scan = Scan(Pose2D(x, y, theta), angles, ranges, float(range_min), float(range_max))
    except ScanError as exc:
        raise DecodeError(str(exc), (int(seq), float(stamp), session)) from None
    return limits.check(WireScan(int(seq), float(stamp), scan, session))


def encode_binary(
    scan: Scan, seq: int, stamp: float = 0.0, explicit_angles: bool | None = None, session: int | None = None
) -> bytes:
    """The binary encoding of a scan: version 2 with a `session` id, else version 1. Evenly spaced
    beams are sent as angle_min + increment unless `explicit_angles` is True; other beams always
    with explicit angles.

    Its float32 fields hold what a float32 can: a range_max beyond it is sent as +inf (no maximum,
    what it means at that length: the service caps it at its trusted range anyway) and readings
    beyond it as +inf (no return, likewise). A range_min, angle increment or explicit angle beyond
    it (a scan the service refuses anyway) raises `ScanError`, not struct's OverflowError."""
    n = scan.num_beams
    angles = scan.angles
    even = n < 2 or bool(np.allclose(np.diff(angles), angles[1] - angles[0], rtol=0, atol=1e-9))
    explicit = (not even) if explicit_angles is None else explicit_angles
    angle_min = float(angles[0]) if n else 0.0
    increment = float(angles[1] - angles[0]) if n > 1 else 0.0
    range_max = scan.range_max if scan.range_max <= F32_MAX else math.inf
    widest = max(scan.range_min, abs(increment), float(np.abs(angles).max()) if explicit and n else 0.0)
    if widest > F32_MAX:
        raise ScanError(
            f"{widest:g} does not fit the binary encoding's float32 (range_min, the angle increment, "
            "explicit angles); send the scan as JSON"
        )
    fields = (
        FLAG_ANGLES if explicit else 0, 0, seq, stamp, scan.pose.x, scan.pose.y,
        scan.pose.theta, scan.range_min, range_max, angle_min, increment, n,
    )  # fmt: skip
    if session is None:
        header = HEADER.pack(MAGIC, VERSION, *fields)
    else:
        header = HEADER_V2.pack(MAGIC, VERSION_SESSION, *fields, session)
    parts = [header]
    if explicit:
        parts.append(angles.astype("<f4").tobytes())
    with np.errstate(over="ignore"):  # readings beyond float32 become +inf: no return (above)
        parts.append(scan.ranges.astype("<f4").tobytes())
    return b"".join(parts)


def encode_json(scan: Scan, seq: int, stamp: float = 0.0, session: int | None = None) -> bytes:
    """The JSON encoding of a scan, exact: +inf (no return) becomes null; beams with an invalid
    reading (NaN, which JSON cannot hold) or a reading of -inf (below any range_min, e.g. ROS's
    "too close to measure", REP 117) are left out, since every sensor model ignores them; the
    compact angle_min + increment form is used only when it decodes to these angles bit for bit."""
    # Not -inf as null: null means +inf, no return, which a map with no_return_range > 0 clears as
    # free space along the beam, through the obstacle too close to measure (binary keeps -inf).
    valid = ~np.isnan(scan.ranges) & (scan.ranges != -math.inf)
    angles = scan.angles[valid]
    ranges = scan.ranges[valid]
    n = int(angles.size)
    message: dict[str, object] = {
        "seq": seq,
        "stamp": stamp,
        **({} if session is None else {"session": session}),
        "pose": {"x": scan.pose.x, "y": scan.pose.y, "theta": scan.pose.theta},
        "range_min": scan.range_min,
        "ranges": [None if r == math.inf else r for r in ranges.tolist()],
    }
    if math.isfinite(scan.range_max):
        message["range_max"] = scan.range_max
    increment = float(angles[1] - angles[0]) if n > 1 else 0.0
    if n > 1 and np.array_equal(angles[0] + increment * np.arange(n, dtype=np.float64), angles):
        message["angle_min"] = float(angles[0])
        message["angle_increment"] = increment
    else:
        message["angles"] = angles.tolist()
    return json.dumps(message, separators=(",", ":")).encode()


def _first_error(exc: ValidationError) -> str:
    """The first validation error, safe to log and to show: field names come from the sender, so
    they are quoted (no newlines or control characters get through) and cut short."""
    err = exc.errors()[0]
    where = ".".join(_safe_text(str(p), 40) for p in err.get("loc", ()))
    # A check of the whole message (`ScanMessage._check_angles`) has no field to name, and pydantic
    # puts "Value error, " before its sentence: "2 angles but 3 ranges" says it all.
    what = _safe_text(str(err.get("msg")).removeprefix("Value error, "), 200)
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"{where}: {what}{more}" if where else f"{what}{more}"


def _safe_text(text: str, limit: int) -> str:
    """`text` as is when it is short and plain, else its repr, cut to `limit` characters."""
    if not text.isprintable() or len(text) > limit:
        text = repr(text[:limit])
    return text
