"""Reader for CARMEN text logs (plain or gzip-compressed), front-laser messages only.

Messages read (one per line, whitespace-separated; the full spec is in
`../shared/datasets/README.md`):

`FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_ts host logger_ts`
    `x y theta` is the corrected ROBOT pose. The laser sits `robot_frontlaser_offset` metres ahead
    of the robot along its heading (the value of the last `PARAM robot_frontlaser_offset` line
    before this message, 0 before any), so the SENSOR pose is
    `(x + off*cos(theta), y + off*sin(theta), theta)`. The beams span 180 degrees from -90 degrees:
    beam i is at `-pi/2 + i*pi/n` for n = 180 or 360 (the last beam stops one step short of +90
    degrees) and `-pi/2 + i*pi/(n-1)` for n = 181 or 361 (both ends included). For any other n the
    same rule is extended by parity: odd n uses `pi/(n-1)`, even n uses `pi/n`. `range_max` is the
    `robot_front_laser_max` PARAM in force, else `DEFAULT_FLASER_RANGE_MAX` (80 m).
`ROBOTLASER1 type start_angle fov angular_res max_range accuracy remission_mode n r1..rn
k rem1..remk laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd_safety side_safety
turn_axis ts host logger_ts`
    The LASER pose is given directly; beam i is at `start_angle + i*angular_res`;
    `range_max = max_range`.

Readings at or above `range_max` are kept as they are: `Scan` treats them as "no return".
`range_min` is `DEFAULT_RANGE_MIN` (1 mm) rather than 0, so that zero readings, the laser's "no
measurement" code, are ignored, as are negative readings. `#` comments, `ODOM`,
`NEFF`, `SYNC`, `RLASER`, `TRUEPOS`, `ROBOTLASER2` (the rear laser) and every unknown message type
are skipped (comments whatever their encoding: the rest of a log must be UTF-8, or UTF-16 or UTF-32
with its byte order mark);
PARAM lines are skipped except for the two parameters above.

Every FLASER / ROBOTLASER1 line must have exactly the number of fields the format implies: a line
that lost a reading would otherwise shift every later field and silently read a range as the pose.

What the real files (`../shared/datasets/*.log.gz`) contain, checked when this reader was written:

* intel-corrected: 910 FLASER of 180 beams, `robot_frontlaser_offset 0.0`, no
  `robot_front_laser_max` (so 80 m; readings up to 81.83 appear). No log has zero or negative readings.
* freiburg-campus-corrected: 2008 FLASER of 360 beams; `robot_frontlaser_offset` is -0.04 (the
  laser sits 4 cm BEHIND the robot's reference point) and `robot_front_laser_max` 80.99 (readings up
  to 81.91 appear). Every FLASER timestamp is 0. The first FLASER has the robot pose (0, 0, 0): a
  genuine pose, the trajectory's origin, not a placeholder (its end points match the next scan's).
* csail-robotlaser: 686 ROBOTLASER1 of 361 beams, `start_angle -1.570796`, `angular_res 0.008727`
  (pi/360 rounded: the last beam is at +1.570924, 0.13 mrad past +90 degrees; we follow the file),
  `max_range 80` with readings up to 81.91, no remissions. The laser pose fields ARE where the spec
  puts them: on every line they equal the robot pose fields (the laser offset is folded in, or
  zero) and they trace a continuous trajectory. Only the first line has the pose (0, 0, 0), again a
  genuine origin.

How that was checked: with these conventions, consecutive scans' end points lie a median 2 to 6 cm
from the previous scan's; mirroring the beam order raises that to 0.3-0.4 m, and moving the laser
30 cm along the heading or turning it by 0.05 rad also makes it worse, on all three logs.
"""

from __future__ import annotations

import codecs
import contextlib
import gzip
import io
import math
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..scan import MAX_BEAMS, directions_finite
from .base import (
    UNBOUNDED_RANGE_MAX,
    Dataset,
    DatasetBuilder,
    DatasetError,
    check_range_window,
    dataset_name,
    open_log,
)

#: `range_max` of FLASER scans when the log has no `robot_front_laser_max` PARAM.
DEFAULT_FLASER_RANGE_MAX = 80.0

