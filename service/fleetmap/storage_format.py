"""How the durable store lays scans, tiles and whole maps out as bytes: journal rows, tile rows and
the single-file snapshots of `GET /maps/{id}/snapshot`. Every format returns exactly what was stored
(each layer's bits, NaN included)."""

from __future__ import annotations

import contextlib
import io
import json
import math
import struct
import threading
import tokenize
import zipfile
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING

import numpy as np
from numba import njit
from pydantic import ValidationError

from fleetmap.config import MAX_COORDINATE, MapConfig
from fleetmap.database import StorageError
from fleetmap.export import Window
from fleetmap.grid_map import GridMap
from fleetmap.scan import Pose2D, Scan
from fleetmap.tiles import LayerArray, TileKey, TileLimitError, layer_arrays, tile_bytes
from fleetmap.upload_spool import as_file, check_stop, close_spool, spooled_file, upload_zip

if TYPE_CHECKING:
    from fleetmap.memory_budget import UploadReservation

# -- encodings ---------------------------------------------------------------------------------------

_SCAN_HEADER = struct.Struct("<Bdddddi")  # version, x, y, theta, range_min, range_max, n
#: Journal scans, version 2: the version 1 header, then a flags byte. Flag `_FAN`: the angles are
#: `angle_min + angle_increment * arange(n)` bit for bit, stored as those two float64; else n float64.
#: Flag `_RANGES_F32`: every range is exactly a float32 (as the binary wire encoding sends them, NaN
#: aside), stored as n float32; else n float64. A 1081-beam scan from the binary encoding takes 4.4 KB
#: instead of 17 KB: the journal is most of the service's disk writes.
_SCAN_FLAGS = struct.Struct("<B")
_FAN, _RANGES_F32 = 1, 2
#: Version 3 (what `scan_to_blob` writes): version 2 followed by the CRC-32 of everything before it.
#: SQLite checks no page's contents, and a version 2 row with a flipped bit in its poses or ranges
#: decoded as another valid scan, so a damaged journal replayed silently into a different map.
_SCAN_CRC = struct.Struct("<I")
#: The version `scan_to_blob` writes; `scan_from_blob` reads it and every earlier one.
_SCAN_VERSION = 3


@njit(cache=True, nogil=True)
def _rebuilds(angles: np.ndarray, inc: float) -> bool:
    """Whether `angles[0] + inc * k` (as `Scan.from_fan` computes it) is `angles[k]` for every k."""
    for k in range(angles.size):  # noqa: SIM110 - a compiled loop, not a generator
        if angles[0] + inc * float(k) != angles[k]:
            return False
    return True


@njit(cache=True, nogil=True)
def _all_float32(values: np.ndarray) -> bool:
    """Whether every value is exactly a float32 (NaN counts: its payload carries no meaning here)."""
    for v in values:  # noqa: SIM110 - a compiled loop, not a generator
        if np.float64(np.float32(v)) != v and not np.isnan(v):
            return False
    return True


def _fan_of(angles: np.ndarray) -> tuple[float, float] | None:
    """(angle_min, angle_increment) that rebuild `angles` exactly as `Scan.from_fan` does, if any."""
    n = angles.size
    if n < 2:
        return None
    step = float(angles[1] - angles[0])
    span = float(angles[-1] - angles[0]) / (n - 1)
    # The difference of the first two angles is within an ulp or two of the increment; a float32
    # increment (the binary encoding) is recovered exactly by rounding to float32.
    for inc in (step, float(np.float32(step)), span, float(np.float32(span)),
                math.nextafter(step, math.inf), math.nextafter(step, -math.inf)):  # fmt: skip
        if math.isfinite(inc) and _rebuilds(angles, inc):
            return float(angles[0]), inc
    return None


def scan_to_blob(scan: Scan) -> bytes:
    """An exact serialisation of an engine scan for the journal (`_SCAN_VERSION`: compact when it
    can be, with a checksum)."""
    flags = 0
    parts = []
    fan = _fan_of(scan.angles)
    if fan is not None:
        flags |= _FAN
        parts.append(struct.pack("<dd", *fan))
    else:
        parts.append(scan.angles.astype("<f8").tobytes())
    if _all_float32(scan.ranges):
        flags |= _RANGES_F32
        parts.append(scan.ranges.astype("<f4").tobytes())
    else:
        parts.append(scan.ranges.astype("<f8").tobytes())
    pose = scan.pose
    head = _SCAN_HEADER.pack(
        _SCAN_VERSION, pose.x, pose.y, pose.theta, scan.range_min, scan.range_max, scan.num_beams
    )
    body = head + _SCAN_FLAGS.pack(flags) + b"".join(parts)
    return body + _SCAN_CRC.pack(zlib.crc32(body))


