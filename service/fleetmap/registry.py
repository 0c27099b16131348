"""The map registry: every map the service holds, the robots that feed them, and the integration
workers. This is where the service's state lives.

Scans arrive from Zenoh callbacks and REST requests through `submit`, which never blocks: it checks
the robot's sequence number (duplicates are ignored, gaps counted as lost) and puts the scan on a
per-robot FIFO of a `FairQueue`. Worker threads take scans round-robin across robots, one scan of
a robot at a time (so each robot's scans are integrated in order), plan them without any lock and
apply them under the map's lock. When the robot's FIFO is full, the NEWEST scan is refused and
counted as `dropped` (REST callers get 503 and may retry); robots that must not lose scans publish
with Zenoh's blocking congestion control, and the service is sized to keep up.

With a `DurableStore`, each applied scan is journaled under the map's lock (so the journal's order is
the order of application) and counts as integrated (stats, REST answer) only once its journal row is
committed. Viewers see its tiles change at once. Map changes (create, delete, replace) are queued
on the same journal in order, and callers that answer a client (`wait=True`) return only once the
change is committed. A map is deleted or replaced under its lock and the registry's (`_removing`), so
a scan whose map went while it was planned is applied and journaled nowhere, and its caller is told.

What the registry holds of each map and scan (`MapEntry`, `Job`, `IngestRejected`) is in
`map_entry.py`; what it answers a robot's delivery query (`delivery_status`), in `delivery.py`.
"""

from __future__ import annotations

import contextlib
import functools
import heapq
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from typing import NoReturn

from fleetmap import delivery
from fleetmap.codec import DEFAULT_LIMITS, InputLimits, WireScan
from fleetmap.config import MapConfig
from fleetmap.database import StorageError
from fleetmap.export import Window
from fleetmap.fair_queue import FULL_BYTES, FULL_GROUP, FULL_SOURCE, FULL_TOTAL, FairQueue, QueueClosed
from fleetmap.grid_map import GridMap, IntegrationResult, WindowCleared
from fleetmap.map_entry import DEFERRED, SHUTTING_DOWN, Expectation, IngestRejected, Job, MapEntry
from fleetmap.memory_budget import MemoryBudget, MemoryBudgetError, UploadReservation, format_size
from fleetmap.persistence import DurableStore, StoredJournal, unreadable_database
from fleetmap.rate_limited_log import RateLimitedLog
from fleetmap.robot_state import CONFLICT_SHOWN, NO_SESSION, RobotState, session_key
from fleetmap.scan import Scan, ScanError
from fleetmap.storage_format import cleared_window_to_blob, scan_to_blob
from fleetmap.tiles import TileLimitError, layer_arrays, slot_bytes
from fleetmap.tombstones import Tombstone, Tombstones
from fleetmap.unmapped_refusals import UnmappedRefusals
from fleetmap.wire import DeliveryStatus, is_valid_id

log = logging.getLogger("fleetmap.registry")

#: Scans the ingest queue holds per robot: a whole `ScanPublisher` backlog (1000 by default), which a
#: robot's recovered scans arrive as, at network speed, after a dead zone or a restart of the service.
QUEUE_PER_ROBOT = 1024
#: Scans the ingest queue holds in all; one map holds at most half (`FairQueue`'s `per_group`):
#: eight robots of one map recovering a full backlog at once.
QUEUE_TOTAL = 16384
#: Bytes of decoded beams the ingest queue holds at most, whatever the counts allow: 16384 scans of
#: 1081 beams would take 283 MB (17.3 KB each), so this bound comes first with them (some 15,500
#: fit), and as many of 16,384 beams would take 4.3 GB, which the memory budget does not see.
QUEUE_BYTES = 256 << 20
#: Seconds a map change made with `wait=True` waits to be committed before `NotDurable` is raised.
DURABLE_WAIT = 30.0
#: Seconds between progress lines while a map's journal is replayed at start.
RESTORE_REPORT = 5.0


class MapNotFound(KeyError):
    def __str__(self) -> str:
        return f"no map {self.args[0]!r}"


class MapConflict(ValueError):
    """PUT of a configuration that differs from an existing map's."""


class InvalidId(ValueError):
    pass


class NotDurable(Exception):
    """A map change took effect in memory but was not committed to storage (in time)."""


def _failure_site(exc: BaseException) -> str:
    """An exception's kind and where it was raised (`KeyError@/path/file.py:123`): what tells one
    bug from another, for rate-limiting their tracebacks."""
    where = exc.__traceback__
    while where is not None and where.tb_next is not None:
        where = where.tb_next
    if where is None:
        return type(exc).__name__
    return f"{type(exc).__name__}@{where.tb_frame.f_code.co_filename}:{where.tb_lineno}"


