"""docs/protocol.md stays true: its hexdump is what the codec writes, its JSON example decodes, and
its stated header layout matches the codec's."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from fleetmap import codec
from fleetmap.scan import Scan

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def test_hexdump_is_what_the_codec_writes() -> None:
    text = DOC.read_text()
    dump = re.search(r"```\noffset +bytes.*?\n(.*?)```", text, re.S)
    assert dump, "the hexdump block"
    data = bytearray()
    for line in dump.group(1).splitlines():
        offset, _, rest = line.partition("  ")
        assert int(offset, 16) == len(data)
        data += bytes(int(b, 16) for b in re.findall(r"\b[0-9a-f]{2}\b", rest.split("   ")[0]))
    scan = Scan.from_fan((1.5, -2.25, 0.5), -0.25, 0.25, [1.0, math.inf, math.nan], 0.05, 30.0)
    assert bytes(data) == codec.encode_binary(scan, 42, stamp=1700000000.25)
    assert len(data) == 84 == codec.HEADER.size + 4 * 3
    decoded = codec.decode(bytes(data), codec.BINARY_ENCODING)
    assert (decoded.seq, decoded.stamp) == (42, 1700000000.25)


def test_json_example_decodes() -> None:
    text = DOC.read_text()
    example = re.search(r"```json\n(.*?)```", text, re.S)
    assert example
    message = json.loads(example.group(1))
    wire = codec.decode(example.group(1).encode(), codec.JSON_ENCODING)
    assert wire.seq == message["seq"] == 42
    assert wire.scan.ranges.tolist() == [1.0, math.inf, 2.5]


def test_documented_header_offsets_match_the_codec() -> None:
    rows = re.findall(r"^\| (\d+) +\| (\d+) +\| (\w+) +\| ([\w ]+?) +\|", DOC.read_text(), re.M)
    fmt = {"bytes": "4s", "u8": "B", "u16": "H", "u64": "Q", "f64": "d", "f32": "f", "u32": "I"}
    # Version 2's header is version 1's followed by the session id.
    assert rows[0][3] == "magic" and rows[-2][3] == "n" and rows[-1][3] == "session"
    assert "<" + "".join(fmt[t] for _, _, t, _ in rows) == codec.HEADER_V2.format
    assert "<" + "".join(fmt[t] for _, _, t, _ in rows[:-1]) == codec.HEADER.format
    offset = 0
    for start, size, _, _ in rows:
        assert int(start) == offset
        offset += int(size)
    assert offset == codec.HEADER_V2.size == 80 and int(rows[-1][0]) == codec.HEADER.size == 72


def test_the_refusal_reasons_the_doc_quotes_are_the_decoders() -> None:
    """A robot implemented from the doc matches the reasons it quotes. The doc quoted
    `extra: Extra inputs are not permitted` for any unknown field, while the reason names the field,
    and did not say that a range_min at or beyond the trusted range is refused."""
    text = " ".join(DOC.read_text().split())
    good = {"seq": 1, "pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": 0.0, "angle_increment": 0.1,
            "ranges": [1.0]}  # fmt: skip
    scan = Scan.from_fan((0, 0, 0), 0.0, 0.1, [1.0], 1500.0, math.inf)
    quoted = {
        "sesion: Extra inputs are not permitted": (
            json.dumps({**good, "sesion": 1}).encode(),
            "application/json",
        ),
        "range_min 1500 m is beyond the limit of 1000 m": (
            codec.encode_binary(scan, 1),
            codec.BINARY_ENCODING,
        ),
        "binary scan of 3 beams must be 84 bytes, got 80": (
            codec.encode_binary(Scan.from_fan((0, 0, 0), 0.0, 0.1, [1.0] * 3), 1)[:80],
            codec.BINARY_ENCODING,
        ),
    }
    for reason, (payload, encoding) in quoted.items():
        assert f"`{reason}`" in text, reason
        try:
            codec.decode(payload, encoding)
        except codec.DecodeError as exc:
            assert reason in str(exc), (reason, str(exc))
        else:
            raise AssertionError(f"{reason}: decoded")
    assert "`extra: Extra inputs are not permitted`" not in text  # no field is named extra