def scan_from_blob(blob: bytes) -> Scan:
    """The scan `scan_to_blob` stored (versions 1, 2 and 3); `StorageError` if the row is corrupt."""
    try:
        version, x, y, theta, range_min, range_max, n = _SCAN_HEADER.unpack_from(blob)
        at = _SCAN_HEADER.size
        if version == 1:
            if n < 0 or len(blob) != at + 16 * n:
                raise StorageError("corrupt journal entry")
            body = np.frombuffer(blob, dtype="<f8", offset=at)
            return Scan(Pose2D(x, y, theta), body[:n].copy(), body[n:].copy(), range_min, range_max)
        if version == 3:  # version 2 and its CRC-32: checked, then read as version 2 without it
            body_size = len(blob) - _SCAN_CRC.size
            (crc,) = _SCAN_CRC.unpack_from(blob, body_size)
            blob = blob[:body_size]
            if zlib.crc32(blob) != crc:
                raise StorageError("corrupt journal entry: its checksum does not match its contents")
        elif version != 2:
            raise StorageError("corrupt journal entry")
        if n < 0:
            raise StorageError("corrupt journal entry")
        (flags,) = _SCAN_FLAGS.unpack_from(blob, at)
        at += _SCAN_FLAGS.size
        size = at + (16 if flags & _FAN else 8 * n) + (4 if flags & _RANGES_F32 else 8) * n
        if flags & ~(_FAN | _RANGES_F32) or len(blob) != size:
            raise StorageError("corrupt journal entry")
        if flags & _FAN:
            angle_min, inc = struct.unpack_from("<dd", blob, at)
            angles = angle_min + inc * np.arange(n, dtype=np.float64)
            at += 16
        else:
            angles = np.frombuffer(blob, dtype="<f8", count=n, offset=at).copy()
            at += 8 * n
        if flags & _RANGES_F32:
            ranges = np.frombuffer(blob, dtype="<f4", count=n, offset=at).astype(np.float64)
        else:
            ranges = np.frombuffer(blob, dtype="<f8", count=n, offset=at).copy()
        return Scan(Pose2D(x, y, theta), angles, ranges, range_min, range_max)
    except (struct.error, ValueError) as exc:  # too short, or a Scan that cannot be (ScanError)
        raise StorageError(f"corrupt journal entry: {exc}") from exc


#: A journal row that is not a scan: a window of cells made unknown (`GridMap.clear_window`, `DELETE
#: /maps/{id}/region`). This version byte (no scan's), the window's i0, j0, i1 and j1, then the CRC-32
#: of what comes before. Replayed in journal order with the scans, so a restart forgets the cells
#: just where the running service did.
_CLEARED_WINDOW = struct.Struct("<Bqqqq")
_CLEARED_WINDOW_VERSION = 100


def cleared_window_to_blob(window: Window) -> bytes:
    """The journal row of a window cleared (`journal_row_from_blob` reads it back)."""
    body = _CLEARED_WINDOW.pack(_CLEARED_WINDOW_VERSION, window.i0, window.j0, window.i1, window.j1)
    return body + _SCAN_CRC.pack(zlib.crc32(body))


def journal_row_from_blob(blob: bytes) -> Scan | Window:
    """What a journal row holds: a scan (`scan_to_blob`, any version `scan_from_blob` reads) or a
    window of cells cleared (`cleared_window_to_blob`); `StorageError` if the row is corrupt."""
    if blob[:1] != bytes([_CLEARED_WINDOW_VERSION]):
        return scan_from_blob(blob)
    if len(blob) != _CLEARED_WINDOW.size + _SCAN_CRC.size:
        raise StorageError("corrupt journal entry: a cleared window of the wrong size")
    (crc,) = _SCAN_CRC.unpack_from(blob, _CLEARED_WINDOW.size)
    if zlib.crc32(blob[: _CLEARED_WINDOW.size]) != crc:
        raise StorageError("corrupt journal entry: its checksum does not match its contents")
    _, i0, j0, i1, j1 = _CLEARED_WINDOW.unpack_from(blob)
    return Window(i0, j0, i1, j1)


#: Stored tiles, format 2 (docs/durability.md, "Tile rows"): this magic, then zlib (level 1) of one
#: byte (the number of arrays) and, per stored array in the store's order, a kind byte and its data.
TILE_MAGIC = b"FMT2"
#: Kinds: every cell holds the array's never-observed value (no data); a bit mask of the cells that
#: do not, then their values; all cells' values.
TILE_UNKNOWN, TILE_SPARSE, TILE_DENSE = 0, 1, 2


def _as_bits(array: np.ndarray, dtype: type) -> np.ndarray:
    """`array` (of `dtype`) flat, as little-endian unsigned integers of the same width: cells are
    compared and stored as bit patterns, so every NaN payload and -0.0 round-trip exactly."""
    if array.dtype != np.dtype(dtype):
        raise ValueError(f"tile array of dtype {array.dtype}, expected {np.dtype(dtype)}")
    little = np.dtype(dtype).newbyteorder("<")
    return np.ascontiguousarray(array, dtype=little).reshape(-1).view(f"<u{little.itemsize}")