GZIP_MAGIC = b"\x1f\x8b"
#: The byte order marks of UTF-32 and UTF-16 text, little- and big-endian, each with its codec
#: (which reads the mark to tell the byte order). UTF-32's first: its little-endian mark starts
#: with UTF-16's.
_BYTE_ORDER_MARKS = (
    (codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"), (codecs.BOM_UTF16_LE, "utf-16"),
    (codecs.BOM_UTF16_BE, "utf-16"),
)  # fmt: skip

# Field counts around the ranges, from the message layouts in the module docstring.
_FLASER_TAIL = 9  # x y theta odom_x odom_y odom_theta ipc_ts host logger_ts
_ROBOTLASER1_HEAD = 9  # tag type start_angle fov angular_res max_range accuracy remission_mode n
_ROBOTLASER1_TAIL = 14  # laser pose, robot pose, tv rv fwd_safety side_safety turn_axis ts host logger_ts


class _LineError(Exception):
    """Raised by the line parsers; the caller adds the file name and line number."""


def flaser_angles(n: int) -> np.ndarray:
    """Beam bearings of an n-beam FLASER scan (see the module docstring for the rule)."""
    step = math.pi / (n - 1) if n % 2 == 1 and n > 1 else math.pi / n
    return -math.pi / 2 + step * np.arange(n, dtype=np.float64)


def read_carmen(
    path: str | Path,
    *,
    range_min: float | None = None,
    range_max: float | None = None,
    stream: BinaryIO | None = None,
) -> Dataset:
    """Read a CARMEN log (plain text or gzip, detected by content) into a `Dataset`.

    `range_min` (default 1e-3) and `range_max` (default: the log's, per message) override the
    log's values for every scan; `range_max=math.inf` means no limit. `stream`, when given, is the
    file already open (`open_log`, at its start), read instead of opening `path`, which then names
    it only. Raises `DatasetError` naming the file and line for a malformed line, for a file that
    is not text, and for a log without any FLASER or ROBOTLASER1 message. Raises
    `FileNotFoundError` / `OSError` when the file can't be opened.
    """
    path = Path(path)
    rmin, rmax_override = check_range_window(range_min, range_max)
    if stream is None:
        with open_log(path) as opened:
            return _read_carmen(opened, path, rmin, rmax_override)
    return _read_carmen(stream, path, rmin, rmax_override)


def _read_carmen(stream: BinaryIO, path: Path, rmin: float, rmax_override: float | None) -> Dataset:
    """`read_carmen` of an open `stream`, the range window checked."""
    builder = DatasetBuilder()
    state = _ParseState()
    lineno = 0
    try:
        for lineno, line in _numbered_lines(stream, path):
            try:
                _parse_line(line, state, builder, rmin, rmax_override)
            except _LineError as exc:
                raise DatasetError(f"{path}:{lineno}: {exc}") from None
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise DatasetError(f"{path}: corrupt gzip data after line {lineno}: {exc}") from None
    if len(builder) == 0:
        raise DatasetError(
            f"{path}: no FLASER or ROBOTLASER1 message in {lineno} lines: not a CARMEN laser log"
        )
    return builder.build(name=dataset_name(path), path=path, format="carmen", range_min=rmin)


def _numbered_lines(stream: BinaryIO, path: Path) -> Iterator[tuple[int, str]]:
    """(1-based line number, decoded line) of a plain or gzip file. A UTF-8 byte order mark at the
    start of the file is not part of its first line: an editor that saves with one (Notepad) put
    it in front of that line's tag, which then named no known message and was skipped without a
    word, so a log lost its first scan, or its robot_frontlaser_offset, which moved every scan.

    Lines end at LF, CR LF or a lone CR, as in Python's text files ("universal newlines"): a log
    with classic Mac line endings (CR alone) was one line, its first word a `#` comment or a
    PARAM, and was refused as 'no FLASER or ROBOTLASER1 message in 1 lines: not a CARMEN laser
    log'; a lone CR between two lines (logs joined) made them one, refused as malformed.

    A file that starts with a UTF-16 byte order mark is UTF-16 text: Windows PowerShell 5's `>`
    writes so (`gzip -dc intel.log.gz > intel.log`), and such a log was refused as 'not UTF-8
    text: not a CARMEN log'. One that starts with a UTF-32 mark is UTF-32 text (`Out-File
    -Encoding utf32`): read as UTF-16, whose little-endian mark its own starts with, it was
    refused as holding no laser message."""
    compressed = stream.read(2) == GZIP_MAGIC
    stream.seek(0)
    lineno = 0
    with gzip.GzipFile(fileobj=stream, mode="rb") if compressed else contextlib.nullcontext(stream) as f:
        head = f.read(4)
        codec = next((codec for mark, codec in _BYTE_ORDER_MARKS if head.startswith(mark)), None)
        if codec is not None:
            f.seek(0)  # the codec reads the mark, to tell the byte order
            yield from _marked_lines(f.read(), path, codec)
            return
        f.seek(0)
        for raw in f:
            body = raw[:-1] if raw.endswith(b"\n") else raw
            if body.endswith(b"\r"):  # CR LF, one line end
                body = body[:-1]
            # The check first: nearly every line has no CR, and is not copied by a split.
            for piece in body.split(b"\r") if b"\r" in body else (body,):
                lineno += 1
                yield lineno, _decode_line(piece, lineno, path)


def _decode_line(line: bytes, lineno: int, path: Path) -> str:
    """A UTF-8 line of a log as text (the byte order mark dropped from the first). A `#` comment
    that is not UTF-8 is free text in another encoding (a header saying 'Universität' in Latin-1),
    which the parser skips unread: it comes with its odd bytes replaced, where it had the whole log
    refused as 'not UTF-8 text: not a CARMEN log'. Any other line that is not UTF-8 raises
    `DatasetError` naming it."""
    encoding = "utf-8-sig" if lineno == 1 else "utf-8"
    try:
        return line.decode(encoding)
    except UnicodeDecodeError:
        text = line.decode(encoding, errors="replace")
        if text.lstrip().startswith("#"):
            return text
        raise DatasetError(f"{path}:{lineno}: not UTF-8 text: not a CARMEN log") from None


def _marked_lines(data: bytes, path: Path, codec: str) -> Iterator[tuple[int, str]]:
    """(1-based line number, line) of text in `codec` (`utf-16` or `utf-32`) that starts with its
    byte order mark, lines ending as `_numbered_lines` ends them (LF, CR LF or CR). A whole log in
    memory is a few MB."""
    name = codec.upper()
    try:
        text = data.decode(codec)
    except UnicodeDecodeError as exc:
        raise DatasetError(
            f"{path}: not {name} text (byte {exc.start}), though it starts as {name} does"
        ) from None
    # A StringIO with newline=None ends lines at LF, CR LF and CR only (str.splitlines ends them
    # at form feeds and other separators too, where a UTF-8 log's lines do not end).
    yield from enumerate(io.StringIO(text, newline=None), start=1)


class _ParseState:
    """The PARAM values in force at the current line."""

    def __init__(self) -> None:
        self.frontlaser_offset = 0.0
        self.front_laser_max = DEFAULT_FLASER_RANGE_MAX
        #: Where `front_laser_max` comes from, for errors: a log without the PARAM (the Intel log)
        #: must not be told its PARAM is wrong.
        self.front_laser_max_source = "FLASER's default range_max (no PARAM robot_front_laser_max before it)"
        # Angle arrays shared by every scan with the same layout (DatasetBuilder stores each once).
        self.angle_cache: dict[tuple[float, ...], np.ndarray] = {}

    def angles(self, key: tuple[float, ...], make: Callable[[], np.ndarray]) -> np.ndarray:
        arr = self.angle_cache.get(key)
        if arr is None:
            arr = self.angle_cache[key] = make()
        return arr


def _parse_line(
    line: str, state: _ParseState, builder: DatasetBuilder, rmin: float, rmax_override: float | None
) -> None:
    tokens = line.split()
    if not tokens:
        return
    tag = tokens[0]
    if tag == "FLASER":
        _parse_flaser(tokens, state, builder, rmin, rmax_override)
    elif tag == "ROBOTLASER1":
        _parse_robotlaser1(tokens, state, builder, rmin, rmax_override)
    elif tag == "PARAM" and len(tokens) >= 2:
        name = tokens[1]
        if name == "robot_frontlaser_offset":
            state.frontlaser_offset = _number(tokens, 2, name)
        elif name == "robot_front_laser_max":
            state.front_laser_max = _number(tokens, 2, name)
            state.front_laser_max_source = "PARAM robot_front_laser_max"
    # Anything else (comments, ODOM, NEFF, SYNC, RLASER, TRUEPOS, unknown types): not needed.


def _parse_flaser(
    tokens: list[str], state: _ParseState, builder: DatasetBuilder, rmin: float, rmax_override: float | None
) -> None:
    n = _count(tokens, 1, "FLASER beam count n")
    _expect_fields(tokens, 2 + n + _FLASER_TAIL, f"FLASER with n={n}")
    ranges = _numbers(tokens, 2, n, "FLASER range")
    x, y, theta = (_number(tokens, 2 + n + k, f"FLASER pose {f}") for k, f in enumerate(("x", "y", "theta")))
    off = state.frontlaser_offset
    pose = (x + off * math.cos(theta), y + off * math.sin(theta), theta)
    if not (math.isfinite(pose[0]) and math.isfinite(pose[1])):  # finite parts, an infinite sum
        raise _LineError(f"FLASER sensor pose {pose} (robot pose plus robot_frontlaser_offset) is not finite")
    rmax = _scan_range_max(rmax_override, state.front_laser_max, rmin, state.front_laser_max_source)
    builder.add(pose, state.angles((n,), lambda: flaser_angles(n)), ranges, rmax)


def _parse_robotlaser1(
    tokens: list[str], state: _ParseState, builder: DatasetBuilder, rmin: float, rmax_override: float | None
) -> None:
    n = _count(tokens, _ROBOTLASER1_HEAD - 1, "ROBOTLASER1 beam count n")
    # The remission count sits right after the ranges: check there is a field there before reading it.
    what = f"ROBOTLASER1 with n={n}"
    _expect_fields(tokens, _ROBOTLASER1_HEAD + n + 1 + _ROBOTLASER1_TAIL, what, minimum=True)
    k = _count(tokens, _ROBOTLASER1_HEAD + n, "ROBOTLASER1 remission count", allow_zero=True)
    _expect_fields(tokens, _ROBOTLASER1_HEAD + n + 1 + k + _ROBOTLASER1_TAIL, f"{what}, k={k}")
    start = _number(tokens, 2, "ROBOTLASER1 start_angle")
    step = _number(tokens, 4, "ROBOTLASER1 angular_res")
    max_range = _number(tokens, 5, "ROBOTLASER1 max_range", finite=False)
    ranges = _numbers(tokens, _ROBOTLASER1_HEAD, n, "ROBOTLASER1 range")
    base = _ROBOTLASER1_HEAD + n + 1 + k
    x, y, theta = (
        _number(tokens, base + j, f"ROBOTLASER1 laser pose {f}") for j, f in enumerate(("x", "y", "theta"))
    )
    angles = state.angles((n, start, step), lambda: _robotlaser1_angles(n, start, step))
    if not directions_finite(theta, angles):
        # Refused here, with the line, for the reason `_robotlaser1_angles` gives: `Scan` refuses it.
        raise _LineError(f"ROBOTLASER1 beam directions laser_theta {theta} + beam angle overflow")
    rmax = _scan_range_max(rmax_override, max_range, rmin, "ROBOTLASER1 max_range")
    builder.add((x, y, theta), angles, ranges, rmax)


def _robotlaser1_angles(n: int, start: float, step: float) -> np.ndarray:
    """Beam i's bearing `start + i*step`; `_LineError` when one is not finite. Both numbers are
    finite, but their sum can overflow (a step of 1e308), and a `Scan` refuses infinite bearings:
    it is the line that is malformed, and it must be reported when the file is loaded, not when the
    scan is built mid-iteration (which stopped `fleetmap build` with a traceback)."""
    with np.errstate(over="ignore", invalid="ignore"):
        angles = start + step * np.arange(n, dtype=np.float64)
    if not np.all(np.isfinite(angles)):
        raise _LineError(f"ROBOTLASER1 beam angles start_angle {start} + i * angular_res {step} overflow")
    return angles


def _scan_range_max(override: float | None, from_log: float, rmin: float, what: str) -> float:
    if override is not None:
        return override
    rmax = UNBOUNDED_RANGE_MAX if from_log == math.inf else from_log
    if not (rmax > rmin and rmax <= UNBOUNDED_RANGE_MAX):
        raise _LineError(
            f"{what} = {from_log} is not a usable range_max (must be > range_min {rmin} and <= "
            f"{UNBOUNDED_RANGE_MAX:g}); give a range_max (fleetmap build --range-max) to override it"
        )
    return rmax


def _expect_fields(tokens: list[str], expected: int, what: str, *, minimum: bool = False) -> None:
    if len(tokens) < expected or (not minimum and len(tokens) != expected):
        raise _LineError(
            f"{what} needs {'at least ' if minimum else ''}{expected} fields, found {len(tokens)}"
        )


def _count(tokens: list[str], i: int, what: str, *, allow_zero: bool = False) -> int:
    if i >= len(tokens):
        raise _LineError(f"line ends before the {what}")
    try:
        n = int(tokens[i])
    except ValueError:
        raise _LineError(f"{what} must be an integer, got {tokens[i]!r}") from None
    if n < (0 if allow_zero else 1) or n > MAX_BEAMS:
        raise _LineError(f"{what} = {n} is out of range")
    return n


def _number(tokens: list[str], i: int, what: str, *, finite: bool = True) -> float:
    if i >= len(tokens):
        raise _LineError(f"line ends before the {what}")
    try:
        v = float(tokens[i])
    except ValueError:
        raise _LineError(f"{what} must be a number, got {tokens[i]!r}") from None
    if finite and not math.isfinite(v):
        raise _LineError(f"{what} must be finite, got {tokens[i]!r}")
    return v


def _numbers(tokens: list[str], start: int, n: int, what: str) -> np.ndarray:
    """`n` floats from `tokens[start:]`. NaN and inf are allowed: `Scan` gives them a meaning."""
    try:
        return np.array([float(t) for t in tokens[start : start + n]], dtype=np.float64)
    except ValueError:
        for j, t in enumerate(tokens[start : start + n]):
            try:
                float(t)
            except ValueError:
                raise _LineError(f"{what} {j} must be a number, got {t!r}") from None
        raise  # unreachable: some token failed above