class MapRegistry:
    """All maps, their robots and the integration workers."""

    def __init__(
        self,
        default_config: MapConfig | None = None,
        auto_create: bool = True,
        workers: int = 2,
        queue_per_robot: int = QUEUE_PER_ROBOT,
        queue_total: int = QUEUE_TOTAL,
        queue_bytes: int = QUEUE_BYTES,
        on_integrated: Callable[[MapEntry, Job, IntegrationResult, float], None] | None = None,
        durable: DurableStore | None = None,
        max_auto_maps: int = 256,
        max_robots_per_map: int = 1024,
        memory_budget: MemoryBudget | None = None,
        input_limits: InputLimits = DEFAULT_LIMITS,
    ) -> None:
        self.default_config = default_config or MapConfig()
        self.auto_create = auto_create
        self.maps: dict[str, MapEntry] = {}
        self.lock = threading.RLock()  # guards `maps` and every RobotState / counter
        # Sources are (map, robot); one map holds at most half the queue, so a sender flooding it
        # under many robot ids leaves room for every other map's robots.
        self.queue: FairQueue[tuple[str, str], Job] = FairQueue(
            queue_per_robot, queue_total, group=lambda source: source[0], per_group=max(1, queue_total // 2),
            size_of=_queued_bytes, max_bytes=queue_bytes,
        )  # fmt: skip
        # Generations name a map's incarnation beyond this process: a tile's ETag holds it, and a
        # browser revalidates a tile cached before a restart. Counting from 1 again, a map deleted and
        # created again before the restart came back with the old map's generation (and, changed as
        # often, its tile versions): the old map's cached tile got 304. Taken from the microseconds
        # since the epoch, a process's generations are above every earlier one's, unless it made
        # more than a million maps a second. A map's change versions start at its generation too,
        # for the event ids a reconnecting client sends back (`ChangeFeed`), so a generation is also
        # above every change version a map removed before it gave (`_next_generation`).
        self._last_generation = 0
        #: The highest change version of the maps removed so far (`_retire`): the next map starts above.
        self._removed_versions = 0
        #: Called as `on_integrated(entry, job, result, seconds)` for each scan once it counts as
        #: integrated (journaled, with persistence), on that thread; it must be quick and not raise.
        #: The REST app's metrics set it when the registry was built without one.
        self.on_integrated = on_integrated
        self.durable = durable
        #: Every map's tiles are charged to it (`TileStore.charge`); None: no limit, nothing counted.
        self.memory_budget = memory_budget
        # Scans create maps, so scans with made-up map ids could create them without end: past this
        # many maps, only PUT /maps/{id} creates one.
        self.max_auto_maps = max_auto_maps
        # Likewise for robot ids: a sender cycling through ids must not grow state (or logs) at will.
        self.max_robots_per_map = max_robots_per_map
        #: What the service accepts of a robot's scan (`serve --world-bound`, `--max-beams`,
        #: `--max-range`): every way in (Zenoh, REST, ROS 2) decodes and checks scans against it.
        self.input_limits = input_limits
        #: (map id, robot id) of every liveliness token present (`set_online`), whether or not its map
        #: exists: a map created or installed under that id later shows those robots online at once.
        self._alive: set[tuple[str, str]] = set()
        #: The robots of deleted and replaced maps, so that copies of their old scans (a robot's cache,
        #: fetched after a restart) and their tokens do not bring those maps back.
        self.tombstones = Tombstones()
        #: Scans refused for want of their map, or of room on it (`_refuse_unmapped`), for the
        #: delivery query.
        self.unmapped = UnmappedRefusals(self._alive)
        # One line per robot per CONFLICT_SHOWN while its id conflict goes on (a scan of each says so).
        self._conflict_log = RateLimitedLog(log, interval=CONFLICT_SHOWN)
        # Maps created by a scan and removed again when it is refused: anyone who can publish (a Zenoh
        # peer) can do that with every scan under a new map id, two lines a scan, hundreds a second;
        # now at most 20 lines per LOG_INTERVAL in all.
        self._auto_map_log = RateLimitedLog(log)
        # A failing disk fails every map's snapshot at every interval: with 200 maps, 200 lines each
        # `--snapshot-interval` (and 30 maps at 0.5 s: 128 lines in 5 s), while the journal's own
        # failures were already one line per LOG_INTERVAL. One category for all maps: one line per
        # LOG_INTERVAL names a map and counts the others; /healthz lists them all.
        self._snapshot_log = RateLimitedLog(log)
        # Integrations that raised (bugs): one traceback per kind and place every 5 s.
        self._bug_log = RateLimitedLog(log)
        # Robots' scans their map refused at integration (past max_tiles, the memory budget): one
        # line per robot every 5 s, as the ingest logs the refusals before integration.
        self._refusal_log = RateLimitedLog(log)
        self._workers = [
            threading.Thread(target=self._work, name=f"fleetmap-integrate-{k}", daemon=True)
            for k in range(workers)
        ]
        self._started = False
        #: Set by `close` under the lock: `submit` then takes nothing (see there).
        self._closing = False

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> None:
        """Restore durable maps (snapshot + journal replay), then start the workers and snapshots."""
        if self._started:
            return
        self._started = True
        if self.durable is not None:
            self._restore()
            self.durable.start_periodic(self.snapshot_all)
        for t in self._workers:
            t.start()

    def close(self, timeout: float = 30.0) -> tuple[str, ...]:
        """Stop taking scans, finish the queued ones, stop the workers, snapshot every map with
        something unsaved (also one with no scan since its last snapshot: its robots' counters of
        refused messages may have changed, and only a snapshot keeps them: `_unsaved`). A scan
        submitted from now on is refused without a trace (`submit`). Returns the maps storage failed
        to keep (a durable registry): scans applied while the journal failed that this last snapshot
        could not store either, or a creation, restore or deletion not stored; a restart finds them
        as they were stored last."""
        with self.lock:  # so that no `submit` sees the registry open and then the queue closed
            self._closing = True
            self.queue.close()
        for t in self._workers:
            if t.is_alive():
                t.join(timeout)
        if self.durable is None:
            return ()
        # Unpaced from here (and a periodic pass under way finished first): no worker needs the cores.
        self.durable.stop_periodic()
        # Not `every_map`: a map with nothing unsaved gains nothing from a snapshot, and each costs a
        # writer round trip and a synced transaction (5,000 idle maps took 27 s to stop).
        self.snapshot_all(False, last=True)
        self.durable.close()
        health = self.durable.health()
        return tuple(sorted({*health.maps_awaiting_snapshot, *health.map_changes_not_stored}))

    def _restore(self) -> None:
        """Restore every stored map (`DurableStore.load`) and replay its journal. The log says how
        far it is every `RESTORE_REPORT` seconds, in the maps and in a long journal, and ends with
        one line of totals: a line per map made 5,000 lines of a start with 5,000 maps (a map whose
        replay took that long still gets its own line). A map that cannot be restored stops the
        start with a `StorageError` naming it."""
        assert self.durable is not None
        self.tombstones = Tombstones(self.durable.load_tombstones(), now=time.time())
        started = last_report = time.monotonic()
        tiles = replayed = 0
        try:
            stored = self.durable.load()
            for restored, (map_id, gmap, counters, journal) in enumerate(stored):
                if time.monotonic() - last_report >= RESTORE_REPORT:
                    last_report = time.monotonic()
                    log.info(
                        "restoring maps: %d of %d restored (%.0f s)",
                        restored, len(stored), last_report - started,
                    )  # fmt: skip
                before = last_report
                last_report = self._restore_map(map_id, gmap, counters, journal, last_report)
                tiles += len(gmap.store)
                replayed += len(journal)
                # At debug level, unless its replay reported progress: the line ends what those began.
                level = logging.INFO if last_report != before else logging.DEBUG
                log.log(
                    level, "restored map %s: %d tiles, %d journal scans replayed", map_id, len(gmap.store),
                    len(journal), extra={"map_id": map_id},
                )  # fmt: skip
        finally:
            self.durable.restored()
        log.info(
            "restored %d map(s) in %.1f s: %d tiles, %d journal scans replayed",
            len(stored), time.monotonic() - started, tiles, replayed,
        )  # fmt: skip

    def _restore_map(
        self, map_id: str, gmap: GridMap, counters: dict, journal: StoredJournal, last_report: float
    ) -> float:
        """Restore one stored map: its saved counters, its journal replayed through the registry's
        bookkeeping, and the map added. `last_report`: when the log last said how far the restore
        is; returns it as this map leaves it."""
        assert self.durable is not None
        entry = MapEntry(map_id, gmap, self._next_generation())
        entry.scans_integrated = counters["scans_integrated"]
        entry.scans_rejected = counters["scans_rejected"]
        entry.robots = counters["robots"]
        entry.unjournaled_stored = entry.unjournaled()  # as stored: no snapshot due for them
        entry.robots_stored = frozenset(entry.robots)
        started = time.monotonic()
        for replayed, (robot_id, seq, stamp, session, refused, row) in enumerate(journal):
            try:
                self._replay(gmap, row)
            except (TileLimitError, ValueError) as exc:
                # The engine applied every journaled row once; one it refuses now (its map's
                # configuration edited or damaged since: a lower max_tiles) is a damaged database,
                # which stopped the start with a traceback.
                raise unreadable_database(
                    self.durable.path, map_id, f"journal scan {replayed + 1} of {len(journal)}: {exc}"
                ) from None
            if time.monotonic() - last_report >= RESTORE_REPORT:
                # 20,000 scans take 10-20 s: say the service is busy, not stuck.
                last_report = time.monotonic()
                log.info(
                    "restoring map %s: %d of %d journal scans replayed (%.0f s)",
                    map_id, replayed, len(journal), last_report - started, extra={"map_id": map_id},
                )  # fmt: skip
            if isinstance(row, Window):  # a window cleared (`clear_window`): no robot's scan
                continue
            scan = row
            robot = entry.robot(robot_id)
            robot.scans_integrated += 1
            # The journal holds integrated scans only, so a gap in a robot's seqs since the
            # snapshot is counted as lost, as `submit` counted it (scans refused or dropped in
            # the gap, whose counts died with the process, count as lost too), and a seq that
            # is not new was a restart; sessions interleaving were an id conflict, seen now.
            # A row the robot's saved bookkeeping already holds (accepted before the snapshot,
            # applied after it) is a duplicate to it: counted once, when it was accepted. The
            # scans of its session refused before it that the row names are counted refused first.
            for refused_seq, resend in refused:
                if session is not None:  # (only rows of scans with a session id name them)
                    robot.replay_refusal(refused_seq, stamp, session, resend, time.time())
            if not robot.is_duplicate(seq, stamp, session):
                robot.accept(seq, stamp, session, time.time())
                ledger = robot.sessions[session_key(session)].ledger
                ledger.settle(ledger.open(seq), integrated=True)
            robot.last_stamp = stamp
            robot.add_pose(scan.pose)
            # Heard after the snapshot (whose counters hold every older `last_heard`), in journal
            # order: the robots that go first below are the ones heard from least recently.
            robot.last_heard = time.time()
            entry.scans_integrated += 1
        # A database written before forgotten robots were deleted from it holds every robot the
        # map ever saw, and robots first heard since the snapshot add to its robots: the map
        # holds at most `max_robots_per_map`, as `_room_for` keeps it while the service runs.
        self._forget_idle(entry, len(entry.robots) - self.max_robots_per_map)
        # Charged after the replay, which the budget must never refuse: those scans were accepted.
        self._charged(gmap)
        # Its bounds read every tile once (0.2-0.5 s for a 1 km map of 6,400 tiles): here, before
        # anything is served, rather than under the map's lock in the first GET /maps/{id}.
        gmap.known_bounds()
        self._add(entry)
        return last_report

    @staticmethod
    def _replay(gmap: GridMap, row: Scan | Window) -> None:
        """Apply one journal row to `gmap` as it was applied when it was journaled: a window cleared
        (`clear_window`), or a scan (the same engine, in journal order: the same map)."""
        if isinstance(row, Window):
            gmap.clear_window(row.i0, row.j0, row.i1, row.j1)
        else:
            gmap.integrate(row)

    def _charged(self, gmap: GridMap) -> GridMap:
        """`gmap`, its store charged to the memory budget unless it is already (an upload's map,
        charged with its reservation: `upload_reservation`)."""
        if self.memory_budget is not None and gmap.store.budget is None:
            gmap.store.charge(self.memory_budget)
        return gmap

    @contextlib.contextmanager
    def upload_reservation(self, replacing: MapEntry | None) -> Iterator[UploadReservation | None]:
        """The memory budget's room for an upload's map (None without a budget), for the reader to
        `charge` its map's store with before it allocates the tiles, and for `replace` to install;
        released on leaving, whatever ended the upload, unless it was installed. `replacing`: the
        map the upload replaces as it was looked up (None: none), whose bytes count as free for
        it (`MemoryBudget.reserve_replacing` says why that holds if it is replaced or grows
        meanwhile)."""
        if self.memory_budget is None:
            yield None
            return
        reservation = UploadReservation(
            self.memory_budget, None if replacing is None else replacing.gmap.store
        )
        try:
            yield reservation
        finally:
            reservation.release()

    def snapshot_all(self, only_overdue: bool = False, every_map: bool = False, last: bool = False) -> None:
        """Snapshot every map with journaled scans, and at a full pass (not `only_overdue`) every map
        with counts or tombstones only a snapshot stores (`_unsaved`); only those past the row
        threshold if `only_overdue`; every map with `every_map`. A map whose snapshot fails (a full
        or failing disk) is logged and reported by `DurableStore.health`, and the others are still
        snapshotted. `last`: the registry is closing, and a failed snapshot is not retried (its line
        says so); any other pass ends, with the snapshot under way, once the registry closes."""
        if self.durable is None:
            return
        # The last pass queues every map's snapshot before it waits for any (`last_snapshot`).
        taken: list[tuple[MapEntry, list[tuple[dict, int]], Future[int]]] = []
        for entry in self.list():
            if not last and self.durable.stopping:
                # The stop waits for this pass (`stop_periodic`), then its own takes the maps left,
                # in shared transactions: one synced snapshot after another here, a stop during the
                # first pass after a crash restore of 5,000 maps took 52 s.
                return
            # Refusals, duplicates and drops are journaled nowhere: only a snapshot stores their
            # counts (and a forgotten robot's tombstone). Checked at the full passes only, which the
            # refusals alone make due: a map whose robots' scans were all refused since its last
            # snapshot was never snapshotted, and a crash hours later took their counts along.
            unsaved = not only_overdue and self._unsaved(entry)
            needed = self.durable.needs_snapshot(entry.id) or unsaved
            if every_map or (needed and (not only_overdue or self.durable.overdue(entry.id))):
                saved: list[tuple[dict, int]] = []  # what the snapshot stores of the map's robots
                counters = functools.partial(self._saved_counters, entry, saved)
                # Listed above, perhaps seconds ago (each snapshot takes its time): the map may have
                # been deleted or replaced since, and a new map of its id must not get its snapshot.
                current = functools.partial(self._is_current, entry)
                if last:
                    taken.append(
                        (entry, saved, self.durable.last_snapshot(entry.id, entry.gmap, counters, current))
                    )
                else:
                    self._snapshot_stored(entry, saved, functools.partial(
                        self.durable.snapshot, entry.id, entry.gmap, counters, current
                    ), last)  # fmt: skip
        if last:  # (`taken` holds the last pass's snapshots, queued above)
            self.durable.last_snapshots_queued()
            for entry, saved, written in taken:
                self._snapshot_stored(entry, saved, written.result, last)
            # The failures held back after the first one's line (a full disk fails every map's):
            # no later line of theirs would count them, the service is stopping.
            self._snapshot_log.log_held(
                logging.ERROR,
                "%d more snapshot failures at the stop, not logged one by one (the last line names the "
                "maps storage failed to keep)",
            )

    def _snapshot_stored(
        self, entry: MapEntry, saved: list[tuple[dict, int]], written: Callable[[], int], last: bool
    ) -> None:
        """Wait for a snapshot of map `entry` (`written()`, raising its failure) whose counters are
        `saved` (`_saved_counters`): what it stored is pending no more; a failure is logged."""
        try:
            written()
            if saved:
                stored, unjournaled = saved[0]
                self._stones_stored(entry, stored["forgotten"])
                entry.unjournaled_stored = unjournaled
                entry.robots_stored = frozenset(stored["robots"])
        except (sqlite3.Error, OSError, StorageError) as exc:
            then = "the last one: the service is stopping" if last else "retried at the next one"
            self._snapshot_log.error(
                "snapshot", f"snapshot of map {entry.id} failed ({then}): {exc}", map_id=entry.id
            )

    def _current(self, entry: MapEntry) -> MapEntry | None:
        """The map of `entry`'s id now: `entry` itself while it is not retired, else the map that
        replaced it, or None. Called under the map's lock (`clear_window`): the registry's comes
        second, the one order they nest in."""
        if not entry.retired:
            return entry
        with self.lock:
            return self.maps.get(entry.id)

    def _is_current(self, entry: MapEntry) -> bool:
        """Whether `entry` is still the map of its id (not deleted or replaced). Called under the
        map's lock (`DurableStore.snapshot`): the registry's comes second, the one order they nest in."""
        with self.lock:
            return self.maps.get(entry.id) is entry

    def _unsaved(self, entry: MapEntry) -> bool:
        """Whether map `entry` holds what only a snapshot stores and its last one did not: scans
        counted without a journal row (`MapEntry.unjournaled`), the tombstones of robots it
        forgot (`MapEntry.unstored_stones`; a robot's token can make a full map forget one, with no
        scan at all), or robots it does not hold (`MapEntry.robots_stored`: one that only its
        liveliness token made was forgotten by every restart, its `fleetmap_robot_online` with it)."""
        with self.lock:
            return (
                entry.unjournaled() != entry.unjournaled_stored
                or bool(entry.unstored_stones)
                or not entry.robots_stored.issuperset(entry.robots)
            )

    def _saved_counters(self, entry: MapEntry, taken: list[tuple[dict, int]]) -> dict:
        """What a snapshot of map `entry` stores of its robots (and appends to `taken`, with its
        `MapEntry.unjournaled` then): their
        counters, and the tombstones of the robots it forgot that storage does not hold yet, those
        `self.tombstones` still holds: the others were pruned (`MAX_TOMBSTONES`, `TOMBSTONE_DAYS`),
        and kept here while snapshots failed (a failing disk), they piled up without bound, one per
        robot id a sender cycled through into the full map."""
        with self.lock:
            held = self.tombstones.get
            entry.unstored_stones = {
                rid: stone for rid, stone in entry.unstored_stones.items() if held(entry.id, rid) is stone
            }
            saved = {
                "scans_integrated": entry.scans_integrated,
                "scans_rejected": entry.scans_rejected,
                "robots": {rid: state.saved() for rid, state in entry.robots.items()},
                "forgotten": list(entry.unstored_stones.values()),
            }
            taken.append((saved, entry.unjournaled()))
        return saved

    def _stones_stored(self, entry: MapEntry, stones: list[Tombstone]) -> None:
        """A snapshot of map `entry` stored `stones` (its `_saved_counters`): not pending any more,
        unless its robot was forgotten again since (a newer stone, stored by the next snapshot)."""
        with self.lock:
            for stone in stones:
                if entry.unstored_stones.get(stone.robot_id) is stone:
                    del entry.unstored_stones[stone.robot_id]

    # -- maps ------------------------------------------------------------------------------------

    def create(
        self,
        map_id: str,
        config: MapConfig | None = None,
        wait: bool = False,
        by_scan: bool = False,
        expect: Expectation | None = None,
    ) -> tuple[MapEntry, bool]:
        """Create a map, or return the existing one if its configuration is the same
        (`MapConfig.same_map_as`: its layers in any order, a preset as its values).
        Returns (entry, created). Raises MapConflict for a different configuration, and
        MemoryBudgetError, nothing made, for a new map of a `config` given whose one tile needs more
        than the whole memory budget (`MemoryBudget.check_tile`; the default configuration, which
        scans and robots' tokens create maps of, is warned of at start instead). With `wait`, the
        map, new or found, is committed to storage before this returns (else NotDurable). `by_scan`: created
        for a scan (auto-create), its log line rate-limited. `expect(existing)` is called with the
        map of that id (None if none) under the registry's lock before anything changes: whatever it
        raises propagates with nothing changed (a conditional write's precondition)."""
        _check_id("map id", map_id)
        given, config = config, config or self.default_config
        stored = None
        with self.lock:
            existing = self.maps.get(map_id)
            if expect is not None:
                expect(existing)
            if existing is None and given is not None and self.memory_budget is not None:
                tile = slot_bytes(given.tile_size, layer_arrays(given.layers))
                self.memory_budget.check_tile(tile, f"map {map_id!r} was not made")
            if existing is not None:
                differences = existing.config.differences(config)
                if differences:
                    raise MapConflict(
                        f"map {map_id!r} exists with a different configuration (the map's "
                        f"{'; '.join(differences)}); delete it first"
                    )
                existing.provisional = False  # asked for by name: it stays even if its scans are refused
                if wait and self.durable is not None:
                    # Answered once the map is stored, as the PUT that created it is: its creation may
                    # still wait for the journal writer (a concurrent PUT's, a robot's first scan's),
                    # or have failed (a client retrying after a 503: retried now).
                    stored = self.durable.map_stored(map_id)
                entry, created = existing, False
            else:
                entry = MapEntry(map_id, self._charged(GridMap(config)), self._next_generation())
                self._add(entry)
                if self.durable is not None:
                    stored = self.durable.map_created(map_id, entry.gmap)  # queued before any of its scans
                if by_scan:
                    self._auto_map_log.log(
                        logging.INFO, f"created:{map_id}", f"created map {map_id}", map_id=map_id
                    )
                else:
                    log.info("created map %s", map_id, extra={"map_id": map_id})
                created = True
        if wait:
            _wait_stored(stored, f"map {map_id!r} was created" if created else f"map {map_id!r} exists")
        return entry, created

    def replace(
        self,
        map_id: str,
        gmap: GridMap,
        wait: bool = False,
        expect: Expectation | None = None,
        reservation: UploadReservation | None = None,
    ) -> MapEntry:
        """Install `gmap` (an uploaded snapshot or nav2 map) as map `map_id`, replacing any map of
        that id (whose entry then points to the new one: `MapEntry.replaced_by`). With `wait`, it is
        committed to storage before this returns (else NotDurable). `expect` as for `create`, called
        with the map being replaced (None if none) under its lock and the registry's. `reservation`:
        the upload's (`upload_reservation`), whose bytes become the map's charge; MemoryBudgetError,
        nothing changed, if it was released meanwhile (the request was cancelled). Without one,
        `gmap` is charged what it holds, even past the limit."""
        _check_id("map id", map_id)
        # Its tiles are encoded here, before the lock: no one else sees `gmap` yet, and a big map
        # takes seconds, during which scans and every other request need the lock.
        tiles = self.durable.tile_rows(gmap) if self.durable is not None else []
        gmap.known_bounds()  # (likewise: every tile read once, which the first GET would do under the lock)
        stored = None
        with self._removing(map_id) as old:
            if expect is not None:
                expect(old)
            if reservation is not None:
                reservation.install(gmap.store)  # the last step that may refuse: nothing changed yet
            dropped = self._retire(old) if old is not None else []
            # The old map's robots' cached scans must not go into the upload either.
            buried = self._bury(old) if old is not None else []
            entry = MapEntry(map_id, self._charged(gmap), self._next_generation())
            self._add(entry)
            if old is not None:
                old.replaced_by = entry
            if self.durable is not None:
                stored = self.durable.map_created(map_id, gmap, tiles, buried=buried)
        for job in dropped:
            self._finish_gone(job)
        log.info(
            "installed map %s from an upload (%d tiles)", map_id, len(gmap.store), extra={"map_id": map_id}
        )
        if wait:
            _wait_stored(stored, f"map {map_id!r} was installed")
        return entry

    def get(self, map_id: str) -> MapEntry:
        with self.lock:
            entry = self.maps.get(map_id)
        if entry is None:
            raise MapNotFound(map_id)
        return entry

    def delete(self, map_id: str, wait: bool = False, expect: Expectation | None = None) -> None:
        """Remove a map and its queued scans (their callers are answered at once: not integrated);
        raises MapNotFound. Waits for the map's lock, so a scan being applied finishes first (a scan
        still being planned is then applied nowhere). With `wait`, the deletion is committed to
        storage before this returns (else NotDurable). `expect` as for `create`, called with the map
        under its lock and the registry's; with None when the map is gone but its deletion is still
        being stored (no map at all: MapNotFound, not `expect`)."""
        stored = None
        with self._removing(map_id) as old:
            if old is None:
                # A client retrying a DELETE it was told was not stored: done once it is.
                stored = self.durable.retry_map_change(map_id) if self.durable is not None else None
                if stored is None:
                    # No map: that answer comes first, whatever the request's conditions (RFC 9110,
                    # 13.2.1: a failure found before the method is processed takes precedence).
                    raise MapNotFound(map_id)
                if expect is not None:
                    expect(None)  # the map this retry removed cannot be compared any more
                dropped = []
            else:
                if expect is not None:
                    expect(old)
                dropped = self._retire(old)
                buried = self._bury(old)
                if self.durable is not None:
                    stored = self.durable.map_deleted(map_id, buried)
        for job in dropped:
            self._finish_gone(job)
        log.info("deleted map %s", map_id, extra={"map_id": map_id})
        if wait:
            _wait_stored(stored, f"map {map_id!r} was deleted")

    def _bury(self, old: MapEntry) -> list[Tombstone]:
        """Bury the robots of map `old`, being deleted or replaced (`Tombstones.bury`), and forget
        their scans refused before they were on it (`UnmappedRefusals.forget`: their tombstones say
        the rest); return the tombstones to store. Call under the registry's lock.

        The robots that waited for it are buried too: those whose scans it refused for want of room
        (or that were refused for want of it before it was made). Left out, after a restart of the
        service the token of a robot the full map had no room for made the deleted map again, and
        the robot's cache, fetched again, put its refused scans from before the deletion in it.
        Their refusals stay remembered: they are what became of those scans (refused, not gone with
        the map). Not those with only a liveliness token on it: any Zenoh peer can declare tokens
        under made-up robot ids without bound, and their stones, a deleted map's, would push out
        the other deleted maps' robots (`MAX_TOMBSTONES`); the robots remembered with refusals are
        bounded (`MAX_UNMAPPED_ROBOTS`)."""
        waiting = self.unmapped.sessions_of(old.id)
        buried = self.tombstones.bury(old.id, old.robots, time.time(), waiting)
        self.unmapped.forget(old.id, old.robots)
        return buried

    @contextlib.contextmanager
    def _removing(self, map_id: str) -> Iterator[MapEntry | None]:
        """Hold map `map_id`'s lock and then the registry's, and yield the map (None if there is none,
        with only the registry's lock held), for the caller to `_retire` it.

        A worker checks `retired` and journals a scan under one hold of the map's lock, and the
        caller queues the map's removal on the journal (`map_deleted`, `map_created`) under both
        locks: so a scan's journal row is either queued before the removal (which then deletes it)
        or not written at all, and no row of a removed map lands after it, where a new map of the
        same id would replay it. The map's lock comes first (the only place where the two nest): a
        worker holds it for a scan's whole apply, and the registry's must not wait that long."""
        while True:
            with self.lock:
                entry = self.maps.get(map_id)
                if entry is None:
                    yield None
                    return
            with entry.gmap.lock, self.lock:
                if self.maps.get(map_id) is entry:
                    yield entry
                    return
            # Replaced while this waited for its lock: try again with the map that is there now.

    def _next_generation(self) -> int:
        """A new map's generation (call under the registry's lock): above every earlier one, above
        the change versions of every map removed before (`_removed_versions`), and at least the
        microseconds since the epoch now, as docs/api.md says of event ids. Counting on from the
        process's start, a map made again after its predecessor's many changes started its versions
        below that one's last: a client resuming with that last id (`Last-Event-ID`) took the new
        map's changes since then as news to the old map it shows, not the reset it needed."""
        now = time.time_ns() // 1000
        self._last_generation = max(self._last_generation + 1, self._removed_versions + 1, now)
        return self._last_generation

    def _retire(self, entry: MapEntry) -> list[Job]:
        """Take map `entry` out of the registry and its queued scans off the queue; return those, for
        the caller to answer with `_finish_gone` once it released the locks. Call it inside
        `_removing` (see there why), or as `_remove_unclaimed` does. The scans are dropped in the
        same registry-lock hold that removes the map: dropped later, the scans of a map created
        again under that id meanwhile would go too; and until then every scan in the queue under
        this map id is of this map."""
        del self.maps[entry.id]
        entry.retired = True
        self._removed_versions = max(self._removed_versions, entry.changes.version)
        # Its bytes go back to the budget now, not once the last reader lets go of the map: a scan
        # sent again after the DELETE that made room was refused 507 while a viewer's event stream
        # still held the map. Retired, it never grows again (no scan is applied to it).
        entry.gmap.store.uncharge()
        return self.queue.drop_source(lambda source: source[0] == entry.id)

    def _remove_unclaimed(self, entry: MapEntry) -> Future | None:
        """Remove map `entry` if it is `provisional` with no scan unsettled: created by a scan, and
        every scan that reached it refused. Call it under the registry's lock, right after counting a
        refusal. Returns None if the map stays, else a Future resolved once the removal is stored
        (at once without storage).

        The map's lock, which `_removing` takes for a DELETE, is not needed: with no scan unsettled
        (and new ones waiting for the registry's lock) no worker holds a scan of this map."""
        if not entry.provisional or entry.unsettled:
            return None
        self._remember_removed(entry)
        self._retire(entry)
        self._auto_map_log.log(
            logging.INFO, f"removed:{entry.id}",
            f"removed map {entry.id} again: every scan that created it was refused", map_id=entry.id,
        )  # fmt: skip
        if self.durable is not None:
            return self.durable.map_deleted(entry.id)
        removed: Future = Future()
        removed.set_result(None)
        return removed

    def clear_window(
        self, entry: MapEntry, window: Window, expect: Expectation | None = None
    ) -> WindowCleared:
        """Forget the cells of `window` in the map of `entry` (`get`; `GridMap.clear_window`: every
        layer back to never-observed there), in order with the map's scans: a scan applied before is
        forgotten there, one applied after observes the cells again. Viewers are told of the changed
        tiles. With storage it is journaled as a scan is, and committed before this returns, so that
        a restart replays it where it happened.

        `expect` as for `create`, called under the map's lock with the map (None if it went since
        `entry` was looked up). Raises `MapConflict` when the map was deleted or replaced since then
        (the window may be another map's cells); `IngestRejected` 503 while the registry closes, or
        when the storage cannot take a cleared window (nothing cleared in either case); `NotDurable`
        when the cells are forgotten in memory but the journal's commit failed (the map's next
        snapshot stores it, unless the service stops first)."""
        map_id = entry.id

        def check() -> None:  # under the map's lock
            if expect is not None:
                # Compared with the map under the id now: one that replaced `entry` since it was looked
                # up is there (its 412 names its ETag), not none.
                expect(self._current(entry))
            if entry.retired:
                raise MapConflict(f"map {map_id!r} was deleted or replaced meanwhile; nothing was cleared")
            if self._closing:  # its row could come after the final snapshot, and the journal's close
                raise IngestRejected(
                    "the service is shutting down: nothing was cleared; send it again once it is back",
                    503, SHUTTING_DOWN,
                )  # fmt: skip

        if self.durable is not None:
            with entry.gmap.lock:
                check()  # a refused request must not raise the layout
            try:  # before anything changes, and without a lock held (it waits for the writer)
                self.durable.allow_cleared_windows()
            except (sqlite3.Error, OSError, StorageError) as exc:
                reason = f"nothing was cleared: the storage cannot take it ({exc})"
                raise IngestRejected(reason, 503) from None
        stored: Future | None = None
        with entry.gmap.lock:
            check()
            cleared = entry.gmap.clear_window(window.i0, window.j0, window.i1, window.j1)
            if cleared.cells and self.durable is not None:
                stored = Future()
                # Under the map's lock, as a scan's row: the journal's order is the order of changes.
                self.durable.journal(
                    map_id, "", 0, time.time(), cleared_window_to_blob(window),
                    lambda _row: stored.set_result(None), stored.set_exception,
                )  # fmt: skip
        if cleared.changed_tiles:
            entry.changes.record(cleared.changed_tiles)  # viewers see the change now
        _wait_stored(stored, f"{cleared.cells} cells of map {map_id!r} were made unknown")
        return cleared

    def list(self) -> list[MapEntry]:
        with self.lock:
            return list(self.maps.values())

    # -- ingest ----------------------------------------------------------------------------------

    def submit(
        self,
        map_id: str,
        robot_id: str,
        wire: WireScan,
        wait: bool = False,
        expect: Expectation | None = None,
        defer_when_full: bool = False,
    ) -> Future | None:
        """Queue a decoded scan for integration, never blocking.

        Returns a Future of the IntegrationResult when `wait`, else None. Raises `InvalidId` for an
        id that is not one, and IngestRejected for a duplicate or a scan from before its map was
        deleted or replaced (status 200: nothing to do), an unknown map without auto-create or past
        `max_auto_maps` (404), a map already holding `max_robots_per_map` robots, none of which can
        be forgotten (429), or a full queue (503). Every refusal is counted on the robot (on the
        map, and for the delivery query, where the scan has no map or no room on it), except one
        while the registry closes (503, kind `SHUTTING_DOWN`): that scan is not taken at all, its
        seq not recorded, so that the next process takes it as new when the robot sends it again (a
        `ScanPublisher`'s cache does).
        A map this creates is `provisional`: it is removed again if the scan is refused here or later
        (and no other scan reached it meanwhile). `expect` as for `create`, called with the map (None
        if there is none and the scan would make it) before anything is counted or changed: whatever
        it raises propagates, the scan taken nowhere (a REST scan's precondition).
        `defer_when_full`: a scan its caller can fetch again (from its publisher's cache:
        `backlog_refetch.py`) that the full queue would refuse is not taken at all, as one while the
        registry closes: its seq not recorded, nothing counted (503, kind `DEFERRED`), so that it is
        new when it comes again, and the caller offers it again once the queue has room.
        """
        _check_id("map id", map_id)
        _check_id("robot id", robot_id)
        with self.lock:
            if self._closing:
                # Not a full queue: counted as one, the seq was recorded as accepted and settled as
                # refused, the closing snapshot saved it so, and the next process refused the robot's
                # cache re-sending it as a duplicate: gone for good (tests/test_crash_exactly_once.py
                # lost 56 scans of a robot so, at a SIGTERM during a cache fetch). Zenoh runs scan
                # callbacks for a moment after the ingest's session closed.
                raise IngestRejected("the service is shutting down: scan not taken", 503, SHUTTING_DOWN)
            entry = self.maps.get(map_id)
            # Not for a scan refused for want of its map (404): an answer that would not have been
            # a success comes before the preconditions (RFC 9110, 13.2.1), as for DELETE /maps/{id}.
            if expect is not None and (entry is not None or self._creates_maps()):
                expect(entry)
            stone = self._covered(map_id, entry, robot_id, wire.session, wire.seq, wire.stamp)
            if stone is not None:
                robot = entry.robots.get(robot_id) if entry is not None else None
                if robot is not None:
                    robot.duplicates += 1
                raise IngestRejected(_covered_reason(stone, wire), 200)
            if entry is None:
                if not self.auto_create:
                    self._refuse_unmapped(map_id, robot_id, wire, f"no map {map_id!r} (auto-create is off)")
                if len(self.maps) >= self.max_auto_maps:
                    # The limit said as such: "holds 300 maps, the most scans may create" (maps made
                    # with PUT count too) named a number that was not the limit.
                    self._refuse_unmapped(
                        map_id, robot_id, wire,
                        f"no map {map_id!r}, and the service already holds {len(self.maps)} maps: scans "
                        f"create a map only while it holds fewer than {self.max_auto_maps}; create it "
                        "with PUT /maps/{id}",
                    )  # fmt: skip
                entry, _ = self.create(map_id, by_scan=True)
                entry.provisional = True
            if not self._room_for(entry, robot_id):
                entry.scans_rejected += 1  # counted on the map: the robot has no state to count it on
                reason = f"map {map_id!r} already has {len(entry.robots)} robots, the most it may have"
                self._refuse_unmapped(map_id, robot_id, wire, reason, 429)
            robot = entry.robot(robot_id)
            robot.last_heard = now = time.time()
            seq, stamp, session = wire.seq, wire.stamp, wire.session
            if robot.is_duplicate(seq, stamp, session):
                seqs = robot.count_duplicate(session)
                raise IngestRejected(f"duplicate seq {seq} (last accepted {seqs.last_seq})", 200)
            job = Job(map_id, robot_id, wire, entry.generation, time.monotonic())
            if defer_when_full and (full := self.queue.refusal((map_id, robot_id), job)) is not None:
                # Nothing recorded: it comes again from its publisher's cache, new then.
                reason = f"ingest queue full: scan deferred ({self._queue_full(full, map_id)})"
                self._remove_unclaimed(entry)
                raise IngestRejected(reason, 503, DEFERRED)
            # Recorded before the queue is tried so a dropped scan is not also counted as lost.
            if robot.accept(seq, stamp, session, now):
                self._conflict_log.warning(
                    f"id conflict {map_id}/{robot_id}",
                    f"robot id conflict on map {map_id!r}: scans of {robot_id!r} come from more than one "
                    "publisher session at once (two robots publishing under one id?); the scans of each "
                    f"are integrated, see id_conflict in GET /maps/{map_id}",
                    map_id=map_id,
                    robot_id=robot_id,
                )
            job.receipt = robot.sessions[session_key(session)].ledger.open(seq)
            if wait:
                job.future = Future()
            full = self.queue.offer((map_id, robot_id), job)
            if full is not None:
                self._settle(job, integrated=False)
                robot.dropped += 1
                robot.note_refused(seq, session)  # a retry of it is not a duplicate
                reason = f"ingest queue full: scan dropped ({self._queue_full(full, map_id)})"
                robot.last_error = f"scan seq {seq}: {reason}"
                if self._remove_unclaimed(entry) is not None:
                    reason += f"; map {map_id!r}, created for it, was removed again"
                raise IngestRejected(reason, 503)
            entry.unsettled += 1
            robot.unsettled += 1
            return job.future

    def _covered(
        self, map_id: str, entry: MapEntry | None, robot_id: str, session: int | None, seq: int, stamp: float
    ) -> Tombstone | None:
        """The tombstone that makes the scan `seq` (of `stamp`, of publisher session `session`) of
        robot `robot_id` on map `map_id` (`entry`, None: none now) a copy of one from before the map
        went or forgot the robot (`Tombstones.covers`), or None (call under the registry's lock).
        Without a session id, once the robot has a scan without one on the map (it went on, or
        started its sequence again, past the tombstone), a seq past the map's last of them is new,
        as it would be had the map never gone: the tombstone's, still at the old run's seq, took the
        new run's next scans for copies. A seq not past it the tombstone still tells: the map's own
        bookkeeping takes a copy of seq 0 for a restart (its run has no seq 0 of its own to tell a
        copy by), and a robot's cache fetched again begins with one: it and every copy after it
        were integrated into the new map."""
        if session is None and entry is not None:
            robot = entry.robots.get(robot_id)
            plain = robot.sessions.get(NO_SESSION) if robot is not None else None
            if plain is not None and seq > plain.last_seq:
                return None
        return self.tombstones.covers(map_id, robot_id, session, seq, stamp)

    def _queue_full(self, full: str, map_id: str) -> str:
        """Which bound of the ingest queue refused a scan of map `map_id` (`FairQueue.offer`'s
        `full`), for its reason: "ingest queue full" alone did not say whether the robot sends
        faster than it is integrated, or other robots (of its map, or of all maps) fill the queue."""
        queue = self.queue
        if full == FULL_SOURCE:
            return f"the robot's queue holds {queue.per_source} scans waiting"
        if full == FULL_GROUP:
            return f"map {map_id!r}'s share of the queue, {queue.per_group} scans of all its robots, is full"
        if full == FULL_TOTAL:
            return f"the queue holds {queue.total} scans of all maps' robots waiting"
        if full == FULL_BYTES:
            return f"the queue holds {format_size(queue.max_bytes)} of all maps' scans waiting"
        return "the queue is closed"

    def _refuse_unmapped(
        self, map_id: str, robot_id: str, wire: WireScan, reason: str, status: int = 404
    ) -> NoReturn:
        """Refuse a scan for want of its map (404), or of room for its robot on it (429): remember
        it for the delivery query (`UnmappedRefusals`), then raise IngestRejected. Call under the
        registry's lock."""
        self.unmapped.remember(map_id, robot_id, wire.seq, wire.session, reason)
        raise IngestRejected(reason, status)

    def _remember_removed(self, entry: MapEntry) -> None:
        """Map `entry`, created by scans that were all refused, is being removed again
        (`_remove_unclaimed`): remember its robots' sessions for the delivery query, as scans
        refused for want of a map are (`UnmappedRefusals`). Their ledgers go with the map, and the query
        answered `no_map` and nothing of them: a flush waited for ever for scans the service had
        refused (its memory budget used up, its queue full). Every session the robot knows, those
        pushed out of its recent ones too (more robots under one id than `MAX_SESSIONS`): with the
        recent ones only, the others' flushes, told `no_map` alone, waited until their timeout. Call
        under the registry's lock."""
        for robot_id, robot in entry.robots.items():
            for key, seqs in robot.every_session():
                ledger = seqs.ledger
                if key != NO_SESSION and ledger.first_seq is not None and ledger.refused:
                    reason = robot.last_error or "refused"
                    self.unmapped.remember(
                        entry.id, robot_id, ledger.first_seq, key, reason, seqs.last_seq, ledger.refused
                    )

    def reject(
        self, map_id: str, robot_id: str, reason: str, scan_id: tuple[int, float, int | None] | None = None
    ) -> None:
        """Count a message that could not be decoded, or that broke the input limits, on its robot if
        the ids are valid (and its map exists: a refused scan creates none; without its map, or room
        on it, a scan with a `scan_id` and a session id is remembered for the delivery query).

        `scan_id`, the (seq, stamp, session) of a message read that far (`codec.DecodeError.scan_id`)
        with a session id, settles that scan as refused in its session's ledger, its seq recorded as
        accepted, as a scan the full queue drops is: otherwise the next seq counted it as lost
        ("never reached the service"), and the last scan of a session was never settled, so a
        robot's `flush` waited for it until its timeout (for ever without one). A copy of a scan
        already counted (its seq not new: the cache fetched again after a restart) is a duplicate,
        as `submit` counts it. Scans without a session id keep to the rule of undecodable ones (their
        seq is not recorded): their seq bookkeeping is one that every sender without a session id on
        the robot's key shares, which a refused message (garbage, as likely as not) must not move."""
        if not (is_valid_id(map_id) and is_valid_id(robot_id)):
            return
        with self.lock:
            entry = self.maps.get(map_id)
            stone = None
            if scan_id is not None:
                stone = self._covered(map_id, entry, robot_id, scan_id[2], scan_id[0], scan_id[1])
            if stone is not None:
                # A copy of a scan from before its map went (or its robot was forgotten): ignored as
                # `submit` ignores one, first. Remembered as a robot's without a map, it hid the
                # tombstone's "in no map now" of the session's other scans from the delivery query
                # (a flush never settled); on a full map it made an idle robot be forgotten for it.
                robot = entry.robots.get(robot_id) if entry is not None else None
                if robot is not None:
                    robot.duplicates += 1
                return
            if entry is None or not self._room_for(entry, robot_id):
                if entry is not None:
                    entry.scans_rejected += 1  # counted on the map only: no new robot for garbage
                if scan_id is not None:  # for the delivery query: its robot's flush would wait for ever
                    self.unmapped.remember(map_id, robot_id, scan_id[0], scan_id[2], reason)
                return
            robot = entry.robot(robot_id)
            robot.last_heard = now = time.time()
            if scan_id is not None and scan_id[2] is not None:
                seq, stamp, session = scan_id
                if robot.is_duplicate(seq, stamp, session):
                    robot.count_duplicate(session)
                    return
                robot.accept(seq, stamp, session, now)
                ledger = robot.sessions[session_key(session)].ledger
                ledger.settle(ledger.open(seq), integrated=False)
            robot.scans_rejected += 1
            robot.last_error = reason
            entry.scans_rejected += 1

    def _room_for(self, entry: MapEntry, robot_id: str) -> bool:
        """Whether map `entry` may hold robot `robot_id` (call under the registry's lock): it does
        already, or the map has fewer than `max_robots_per_map` robots, or one of them can make
        room by being forgotten: a robot that is not online and has no scan waiting. Of those, one
        whose every message was refused goes first (it holds only its refusals, which the map's
        count keeps, so garbage under changing robot ids cannot lock real robots out), else the one
        heard from least recently. Without the latter a map that had seen as many robots over its
        life (robots come and go, get renamed, are replaced) refused every new robot for good.
        A forgotten robot that comes back starts afresh: its first new scan is accepted as a first.
        But the map remembers the last seq of each of its publisher sessions (`Tombstones.forget`),
        so its scans from before, sent again from its cache (after a restart of the service, or
        its link's), are ignored as duplicates, not integrated twice."""
        if robot_id in entry.robots or len(entry.robots) < self.max_robots_per_map:
            return True
        return self._forget_idle(entry, 1) == 1

    def _forget_idle(self, entry: MapEntry, count: int) -> int:
        """Forget up to `count` robots of map `entry` that are not online and have no scan waiting,
        in `_room_for`'s order (those whose every message was refused first, then the ones heard
        from least recently), each remembered by a tombstone (`Tombstones.forget`), which the map's
        next snapshot stores (`MapEntry.unstored_stones`); return how many (call under the
        registry's lock)."""
        if count <= 0:
            return 0
        idle = [(rid, st) for rid, st in entry.robots.items() if not st.online and not st.unsettled]
        chosen = heapq.nsmallest(count, idle, key=_forgetting_order)
        now = time.time()
        for rid, state in chosen:
            stone = self.tombstones.forget(entry.id, rid, state, now)
            if stone is not None and self.durable is not None:
                entry.unstored_stones[rid] = stone
            entry.forget(rid)
        self.unmapped.forget(entry.id, [rid for rid, _ in chosen])
        return len(chosen)

    def _creates_maps(self) -> bool:
        """Whether a scan (or token) of a map that does not exist would create it now: auto-create
        on, and fewer than `max_auto_maps` maps held (call under the registry's lock)."""
        return self.auto_create and len(self.maps) < self.max_auto_maps

    def set_online(self, map_id: str, robot_id: str, online: bool) -> str | None:
        """A robot's liveliness token appeared or went away. Returns None once its map shows the
        robot so (or, for a token gone, shows it nowhere online), else why the map does not show the
        robot online though its token appeared: there is no map and the token may not create one,
        or the map holds its most robots and none can make room. The caller's log line says so: it
        said "robot M/R is online" of a robot that `GET /maps/{id}` and `/metrics` did not list."""
        if not (is_valid_id(map_id) and is_valid_id(robot_id)):
            return "invalid map or robot id" if online else None
        with self.lock:
            if online:
                self._alive.add((map_id, robot_id))
            else:
                self._alive.discard((map_id, robot_id))
            entry = self.maps.get(map_id)
            if entry is None:
                if not online:
                    return None
                if not self.auto_create:
                    return f"there is no map {map_id!r}, and tokens and scans create none (--no-auto-create)"
                if len(self.maps) >= self.max_auto_maps:
                    return (
                        f"there is no map {map_id!r}, and the service already holds {len(self.maps)} maps: "
                        f"tokens and scans create a map only while it holds fewer than {self.max_auto_maps}"
                    )
                if self.tombstones.buried(map_id, robot_id):
                    # Its map was deleted under it: a token seen again (a restart) is no new robot.
                    return f"its map {map_id!r} was deleted (or replaced) under it, and is not made again"
                entry, _ = self.create(map_id)
            elif online:
                entry.provisional = False  # the token would have created the map: it stays
            elif robot_id not in entry.robots:
                # Nothing to show offline: making room for it would forget an idle robot (and any
                # Zenoh peer can declare and drop tokens under made-up robot ids).
                return None
            if not self._room_for(entry, robot_id):
                if not online:
                    return None
                return (
                    f"map {map_id!r} already has {len(entry.robots)} robots, the most it may have, "
                    "every one online or with scans waiting"
                )
            robot = entry.robot(robot_id)
            robot.last_heard = time.time()
            if robot.online != online:
                robot.online = online
                entry.touch(robot)
            return None

    def mark_online(self, map_id: str, robot_id: str) -> None:
        """After a scan of `robot_id` was accepted while its liveliness (or ROS publisher) token
        lives: show the robot online if its map exists (the map, or the robot's state, may have been
        created after the token appeared). In one hold of the lock, and never creating a map: a map
        deleted since the scan stays deleted, where a look-up then `set_online` made it again."""
        with self.lock:
            entry = self.maps.get(map_id)
            if entry is None:
                return
            state = entry.robots.get(robot_id)
            if state is None or not state.online:
                self.set_online(map_id, robot_id, True)

    def _add(self, entry: MapEntry) -> None:
        """Install a new map entry (under the registry's lock), its robots whose liveliness tokens
        are present shown online: a map deleted and created again, or restored from a snapshot,
        while its robots live, would otherwise show them offline until their next scan."""
        self.maps[entry.id] = entry
        for map_id, robot_id in self._alive:
            if map_id == entry.id and self._room_for(entry, robot_id):
                robot = entry.robot(robot_id)
                robot.online = True
                entry.touch(robot)

    def iter_robots(self) -> Iterator[tuple[str, str, RobotState]]:
        """(map id, robot id, state) of every robot of every map. Holds the registry's lock until the
        iteration ends: consume it whole, at once (`GET /healthz` counts the robots online)."""
        with self.lock:
            for entry in self.maps.values():
                for robot_id, state in entry.robots.items():
                    yield entry.id, robot_id, state

    # -- integration -----------------------------------------------------------------------------

    def _work(self) -> None:
        while True:
            try:
                got = self.queue.get()  # without a timeout: an item, or QueueClosed
            except QueueClosed:
                return
            assert got is not None
            source, job = got
            try:
                self._integrate(job)
            except Exception as exc:  # a bug must not kill the worker; it is logged and counted
                # With its traceback, but rate-limited per kind of failure: a bug that hits every
                # scan would otherwise write hundreds of tracebacks a second.
                what = f"integration of {job.map_id}/{job.robot_id} seq {job.wire.seq} failed: {exc!r}"
                fields = {"map_id": job.map_id, "robot_id": job.robot_id, "seq": job.wire.seq}
                self._bug_log.error(_failure_site(exc), what, exc, **fields)
                self._finish_rejected(job, f"internal error: {exc}")
            finally:
                self.queue.done(source)

    def _integrate(self, job: Job) -> None:
        if self.durable is not None:
            # While the disk stalls, scans wait in the ingest queue, whose bounds hold, rather than
            # applied in memory behind a commit that does not come back, without end.
            self.durable.wait_for_journal_room()
        with self.lock:
            entry = self.maps.get(job.map_id)
        if entry is None or entry.generation != job.generation:
            self._finish_gone(job)
            return
        started = time.perf_counter()
        scan = job.wire.scan
        # The journal blob is made before the lock: nothing under the map lock should need the GIL
        # longer than it must.
        blob = scan_to_blob(scan) if self.durable is not None else b""
        try:
            plan = entry.gmap.plan(scan)
            with entry.gmap.lock:
                # Checked, applied and journaled in one hold of the map's lock, under which a
                # DELETE or replace retires the map (`_removing`): while it was planned, the map may
                # have gone, and a new one of the same id would replay a row journaled now.
                if entry.retired:
                    result = None
                else:
                    result = entry.gmap.apply(plan)
                    job.applied_at = time.monotonic()
                    if self.durable is not None:
                        job.journaled = True
                        # Under the map's lock: the journal's order is the order of application.
                        elapsed = time.perf_counter() - started
                        self.durable.journal(
                            job.map_id, job.robot_id, job.wire.seq, job.wire.stamp, blob,
                            lambda _row: self._mark_integrated(entry, job, result, elapsed),
                            lambda exc: self._mark_not_durable(job, exc), job.wire.session,
                            self._unjournaled_refusals(entry, job),
                        )  # fmt: skip
        except (ScanError, TileLimitError) as exc:
            # The service's budget is not the scan's fault: 507 (Insufficient Storage), not 422, and
            # a retry once memory is freed is integrated, not taken for a duplicate
            # (`RobotState.refused_scans`).
            # A scan without a session id refused here keeps its seq free as well, as one the decoder
            # refuses does (docs/protocol.md, "Limits": the map's max_tiles is one): its seq was
            # recorded when it was queued, and the next scan sent under it (a REST client's, whose
            # automatic seq stays after a 422) was ignored as a duplicate, never integrated.
            budget = isinstance(exc, MemoryBudgetError)
            retriable = budget or job.wire.session is None
            self._finish_rejected(job, str(exc), 507 if budget else 422, retriable=retriable)
            return
        if result is None:
            self._finish_gone(job)
            return
        entry.changes.record(result.changed_tiles)  # viewers see the change now
        if self.durable is None:
            self._mark_integrated(entry, job, result, time.perf_counter() - started)

    def _unjournaled_refusals(self, entry: MapEntry, job: Job) -> Sequence[tuple[int, bool]] | None:
        """What the journal row of `job`'s scan names besides it (`RobotState.unjournaled_refusals`):
        the refused scans of its session before it, which the replay after a crash counts as
        refused, not lost; None when there are none (looked at without the registry's lock first:
        the common case takes no lock). Called under the map's lock (the registry's comes second)."""
        session, receipt = job.wire.session, job.receipt
        if session is None or receipt is None or not receipt.ledger.unjournaled:
            return None
        with self.lock:
            robot = entry.robots.get(job.robot_id)
            return None if robot is None else robot.unjournaled_refusals(job.wire.seq, session) or None

    def _mark_integrated(self, entry: MapEntry, job: Job, result: IntegrationResult, elapsed: float) -> None:
        """The scan is applied (and durable, with persistence): count it and answer its caller."""
        pose = job.wire.scan.pose
        with self.lock:
            self._settle(job, integrated=True)
            if entry.generation == job.generation:
                entry.unsettled -= 1
                entry.provisional = False  # it holds a scan now
                entry.scans_integrated += 1
                robot = entry.robot(job.robot_id)
                robot.unsettled -= 1
                robot.scans_integrated += 1
                robot.last_stamp = job.wire.stamp
                robot.add_pose(pose)
                entry.touch(robot)
        if self.on_integrated is not None:
            self.on_integrated(entry, job, result, elapsed)
        if job.future:
            job.future.set_result(result)

    def _mark_not_durable(self, job: Job, exc: Exception) -> None:
        """The scan is applied but its journal commit failed: count it and answer its caller 503.
        Readers already see it; the map's next snapshot makes it durable once storage works."""
        reason = (
            f"the scan was applied but could not be made durable (storage error: {exc}); the map's next "
            "snapshot saves it once storage works again, and a retry with the same seq is ignored as a "
            "duplicate; see GET /healthz"
        )
        self._finish_rejected(job, reason, 503, applied=True)

    def _finish_rejected(
        self, job: Job, reason: str, status: int = 422, applied: bool = False, retriable: bool = False
    ) -> None:
        """A scan that does not count as integrated: count it on its robot (as `not_durable` if it
        was `applied`, else as rejected) with `reason` as its last error, and answer its caller
        `status`. A `retriable` scan (refused for the service's sake, or sent without a session id:
        `_integrate`) may be sent again with its seq (`RobotState.refused_scans`). A `provisional` map
        that this refusal leaves with no scan unsettled is removed again (`_remove_unclaimed`), and
        the caller answered once that is stored."""
        removed = None
        with self.lock:
            self._settle(job, integrated=False)
            entry = self.maps.get(job.map_id)
            if entry is not None and entry.generation == job.generation:
                entry.unsettled -= 1
                robot = entry.robot(job.robot_id)
                robot.unsettled -= 1
                robot.last_error = reason
                if retriable:
                    robot.note_refused(job.wire.seq, job.wire.session)
                if applied:
                    robot.not_durable += 1
                    entry.provisional = False  # it holds the scan, durable or not
                else:
                    robot.scans_rejected += 1
                    entry.scans_rejected += 1
                    removed = self._remove_unclaimed(entry)
        future = job.future
        if future is None:
            if not applied:  # (a failed commit is logged by the journal)
                # No one else is told: a Zenoh or ROS robot gets no answer (a REST client gets this).
                self._refusal_log.warning(
                    f"refused:{job.map_id}/{job.robot_id}",
                    f"scan seq {job.wire.seq} from {job.map_id}/{job.robot_id} refused: {reason}",
                    map_id=job.map_id, robot_id=job.robot_id, seq=job.wire.seq,
                )  # fmt: skip
            return
        if removed is None:
            _refuse(future, IngestRejected(reason, status))
        else:
            refusal = IngestRejected(
                f"{reason}; map {job.map_id!r}, created for this scan, was removed again", status
            )
            removed.add_done_callback(lambda _stored: _refuse(future, refusal))

    def _finish_gone(self, job: Job) -> None:
        """A scan whose map was deleted or replaced before the scan was applied (queued, or while it
        was planned): it is integrated into no map. Nothing is counted (the map's counters went with
        it, and a new map of that id never saw the scan); its caller gets 404, or 409 if a new map of
        that id exists by now."""
        with self.lock:
            self._settle(job, integrated=False)  # its robot's ledger went with the map, or is a new map's
            replaced = job.map_id in self.maps
        if job.future is None:
            return
        if replaced:
            reason = (
                f"map {job.map_id!r} was replaced (deleted and created again, or replaced by an upload) "
                "before the scan was integrated: it was not integrated, into the old map or the new one"
            )
        else:
            reason = f"map {job.map_id!r} was deleted before the scan was integrated: it was not integrated"
        _refuse(job.future, IngestRejected(reason, 409 if replaced else 404))

    @staticmethod
    def _settle(job: Job, integrated: bool) -> None:
        """Settle `job`'s scan in its session's ledger (call under the registry's lock)."""
        if job.receipt is not None:
            job.receipt.ledger.settle(job.receipt, integrated)

    # -- reporting -------------------------------------------------------------------------------

    def delivery_status(self, map_id: str, robot_id: str, session: int | None = None) -> DeliveryStatus:
        """What became of robot `robot_id`'s scans on map `map_id`: the Zenoh delivery query's answer
        (`delivery.delivery_status`). Holds the registry's lock briefly."""
        return delivery.delivery_status(self, map_id, robot_id, session)

    def backlog(self) -> tuple[int, float]:
        """(scans waiting for integration, seconds the oldest of them has waited). Cheap: one short
        lock and a look at the head of each robot's FIFO (the oldest scan is at the head of one of
        them). Scans being integrated are no longer waiting and are not counted."""
        depth, heads = self.queue.heads()
        if not heads:
            return depth, 0.0
        oldest = min(job.enqueued_at for job in heads)
        return depth, max(0.0, time.monotonic() - oldest)


def _forgetting_order(item: tuple[str, RobotState]) -> tuple[bool, float]:
    """Which robot a full map forgets first (`MapRegistry._forget_idle`): one whose every message
    was refused (none of its scans is in the map: `RobotState.in_map`), then the one heard from
    least recently. Not "it has no seq": a scan refused at the input limits with a session id has
    its seq recorded (`MapRegistry.reject`), and such scans under made-up robot ids pushed real
    offline robots out first."""
    return item[1].in_map, item[1].last_heard


def _covered_reason(stone: Tombstone, wire: WireScan) -> str:
    """Why the scan `wire`, covered by `stone` (`Tombstones.covers`), is ignored (a 200 answer)."""
    had = f"the service had seq {stone.last_seq(wire.session)} of this publisher then"
    if stone.forgotten:
        return (
            f"seq {wire.seq} is from before map {stone.map_id!r} forgot robot {stone.robot_id!r} to make "
            f"room for another robot ({had}; the scans it had are in the map): ignored"
        )
    return f"seq {wire.seq} is from before map {stone.map_id!r} was deleted or replaced ({had}): ignored"


def _queued_bytes(job: Job) -> int:
    """What a queued scan holds: its decoded beams (float64 bearings and ranges)."""
    scan = job.wire.scan
    return scan.ranges.nbytes + scan.angles.nbytes


def _refuse(future: Future, refusal: IngestRejected) -> None:
    """Fail a scan's future with `refusal` unless it is answered already."""
    if not future.done():
        future.set_exception(refusal)


def _wait_stored(stored: Future | None, done: str) -> None:
    """Wait for a map change's commit (None: no storage); `done` says what took effect in memory."""
    if stored is None:
        return
    try:
        stored.result(timeout=DURABLE_WAIT)
    except TimeoutError:
        raise NotDurable(f"{done}, but is not yet stored after {DURABLE_WAIT:g} s; it will be") from None
    except Exception as exc:
        raise NotDurable(f"{done}, but could not be stored: {exc}") from None


def _check_id(what: str, value: str) -> None:
    if not is_valid_id(value):
        raise InvalidId(f"{what} {value!r} must match [A-Za-z0-9_-]{{1,64}}")