def _unknown_bits(a: LayerArray) -> np.ndarray:
    return _as_bits(np.array([a.unknown], dtype=a.dtype), a.dtype)


def tile_to_blob(arrays: Sequence[np.ndarray], layout: Sequence[LayerArray]) -> bytes:
    """One tile's stored arrays (`layout`'s order, as `TileStore.arrays`), losslessly and compactly.

    Most cells of most arrays still hold their never-observed value (a bench map's tiles: 70 % of
    log-odds, 98 % of hits, 94 % of TSDF), so each array is stored as a bit mask of the other
    cells and their values, or not at all, or whole when that is smaller; zlib then squeezes the
    rest. 17 tiles (22 MB of arrays) take 26 ms instead of the 43 ms of compressing them whole, and
    0.87 MB instead of 1.03 MB. `tile_from_blob` / `decode_tile` give back the exact bits."""
    body = [bytes([len(layout)])]
    for a, array in zip(layout, arrays, strict=True):
        bits = _as_bits(array, a.dtype)
        known = bits != _unknown_bits(a)
        count = int(np.count_nonzero(known))
        if count == 0:
            body.append(bytes([TILE_UNKNOWN]))
        elif count * bits.itemsize + bits.size // 8 < bits.nbytes:
            body += [bytes([TILE_SPARSE]), np.packbits(known).tobytes(), bits[known].tobytes()]
        else:
            body += [bytes([TILE_DENSE]), bits.tobytes()]
    return TILE_MAGIC + zlib.compress(b"".join(body), 1)


