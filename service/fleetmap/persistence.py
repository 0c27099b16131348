"""Durable maps: SQLite (WAL) in the data directory holds map configurations, tile snapshots, robot
counters and a journal of accepted scans.

The contract (see docs/durability.md):
- A scan is journaled in the order it was applied to its map (the registry appends under the map's
  lock) and counts as integrated only after its journal row is committed. `JournalWriter` commits in
  groups: one transaction (one fsync) for every scan that arrived in the last few milliseconds.
- A snapshot of a map first makes every applied scan durable, then copies the tiles that changed
  since the last snapshot together with the id of the last journal row they include, and writes
  them under a new generation; one small transaction then switches the map to that generation with
  its robot counters and journal id: a crash leaves either the old snapshot with its journal or the
  new one, never a mix. Journal rows up to that id are dead from then on; the writer deletes them
  a few at a time.
- On start, each map is its snapshot plus its journal rows after it, replayed in order: exactly the
  map of all durable scans.
SQLite's atomic commits mean no half-written tile or journal row can survive a crash.
"""

from __future__ import annotations

import collections
import contextlib
import io
import json
import logging
import math
import os
import queue
import shutil
import sqlite3
import struct
import threading
import time
import zipfile
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from fleetmap.config import STORED_CONFIG, MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.scan import Pose2D, Scan
from fleetmap.tiles import LayerArray

log = logging.getLogger("fleetmap.persistence")

DB_NAME = "fleetmap.db"
#: After a snapshot, passive checkpoints on the snapshot connection until one finds fewer than
#: CHECKPOINT_TAIL_FRAMES new WAL frames (4 KiB each; at most CHECKPOINT_PASSES of them); the journal
#: writer then copies the rest, so the WAL can start over. See `DurableStore._checkpoint`.
CHECKPOINT_PASSES = 4
CHECKPOINT_TAIL_FRAMES = 256
#: Refuse to start with less free space than this in the data directory.
MIN_FREE_BYTES = 64 * 1024 * 1024
SCHEMA = """
CREATE TABLE IF NOT EXISTS maps (
    id TEXT PRIMARY KEY,
    config TEXT NOT NULL,
    created_at REAL NOT NULL,
    snapshot_journal_id INTEGER NOT NULL DEFAULT 0,
    snapshot_gen INTEGER NOT NULL DEFAULT 0,
    clock INTEGER NOT NULL DEFAULT 0,
    scans_integrated INTEGER NOT NULL DEFAULT 0,
    scans_rejected INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS tiles (
    map_id TEXT NOT NULL,
    ti INTEGER NOT NULL,
    tj INTEGER NOT NULL,
    gen INTEGER NOT NULL,
    version INTEGER NOT NULL,
    data BLOB NOT NULL,
    PRIMARY KEY (map_id, ti, tj, gen)
);
CREATE TABLE IF NOT EXISTS robots (
    map_id TEXT NOT NULL,
    robot_id TEXT NOT NULL,
    state TEXT NOT NULL,
    PRIMARY KEY (map_id, robot_id)
);
CREATE TABLE IF NOT EXISTS journal (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    map_id TEXT NOT NULL,
    robot_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    stamp REAL NOT NULL,
    scan BLOB NOT NULL
);
CREATE INDEX IF NOT EXISTS journal_map ON journal (map_id, id);
"""


class StorageError(RuntimeError):
    """The data directory cannot hold the maps (unwritable, full, corrupt). The message says why."""


# -- encodings ---------------------------------------------------------------------------------------

_SCAN_HEADER = struct.Struct("<Bdddddi")  # version, x, y, theta, range_min, range_max, n
#: Journal scans, version 2: the version 1 header, then a flags byte. Flag `_FAN`: the angles are
#: `angle_min + angle_increment * arange(n)` bit for bit, stored as those two float64; else n float64.
#: Flag `_RANGES_F32`: every range is exactly a float32 (as the binary wire encoding sends them, NaN
#: aside), stored as n float32; else n float64. A 1081-beam scan from the binary encoding takes 4.4 KB
#: instead of 17 KB: the journal is most of the service's disk writes.
_SCAN_FLAGS = struct.Struct("<B")
_FAN, _RANGES_F32 = 1, 2


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
    """An exact serialisation of an engine scan for the journal (version 2, compact when it can be)."""
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
    head = _SCAN_HEADER.pack(
        2, scan.pose.x, scan.pose.y, scan.pose.theta, scan.range_min, scan.range_max, scan.num_beams
    )
    return head + _SCAN_FLAGS.pack(flags) + b"".join(parts)


