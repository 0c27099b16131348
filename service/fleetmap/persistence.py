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

`DurableStore` is built from three modules: `database` (the schema and the data directory's checks),
`journal` (the group-committing writer thread) and `storage_format` (scans, tiles and snapshot files
as bytes).
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import threading
import time
import zlib
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetmap.config import STORED_CONFIG, MapConfig
from fleetmap.database import CLEARED_WINDOWS_LAYOUT, StorageError, connect, open_database
from fleetmap.export import Window
from fleetmap.grid_map import GridMap
from fleetmap.journal import JournalEntry, JournalWriter
from fleetmap.robot_state import RobotState
from fleetmap.scan import Scan
from fleetmap.storage_format import journal_row_from_blob, tile_from_blob, tile_to_blob
from fleetmap.tombstones import MAX_TOMBSTONES, Tombstone, forgotten_before

log = logging.getLogger("fleetmap.persistence")

#: Default seconds between snapshots of a changed map, and journal rows that make one due sooner.
SNAPSHOT_INTERVAL = 30.0
SNAPSHOT_ROWS = 20000

#: After a snapshot, passive checkpoints on the snapshot connection until one finds fewer than
#: CHECKPOINT_TAIL_FRAMES new WAL frames (4 KiB each; at most CHECKPOINT_PASSES of them); the journal
#: writer then copies the rest, so the WAL can start over. See `DurableStore._checkpoint`.
CHECKPOINT_PASSES = 4
CHECKPOINT_TAIL_FRAMES = 256

#: The tables whose rows belong to one map (column `map_id`), besides its own row in `maps`.
MAP_TABLES = ("tiles", "robots", "journal")


def _delete_map_rows(conn: sqlite3.Connection, map_id: str) -> None:
    """Inside an open transaction, delete everything stored of map `map_id` but its row in `maps`."""
    for table in MAP_TABLES:
        conn.execute(f"DELETE FROM {table} WHERE map_id = ?", (map_id,))


def _bury(conn: sqlite3.Connection, buried: Sequence[Tombstone]) -> None:
    """Inside an open transaction, store the tombstones `buried` (replacing a robot's earlier one:
    `Tombstones.bury` and `Tombstones.forget` merged them) and delete those past `TOMBSTONE_DAYS`."""
    if not buried:
        return
    conn.executemany(
        "INSERT OR REPLACE INTO tombstones (map_id, robot_id, deleted_at, sessions, forgotten, plain_seq, "
        "plain_stamp) VALUES (?, ?, ?, ?, ?, ?, ?)",
        [
            (
                t.map_id,
                t.robot_id,
                t.deleted_at,
                t.sessions_json(),
                int(t.forgotten),
                *(t.plain or (None, None)),
            )
            for t in buried
        ],
    )
    conn.execute("DELETE FROM tombstones WHERE deleted_at < ?", (forgotten_before(time.time()),))


def changed_tiles(gmap: GridMap, since: int) -> list[tuple[tuple[int, int], int, list[np.ndarray]]]:
    """Copies of the tiles whose version is above `since`: (key, version, arrays in store order).
    The caller holds the map's lock."""
    store = gmap.store
    pools = [store.pools[a.name] for a in store.arrays]
    return [
        (store.keys[slot], int(store.versions[slot]), [pool[slot].copy() for pool in pools])
        for slot in store.changed_since(since).tolist()
    ]


def unreadable_database(path: Path, map_id: str | None, exc: BaseException | str) -> StorageError:
    """The error that stops the service at start when its database cannot be read."""
    where = "" if map_id is None else f" (map {map_id!r})"
    reason = " ".join(str(exc).split())  # one line, also for pydantic's multi-line messages
    if isinstance(exc, sqlite3.OperationalError) and reason in (
        "database is locked",
        "database table is locked",
    ):
        # Another program holds a write lock (a `sqlite3` shell in a transaction, a backup tool):
        # the database is fine, and the advice to restore it from a backup would throw maps away.
        return StorageError(
            f"cannot read the map database {path}{where}: another program kept it locked for longer "
            "than the service waits (a sqlite3 shell in a transaction, a backup tool?); the database "
            "is not damaged: end that program, then start the service again"
        )
    return StorageError(
        f"cannot read the map database {path}{where}: {reason}; the service does not start on a damaged "
        "database: restore the data directory from a backup, or move it aside"
    )


def _check_journal_columns(
    robot_id: object, seq: object, stamp: object, session: object, blob: object
) -> None:
    """`StorageError` unless a journal row's columns hold what the writer stores in them. SQLite
    keeps whatever type a value had in any column (a row edited by hand, a damaged page), and such
    a value (a scan or a seq stored as text) stopped the replay with a traceback."""
    if not (
        isinstance(robot_id, str)
        and isinstance(seq, int)
        and isinstance(stamp, (int, float))
        and (session is None or isinstance(session, int))
        and isinstance(blob, bytes)
    ):
        kinds = ", ".join(type(v).__name__ for v in (robot_id, seq, stamp, session, blob))
        raise StorageError(
            f"corrupt journal entry: its robot id, seq, stamp, session and scan are of types {kinds}"
        )


def _journal_refusals(named: object) -> list[tuple[int, bool]]:
    """The refusals a journal row names (its `refused` column, `DurableStore.journal`): (seq, may
    be sent again) pairs; `StorageError` for anything else."""
    if named is None:
        return []
    try:
        pairs = json.loads(named) if isinstance(named, str) else None
        refused = [(seq, bool(resend)) for seq, resend in pairs]  # type: ignore[union-attr]
    except (ValueError, TypeError):
        refused = None
    if refused is None or not all(type(seq) is int and 0 <= seq < 2**63 for seq, _ in refused):
        raise StorageError(f"corrupt journal entry: its refused seqs are {str(named)[:100]!r}")
    return refused


def _check_map_columns(
    config: object, snap_id: object, snap_gen: object, clock: object, integrated: object,
    rejected: object, created: object,
) -> None:  # fmt: skip
    """`StorageError` unless a `maps` row's columns hold what the service stores in them: the
    configuration as text, whole numbers for the journal id, generation, clock and counters, a
    number for the creation time. SQLite keeps whatever type a value had in any column (a row edited
    by hand, a damaged page): a clock or a generation stored as text stopped the start with a
    traceback, and a counter stored as a fraction started a service whose every GET of the map (and
    GET /maps) was a 500."""
    counts = {
        "snapshot_journal_id": snap_id, "snapshot_gen": snap_gen, "clock": clock,
        "scans_integrated": integrated, "scans_rejected": rejected,
    }  # fmt: skip
    wrong = [name for name, value in counts.items() if type(value) is not int]
    if type(config) is not str:
        wrong.append("config")
    if type(created) not in (int, float):
        wrong.append("created_at")
    if wrong:
        raise StorageError(f"corrupt maps row: {', '.join(wrong)} not of the type the service stores")


class StoredJournal:
    """A map's journal rows after its snapshot, in order, read and decoded `BATCH` rows at a time
    while they are replayed. Decoded all at once before the replay, they took 17 KB a scan of 1081
    beams: a restart after 20,000 scans (the rows that make a snapshot due) peaked at 590 MB instead
    of 210 MB for one map, and as much again for each other map, so a service that ran well within
    its memory limit could not start again after a crash. Iterating raises `StorageError`
    (`unreadable_database`) for a row that does not decode.

    The rows are read on `conn`, the connection `DurableStore.load` read the maps on, which stays
    open until `DurableStore.restored`: a connection of its own per map cost 0.5 ms a map for its
    first read (the schema, the WAL index), 2.5 s of a start that restores 5,000 maps with scans to
    replay. A journal with no rows (every map after a clean stop) reads nothing."""

    BATCH = 256

    def __init__(self, conn: sqlite3.Connection, path: Path, map_id: str, after: int, count: int) -> None:
        self.conn, self.path, self.map_id, self.after, self.count = conn, path, map_id, after, count

    def __len__(self) -> int:
        return self.count

    def __iter__(
        self,
    ) -> Iterator[tuple[str, int, float, int | None, list[tuple[int, bool]], Scan | Window]]:
        """(robot id, seq, stamp, session id or None, the seqs of its session refused before it
        that it names with whether each may be sent again (`DurableStore.journal`), scan) of each
        row, in journal order; a row that cleared a window of cells (`MapRegistry.clear_window`)
        has that `Window` for its scan, no robot id (""), seq 0 and the time it was cleared."""
        if not self.count:
            return
        try:
            last = self.after
            while True:
                # A batch is fetched whole before any row is decoded: a cursor left open by a row
                # that does not decode kept a read lock, and the shutdown's checkpoint waited 30 s.
                rows = self.conn.execute(
                    "SELECT id, robot_id, seq, stamp, session, refused, scan FROM journal "
                    "WHERE map_id = ? AND id > ? "
                    "ORDER BY id LIMIT ?",
                    (self.map_id, last, self.BATCH),
                ).fetchall()
                if not rows:
                    return
                for row_id, robot_id, seq, stamp, session, named, blob in rows:
                    try:
                        _check_journal_columns(robot_id, seq, stamp, session, blob)
                        refused = _journal_refusals(named)
                        row = journal_row_from_blob(blob)
                    except StorageError as exc:
                        raise unreadable_database(
                            self.path, self.map_id, f"journal row {row_id}: {exc}"
                        ) from None
                    yield robot_id, seq, stamp, session, refused, row
                last = rows[-1][0]
        except sqlite3.DatabaseError as exc:
            raise unreadable_database(self.path, self.map_id, exc) from None


# -- the durable store the registry uses ------------------------------------------------------------------


#: One stored tile: its key (tile i, tile j), version and `tile_to_blob` blob.
TileRow = tuple[tuple[int, int], int, bytes]


@dataclass(frozen=True)
class StorageHealth:
    """How the data directory is doing (`DurableStore.health`, reported by `GET /healthz`).

    `ok` is False while the last journal commit or the last snapshot failed, while a map holds
    scans whose journal commit failed (they are applied in memory but only the map's next snapshot
    makes them durable), and while the creation, restore or deletion of a map is not stored
    (`map_changes_not_stored`: retried until it is). `last_error` and `last_error_at` (Unix time)
    describe the latest failure and stay after recovery; `scans_not_durable` counts, since start,
    the scans whose journal commit failed."""

    ok: bool
    last_error: str | None
    last_error_at: float | None
    scans_not_durable: int
    maps_awaiting_snapshot: tuple[str, ...]
    map_changes_not_stored: tuple[str, ...]


class DurableStore:
    """Persistence for a `MapRegistry`: restore on start, journal while running, snapshot now and then.

    The registry calls `map_created`, `map_deleted` (and `retry_map_change` when a client repeats
    one that was not stored) and, under a map's lock, `journal`; this class calls back
    `on_durable(journal_id)` once a scan's row is committed.

    Snapshot frequency trades restart time (journal rows to replay) against the work a snapshot
    does while scans arrive: it copies every changed tile (about 1.3 MB each with all layers) under
    the map's lock, encodes and writes them one by one (`tile_to_blob`), and checkpoints the WAL
    (copying every journal row written since into the database file). Every 30 s or 20 000 rows
    keeps a restart's replay to about 10-20 s at 400 scans/s. After each tile the snapshot thread
    sleeps `snapshot_pace` times as long as the tile took, so it uses at most 1 / (1 + pace) of a
    core (a quarter by default) instead of one for tens of ms; once the service stops
    (`stop_periodic`), its last snapshots go at full speed.
    """

    def __init__(
        self,
        data_dir: Path,
        snapshot_interval: float = SNAPSHOT_INTERVAL,
        snapshot_rows: int = SNAPSHOT_ROWS,
        snapshot_pace: float = 3.0,
    ) -> None:
        self.data_dir = Path(data_dir)
        # Held until `close`: no second service may use this directory meanwhile.
        self.path, self._dir_lock = open_database(self.data_dir)
        self.writer = JournalWriter(self.path, on_error=self._storage_failed)
        #: Whether the database's layout is known to allow cleared windows (`allow_cleared_windows`).
        self._cleared_windows = False
        self.snapshot_interval = snapshot_interval
        self.snapshot_rows = snapshot_rows
        self.snapshot_pace = snapshot_pace
        # Storage health (see `health`), written by the writer and snapshot threads.
        self._health_lock = threading.Lock()
        self._journal_error: str | None = None  # the last journal commit failed with this
        self._snapshot_errors: dict[str, str] = {}  # map id -> why its last snapshot failed
        self._last_error: tuple[str, float] | None = None
        self._not_durable = 0
        #: Storage failures since start by operation (`journal_commit`, `snapshot`, `map_change`),
        #: for `fleetmap_storage_failures_total`: `health` says whether storage fails now, these
        #: that it failed between two scrapes even if it has recovered since.
        self.failures: dict[str, int] = {}
        # map id -> failed journal commits of its scans not yet covered by a snapshot
        self._awaiting: dict[str, int] = {}
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
        # map id -> (robot id -> tombstone): those a change of the map buried whose transaction has
        # not committed (a failing disk). The writer retries that change, but a later change of the
        # same map id supersedes it (`JournalWriter.change_map`), and must store them instead: else
        # a deletion answered 503, then the map created again, lost its tombstones, and a restart
        # let the old map's robots' cached scans into the new map. Writer thread only (`_burying`).
        self._unburied: dict[str, dict[str, Tombstone]] = {}
        # Guards what a map's incarnation owns of the dicts above when a thread other than the one
        # that (re)created or deleted the map writes them: the writer's scan callbacks and the
        # snapshot thread check `_created` and write in one hold, so a map deleted and created again
        # in between does not get the old map's snapshot clock or journal id (see `_write_snapshot`).
        self._maps_lock = threading.Lock()
        # Only checkpoints: a checkpoint takes no write lock, so it runs beside the journal's commits.
        self._snapshot_conn = connect(self.path, synchronous="NORMAL", autocheckpoint=False)
        #: The connection `load` reads the maps and their journals on, until `restored`.
        self._restore_conn: sqlite3.Connection | None = None

    def _burying(self, map_id: str, buried: Sequence[Tombstone]) -> list[Tombstone]:
        """On the writer thread, in a change of map `map_id` that buries `buried`: those and the
        ones earlier changes of the map buried but never stored, for the change's transaction to
        store (a robot's newer tombstone replaces its older one: `Tombstones.bury` merged them).
        They stay pending until `_buried` says the transaction committed."""
        pending = self._unburied.setdefault(map_id, {})
        pending.update((stone.robot_id, stone) for stone in buried)
        return list(pending.values())

    def _buried(self, map_id: str) -> None:
        """On the writer thread: the change of map `map_id` committed, with its pending tombstones."""
        self._unburied.pop(map_id, None)

    def _next_gen(self) -> int:
        with self._gen_lock:
            self._last_gen = max(self._last_gen + 1, time.time_ns())
            return self._last_gen

    # -- start ---------------------------------------------------------------------------------------

    def load(self) -> list[tuple[str, GridMap, dict, StoredJournal]]:
        """Every stored map: (id, map from its snapshot, saved counters (its robots as `RobotState`),
        journal rows after it).

        The caller (the registry) replays the journal rows in order through its own bookkeeping;
        they are read as it goes (`StoredJournal`), on a connection this store keeps open until
        `restored` (or `close`): iterate them before then.

        Raises `StorageError` naming the database file (and the map, when one map's rows are the
        problem) if it cannot be read: a corrupt file, tile, journal row or configuration. The
        service then refuses to start rather than serve a map that is not what its robots made."""
        self.restored()
        conn = self._restore_conn = connect(self.path)
        map_id = None
        try:
            out = []
            stored_maps = conn.execute(
                "SELECT id, config, snapshot_journal_id, snapshot_gen, clock, scans_integrated, "
                "scans_rejected, created_at FROM maps"
            ).fetchall()
            # Rows of maps that are not stored: left by versions that wrote a map's scans although
            # its creation had failed to commit. Nothing would ever read or delete them.
            for table in MAP_TABLES:
                conn.execute(f"DELETE FROM {table} WHERE map_id NOT IN (SELECT id FROM maps)")
            # Each configuration stored, validated once: thousands of maps made by the same
            # `PUT /maps/{id}` body (or scans, with the default) share one. A MapConfig is frozen, and
            # a GridMap shares the one it is given. (0.1 ms a validation: 0.5 s for 5,000 maps.)
            configs: dict[str, MapConfig] = {}
            for map_id, *columns in stored_maps:  # (map_id: for the error, if this one's rows are bad)
                out.append(self._load_map(conn, configs, map_id, *columns))
            return out
        # ValueError: a stored configuration that does not validate (pydantic's ValidationError).
        except (sqlite3.DatabaseError, zlib.error, StorageError, ValueError) as exc:
            self.restored()
            raise unreadable_database(self.path, map_id, exc) from None
        except BaseException:
            self.restored()
            raise

    def restored(self) -> None:
        """The maps `load` returned are restored, their journals replayed: close the connection they
        were read on (nothing if none is open)."""
        conn, self._restore_conn = self._restore_conn, None
        if conn is not None:
            conn.close()

    def load_tombstones(self) -> list[Tombstone]:
        """The robots of deleted and replaced maps, and those forgotten by full maps, still
        remembered (`tombstones.py`); a forgotten robot's whose map is not stored is made a deleted
        map's, and those past `TOMBSTONE_DAYS`, or the oldest past `MAX_TOMBSTONES` (forgotten
        robots' first), are deleted from the database here."""
        conn = connect(self.path)
        try:
            with conn:
                conn.execute("DELETE FROM tombstones WHERE deleted_at < ?", (forgotten_before(time.time()),))
                # A forgotten robot's stone whose map is not stored: an older service deleted the map
                # (it writes no `forgotten`, so the row stayed so). The robot's scans went with it.
                conn.execute(
                    "UPDATE tombstones SET forgotten = 0 "
                    "WHERE forgotten AND map_id NOT IN (SELECT id FROM maps)"
                )
                # Past the bound, live maps' forgotten robots go first, as `Tombstones.prune` has it.
                conn.execute(
                    "DELETE FROM tombstones WHERE rowid IN (SELECT rowid FROM tombstones "
                    "ORDER BY forgotten, deleted_at DESC LIMIT -1 OFFSET ?)",
                    (MAX_TOMBSTONES,),
                )
            rows = conn.execute(
                "SELECT map_id, robot_id, deleted_at, sessions, forgotten, plain_seq, plain_stamp "
                "FROM tombstones"
            ).fetchall()
            return [Tombstone.from_row(*row) for row in rows]
        except (sqlite3.DatabaseError, ValueError) as exc:
            raise unreadable_database(self.path, None, exc) from None
        finally:
            conn.close()

    def _load_map(
        self,
        conn: sqlite3.Connection,
        configs: dict[str, MapConfig],
        map_id: str,
        config_json: str,
        snap_id: int,
        snap_gen: int,
        clock: int,
        integrated: int,
        rejected: int,
        created: float,
    ) -> tuple[str, GridMap, dict, StoredJournal]:
        """One stored map (a row of `maps`): its snapshot's tiles loaded, what the snapshot made
        obsolete deleted, and its journal rows after the snapshot, to be read as they are replayed.
        `configs`: the configurations validated so far, by their stored JSON; this map's is added."""
        _check_map_columns(config_json, snap_id, snap_gen, clock, integrated, rejected, created)
        config = configs.get(config_json)
        if config is None:
            # Stored before today's limits, perhaps: a map that was accepted keeps loading.
            config = configs[config_json] = MapConfig.model_validate_json(
                config_json, context={STORED_CONFIG: True}
            )
        gmap = GridMap(config)
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
        if len(rows) > gmap.config.max_tiles:
            # (A configuration edited or damaged since: the store refused the tiles with "the scan
            # needs N new tile(s)", a traceback at start.)
            raise StorageError(
                f"{len(rows)} stored tiles are more than its configuration's max_tiles "
                f"({gmap.config.max_tiles})"
            )
        if rows:
            gmap.store.create([(ti, tj) for ti, tj, _, _ in rows])
            for ti, tj, version, data in rows:
                slot = gmap.store.slots[(ti, tj)]
                for a, arr in zip(gmap.store.arrays, tile_from_blob(data, gmap), strict=True):
                    gmap.store.pools[a.name][slot] = arr
                gmap.store.versions[slot] = version
        gmap.store.restore_clock(max(clock, max((r[2] for r in rows), default=0)))
        robots = {}
        for rid, state in conn.execute("SELECT robot_id, state FROM robots WHERE map_id = ?", (map_id,)):
            try:
                robots[rid] = RobotState.from_saved(json.loads(state))
            except ValueError as exc:  # a damaged row: `load` refuses the database, naming the map
                raise ValueError(f"robot {rid!r}: {exc}") from None
        count, last = conn.execute(
            "SELECT COUNT(*), MAX(id) FROM journal WHERE map_id = ? AND id > ?", (map_id, snap_id)
        ).fetchone()
        journal = StoredJournal(conn, self.path, map_id, snap_id, count)
        self._last_journal_id[map_id] = int(last or snap_id)
        self._rows_since[map_id] = count
        # Tiles replayed from the journal are newer than the stored snapshot; restored tiles
        # are not, so only versions above the restored clock count as changed.
        self._snapshot_clock[map_id] = gmap.store.clock
        counters = {"scans_integrated": integrated, "scans_rejected": rejected, "robots": robots}
        return map_id, gmap, counters, journal

    # -- hooks called by the registry -------------------------------------------------------------------

    @staticmethod
    def tile_rows(gmap: GridMap) -> list[TileRow]:
        """Every tile of `gmap` as `map_created` stores it, for a map no one else reads or writes yet
        (one being created or restored). About 1.5 ms per 256-cell tile with every layer, so a restored
        map's are encoded before `map_created` is called under the registry's lock."""
        # Encoded from the pools as they are, a tile at a time: no one else sees a map being created,
        # and copying every tile first (`changed_tiles`) held a second copy of the whole map while a
        # snapshot upload or nav2 import was stored (1.7 GB more for a 1 km map of 6,400 tiles).
        store = gmap.store
        layout = store.arrays
        return [
            (
                key,
                int(store.versions[slot]),
                tile_to_blob([store.pools[a.name][slot] for a in layout], layout),
            )
            for key, slot in store.slots.items()
        ]

    def map_created(
        self,
        map_id: str,
        gmap: GridMap,
        tiles: list[TileRow] | None = None,
        buried: Sequence[Tombstone] = (),
    ) -> Future:
        """Record a new map (or one restored from a snapshot file, with its tiles: `tile_rows`, made
        here when not given), and `buried`, the robots of the map it replaces (`Tombstones.bury`;
        with those of an earlier change of the map id that never committed, see `_burying`).
        Queued, not waited for: called under the registry's lock, it is ordered before any of the
        map's scans. The future resolves once the map is committed.

        The map's journal starts after the journal's current sequence, so rows a deleted map of the
        same id left behind are never replayed into this one. (The registry queues no row of a removed
        map after its removal: see `MapRegistry._removing`.)"""
        if tiles is None:
            tiles = self.tile_rows(gmap)
        config_json, clock = gmap.config.model_dump_json(), gmap.store.clock
        gen = self._next_gen()
        created = time.time()
        with self._maps_lock:
            self._created[map_id] = created
            self._rows_since[map_id] = 0
            self._snapshot_clock[map_id] = clock

        first_attempt = True

        def op(conn: sqlite3.Connection) -> None:
            nonlocal first_attempt
            stones = self._burying(map_id, buried)  # first: pending whatever in this op fails
            self.writer.trim(map_id, None)  # the DELETE below removes them all
            if first_attempt:  # (a retry must keep what this map's own failed scans left to save)
                self._forget_health(map_id)  # a previous map of this id, replaced whole, takes its own along
                first_attempt = False
            conn.execute("BEGIN IMMEDIATE")
            _delete_map_rows(conn, map_id)
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
            _bury(conn, stones)
            conn.execute("COMMIT")
            self._buried(map_id)
            with self._maps_lock:
                # Only while this map is the one of its id: removed before its creation was stored
                # (`map_deleted` has dropped the id's bookkeeping already), set here it stayed for good.
                if self._created.get(map_id) == created:
                    self._last_journal_id[map_id] = 0

        return self.writer.change_map(map_id, self._reporting(f"storing the new map {map_id!r} failed", op))

    def map_deleted(self, map_id: str, buried: Sequence[Tombstone] = ()) -> Future:
        """Forget a map, and remember `buried`, its robots (`Tombstones.bury`), in the same
        transaction (with those of an earlier change of the map id that never committed: this one
        supersedes it, see `_burying`). Queued after its journaled scans, not waited for; the
        future resolves once the deletion is committed."""

        def op(conn: sqlite3.Connection) -> None:
            stones = self._burying(map_id, buried)  # first: pending whatever in this op fails
            self.writer.trim(map_id, None)  # the DELETE below removes them all
            self._forget_health(map_id)  # again: its last scans' commits may have failed since
            conn.execute("BEGIN IMMEDIATE")
            conn.execute("DELETE FROM maps WHERE id = ?", (map_id,))
            _delete_map_rows(conn, map_id)
            _bury(conn, stones)
            conn.execute("COMMIT")
            self._buried(map_id)

        # Everything kept per map id goes with it: maps are created and deleted under new ids for
        # the service's whole life (and a scan refused for a map it created removes that map again),
        # so entries kept for every id ever seen would grow without end. `journal`'s callbacks of
        # its last scans, committed after this, leave them alone (see there).
        with self._maps_lock:
            for d in (self._rows_since, self._snapshot_clock, self._created, self._last_journal_id):
                d.pop(map_id, None)
        self._forget_health(map_id)
        return self.writer.change_map(map_id, self._reporting(f"deleting map {map_id!r} failed", op))

    def _reporting(
        self, what: str, op: Callable[[sqlite3.Connection], None]
    ) -> Callable[[sqlite3.Connection], None]:
        """`op`, with its storage failures recorded for `health` as `what`."""

        def reported(conn: sqlite3.Connection) -> None:
            try:
                op(conn)
            except sqlite3.Error as exc:
                self._failure(what, exc, "map_change")
                raise

        return reported

    def map_stored(self, map_id: str) -> Future:
        """A future resolved once every change of map `map_id` queued so far is stored (its creation
        may still be queued), retrying the last one if it failed; it fails with the error if that
        still does not commit."""
        return self.writer.retry(map_id)

    def retry_map_change(self, map_id: str) -> Future | None:
        """If the last change of map `map_id` is not stored (`map_changes_not_stored`), retry it: the
        future resolves once it is stored, or fails with the error. None if nothing is pending."""
        return self.writer.retry(map_id) if map_id in self.writer.unstored else None

    def _forget_health(self, map_id: str) -> None:
        with self._health_lock:
            self._awaiting.pop(map_id, None)
            self._snapshot_errors.pop(map_id, None)

    def allow_cleared_windows(self) -> None:
        """Raise the database's layout to `CLEARED_WINDOWS_LAYOUT` if it is lower, committed before
        this returns: before the first journal row of a cleared window, which an older fleetmap
        would take for a corrupt row (it refuses the newer layout instead). Raises `sqlite3.Error`
        or `OSError` if that cannot be stored (nothing is cleared then). Never call it while holding a
        lock a durability callback takes: it waits for the writer."""
        if self._cleared_windows:
            return

        def raise_layout(conn: sqlite3.Connection) -> None:
            (version,) = conn.execute("PRAGMA user_version").fetchone()
            if version < CLEARED_WINDOWS_LAYOUT:
                conn.execute(f"PRAGMA user_version = {CLEARED_WINDOWS_LAYOUT}")

        self.writer.run(raise_layout)
        self._cleared_windows = True

    def journal(
        self, map_id: str, robot_id: str, seq: int, stamp: float, blob: bytes,
        on_durable: Callable[[int], None], on_failed: Callable[[Exception], None],
        session: int | None = None, refused: Sequence[tuple[int, bool]] | None = None,
    ) -> None:  # fmt: skip
        """Append an applied scan (its `scan_to_blob`, made before taking the lock); MUST be called
        under the map's lock so the journal's order is the order scans were applied in. `refused`:
        the seqs of its session refused before it, each with whether it may be sent again
        (`RobotState.unjournaled_refusals`), which its row names for the replay after a crash.

        `on_durable(journal_id)` follows once its row is committed. If that commit fails (a full or
        failing disk), `on_failed(error)` follows instead: the scan stays applied in memory, and the
        map's next snapshot (at most `snapshot_interval` later, once storage works) makes it
        durable with the tiles it changed."""

        incarnation = self._created.get(map_id)

        def durable(row_id: int) -> None:
            # Committed after its map was deleted (its removal queued behind it), or deleted and
            # created again: its row is gone with the old map, and nothing of it is counted.
            with self._maps_lock:
                if self._created.get(map_id) == incarnation:
                    self._last_journal_id[map_id] = row_id
                    self._rows_since[map_id] = self._rows_since.get(map_id, 0) + 1
            self._journal_error = None
            on_durable(row_id)

        def failed(exc: Exception) -> None:
            with self._health_lock:
                self._not_durable += 1
                self._awaiting[map_id] = self._awaiting.get(map_id, 0) + 1
            on_failed(exc)

        named = None if not refused else json.dumps([[number, int(resend)] for number, resend in refused])
        self.writer.append(JournalEntry(map_id, robot_id, seq, stamp, blob, durable, failed, session, named))

    def wait_for_journal_room(self) -> None:
        """Return once the journal has room for another applied scan: at once, unless the disk stalls
        (`JournalWriter.wait_for_room`). Call it before applying a scan, holding no lock."""
        self.writer.wait_for_room()

    def health(self) -> StorageHealth:
        unstored = self.writer.unstored
        with self._health_lock:
            return StorageHealth(
                ok=self._journal_error is None
                and not self._snapshot_errors
                and not self._awaiting
                and not unstored,
                last_error=None if self._last_error is None else self._last_error[0],
                last_error_at=None if self._last_error is None else self._last_error[1],
                scans_not_durable=self._not_durable,
                maps_awaiting_snapshot=tuple(sorted(self._awaiting)),
                map_changes_not_stored=unstored,
            )

    def _failure(self, what: str, exc: BaseException, operation: str) -> str:
        """Record a storage failure for `health` (`what` failed) and count it under `operation`."""
        message = f"{what}: {type(exc).__name__}: {exc}"
        with self._health_lock:
            self._last_error = (message, time.time())
            self.failures[operation] = self.failures.get(operation, 0) + 1
        return message

    # -- snapshots -------------------------------------------------------------------------------------

    def snapshot(
        self,
        map_id: str,
        gmap: GridMap,
        counters: Callable[[], dict],
        current: Callable[[], bool] | None = None,
    ) -> int:
        """Write the tiles changed since the last snapshot and truncate the journal; returns the number
        of tiles written. `current()`, called under the map's lock, says whether `gmap` is still map
        `map_id` (None: it is); if not (deleted or replaced since the caller looked it up), nothing
        is written and 0 returned. A failure (an `sqlite3.Error` or `OSError`, or a `StorageError`
        while the map's own change is not stored) is recorded for `health` and raised; the next
        snapshot then writes every tile changed since the last one that succeeded.

        Under the map's lock the changed tiles are copied and a marker is queued behind every scan
        applied so far; the writer runs the marker after committing (and counting) exactly those
        scans, so the journal id and the `counters()` it records match the copied tiles. The tiles are
        then encoded one at a time (paced by `snapshot_pace`) and written under a new generation
        inside the writer's next group commits (`JournalWriter.attach`), so nothing competes with
        the journal for SQLite's write lock; one small transaction on the writer then switches the
        map to that generation, records the journal id the snapshot includes and drops the tile rows
        it supersedes. The journal rows up to that id are deleted afterwards by the writer,
        `JournalWriter.TRIM_ROWS` per transaction. A crash before the switch leaves the old
        generation and its journal intact (the new rows are ignored and removed at start). Nothing
        here waits on the writer while holding a lock."""
        return self._recorded(
            map_id, lambda: self._write_snapshot(map_id, gmap, counters, current, False)
        ).result()

    def last_snapshot(
        self,
        map_id: str,
        gmap: GridMap,
        counters: Callable[[], dict],
        current: Callable[[], bool] | None = None,
    ) -> Future[int]:
        """`snapshot` for a stopping service, once no scan is integrated any more (after
        `stop_periodic`): it returns once the tiles are encoded and queued, with a future of what
        `snapshot` returns or raises (failures recorded the same way). Its switch rides in the
        writer's transactions like its tile rows (`JournalWriter.attach_op`), in the one that holds
        its last row or a later one, and no checkpoint follows (`close` checkpoints once): the last
        snapshots of many maps share a few synced transactions. Each took five of its own (its rows,
        its switch, its checkpoint's) and waited `JournalWriter.ATTACH_WAIT` for a group commit that
        no scan would make: 5,000 maps restored after a crash (every one with journal rows to
        snapshot) took 33-41 s to stop, past `docker stop`'s 10 s, whose SIGKILL made the next start
        a crash restore again. Once every one is queued, call `last_snapshots_queued`; wait for
        every future before `close`."""
        return self._recorded(map_id, lambda: self._write_snapshot(map_id, gmap, counters, current, True))

    def last_snapshots_queued(self) -> None:
        """Every `last_snapshot` is queued: what they attached to the writer is committed now, not
        once no row has been attached for `JournalWriter.ATTACH_WAIT`."""
        self.writer.commit_attached()

    def _recorded(self, map_id: str, write: Callable[[], Future[int]]) -> Future[int]:
        """`write()`'s outcome, a failure of storage (an `sqlite3.Error` or `OSError`, or a
        `StorageError`: its tile rows were held back, the map's own creation not being stored yet)
        recorded for `health` before the future fails with it, whether `write` raised it or its
        future did."""
        outcome: Future[int] = Future()

        def settle(done: Future[int]) -> None:
            exc = done.exception()
            if exc is None:
                outcome.set_result(done.result())
                return
            if isinstance(exc, (sqlite3.Error, OSError, StorageError)):
                message = self._failure(f"snapshot of map {map_id!r} failed", exc, "snapshot")
                with self._health_lock:
                    self._snapshot_errors[map_id] = message
            outcome.set_exception(exc)

        try:
            written = write()
        except BaseException as exc:
            written = Future()
            written.set_exception(exc)
        written.add_done_callback(settle)
        return outcome

    def _write_snapshot(
        self,
        map_id: str,
        gmap: GridMap,
        counters: Callable[[], dict],
        current: Callable[[], bool] | None,
        last: bool,
    ) -> Future[int]:
        """`snapshot`'s work (`last`: `last_snapshot`'s), resolved once the switch committed."""
        written_tiles: Future[int] = Future()
        with self._snapshot_lock:
            with gmap.lock:
                since = self._snapshot_clock.get(map_id, 0)
                created = self._created.get(map_id)
                # Both were read per map id: once `gmap` is no longer the map of that id, they are
                # another map's, and the switch would store this old map's tiles and counters as the
                # new map's snapshot (and its clock, so that the new map's own tiles were skipped by
                # its later snapshots). Checked after reading them: a map current now was current
                # then (a map never comes back), so they are its own.
                if current is not None and not current():
                    written_tiles.set_result(0)
                    return written_tiles
                copies = changed_tiles(gmap, since)
                clock = gmap.store.clock
                # On the writer, after the scans applied so far and before any later one: the
                # journal id and counters of exactly the copied tiles, and how many of those scans'
                # commits failed (the copy holds them, so this snapshot makes them durable).
                marker = self.writer.submit(
                    lambda conn: (
                        self._last_journal_id.get(map_id, 0),
                        counters(),
                        self._awaiting.get(map_id),
                    )
                )
            last_id, saved, awaiting = marker.result()
            gen = self._next_gen()
            layout = gmap.store.arrays
            written = []
            for key, version, arrays in copies:
                started = time.perf_counter()
                blob = tile_to_blob(arrays, layout)
                # Only while the map is the incarnation copied: a map deleted and created again
                # meanwhile has no row of this generation, and the switch would drop these rows,
                # but a crash before it left them, the newest of their tiles, in the new map.
                written.append(
                    self.writer.attach(
                        "INSERT OR REPLACE INTO tiles (map_id, ti, tj, gen, version, data) "
                        "SELECT ?, ?, ?, ?, ?, ? WHERE EXISTS "
                        "(SELECT 1 FROM maps WHERE id = ? AND created_at = ?)",
                        (map_id, key[0], key[1], gen, version, blob, map_id, created),
                        map_id=map_id,
                    )
                )
                # The machine's few cores also integrate scans: spread the encoding out rather
                # than take a core for tens of ms at once. Not once the service stops (`stop_periodic`):
                # no scan is integrated then, and the pace only delayed the stop (61,000 tiles took
                # 22 s where they need 10) towards the container's kill.
                self._stop.wait((time.perf_counter() - started) * self.snapshot_pace)

            def switch_rows(conn: sqlite3.Connection) -> bool:
                """Inside an open transaction, make generation `gen` the map's snapshot; False (its
                rows dropped) if the map was deleted or re-created meanwhile."""
                row = conn.execute("SELECT created_at FROM maps WHERE id = ?", (map_id,)).fetchone()
                if row is None or row[0] != created:  # deleted or re-created meanwhile
                    conn.execute("DELETE FROM tiles WHERE map_id = ? AND gen = ?", (map_id, gen))
                    return False
                conn.execute(
                    "UPDATE maps SET snapshot_gen = ?, snapshot_journal_id = MAX(snapshot_journal_id, ?), "
                    "clock = ?, scans_integrated = ?, scans_rejected = ? WHERE id = ?",
                    (gen, last_id, clock, saved["scans_integrated"], saved["scans_rejected"], map_id),
                )
                # The counters hold every robot the map holds: a robot it forgot to make room for
                # a new one (`MapRegistry._room_for`) goes from storage too. Kept, rows of every
                # robot id the map ever saw piled up, and a restart brought them all back, past
                # `--max-robots-per-map`, into GET /maps/{id}, /metrics and every robots event.
                conn.execute("DELETE FROM robots WHERE map_id = ?", (map_id,))
                conn.executemany(
                    "INSERT INTO robots (map_id, robot_id, state) VALUES (?, ?, ?)",
                    [(map_id, rid, json.dumps(state)) for rid, state in saved["robots"].items()],
                )
                # Their tombstones (`Tombstones.forget`) in the same transaction: the storage holds
                # each forgotten robot's seqs (its row, or journal rows this switch makes dead)
                # until it holds its tombstone, so its cached scans are never integrated twice.
                _bury(conn, saved.get("forgotten", ()))
                conn.execute(
                    "DELETE FROM tiles WHERE map_id = ? AND gen < ? AND EXISTS (SELECT 1 FROM tiles u WHERE "
                    "u.map_id = tiles.map_id AND u.ti = tiles.ti AND u.tj = tiles.tj AND u.gen = ?)",
                    (map_id, gen, gen),
                )
                return True

            def switched(done: Future) -> None:
                """The switch's outcome (True: committed; False: the map was gone; None: not tried,
                a tile row failed; an exception: undone, it failed), told to `written_tiles` once
                this store's own records follow it."""
                try:
                    outcome = done.result()
                    if outcome is None:
                        next(f for f in written if f.exception() is not None).result()  # raises
                    if isinstance(outcome, BaseException):
                        raise outcome
                    if outcome:
                        self._switched(map_id, created, clock, awaiting)
                except BaseException as exc:
                    written_tiles.set_exception(exc)
                else:
                    written_tiles.set_result(len(copies))

            if last:

                def switch_attached(conn: sqlite3.Connection) -> bool | None | Exception:
                    # A row of an earlier transaction failed: this map's generation lacks it. (Rows
                    # in this one failing fail the switch with them.)
                    if any(f.done() and f.exception() is not None for f in written):
                        return None
                    # A savepoint: a switch that fails half-way (a bug, a statement refused) is
                    # undone alone, not committed half-made with the other maps' in this
                    # transaction; raised, anything but an sqlite3.Error ended the writer thread.
                    conn.execute("SAVEPOINT last_snapshot")
                    try:
                        made = switch_rows(conn)
                    except Exception as exc:
                        conn.execute("ROLLBACK TO last_snapshot")  # (raises if SQLite ended it all)
                        conn.execute("RELEASE last_snapshot")
                        return exc
                    conn.execute("RELEASE last_snapshot")
                    if not made:
                        return False
                    # In the switch's transaction, which `_trim_some` may delete a share of them in
                    # too: a transaction that fails forgets every pending trim.
                    self.writer.trim(map_id, last_id)
                    return True

                self.writer.attach_op(switch_attached, map_id=map_id).add_done_callback(switched)
                return written_tiles
            for future in written:
                future.result()  # every row committed before the switch (raises if one failed)

            def switch(conn: sqlite3.Connection) -> bool:
                conn.execute("BEGIN IMMEDIATE")
                if not switch_rows(conn):
                    conn.execute("COMMIT")
                    return False
                conn.execute("COMMIT")
                # The journal rows up to last_id are dead from this commit on; deleting them here
                # held the journal's commits up for 0.3-0.7 s, so the writer deletes them bit by bit.
                self.writer.trim(map_id, last_id)
                return True

            done: Future[object] = Future()
            try:
                done.set_result(self.writer.run(switch))
            except BaseException as exc:  # (told to `written_tiles` by `switched`)
                done.set_exception(exc)
            switched(done)
            if written_tiles.exception() is None:
                self._checkpoint()
            return written_tiles

    def _switched(self, map_id: str, created: float | None, clock: int, awaiting: int | None) -> None:
        """A snapshot of map `map_id` (the incarnation created at `created`) up to store clock `clock`,
        which covers `awaiting` failed journal commits of its scans, is its stored one now."""
        with self._maps_lock:
            # Not if the map was deleted (and created again) since the switch committed:
            # a new map's clock set to the old one's made its next snapshots skip its tiles.
            if self._created.get(map_id) == created:
                self._snapshot_clock[map_id] = clock
                self._rows_since[map_id] = 0
        with self._health_lock:
            self._journal_error = None  # the writer's transactions commit again
            self._snapshot_errors.pop(map_id, None)
            if awaiting is not None and self._awaiting.get(map_id) == awaiting:
                del self._awaiting[map_id]  # no later scan's commit failed meanwhile

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
        """Whether the map has scans a snapshot would make durable: journaled since the last one, or
        applied while the journal failed."""
        return self._rows_since.get(map_id, 0) > 0 or map_id in self._awaiting

    def overdue(self, map_id: str) -> bool:
        return self._rows_since.get(map_id, 0) >= self.snapshot_rows

    @property
    def stopping(self) -> bool:
        """Whether the service stops (`stop_periodic` was called): only its last snapshots are left."""
        return self._stop.is_set()

    def stop_periodic(self) -> None:
        """Stop the periodic snapshots (`start_periodic`), the one under way finished first, and pace
        no snapshot from now on: the service is stopping, and its last snapshots are all that is
        left to do. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def close(self) -> None:
        self.stop_periodic()
        self.restored()
        self.writer.close()
        with contextlib.suppress(sqlite3.Error):
            self._snapshot_conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self._snapshot_conn.close()
        self._dir_lock.release()

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
        self._journal_error = self._failure("journal commit failed", exc, "journal_commit")