def decode_tile(blob: bytes, layout: Sequence[LayerArray], tile_size: int) -> list[np.ndarray]:
    """The arrays (each `(tile_size, tile_size)`, in `layout`'s order) of a `tile_to_blob` blob.
    Raises `StorageError` saying what is wrong if the blob is not one, or not one of this layout."""
    if blob[: len(TILE_MAGIC)] != TILE_MAGIC:
        raise StorageError(
            "a stored tile is not in tile format 2 (data directories of fleetmap before format 2 "
            "cannot be read; see docs/durability.md)"
        )
    try:
        raw = zlib.decompress(blob[len(TILE_MAGIC) :])
    except zlib.error as exc:
        raise StorageError(f"corrupt tile: {exc}") from None
    cells = tile_size * tile_size
    pos = 1

    def take(n: int) -> memoryview:
        nonlocal pos
        if pos + n > len(raw):
            raise StorageError("corrupt tile: its data ends early")
        pos += n
        return memoryview(raw)[pos - n : pos]

    if not raw or raw[0] != len(layout):
        held = raw[0] if raw else 0
        raise StorageError(f"corrupt tile: it holds {held} arrays, the map's layers have {len(layout)}")
    out = []
    for a in layout:
        unknown = _unknown_bits(a)
        kind = take(1)[0]
        if kind == TILE_UNKNOWN:
            bits = np.full(cells, unknown[0], dtype=unknown.dtype)
        elif kind == TILE_SPARSE:
            known = np.unpackbits(np.frombuffer(take(cells // 8), dtype=np.uint8)).view(bool)
            bits = np.full(cells, unknown[0], dtype=unknown.dtype)
            count = int(np.count_nonzero(known))
            bits[known] = np.frombuffer(take(count * unknown.itemsize), dtype=unknown.dtype)
        elif kind == TILE_DENSE:
            bits = np.frombuffer(take(cells * unknown.itemsize), dtype=unknown.dtype).copy()
        else:
            raise StorageError(f"corrupt tile: unknown array kind {kind}")
        values = bits.view(np.dtype(a.dtype).newbyteorder("<")).astype(a.dtype, copy=False)
        out.append(values.reshape(tile_size, tile_size))
    if pos != len(raw):
        raise StorageError(f"corrupt tile: {len(raw) - pos} bytes after its last array")
    return out


def tile_from_blob(blob: bytes, gmap: GridMap) -> list[np.ndarray]:
    """`decode_tile` for a tile of `gmap`."""
    return decode_tile(blob, gmap.store.arrays, gmap.store.tile_size)


# -- snapshot files (download / restore) ----------------------------------------------------------------

SNAPSHOT_FORMAT = "fleetmap-snapshot-1"


def write_snapshot_file(map_id: str, gmap: GridMap, out: IO[bytes]) -> None:
    """One map as a single file, written to `out` (binary, seekable, at its start): a zip of
    `map.json` (format, id, config) and `tiles.npz` (stored, so that a reader finds it where it lies).

    The compressed arrays go straight into `out` as they are made: besides the copy of the tiles
    (`_copy_tiles`), nothing the size of the map is held in memory. (The file was built in memory
    and then copied out, three copies of the compressed map besides the tiles' copy.) `tiles.npz`
    is written with ZIP64 headers whatever its size, so that a map past 4 GiB is written the same
    way as any other (zipfile cannot switch to them once a member of unknown size has begun)."""
    keys, arrays = _copy_tiles(gmap)
    meta = {"format": SNAPSHOT_FORMAT, "id": map_id, "config": gmap.config.model_dump(mode="json")}
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as zf:
        zf.writestr("map.json", json.dumps(meta, indent=2))
        with zf.open("tiles.npz", "w", force_zip64=True) as member:
            # mypy fears that a key of `arrays` is savez's allow_pickle; they are layer array names.
            np.savez_compressed(member, keys=np.array(keys, dtype=np.int64).reshape(-1, 2), **arrays)  # type: ignore[arg-type]


def snapshot_file(map_id: str, gmap: GridMap) -> bytes:
    """`write_snapshot_file` into bytes: for small maps and tests (the service streams downloads
    through a temporary file)."""
    buf = io.BytesIO()
    write_snapshot_file(map_id, gmap, buf)
    return buf.getvalue()


def _copy_tiles(gmap: GridMap) -> tuple[list[TileKey], dict[str, np.ndarray]]:
    """Every tile key of `gmap` and a copy of each stored array, `(n, tile_size, tile_size)` in the
    keys' order, as of one moment (under the map's lock).

    The copies are allocated, and their memory touched, before the lock is taken: a fresh array
    is only mapped in as it is first written, and that took 4.2 s for the 1.7 GB of a 1 km map of
    6,400 tiles, which integration of that map waited for. Under the lock only the bytes are copied
    (0.2 s); the tiles are the first n slots of each pool, in the keys' order (`TileStore.keys`)."""
    store = gmap.store
    t = store.tile_size
    for _ in range(3):
        n = len(store.keys)
        arrays = {a.name: np.empty((n, t, t), dtype=a.dtype) for a in store.arrays}
        for array in arrays.values():
            array.fill(0)
        with gmap.lock:
            if len(store.keys) == n:  # else tiles were created meanwhile: allocate again
                for name, array in arrays.items():
                    array[...] = store.pools[name][:n]
                return list(store.keys), arrays
    with gmap.lock:  # a map growing that fast: copy under the lock
        n = len(store.keys)
        return list(store.keys), {a.name: store.pools[a.name][:n].copy() for a in store.arrays}


#: The most bytes an uploaded snapshot's `map.json` may hold (a configuration takes about 1 KB).
MAX_SNAPSHOT_META_BYTES = 1 << 20
#: The most bytes an uploaded snapshot's tiles may hold decompressed: `tiles.npz`, and all the arrays
#: in it together. 4 GiB is about 3200 tiles of every layer at the default tile size, and with the
#: request body limit it bounds what one upload makes the service allocate.
MAX_SNAPSHOT_BYTES = 4 << 30
#: The longest .npy header read (numpy's own default limit; these arrays' headers take 128 bytes).
_NPY_HEADER_MAX = 10_000
#: Bytes decompressed per read while filling a layer (a bound on the copy held besides the pools).
_READ_CHUNK = 1 << 24
#: What zipfile raises for a corrupt archive or member: a bad CRC or header (BadZipFile), corrupt
#: deflate data (zlib.error), a compressed stream that ends early (EOFError), a compression method
#: this Python lacks (NotImplementedError), a local header's name that is not the UTF-8 its flag
#: says (UnicodeDecodeError: zipfile decodes it to compare it with the directory's when a member is
#: opened; it was a 500). Offsets outside the file are refused when it is opened (`upload_zip`).
_ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, UnicodeDecodeError)


class SnapshotError(ValueError):
    """Why bytes are not a snapshot file this service can install; nothing was changed. `status` is
    413 for a member past a size limit, 507 for tiles the memory budget has no room for, else 422;
    `errors` holds the validation errors of an invalid configuration (pydantic's, located from the
    top of the file: `("map.json", "config", ...)`)."""

    def __init__(self, message: str, status: int = 422, errors: list[dict] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.errors = errors or []


@dataclass(frozen=True)
class _Npy:
    """One array of `tiles.npz` whose header has been read (not its data)."""

    info: zipfile.ZipInfo
    path: str  # for messages: tiles.npz/<name>.npy
    dtype: np.dtype
    shape: tuple[int, ...]
    fortran: bool
    offset: int  # bytes of the member before the data


def _member(zf: zipfile.ZipFile, name: str, path: str, limit: int | None = None) -> zipfile.ZipInfo:
    """The entry `name` of `zf`, if it exists, is not encrypted and says it holds at most `limit`
    bytes decompressed (413 if more: refused before anything is decompressed)."""
    try:
        info = zf.getinfo(name)
    except KeyError:
        raise SnapshotError(f"not a fleetmap snapshot: it has no {path}") from None
    if limit is not None and info.file_size > limit:
        raise SnapshotError(
            f"snapshot member {path} is {info.file_size} bytes decompressed, more than the limit of {limit}",
            413,
        )
    if info.flag_bits & 0x1:
        raise SnapshotError(f"snapshot member {path} is encrypted")
    return info


def _read_member(zf: zipfile.ZipFile, name: str, limit: int) -> bytes:
    """All of member `name`, refused (413) if its ZipInfo says it holds more than `limit` bytes, and
    read with that bound whatever its header says (zipfile also stops at the declared size, then
    checks the CRC)."""
    info, path = _member(zf, name, name, limit), name
    try:
        with zf.open(info) as fp:
            data = fp.read(limit + 1)
    except _ZIP_ERRORS as exc:
        raise SnapshotError(f"snapshot member {path} cannot be read (the file is corrupt): {exc}") from None
    if len(data) > limit:
        raise SnapshotError(f"snapshot member {path} holds more than the limit of {limit} bytes", 413)
    return data


class _Window(io.RawIOBase):
    """Bytes `[start, start + length)` of `base` (a binary file that can seek) as a read-only file
    of their own that can seek: a member the zip stores uncompressed, read where it lies. Not safe
    to use beside another reader of `base` at once (each read seeks it).

    It checks the member as zipfile would have while it is read, not in a pass of its own: a read
    that reaches past the bytes checked so far adds what it brings beyond them to their CRC-32, and
    `verify` reads whatever was never read, once, and compares. The readers of `tiles.npz` go
    mostly front to back (each array's data once, in order), so `verify` reads little more than the
    inner zip's directory. (Checking the CRC first read all of tiles.npz once more before its
    arrays: up to 4 GiB of spool read twice.)"""

    def __init__(self, base: IO[bytes], start: int, length: int, crc: int, name: str) -> None:
        super().__init__()
        self._base, self._start, self._length, self._pos = base, start, length, 0
        self._expected, self._name = crc, name
        self._checked, self._crc = 0, 0  # bytes [0, _checked) are in _crc

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        origin = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._length}[whence]
        if origin + offset < 0:
            raise ValueError(f"negative seek position {origin + offset}")
        self._pos = origin + offset
        return self._pos

    def readinto(self, buffer: bytearray | memoryview) -> int:  # type: ignore[override]
        n = max(0, min(len(buffer), self._length - self._pos))
        if not n:
            return 0
        data = self._read_at(self._pos, n)
        memoryview(buffer)[: len(data)] = data
        self._pos += len(data)
        return len(data)

    def _read_at(self, at: int, n: int) -> bytes:
        """At most `n` bytes from `at`, added to the CRC as far as they continue the bytes checked."""
        self._base.seek(self._start + at)
        data = self._base.read(n)
        if at <= self._checked < at + len(data):
            self._crc = zlib.crc32(memoryview(data)[self._checked - at :], self._crc)
            self._checked = at + len(data)
        return data

    def verify(self) -> None:
        """Read the bytes not read yet and check the CRC-32 of all of them against the one the zip
        declares: raises `zipfile.BadZipFile` (in zipfile's words) if it differs, `EOFError` if the
        file ends before the member does."""
        while self._checked < self._length:
            if not self._read_at(self._checked, min(_READ_CHUNK, self._length - self._checked)):
                raise EOFError(f"the file ends {self._length - self._checked} bytes before {self._name} does")
        if self._crc != self._expected:
            raise zipfile.BadZipFile(f"Bad CRC-32 for file {self._name!r}")


def _data_start(fp: IO[bytes], info: zipfile.ZipInfo) -> int:
    """Where member `info`'s data starts in `fp`: after its local header, 30 bytes, then the name and
    the extra field, whose lengths are at bytes 26 and 28 (PKWARE APPNOTE 4.3.7). The extra field may
    differ from the central directory's, so it is read here; zipfile has checked the header already."""
    fp.seek(info.header_offset)
    header = fp.read(30)
    if len(header) != 30 or header[:4] != b"PK\x03\x04":
        raise zipfile.BadZipFile(f"bad local file header of {info.filename}")
    name_length, extra_length = struct.unpack_from("<HH", header, 26)
    return info.header_offset + 30 + name_length + extra_length


def _tiles_npz(
    outer: zipfile.ZipFile, fp: IO[bytes], limit: int, stack: contextlib.ExitStack,
    stop: threading.Event | None = None,
) -> tuple[IO[bytes], Callable[[], None]]:  # fmt: skip
    """Member `tiles.npz` of the snapshot `outer` (read from `fp`) as a file that can seek, checked as
    `_read_member` checks a member (its declared size against `limit`, its local header, its CRC)
    but never held in memory whole, and a function that completes the check. A stored member (what
    `snapshot_file` writes) is read where it lies in `fp`, read once: its CRC is summed as its
    arrays are read, and the function given back reads what they left and compares it. A compressed
    one (a snapshot zipped again by some tool) is decompressed into a spool (`stack` closes it) and
    checked whole as that is written; its function does nothing. Both raise `SnapshotError` for a
    corrupt member. Raises `SpoolFailed` if the spool has no room, `UploadStopped` once `stop` is
    set (checked between chunks of the decompression)."""
    path = "tiles.npz"
    info = _member(outer, path, path, limit)

    def corrupt(exc: BaseException) -> SnapshotError:
        return SnapshotError(f"snapshot member {path} cannot be read (the file is corrupt): {exc}")

    if info.compress_type == zipfile.ZIP_STORED and info.compress_size == info.file_size:
        try:
            with outer.open(info):  # zipfile checks the local header (its name, flags); no data read
                pass
            window = _Window(fp, _data_start(fp, info), info.file_size, info.CRC, path)
        except _ZIP_ERRORS as exc:
            raise corrupt(exc) from None

        def verify() -> None:
            try:
                window.verify()
            except _ZIP_ERRORS as exc:
                raise corrupt(exc) from None

        return io.BufferedReader(window), verify
    copy = spooled_file()
    stack.callback(close_spool, copy)
    size = 0
    try:
        with outer.open(info) as member:
            while chunk := member.read(_READ_CHUNK):
                check_stop(stop)
                size += len(chunk)
                if size > limit:
                    raise SnapshotError(
                        f"snapshot member {path} holds more than the limit of {limit} bytes", 413
                    )
                copy.write(chunk)  # its errors are SpoolFailed, the server's, not the file's (_ZIP_ERRORS)
    except _ZIP_ERRORS as exc:
        raise corrupt(exc) from None
    copy.seek(0)
    return copy, lambda: None


def _snapshot_config(zf: zipfile.ZipFile, max_tiles: int | None) -> MapConfig:
    """The configuration in `map.json`, its `max_tiles` lowered to `max_tiles` if given."""
    raw = _read_member(zf, "map.json", MAX_SNAPSHOT_META_BYTES)
    try:
        meta = json.loads(raw)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError; nesting
        raise SnapshotError(f"not a fleetmap snapshot: map.json is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise SnapshotError(
            f"not a fleetmap snapshot: map.json holds a JSON {type(meta).__name__}, not an object"
        )
    if meta.get("format") != SNAPSHOT_FORMAT:
        raise SnapshotError(f"not a {SNAPSHOT_FORMAT} file: map.json's format is {meta.get('format')!r}")
    if "config" not in meta:
        raise SnapshotError("snapshot map.json has no config")
    try:
        config = MapConfig.model_validate(meta["config"])
    except ValidationError as exc:
        errors = [{**e, "loc": ("map.json", "config", *e["loc"])} for e in exc.errors(include_url=False)]
        raise SnapshotError(
            f"snapshot map.json: the configuration is invalid ({exc.error_count()} problem(s))", errors=errors
        ) from None
    if max_tiles is not None and config.max_tiles > max_tiles:
        config = config.model_copy(update={"max_tiles": max_tiles})
    return config


def _npy_header(npz: zipfile.ZipFile, name: str) -> _Npy:
    """The header of array `name` of `tiles.npz`, reading no more than the header (at most
    _NPY_HEADER_MAX bytes). `_check_npy` then bounds its data by what the header may say."""
    path = f"tiles.npz/{name}.npy"
    info = _member(npz, f"{name}.npy", path)
    readers = {1: np.lib.format.read_array_header_1_0, 2: np.lib.format.read_array_header_2_0}
    try:
        with npz.open(info) as fp:
            major, _minor = np.lib.format.read_magic(fp)
            if major not in readers:
                raise ValueError(f"unsupported .npy format version {major}")
            shape, fortran, dtype = readers[major](fp, max_header_size=_NPY_HEADER_MAX)
            offset = fp.tell()
    except _ZIP_ERRORS as exc:
        raise SnapshotError(f"snapshot member {path} cannot be read (the file is corrupt): {exc}") from None
    # numpy's words for a header it cannot parse. TokenError (not a ValueError) comes from the
    # tokenizer numpy falls back on when `literal_eval` fails: an unterminated ''' in a header (a
    # flipped bit of a deflated tiles.npz made one) was a 500.
    except (ValueError, TypeError, SyntaxError, tokenize.TokenError) as exc:
        raise SnapshotError(f"snapshot member {path} is not a valid .npy array ({exc})") from None
    return _Npy(info, path, np.dtype(dtype), tuple(shape), bool(fortran), offset)


def _check_npy(npy: _Npy, dtype: np.dtype | None, shape: tuple[int, ...], what: str) -> None:
    """That `npy` is of `dtype` (None: any integer type; either byte order) and `shape` (-1: any
    length >= 0), and that its member says it holds exactly that much data after the header (from
    its ZipInfo: nothing is decompressed), so that what is read later is bounded by `shape`."""
    native = npy.dtype.newbyteorder("=")
    if dtype is None and npy.dtype.kind not in "iu":
        raise SnapshotError(f"snapshot {npy.path} has dtype {npy.dtype}, expected integers")
    if dtype is not None and native != dtype:
        raise SnapshotError(f"snapshot {npy.path} has dtype {npy.dtype}, expected {dtype}")
    if len(npy.shape) != len(shape) or any(
        n < 0 or (m >= 0 and n != m) for n, m in zip(npy.shape, shape, strict=True)
    ):
        raise SnapshotError(f"snapshot {npy.path} has shape {npy.shape}, expected {what}")
    size = math.prod(npy.shape) * npy.dtype.itemsize
    if npy.info.file_size - npy.offset != size:
        raise SnapshotError(
            f"snapshot {npy.path} holds {npy.info.file_size - npy.offset} bytes of data, its shape and "
            f"dtype need {size}"
        )


def _read_npy(
    npz: zipfile.ZipFile, npy: _Npy, out: np.ndarray | None = None, stop: threading.Event | None = None
) -> np.ndarray:
    """The data of a checked array (`_check_npy`), streamed into `out` (C-contiguous, of its shape)
    when given. Never reads more than its header declared; a member that ends early is refused.
    Raises `UploadStopped` once `stop` is set (checked between chunks)."""
    fits = out is not None and not npy.fortran and out.dtype == npy.dtype
    stored_shape = npy.shape[::-1] if npy.fortran else npy.shape
    buf = out if out is not None and fits else np.empty(stored_shape, dtype=npy.dtype)
    dest = buf.reshape(-1).view(np.uint8).data  # its memoryview
    try:
        with npz.open(npy.info) as fp:
            fp.read(npy.offset)
            at = 0
            while at < len(dest):
                check_stop(stop)
                chunk = fp.read(min(_READ_CHUNK, len(dest) - at))
                if not chunk:
                    raise SnapshotError(f"snapshot member {npy.path} ends early")
                dest[at : at + len(chunk)] = chunk
                at += len(chunk)
            fp.read(1)  # at the declared end: zipfile checks the CRC here
    except _ZIP_ERRORS as exc:
        raise SnapshotError(
            f"snapshot member {npy.path} cannot be read (the file is corrupt): {exc}"
        ) from None
    values = buf.T if npy.fortran else buf
    if out is not None and not fits:
        out[...] = values
    return values


def _snapshot_keys(
    npz: zipfile.ZipFile, config: MapConfig, layout: Sequence[LayerArray], max_bytes: int
) -> list[TileKey]:
    """The tile keys in `tiles.npz/keys.npy`: integers, no two alike, each a tile that meets the
    world of +-MAX_COORDINATE metres, at most `config.max_tiles` of them and at most `max_bytes` of
    layer arrays (413)."""
    npy = _npy_header(npz, "keys")
    _check_npy(npy, None, (-1, 2), "(tiles, 2)")
    n, t = npy.shape[0], config.tile_size
    if n > config.max_tiles:
        raise SnapshotError(f"the snapshot has {n} tiles, more than max_tiles {config.max_tiles}")
    size = n * tile_bytes(t, layout)
    if size > max_bytes:
        raise SnapshotError(
            f"the snapshot's {n} tiles of {t}x{t} cells hold {size} bytes of layer arrays, more than the "
            f"limit of {max_bytes}",
            413,
        )
    raw = _read_npy(npz, npy)
    edge = t * config.resolution
    lo, hi = math.floor(-MAX_COORDINATE / edge), math.floor(MAX_COORDINATE / edge)
    keys = [(int(i), int(j)) for i, j in raw.tolist()]
    seen: set[TileKey] = set()
    for key in keys:
        if not (lo <= key[0] <= hi and lo <= key[1] <= hi):
            raise SnapshotError(
                f"snapshot tile {key} lies beyond the world bound of +-{MAX_COORDINATE:g} m (tile keys "
                f"from {lo} to {hi} at this tile size and resolution)"
            )
        if key in seen:
            raise SnapshotError(f"snapshot tile {key} is there twice")
        seen.add(key)
    return keys


def _value_range(a: LayerArray, config: MapConfig) -> tuple[float, float, bool, str] | None:
    """The values the engine can store in array `a` of a map of `config`: (low, high, whether NaN
    is allowed, in words), or None when every value of its dtype is. The bounds are float32, as
    stored: the kernels round the clamped float64 value to float32 (`updated_log_odds`)."""
    if a.name == "log_odds":  # NaN is unknown; every update clamps to [l_min, l_max]
        _, _, l_min, l_max = config.occupancy.resolved()
        lo, hi = float(np.float32(l_min)), float(np.float32(l_max))
        return lo, hi, True, f"NaN (unknown) or within the map's clamp [{l_min:g}, {l_max:g}]"
    if a.name == "tsdf":  # unknown is 0 (weight 0); a mean of values clamped to [-1, 1]
        return -1.0, 1.0, False, "within [-1, 1]"
    if a.name == "tsdf_weight":  # unknown is 0; one per beam, capped at max_weight
        return 0.0, float(np.finfo(np.float32).max), False, "finite and >= 0"
    return None  # hits, misses: any uint32


@njit(cache=True, nogil=True)
def _first_outside(values: np.ndarray, lo: float, hi: float, nan_ok: bool) -> int:
    """The index of the first value not in [lo, hi] (NaN counts as in it only if `nan_ok`), or -1."""
    for k in range(values.size):
        v = values[k]
        if not (lo <= v <= hi) and not (nan_ok and np.isnan(v)):
            return k
    return -1


def _check_values(a: LayerArray, values: np.ndarray, keys: list[TileKey], config: MapConfig) -> None:
    """That every cell of `values` (array `a` of tiles `keys`) holds a value the engine could have."""
    allowed = _value_range(a, config)
    if allowed is None or not values.size:
        return
    lo, hi, nan_ok, words = allowed
    at = _first_outside(values.reshape(-1), lo, hi, nan_ok)
    if at >= 0:
        t = config.tile_size
        slot, local = divmod(at, t * t)
        lj, li = divmod(local, t)
        ti, tj = keys[slot]
        value = values.reshape(-1)[at]
        raise SnapshotError(
            f"snapshot tiles.npz/{a.name}.npy holds {value} at cell ({ti * t + li}, {tj * t + lj}); "
            f"{a.name} must be {words}"
        )


def map_from_snapshot_file(
    data: bytes | IO[bytes], max_tiles: int | None = None, max_bytes: int = MAX_SNAPSHOT_BYTES,
    reservation: UploadReservation | None = None, stop: threading.Event | None = None,
) -> GridMap:  # fmt: skip
    """A map restored from a `snapshot_file`: its bytes, or a binary file open for reading that can
    seek (an upload spooled to disk: `fleetmap.upload_spool`), which is read in place, never held in memory
    whole, and left open. Raises `SnapshotError` with a reason if it is not one, or one this service
    refuses; `SpoolFailed` if a compressed tiles.npz has no room in the temporary directory.

    An upload is untrusted: every member's declared size is checked before it is decompressed
    (`map.json` at most MAX_SNAPSHOT_META_BYTES, `tiles.npz` and its layer arrays together at most
    `max_bytes`), and read with a bound whatever its header says. The keys and every layer's header
    (dtype, shape, data size, from the keys and the tile size) are checked before the map's pools are
    allocated, and the pools are then filled straight from the file, so the memory touched is the
    data the file holds. Every cell is checked against what the engine can store, so a map that is
    installed is one the service could have built. With `reservation` (an upload's room in the
    memory budget), the map's tiles are reserved once every header is checked, before anything is
    allocated, and refused (507) if the budget has no room for them; the map returned is charged
    with them. With `stop`, it raises `UploadStopped` soon after `stop` is set: the reader of an
    upload whose request ended (the shutdown's cutoff) must not decompress and read on for seconds."""
    fp = as_file(data)
    with contextlib.ExitStack() as stack:
        try:
            outer = upload_zip(fp)
        except (*_ZIP_ERRORS, ValueError) as exc:
            raise SnapshotError(f"not a fleetmap snapshot: the body is not a zip file ({exc})") from None
        with outer:
            config = _snapshot_config(outer, max_tiles)
            inner, verify_tiles = _tiles_npz(outer, fp, max_bytes, stack, stop)
        try:
            try:
                npz = upload_zip(inner)
            except (*_ZIP_ERRORS, ValueError) as exc:
                raise SnapshotError(f"snapshot member tiles.npz is not a valid .npz file ({exc})") from None
            with npz:
                layout = layer_arrays(config.layers)
                keys = _snapshot_keys(npz, config, layout, max_bytes)
                t = config.tile_size
                arrays = []
                for a in layout:
                    npy = _npy_header(npz, a.name)
                    _check_npy(
                        npy,
                        np.dtype(a.dtype),
                        (len(keys), t, t),
                        f"{(len(keys), t, t)}: one {t}x{t} tile per key",
                    )
                    arrays.append(npy)
                # Everything checked that can be without the data: only now allocate, and only what it holds.
                gmap = GridMap(config)
                if reservation is not None:
                    try:
                        reservation.charge(gmap.store, len(keys))
                    except TileLimitError as exc:  # the budget's MemoryBudgetError
                        raise SnapshotError(f"the snapshot's {len(keys)} tiles {exc}", 507) from None
                gmap.store.create(keys, fill=False)
                for a, npy in zip(layout, arrays, strict=True):
                    values = gmap.store.pools[a.name][: len(keys)]
                    _read_npy(npz, npy, values, stop)
                    _check_values(a, values, keys, config)
        except SnapshotError:
            # A corrupt tiles.npz is what to name, as when its CRC was checked before its arrays:
            # a changed byte shows first as an array that does not parse or a value out of range.
            verify_tiles()
            raise
        verify_tiles()  # the bytes the arrays did not cover (and the CRC of all)
    return gmap