def scan_from_blob(blob: bytes) -> Scan:
    """The scan `scan_to_blob` stored (versions 1 and 2); `StorageError` if the row is corrupt."""
    try:
        version, x, y, theta, range_min, range_max, n = _SCAN_HEADER.unpack_from(blob)
        at = _SCAN_HEADER.size
        if version == 1:
            if n < 0 or len(blob) != at + 16 * n:
                raise StorageError("corrupt journal entry")
            body = np.frombuffer(blob, dtype="<f8", offset=at)
            return Scan(Pose2D(x, y, theta), body[:n].copy(), body[n:].copy(), range_min, range_max)
        if version != 2 or n < 0:
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


def changed_tiles(gmap: GridMap, since: int) -> list[tuple[tuple[int, int], int, list[np.ndarray]]]:
    """Copies of the tiles whose version is above `since`: (key, version, arrays in store order).
    The caller holds the map's lock."""
    store = gmap.store
    return [
        (key, int(store.versions[slot]), [store.pools[a.name][slot].copy() for a in store.arrays])
        for key, slot in store.slots.items()
        if store.versions[slot] > since
    ]


def tile_from_blob(blob: bytes, gmap: GridMap) -> list[np.ndarray]:
    """`decode_tile` for a tile of `gmap`."""
    return decode_tile(blob, gmap.store.arrays, gmap.store.tile_size)


# -- the database -------------------------------------------------------------------------------------


def open_database(data_dir: Path) -> Path:
    """Check the data directory can hold the maps and create the schema; return the database path.

    Raises `StorageError` with a clear message when the directory cannot be created or written, or
    the disk is (nearly) full, so the service never runs silently in memory only."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StorageError(f"cannot create data directory {data_dir}: {exc.strerror}") from None
    probe = data_dir / ".write-test"
    try:
        with open(probe, "wb") as f:
            f.write(b"\0" * 65536)
            f.flush()
            os.fsync(f.fileno())
        probe.unlink()
    except OSError as exc:
        raise StorageError(f"data directory {data_dir} is not writable: {exc.strerror}") from None
    free = shutil.disk_usage(data_dir).free
    if free < MIN_FREE_BYTES:
        raise StorageError(
            f"data directory {data_dir} has only {free // (1024 * 1024)} MiB free; "
            f"at least {MIN_FREE_BYTES // (1024 * 1024)} MiB are needed"
        )
    path = data_dir / DB_NAME
    try:
        conn = connect(path)
        conn.executescript(SCHEMA)
        conn.close()
    except sqlite3.DatabaseError as exc:
        raise StorageError(f"cannot open the map database {path}: {exc}") from None
    return path


def connect(path: Path, synchronous: str = "FULL", autocheckpoint: bool = True) -> sqlite3.Connection:
    conn = sqlite3.connect(path, timeout=30.0, isolation_level=None, check_same_thread=False)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute(f"PRAGMA synchronous={synchronous}")  # FULL: a commit is on disk when COMMIT returns
    # Debian builds SQLite with SECURE_DELETE on: every freed page would be overwritten with zeros,
    # so truncating the journal (17 KB rows, thousands per snapshot) wrote as many bytes to the WAL
    # as the rows themselves and took hundreds of ms. FAST zeroes deleted cells in b-tree pages but
    # not whole freed pages (their old contents stay until the page is reused, which journal
    # appends do within seconds); the map data is not secret.
    conn.execute("PRAGMA secure_delete=FAST")
    if not autocheckpoint:
        conn.execute("PRAGMA wal_autocheckpoint=0")
    return conn


@dataclass
class JournalEntry:
    map_id: str
    robot_id: str
    seq: int
    stamp: float
    blob: bytes
    on_durable: Callable[[int], None]


#: Queued by `JournalWriter.attach` to wake an idle writer.
_WAKE = object()


class JournalWriter:
    """The one thread that appends to the journal, committing in groups. Its transactions also carry
    the snapshots' tile rows (`attach`) and delete the journal rows snapshots have superseded, a few
    at a time (`trim`)."""

    #: Superseded rows deleted per transaction. A snapshot supersedes up to `snapshot_rows` rows of
    #: 17 KB; deleting them at once held the journal's commits up for hundreds of ms. About 5 us a
    #: row (with secure_delete=FAST), so a group commit carrying a share of them stays short.
    TRIM_ROWS = 256
    #: Seconds the writer waits idle before trimming in a transaction of its own.
    TRIM_IDLE = 0.05
    #: Seconds attached rows wait for a group commit to ride along with before they are committed
    #: alone (a snapshot waits for them; under load a group comes every few ms anyway).
    ATTACH_WAIT = 0.005
    #: Bytes of attached rows one transaction carries at most (at least one row).
    ATTACH_BYTES = 512 * 1024

    def __init__(self, path: Path, on_error: Callable[[Exception], None] | None = None):
        # The journal writer never checkpoints the WAL by itself (a checkpoint copies hundreds of MB);
        # the snapshot thread does after each snapshot, leaving only a short tail to the writer.
        self._conn = connect(path, autocheckpoint=False)
        self._queue: queue.Queue[JournalEntry | Callable[[sqlite3.Connection], None] | object | None] = (
            queue.Queue()
        )
        self._on_error = on_error
        # map id -> the journal id up to which that map's rows are superseded by a snapshot and
        # still to be deleted. Only the writer thread touches it (from `trim`, called in an op).
        self._trim: dict[str, int] = {}
        self._attached: collections.deque[tuple[str, tuple, Future]] = collections.deque()
        self._attached_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="fleetmap-journal", daemon=True)
        self._thread.start()
        self.commits = 0
        self.rows = 0
        self.trimmed = 0

    def trim(self, map_id: str, upto: int | None) -> None:
        """Delete `map_id`'s journal rows with id <= `upto` from now on, `TRIM_ROWS` per transaction
        (riding along with group commits, or alone when the writer is idle); None cancels (a map
        deleted or re-created). Call it ONLY on the writer thread, i.e. inside an op: the rows must
        be superseded by a committed snapshot, because they are deleted whatever happens next.
        Until then they are dead weight that `DurableStore.load` ignores (and deletes)."""
        if upto is None:
            self._trim.pop(map_id, None)
        else:
            self._trim[map_id] = max(upto, self._trim.get(map_id, 0))

    def attach(self, sql: str, params: tuple) -> Future:
        """Execute `sql` with `params` inside one of the writer's next transactions: the next group
        commit, or one of its own once no scan has arrived for `ATTACH_WAIT`. The future is resolved
        when that transaction commits (with the exception if it failed). Never blocks.

        Bulk background writes (a snapshot's tile rows) go this way: written on a second connection
        they compete for SQLite's one write lock, and a journal commit that finds it taken sleeps in
        SQLite's busy handler (1, 2, 5, 10, ... ms); with a snapshot's 17 tile transactions that
        made group commits take 20-60 ms."""
        future: Future = Future()
        with self._attached_lock:
            self._attached.append((sql, params, future))
        self._queue.put(_WAKE)
        return future

    def append(self, entry: JournalEntry) -> None:
        self._queue.put(entry)

    def submit(self, op: Callable[[sqlite3.Connection], object]) -> Future:
        """Queue a database operation for the writer thread, in order with the journal entries
        appended before it (whose rows are committed and acknowledged by then). Never blocks."""
        future: Future = Future()

        def wrapped(conn: sqlite3.Connection) -> None:
            try:
                future.set_result(op(conn))
            except BaseException as exc:  # handed back to whoever waits on the future
                future.set_exception(exc)

        self._queue.put(wrapped)
        return future

    def run(self, op: Callable[[sqlite3.Connection], object]) -> object:
        """`submit` and wait. Never call it while holding a lock a durability callback takes."""
        return self.submit(op).result()

    def flush(self) -> None:
        """Return once everything appended before this call is committed and acknowledged."""
        self.run(lambda conn: None)

    def close(self) -> None:
        """Commit what is queued and attached, delete every superseded row still left, and stop."""
        self._queue.put(None)
        self._thread.join()
        self._conn.close()

    def _run(self) -> None:
        """Commit whatever has arrived, as soon as the writer is free: while one group's fsync runs,
        the next group gathers, so batches grow with the load and an idle service commits a lone
        scan at once. Operations (snapshots, map changes) run in queue order between groups."""
        while True:
            idle = self.ATTACH_WAIT if self._attached else self.TRIM_IDLE if self._trim else None
            try:
                item = self._queue.get(timeout=idle)
            except queue.Empty:  # idle with rows to delete or attached: commit a share of them alone
                self._commit([])
                continue
            batch: list[JournalEntry] = []
            while True:
                if isinstance(item, JournalEntry):
                    batch.append(item)
                elif item is _WAKE:  # attached rows wait for the next group, or for ATTACH_WAIT
                    pass
                else:
                    if batch:  # (an empty one would commit background rows alone: an extra fsync)
                        self._commit(batch)
                    batch = []
                    if item is None:  # shutting down: no hurry, all of them
                        while (self._trim or self._attached) and self._commit([]):
                            pass
                        return
                    assert callable(item)
                    item(self._conn)
                if len(batch) >= 512:
                    break
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
            if batch:
                self._commit(batch)

    def _trim_some(self) -> tuple[str, bool] | None:
        """Inside the open transaction, delete up to `TRIM_ROWS` superseded rows of one map; return
        (map id, whether none of its superseded rows are left) or None if nothing was pending."""
        if not self._trim:
            return None
        map_id, upto = next(iter(self._trim.items()))
        cur = self._conn.execute(
            "DELETE FROM journal WHERE id IN (SELECT id FROM journal WHERE map_id = ? AND id <= ? "
            "ORDER BY id LIMIT ?)",
            (map_id, upto, self.TRIM_ROWS),
        )
        self.trimmed += max(cur.rowcount, 0)
        return map_id, cur.rowcount < self.TRIM_ROWS

    def _take_attached(self) -> list[tuple[str, tuple, Future]]:
        """The attached rows for one transaction: up to `ATTACH_BYTES`, at least one if any."""
        taken: list[tuple[str, tuple, Future]] = []
        size = 0
        with self._attached_lock:
            while self._attached and (not taken or size < self.ATTACH_BYTES):
                taken.append(self._attached.popleft())
                size += sum(len(p) for p in taken[-1][1] if isinstance(p, bytes))
        return taken

    def _commit(self, batch: list[JournalEntry]) -> bool:
        """Commit `batch` (which may be empty), a share of the attached rows and of the superseded
        rows in one transaction; False if there was nothing to do or the commit failed."""
        if not batch and not self._trim and not self._attached:
            return False
        attached = self._take_attached()
        try:
            ids = []
            self._conn.execute("BEGIN IMMEDIATE")
            for e in batch:
                cur = self._conn.execute(
                    "INSERT INTO journal (map_id, robot_id, seq, stamp, scan) VALUES (?, ?, ?, ?, ?)",
                    (e.map_id, e.robot_id, e.seq, e.stamp, e.blob),
                )
                ids.append(cur.lastrowid)
            for sql, params, _future in attached:
                self._conn.execute(sql, params)
            trimmed = self._trim_some()
            self._conn.execute("COMMIT")
        except sqlite3.Error as exc:
            # Nothing of this batch is durable: the scans stay applied in memory but are never
            # counted, and the service reports the storage failure loudly.
            log.error("journal commit failed (%d scans not durable): %s", len(batch), exc)
            with contextlib.suppress(sqlite3.Error):
                self._conn.execute("ROLLBACK")
            for _sql, _params, future in attached:
                future.set_exception(exc)
            # Superseded rows are harmless (ignored and deleted at start); retrying their deletion
            # on a failing disk would only repeat the error every TRIM_IDLE seconds.
            self._trim.clear()
            if self._on_error:
                self._on_error(exc)
            return False
        for _sql, _params, future in attached:
            future.set_result(None)
        if trimmed is not None and trimmed[1]:
            del self._trim[trimmed[0]]
        if not batch:
            return True
        self.commits += 1
        self.rows += len(batch)
        for e, row_id in zip(batch, ids, strict=True):
            e.on_durable(int(row_id))
        return True


# -- snapshot files (download / restore) ----------------------------------------------------------------

SNAPSHOT_FORMAT = "fleetmap-snapshot-1"


def snapshot_file(map_id: str, gmap: GridMap) -> bytes:
    """One map as a single file: a zip of `map.json` (format, id, config) and `tiles.npz`."""
    with gmap.lock:
        keys = list(gmap.store.keys)
        arrays = {a.name: np.stack([gmap.store.tile_array(a.name, k) for k in keys]) if keys else
                  np.zeros((0, gmap.store.tile_size, gmap.store.tile_size), dtype=a.dtype)
                  for a in gmap.store.arrays}  # fmt: skip
    buf = io.BytesIO()
    npz = io.BytesIO()
    np.savez_compressed(npz, keys=np.array(keys, dtype=np.int64).reshape(-1, 2), **arrays)
    meta = {"format": SNAPSHOT_FORMAT, "id": map_id, "config": gmap.config.model_dump(mode="json")}
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        zf.writestr("map.json", json.dumps(meta, indent=2))
        zf.writestr("tiles.npz", npz.getvalue())
    return buf.getvalue()


def map_from_snapshot_file(data: bytes, max_tiles: int | None = None) -> GridMap:
    """A map restored from `snapshot_file` bytes; raises ValueError with a reason if they are not one."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            meta = json.loads(zf.read("map.json"))
            if meta.get("format") != SNAPSHOT_FORMAT:
                raise ValueError(f"not a {SNAPSHOT_FORMAT} file")
            config = MapConfig.model_validate(meta["config"])
            if max_tiles is not None and config.max_tiles > max_tiles:
                config = config.model_copy(update={"max_tiles": max_tiles})
            with np.load(io.BytesIO(zf.read("tiles.npz")), allow_pickle=False) as npz:
                keys = [tuple(int(v) for v in k) for k in npz["keys"]]
                gmap = GridMap(config)
                if len(keys) > config.max_tiles:
                    raise ValueError(
                        f"the snapshot has {len(keys)} tiles, more than max_tiles {config.max_tiles}"
                    )
                gmap.store.create(keys)  # type: ignore[arg-type]
                t = config.tile_size
                for a in gmap.store.arrays:
                    stacked = npz[a.name]
                    if stacked.shape != (len(keys), t, t) or stacked.dtype != np.dtype(a.dtype):
                        raise ValueError(
                            f"layer {a.name} has shape {stacked.shape}, expected {(len(keys), t, t)}"
                        )
                    gmap.store.pools[a.name][: len(keys)] = stacked
    except (KeyError, zipfile.BadZipFile, json.JSONDecodeError, OSError) as exc:
        raise ValueError(f"not a fleetmap snapshot: {exc}") from None
    return gmap


# -- the durable store the registry uses ------------------------------------------------------------------


#: One stored tile: its key (tile i, tile j), version and `tile_to_blob` blob.
TileRow = tuple[tuple[int, int], int, bytes]


class DurableStore:
    """Persistence for a `MapRegistry`: restore on start, journal while running, snapshot now and then.

    The registry calls `map_created`, `map_deleted` and, under a map's lock, `journal`; this class
    calls back `on_durable(journal_id)` once a scan's row is committed.

    Snapshot frequency trades restart time (journal rows to replay) against the work a snapshot
    does while scans arrive: it copies every changed tile (about 1.3 MB each with all layers) under
    the map's lock, encodes and writes them one by one (`tile_to_blob`), and checkpoints the WAL
    (copying every journal row written since into the database file). Every 30 s or 20 000 rows
    keeps a restart's replay to about 10-20 s at 400 scans/s. After each tile the snapshot thread
    sleeps `snapshot_pace` times as long as the tile took, so it uses at most 1 / (1 + pace) of a
    core (a quarter by default) instead of one for tens of ms.
    """

    def __init__(
        self,
        data_dir: Path,
        snapshot_interval: float = 30.0,
        snapshot_rows: int = 20000,
        snapshot_pace: float = 3.0,
    ) -> None:
        self.data_dir = Path(data_dir)
        self.path = open_database(self.data_dir)
        self.writer = JournalWriter(self.path, on_error=self._storage_failed)
        self.snapshot_interval = snapshot_interval
        self.snapshot_rows = snapshot_rows
        self.snapshot_pace = snapshot_pace
        self.failed: str | None = None  # the last storage failure, reported by /healthz
        self._rows_since: dict[str, int] = {}
        self._last_journal_id: dict[str, int] = {}
        self._snapshot_clock: dict[str, int] = {}  # store clock of each map's last snapshot
        self._snapshot_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # Snapshot generations: tile rows are written under a new generation, which becomes the
        # map's only when a small final transaction switches to it. `_created` identifies a map's
        # incarnation, so a snapshot of a map deleted and re-created meanwhile is discarded.
        self._last_gen = 0
        self._gen_lock = threading.Lock()
        self._created: dict[str, float] = {}
        # Only checkpoints: a checkpoint takes no write lock, so it runs beside the journal's commits.
        self._snapshot_conn = connect(self.path, synchronous="NORMAL", autocheckpoint=False)

    def _next_gen(self) -> int:
        with self._gen_lock:
            self._last_gen = max(self._last_gen + 1, time.time_ns())
            return self._last_gen

    # -- start ---------------------------------------------------------------------------------------

    def load(self) -> list[tuple[str, GridMap, dict, list[tuple[str, int, float, Scan]]]]:
        """Every stored map: (id, map from its snapshot, saved counters, journal rows after it).

        The caller (the registry) replays the journal rows in order through its own bookkeeping."""
        conn = connect(self.path)
        try:
            out = []
            for map_id, config_json, snap_id, snap_gen, clock, integrated, rejected, created in conn.execute(
                "SELECT id, config, snapshot_journal_id, snapshot_gen, clock, scans_integrated, "
                "scans_rejected, created_at FROM maps"
            ).fetchall():
                # Stored before today's limits, perhaps: a map that was accepted keeps loading.
                gmap = GridMap(MapConfig.model_validate_json(config_json, context={STORED_CONFIG: True}))
                # Rows of a snapshot that never switched its generation (a crash mid-snapshot) are
                # not part of the map; each tile is its newest committed generation.
                conn.execute("DELETE FROM tiles WHERE map_id = ? AND gen > ?", (map_id, snap_gen))
                # Journal rows the snapshot supersedes that the writer had not deleted yet.
                conn.execute("DELETE FROM journal WHERE map_id = ? AND id <= ?", (map_id, snap_id))
                rows = conn.execute(
                    "SELECT ti, tj, version, data FROM tiles t WHERE map_id = ? AND gen = (SELECT MAX(gen) "
                    "FROM tiles u WHERE u.map_id = t.map_id AND u.ti = t.ti AND u.tj = t.tj)",
                    (map_id,),
                ).fetchall()
                self._created[map_id] = created
                self._last_gen = max(self._last_gen, snap_gen)
                if rows:
                    gmap.store.create([(ti, tj) for ti, tj, _, _ in rows])
                    for ti, tj, version, data in rows:
                        slot = gmap.store.slots[(ti, tj)]
                        for a, arr in zip(gmap.store.arrays, tile_from_blob(data, gmap), strict=True):
                            gmap.store.pools[a.name][slot] = arr
                        gmap.store.versions[slot] = version
                gmap.store.restore_clock(max(clock, max((r[2] for r in rows), default=0)))
                robots = {rid: json.loads(state) for rid, state in conn.execute(
                    "SELECT robot_id, state FROM robots WHERE map_id = ?", (map_id,))}  # fmt: skip
                journal = [
                    (robot_id, seq, stamp, scan_from_blob(blob))
                    for _id, robot_id, seq, stamp, blob in conn.execute(
                        "SELECT id, robot_id, seq, stamp, scan FROM journal WHERE map_id = ? AND id > ? "
                        "ORDER BY id", (map_id, snap_id))
                ]  # fmt: skip
                last = conn.execute("SELECT MAX(id) FROM journal WHERE map_id = ?", (map_id,)).fetchone()[0]
                self._last_journal_id[map_id] = int(last or snap_id)
                self._rows_since[map_id] = len(journal)
                # Tiles replayed from the journal are newer than the stored snapshot; restored tiles
                # are not, so only versions above the restored clock count as changed.
                self._snapshot_clock[map_id] = gmap.store.clock
                counters = {"scans_integrated": integrated, "scans_rejected": rejected, "robots": robots}
                out.append((map_id, gmap, counters, journal))
            return out
        except (sqlite3.DatabaseError, zlib.error) as exc:
            raise StorageError(f"cannot read the map database {self.path}: {exc}") from None
        finally:
            conn.close()

    # -- hooks called by the registry -------------------------------------------------------------------

    @staticmethod
    def tile_rows(gmap: GridMap) -> list[TileRow]:
        """Every tile of `gmap` as `map_created` stores it. About 1.5 ms per 256-cell tile with every
        layer, so a restored map's are encoded before `map_created` is called under the registry's
        lock."""
        layout = gmap.store.arrays
        return [
            (key, version, tile_to_blob(arrays, layout)) for key, version, arrays in changed_tiles(gmap, -1)
        ]

    def map_created(self, map_id: str, gmap: GridMap, tiles: list[TileRow] | None = None) -> Future:
        """Record a new map (or one restored from a snapshot file, with its tiles: `tile_rows`, made
        here when not given). Queued, not waited for: called under the registry's lock, it is
        ordered before any of the map's scans. The future resolves once the map is committed.

        The map's journal starts after the journal's current sequence, so rows a deleted map of the
        same id left behind are never replayed into this one."""
        if tiles is None:
            tiles = self.tile_rows(gmap)
        config_json, clock = gmap.config.model_dump_json(), gmap.store.clock
        gen = self._next_gen()
        created = time.time()
        self._created[map_id] = created

        def op(conn: sqlite3.Connection) -> None:
            self.writer.trim(map_id, None)  # the DELETE below removes them all
            conn.execute("BEGIN IMMEDIATE")
            for table, column in (("tiles", "map_id"), ("robots", "map_id"), ("journal", "map_id")):
                conn.execute(f"DELETE FROM {table} WHERE {column} = ?", (map_id,))
            conn.execute(
                "INSERT OR REPLACE INTO maps (id, config, created_at, clock, snapshot_gen, "
                "snapshot_journal_id) VALUES (?, ?, ?, ?, ?, "
                "(SELECT COALESCE(MAX(seq), 0) FROM sqlite_sequence WHERE name = 'journal'))",
                (map_id, config_json, created, clock, gen),
            )
            conn.executemany(
                "INSERT INTO tiles (map_id, ti, tj, gen, version, data) VALUES (?, ?, ?, ?, ?, ?)",
                [(map_id, k[0], k[1], gen, v, b) for k, v, b in tiles],
            )
            conn.execute("COMMIT")
            self._last_journal_id[map_id] = 0

        self._rows_since[map_id] = 0
        self._snapshot_clock[map_id] = clock
        return self.writer.submit(op)

    def map_deleted(self, map_id: str) -> Future:
        """Forget a map. Queued after its journaled scans, not waited for; the future resolves once
        the deletion is committed."""

        def op(conn: sqlite3.Connection) -> None:
            self.writer.trim(map_id, None)  # the DELETE below removes them all
            conn.execute("BEGIN IMMEDIATE")
            for table, column in (
                ("maps", "id"),
                ("tiles", "map_id"),
                ("robots", "map_id"),
                ("journal", "map_id"),
            ):
                conn.execute(f"DELETE FROM {table} WHERE {column} = ?", (map_id,))
            conn.execute("COMMIT")

        for d in (self._rows_since, self._snapshot_clock):
            d.pop(map_id, None)
        return self.writer.submit(op)

    def journal(self, map_id: str, robot_id: str, seq: int, stamp: float, blob: bytes,
                on_durable: Callable[[int], None]) -> None:  # fmt: skip
        """Append an applied scan (its `scan_to_blob`, made before taking the lock); MUST be called
        under the map's lock so the journal's order is the order scans were applied in."""

        def durable(row_id: int) -> None:
            self._last_journal_id[map_id] = row_id
            self._rows_since[map_id] = self._rows_since.get(map_id, 0) + 1
            on_durable(row_id)

        self.writer.append(JournalEntry(map_id, robot_id, seq, stamp, blob, durable))

    # -- snapshots -------------------------------------------------------------------------------------

    def snapshot(self, map_id: str, gmap: GridMap, counters: Callable[[], dict]) -> int:
        """Write the tiles changed since the last snapshot and truncate the journal; returns the number
        of tiles written.

        Under the map's lock the changed tiles are copied and a marker is queued behind every scan
        applied so far; the writer runs the marker after committing (and counting) exactly those
        scans, so the journal id and the `counters()` it records match the copied tiles. The tiles are
        then encoded one at a time (paced by `snapshot_pace`) and written under a new generation
        inside the writer's next group commits (`JournalWriter.attach`), so nothing competes with
        the journal for SQLite's write lock; one small transaction on the writer then switches the
        map to that generation, records the journal id the snapshot includes and drops the tile rows
        it supersedes. The journal rows up to that id are deleted
        afterwards by the writer, `JournalWriter.TRIM_ROWS` per transaction. A crash before the switch
        leaves the old generation and its journal intact (the new rows are ignored and removed at
        start). Nothing here waits on the writer while holding a lock."""
        with self._snapshot_lock:
            with gmap.lock:
                since = self._snapshot_clock.get(map_id, 0)
                copies = changed_tiles(gmap, since)
                clock = gmap.store.clock
                created = self._created.get(map_id)
                marker = self.writer.submit(lambda conn: (self._last_journal_id.get(map_id, 0), counters()))
            last_id, saved = marker.result()
            gen = self._next_gen()
            layout = gmap.store.arrays
            written = []
            for key, version, arrays in copies:
                started = time.perf_counter()
                blob = tile_to_blob(arrays, layout)
                written.append(
                    self.writer.attach(
                        "INSERT OR REPLACE INTO tiles (map_id, ti, tj, gen, version, data) "
                        "VALUES (?, ?, ?, ?, ?, ?)",
                        (map_id, key[0], key[1], gen, version, blob),
                    )
                )
                # The machine's few cores also integrate scans: spread the encoding out rather
                # than take a core for tens of ms at once.
                time.sleep((time.perf_counter() - started) * self.snapshot_pace)
            for future in written:
                future.result()  # every row committed before the switch (raises if one failed)

            def switch(conn: sqlite3.Connection) -> bool:
                conn.execute("BEGIN IMMEDIATE")
                row = conn.execute("SELECT created_at FROM maps WHERE id = ?", (map_id,)).fetchone()
                if row is None or row[0] != created:  # deleted or re-created meanwhile
                    conn.execute("DELETE FROM tiles WHERE map_id = ? AND gen = ?", (map_id, gen))
                    conn.execute("COMMIT")
                    return False
                conn.execute(
                    "UPDATE maps SET snapshot_gen = ?, snapshot_journal_id = MAX(snapshot_journal_id, ?), "
                    "clock = ?, scans_integrated = ?, scans_rejected = ? WHERE id = ?",
                    (gen, last_id, clock, saved["scans_integrated"], saved["scans_rejected"], map_id),
                )
                conn.executemany(
                    "INSERT OR REPLACE INTO robots (map_id, robot_id, state) VALUES (?, ?, ?)",
                    [(map_id, rid, json.dumps(state)) for rid, state in saved["robots"].items()],
                )
                conn.execute(
                    "DELETE FROM tiles WHERE map_id = ? AND gen < ? AND EXISTS (SELECT 1 FROM tiles u WHERE "
                    "u.map_id = tiles.map_id AND u.ti = tiles.ti AND u.tj = tiles.tj AND u.gen = ?)",
                    (map_id, gen, gen),
                )
                conn.execute("COMMIT")
                # The journal rows up to last_id are dead from this commit on; deleting them here
                # held the journal's commits up for 0.3-0.7 s, so the writer deletes them bit by bit.
                self.writer.trim(map_id, last_id)
                return True

            if self.writer.run(switch):
                self._snapshot_clock[map_id] = clock
                self._rows_since[map_id] = 0
            self._checkpoint()
            return len(copies)

    def _checkpoint(self) -> None:
        """Copy the WAL into the database and let it start over, holding the journal up only briefly.

        The journal writer never checkpoints on its own. A passive checkpoint on another connection
        never blocks its commits, but under continuous ingest it never catches up either: commits
        land while it copies, and SQLite rewinds a WAL only when it is entirely copied as the next
        write begins. So the WAL grew by about 15 MB/s at 400 scans/s, without bound. Here this
        thread copies the bulk (passive, the commits go on), again while the tail shrinks, then the
        writer copies the last few frames between two groups, and its next commit rewinds the WAL.
        The file keeps its size (about one snapshot interval of writes) and is overwritten from the
        start: truncating it (`journal_size_limit`) took a commit 250 ms on this machine's disk."""
        conn = self._snapshot_conn
        with contextlib.suppress(sqlite3.Error):
            previous = None
            for _ in range(CHECKPOINT_PASSES):
                _busy, frames, _copied = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                if previous is not None and frames - previous < CHECKPOINT_TAIL_FRAMES:
                    break
                previous = frames
            self.writer.run(lambda wconn: wconn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone())

    def needs_snapshot(self, map_id: str) -> bool:
        return self._rows_since.get(map_id, 0) > 0

    def overdue(self, map_id: str) -> bool:
        return self._rows_since.get(map_id, 0) >= self.snapshot_rows

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.writer.close()
        with contextlib.suppress(sqlite3.Error):
            self._snapshot_conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self._snapshot_conn.close()

    def checkpoint_step(self) -> None:
        """One passive checkpoint: copy what the WAL gained since the last one into the database,
        beside the journal's commits. The snapshot thread calls it every second, so a snapshot's own
        checkpoint finds little left: copying 30 s of journal (about 350 MB) at once slowed the
        journal's fsyncs for 0.2 s, and the scans meanwhile reached p99 64-74 ms."""
        with self._snapshot_lock, contextlib.suppress(sqlite3.Error):
            self._snapshot_conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()

    def start_periodic(self, snapshot_all: Callable[[bool], None]) -> None:
        """Call `snapshot_all(only_overdue)` every second for maps past `snapshot_rows`, and for every
        changed map each `snapshot_interval` seconds; `checkpoint_step` every second."""

        def loop() -> None:
            last_full = time.monotonic()
            while not self._stop.wait(1.0):
                full = time.monotonic() - last_full >= self.snapshot_interval
                try:
                    snapshot_all(not full)
                except Exception:  # keep snapshotting; the failure is logged and shown in health
                    log.exception("snapshot failed")
                if full:
                    last_full = time.monotonic()
                self.checkpoint_step()

        self._thread = threading.Thread(target=loop, name="fleetmap-snapshot", daemon=True)
        self._thread.start()

    def _storage_failed(self, exc: Exception) -> None:
        self.failed = f"storage error: {exc}"
