"""The journal writer: the one thread that appends accepted scans to the journal, committing in groups
(one transaction, one fsync, for every scan of the last few milliseconds); snapshots hand it their
tile rows and the journal rows they supersede. It also stores map changes (created, replaced,
deleted), retrying one whose transaction failed until it commits (`JournalWriter.change_map`), and
checks before each commit that the database file and its write-ahead log are still the ones it
opened."""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import queue
import sqlite3
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from fleetmap.database import StorageError, connect, user_name, wal_path
from fleetmap.rate_limited_log import RateLimitedLog

log = logging.getLogger("fleetmap.journal")


@dataclass
class JournalEntry:
    """One accepted scan to append: `blob` is `storage_format.scan_to_blob` of it, `session` its
    publisher's session id (None: it sent none), `refused` the JSON of the seqs of its session
    refused before it that the row names (`persistence.DurableStore.journal`; None: none). The
    writer calls
    `on_durable(journal_id)` once its row is committed, or `on_failed(error)` if the transaction
    meant to carry it failed (the row is then never written)."""

    map_id: str
    robot_id: str
    seq: int
    stamp: float
    blob: bytes
    on_durable: Callable[[int], None]
    on_failed: Callable[[Exception], None]
    session: int | None = None
    refused: str | None = None


class _AttachedRow(NamedTuple):
    """A row (or operation) `JournalWriter.attach` (`attach_op`) carries into one of its next
    transactions."""

    map_id: str | None  # held back while this map's change is not stored (`change_map`)
    op: Callable[[sqlite3.Connection], object]  # run inside the transaction; its result is the future's
    size: int  # bytes of the row's blobs, towards `ATTACH_BYTES`
    row: bool  # a row (`attach`), not an operation (`attach_op`)
    future: Future


#: Queued by `JournalWriter.attach` to wake an idle writer.
_WAKE = object()


class JournalWriter:
    """The one thread that appends to the journal, committing in groups. Its transactions also carry
    the snapshots' tile rows (`attach`) and delete the journal rows snapshots have superseded, a few
    at a time (`trim`); between them it runs operations (`submit`) and map changes (`change_map`)."""

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
    #: Seconds between retries of a map change that failed to commit, unless a row of that map
    #: waits for it (a restored map's change carries all its tiles: not one retry per group commit).
    RETRY_IDLE = 1.0
    #: Rows appended and not yet committed (or failed) past which `wait_for_room` holds the
    #: integration workers back: 5 s of scans at 400 a second, about 60 MB with 1081 beams.
    MAX_WAITING = 2048

    def __init__(self, path: Path, on_error: Callable[[Exception], None] | None = None):
        # The journal writer never checkpoints the WAL by itself (a checkpoint copies hundreds of MB);
        # the snapshot thread does after each snapshot, leaving only a short tail to the writer.
        self._conn = connect(path, autocheckpoint=False)
        # Which files the connection writes to (see `_check_database_file`): the database, and its
        # write-ahead log, which `connect` made (or opened) by switching the database to WAL mode.
        self._wal = wal_path(path)
        self._files = {
            file: (what, _file_id(file))
            for file, what in ((path, "the map database"), (self._wal, "the map database's write-ahead log"))
        }
        self._queue: queue.Queue[JournalEntry | Callable[[sqlite3.Connection], None] | object | None] = (
            queue.Queue()
        )
        self._on_error = on_error
        # A full disk fails every commit, hundreds a second: one line per `LOG_INTERVAL`, counting
        # the others, and one when commits succeed again.
        self._failure_log = RateLimitedLog(log)
        self._failed_commits = 0  # since the last commit that succeeded
        self._failed_scans = 0
        # map id -> the journal id up to which that map's rows are superseded by a snapshot and
        # still to be deleted. Only the writer thread touches it (from `trim`, called in an op).
        self._trim: dict[str, int] = {}
        self._attached: collections.deque[_AttachedRow] = collections.deque()
        self._attached_bytes = 0  # of the rows in `_attached`, under `_attached_lock`
        # map id -> the latest change of that map (create, replace, delete) whose transaction failed,
        # retried before every later transaction until it commits (`change_map`). Only the writer
        # thread touches it; `unstored` is its keys for other threads, replaced whole.
        self._unstored: dict[str, Callable[[sqlite3.Connection], object]] = {}
        self.unstored: tuple[str, ...] = ()
        self._last_retry = 0.0  # time.monotonic() of the last retry of every unstored change
        self._attached_lock = threading.Lock()
        # time.monotonic() of each appended row not yet committed (or failed), oldest first, for
        # `backlog`. Scans count as integrated only once their rows commit, so while the disk stalls
        # no counter moves at all (commits and scans integrated alike) and the ingest queue stays
        # empty: only these rows, applied and waiting, show it.
        self._waiting: collections.deque[float] = collections.deque()
        self._waiting_lock = threading.Lock()
        self._room = threading.Condition(self._waiting_lock)  # fewer than MAX_WAITING: `wait_for_room`
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

    def attach(self, sql: str, params: tuple, map_id: str | None = None) -> Future:
        """Execute `sql` with `params` inside one of the writer's next transactions: the next group
        commit, or one of its own once no scan has arrived for `ATTACH_WAIT`. The future is resolved
        when that transaction commits (with the exception if it failed). Never blocks. A row of map
        `map_id` fails, unwritten, while a change of that map is not stored (`change_map`).

        Bulk background writes (a snapshot's tile rows) go this way: written on a second connection
        they compete for SQLite's one write lock, and a journal commit that finds it taken sleeps in
        SQLite's busy handler (1, 2, 5, 10, ... ms); with a snapshot's 17 tile transactions that
        made group commits take 20-60 ms."""

        def row(conn: sqlite3.Connection) -> None:
            conn.execute(sql, params)

        return self._attach(map_id, row, sum(len(p) for p in params if isinstance(p, bytes)), True)

    def attach_op(self, op: Callable[[sqlite3.Connection], object], map_id: str | None = None) -> Future:
        """Run `op` inside one of the writer's next transactions, after the rows attached before it
        (in the same transaction or a later one), as `attach` runs a row. `op` must not begin or end
        the transaction, and raises only `sqlite3.Error` (which fails the whole transaction, every
        row and operation in it). The future is resolved with its result once that transaction
        commits. Never blocks."""
        return self._attach(map_id, op, 0, False)

    def _attach(
        self, map_id: str | None, op: Callable[[sqlite3.Connection], object], size: int, row: bool
    ) -> Future:
        future: Future = Future()
        with self._attached_lock:
            self._attached.append(_AttachedRow(map_id, op, size, row, future))
            self._attached_bytes += size
        self._queue.put(_WAKE)
        return future

    def commit_attached(self) -> None:
        """Commit every row and operation attached so far, next, in transactions of `ATTACH_BYTES`,
        without waiting `ATTACH_WAIT` for a group commit to ride along with: for a caller that knows
        no scan is coming (a stopping service's last snapshots). Never blocks."""
        self._queue.put(self._commit_attached)

    def _commit_attached(self, conn: sqlite3.Connection) -> None:
        while self._attached and self._commit([]):
            pass

    def append(self, entry: JournalEntry) -> None:
        # Under the lock, so that `_waiting` is in the queue's order, which the writer takes rows in.
        with self._waiting_lock:
            self._waiting.append(time.monotonic())
            self._queue.put(entry)

    def backlog(self) -> tuple[int, float]:
        """(rows appended and not yet committed or failed, seconds the oldest of them has waited):
        a disk that stalls shows as an age that grows (`fleetmap_journal_backlog_seconds`)."""
        with self._waiting_lock:
            if not self._waiting:
                return 0, 0.0
            return len(self._waiting), max(0.0, time.monotonic() - self._waiting[0])

    def wait_for_room(self) -> None:
        """Return once fewer than `MAX_WAITING` appended rows wait for their commit: at once, unless
        the disk stalls. Call it holding no lock. Each waiting row holds its scan (about 30 KB with
        1081 beams: decoded, as a blob, and its job), and while no commit came back (a frozen file
        system, a hung network mount) the integration workers went on applying and appending scans
        at full speed: memory grew without bound (1.2 MB/s for two robots at 20 Hz). Held back
        here, scans wait in the ingest queue instead, whose bounds refuse the newest (`dropped`)."""
        with self._room:
            self._room.wait_for(lambda: len(self._waiting) < self.MAX_WAITING)

    def _settled(self, rows: int) -> None:
        """The writer is done with the `rows` oldest appended rows (committed, failed or held back)."""
        with self._waiting_lock:
            for _ in range(min(rows, len(self._waiting))):
                self._waiting.popleft()
            self._room.notify_all()

    def submit(self, op: Callable[[sqlite3.Connection], object]) -> Future:
        """Queue a database operation for the writer thread, in order with the journal entries
        appended before it (whose rows are committed and acknowledged by then). Never blocks. If
        `op` raises, a transaction it left open is rolled back."""
        future: Future = Future()

        def wrapped(conn: sqlite3.Connection) -> None:
            try:
                future.set_result(op(conn))
            except BaseException as exc:  # handed back to whoever waits on the future
                # Not left open: a snapshot's switch that failed inside its transaction made the
                # next group commit fail ("cannot start a transaction within a transaction"), its
                # scans answered 503 as not durable though storage worked again.
                self._roll_back()
                future.set_exception(exc)

        self._queue.put(wrapped)
        return future

    def change_map(self, map_id: str, op: Callable[[sqlite3.Connection], object]) -> Future:
        """Queue a change of map `map_id` (created, replaced or deleted): `op` is one transaction that
        rewrites everything stored of the map, so running it again later has the same effect. The
        future resolves once it commits, or fails with its error.

        If it fails (a full or failing disk), what is stored of the map is not what the service
        serves: a map the service holds would be missing after a restart (and with it every scan
        journaled for it since), or a deleted one would come back. So `op` is kept and retried
        before each of the writer's later transactions (and every `RETRY_IDLE` s while idle) until
        it commits, and meanwhile no row of that map is written: its scans fail (`on_failed`: not
        durable, for its next snapshot to save) and so do its attached rows. A later change of the
        same map replaces it."""

        def change(conn: sqlite3.Connection) -> object:
            self._unstored.pop(map_id, None)  # this change rewrites the map whole: it supersedes it
            return self._change(map_id, op)

        return self.submit(change)

    def retry(self, map_id: str) -> Future:
        """Retry the change of map `map_id` that is not stored, if any, after everything queued so
        far; the future fails with the error if it still does not commit."""

        def again(conn: sqlite3.Connection) -> None:
            op = self._unstored.get(map_id)
            if op is not None:
                self._change(map_id, op)

        return self.submit(again)

    def _check_database_file(self) -> None:
        """Raise `sqlite3.OperationalError` if the database file or its write-ahead log at their paths
        are not the ones the writer opened: the data directory was deleted (or a file replaced)
        while the service ran. SQLite goes on committing into a deleted file, through its open
        descriptor, without an error: scans were counted as integrated and /healthz said ok, and a
        restart found an empty directory or, the log alone deleted (a clean-up of "temporary"
        files), a database without the commits since the last checkpoint."""
        for file, (what, opened) in self._files.items():
            try:
                now = _file_id(file)
            except OSError as exc:
                # Not a sign that it is gone: the data directory's permissions taken away under the
                # service (a chmod or chown of the volume) were reported as the database deleted,
                # "nothing can be made durable any more", though commits resumed with the access.
                raise sqlite3.OperationalError(
                    f"{what} {file} cannot be looked at ({exc.strerror}), so the service cannot tell "
                    f"that it still writes to it: give the user it runs as ({user_name()}) access to "
                    "the data directory again, and commits resume"
                ) from None
            if now != opened:
                raise sqlite3.OperationalError(
                    f"{what} {file} was deleted or replaced while the service ran, so nothing can "
                    "be made durable any more; save each map with GET /maps/{id}/snapshot before "
                    "restarting the service"
                )

    def _change(self, map_id: str, op: Callable[[sqlite3.Connection], object]) -> object:
        """Run a map change on the writer thread; keep it in `_unstored` if its transaction fails."""
        try:
            self._check_database_file()
            result = op(self._conn)
        except BaseException as exc:
            self._roll_back()
            self._save_deleted_log()
            if isinstance(exc, sqlite3.Error):  # storage: retried; anything else is a bug, not retried
                if map_id not in self.unstored:
                    # Once per change, not per retry. Only /healthz and the 503 told before, and the
                    # log said just "created map m" (a map a robot's scan made, which no HTTP client
                    # hears of), then "the change of map m is stored now" of a failure never named.
                    self._failure_log.error(
                        "map_change",
                        f"the change of map {map_id} (created, replaced or deleted) could not be stored: "
                        f"{exc}; it is retried until it is, and the map's scans are not durable meanwhile",
                        map_id=map_id,
                    )
                self._unstored[map_id] = op
            # Published either way: `change_map` may have dropped a failed change this one replaced,
            # and /healthz must not go on listing a map whose rows are no longer held back.
            self._publish_unstored()
            raise
        # (`unstored`, not `_unstored`: `change_map` has already dropped the op this one supersedes.)
        if map_id in self.unstored:
            self._unstored.pop(map_id, None)
            self._publish_unstored()
            log.info("the change of map %s is stored now", map_id, extra={"map_id": map_id})
        return result

    def _publish_unstored(self) -> None:
        """Copy `_unstored`'s keys to `unstored`, which other threads read (replaced whole)."""
        self.unstored = tuple(sorted(self._unstored))

    def _roll_back(self) -> None:
        """End the failed transaction, if one is open. SQLite rolls some failed transactions back by
        itself, not all: left open, one would make every later BEGIN (every journal commit) fail."""
        with contextlib.suppress(sqlite3.Error):
            if self._conn.in_transaction:
                self._conn.execute("ROLLBACK")

    def _save_deleted_log(self) -> None:
        """After a failed transaction: if the write-ahead log was deleted or replaced (see
        `_check_database_file`), copy what it holds into the database, through the connection's
        open descriptor (a checkpoint). Its last commits, acknowledged, were in that log alone: a
        crash before the snapshot thread's next checkpoint (within a second) lost them."""
        try:
            if _file_id(self._wal) == self._files[self._wal][1]:
                return
        except OSError:  # cannot be looked at: not known to be gone (`_check_database_file`)
            return
        try:
            self._conn.execute("PRAGMA wal_checkpoint(FULL)").fetchone()
        except sqlite3.Error as exc:
            self._failure_log.error(
                "deleted log",
                f"the commits in the deleted write-ahead log {self._wal} could not be saved: {exc}",
            )

    def _retry_unstored(self, needed: set[str | None] | None = None) -> None:
        """Retry the map changes that are not stored (on the writer thread, between transactions):
        those of the maps in `needed` (whose rows wait), and every one if `needed` is None or the
        last retry of them all is `RETRY_IDLE` old."""
        now = time.monotonic()
        everyone = needed is None or now - self._last_retry >= self.RETRY_IDLE
        if everyone:
            self._last_retry = now
        for map_id, op in list(self._unstored.items()):
            if everyone or (needed is not None and map_id in needed):
                with contextlib.suppress(sqlite3.Error):  # still failing: kept, its rows held back
                    self._change(map_id, op)

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
            idle = (
                self.ATTACH_WAIT if self._attached
                else self.TRIM_IDLE if self._trim
                else self.RETRY_IDLE if self._unstored
                else None
            )  # fmt: skip
            try:
                item = self._queue.get(timeout=idle)
            except queue.Empty:  # idle with rows to delete or attached, or changes to retry
                self._retry_unstored()
                self._commit([])
                continue
            batch: list[JournalEntry] = []
            while True:
                if isinstance(item, JournalEntry):
                    batch.append(item)
                elif item is _WAKE:  # attached rows wait for the next group, or for ATTACH_WAIT
                    if self._attached_bytes >= self.ATTACH_BYTES:  # (read unlocked: at worst late)
                        break  # a transaction's worth: committed now (see below)
                else:
                    if batch:  # (an empty one would commit background rows alone: an extra fsync)
                        self._commit(batch)
                    batch = []
                    if item is None:
                        self._finish()
                        return
                    assert callable(item)
                    item(self._conn)
                if len(batch) >= 512:
                    break
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
            # Also a transaction's worth of attached rows and no scan: rows attached faster than
            # every ATTACH_WAIT (a stopping service's snapshots, unpaced) never let the writer idle,
            # and piled up in memory until the last was attached: every changed tile of every map.
            if batch or self._attached_bytes >= self.ATTACH_BYTES:
                self._commit(batch)

    def _finish(self) -> None:
        """At shutdown, with no hurry: commit every attached and superseded row left, try the map
        changes not stored once more, and log those that still are not."""
        while (self._trim or self._attached) and self._commit([]):
            pass
        self._retry_unstored()
        for map_id in self._unstored:
            log.error(
                "the last change of map %s (created, replaced or deleted) could not be stored: the "
                "next start finds the map as it was before that change",
                map_id,
                extra={"map_id": map_id},
            )

    def _trim_some(self) -> list[str]:
        """Inside the open transaction, delete up to `TRIM_ROWS` superseded rows, of as many maps as
        they take (those pending longest first); return the maps none of whose superseded rows are
        left. Deleting one map's rows a transaction made a synced transaction of every map's few
        rows: a stop after a crash restore of 500 maps spent 500 of them on it."""
        finished: list[str] = []
        left = self.TRIM_ROWS
        for map_id, upto in self._trim.items():
            if left <= 0:
                break
            cur = self._conn.execute(
                "DELETE FROM journal WHERE id IN (SELECT id FROM journal WHERE map_id = ? AND id <= ? "
                "ORDER BY id LIMIT ?)",
                (map_id, upto, left),
            )
            deleted = max(cur.rowcount, 0)
            self.trimmed += deleted
            if deleted == left:
                break  # (perhaps more of them left)
            finished.append(map_id)
            left -= max(deleted, 1)  # (at least 1: at most TRIM_ROWS statements a transaction)
        return finished

    def _take_attached(self) -> list[_AttachedRow]:
        """The attached rows for one transaction: up to `ATTACH_BYTES`, at least one if any."""
        taken: list[_AttachedRow] = []
        size = 0
        with self._attached_lock:
            while self._attached and (not taken or size < self.ATTACH_BYTES):
                row = self._attached.popleft()
                taken.append(row)
                size += row.size
            self._attached_bytes -= size
        return taken

    def _hold_back(
        self, batch: list[JournalEntry], attached: list[_AttachedRow]
    ) -> tuple[list[JournalEntry], list[_AttachedRow]]:
        """Fail the rows of maps whose change is not stored (see `change_map`); return the others."""
        if not self._unstored:
            return batch, attached
        error = StorageError(
            "its map's creation, restore or deletion could not be stored yet (retried until it is; see "
            "GET /healthz)"
        )
        kept_batch = [e for e in batch if e.map_id not in self._unstored]
        kept_attached = [a for a in attached if a.map_id not in self._unstored]
        for e in batch:
            if e.map_id in self._unstored:
                _tell(e.on_failed, error)
        for a in attached:
            if a.map_id in self._unstored:
                a.future.set_exception(error)
        return kept_batch, kept_attached

    def _commit(self, batch: list[JournalEntry]) -> bool:
        """Commit `batch` (which may be empty), a share of the attached rows and of the superseded
        rows in one transaction; False if there was nothing to do or the commit failed."""
        try:
            return self._commit_batch(batch)
        finally:
            self._settled(len(batch))  # whatever became of them: their rows wait no longer

    def _commit_batch(self, batch: list[JournalEntry]) -> bool:
        """`_commit`'s work, with `batch`'s rows still counted as waiting (`backlog`)."""
        if not batch and not self._trim and not self._attached:
            return False
        attached = self._take_attached()
        if self._unstored:
            needed: set[str | None] = {e.map_id for e in batch}
            self._retry_unstored(needed | {a.map_id for a in attached})
        batch, attached = self._hold_back(batch, attached)
        if not batch and not attached and not self._trim:
            return False
        try:
            ids: list[int] = []
            self._conn.execute("BEGIN IMMEDIATE")
            for e in batch:
                cur = self._conn.execute(
                    "INSERT INTO journal (map_id, robot_id, seq, stamp, scan, session, refused) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (e.map_id, e.robot_id, e.seq, e.stamp, e.blob, e.session, e.refused),
                )
                assert cur.lastrowid is not None  # set by every INSERT
                ids.append(cur.lastrowid)
            results = [a.op(self._conn) for a in attached]
            trimmed = self._trim_some()
            self._check_database_file()  # (two stats: a few us per group commit)
            self._conn.execute("COMMIT")
        except sqlite3.Error as exc:
            # Nothing of this batch is durable: the scans stay applied in memory but are never
            # counted, and the service reports the storage failure loudly.
            self._failed_commits += 1
            self._failed_scans += len(batch)
            self._failure_log.error("commit", _failed_commit(batch, attached, exc))
            self._roll_back()
            self._save_deleted_log()
            for a in attached:
                a.future.set_exception(exc)
            # Superseded rows are harmless (ignored and deleted at start); retrying their deletion
            # on a failing disk would only repeat the error every TRIM_IDLE seconds.
            self._trim.clear()
            if self._on_error:
                _tell(self._on_error, exc)
            for e in batch:
                _tell(e.on_failed, exc)
            return False
        if self._failed_commits:
            log.info(
                "journal commits succeed again, after %d failed (%d scans not durable until their "
                "maps' next snapshots)", self._failed_commits, self._failed_scans,
            )  # fmt: skip
            self._failed_commits = self._failed_scans = 0
        for a, result in zip(attached, results, strict=True):
            a.future.set_result(result)
        for map_id in trimmed:
            del self._trim[map_id]
        if not batch:
            return True
        self.commits += 1
        self.rows += len(batch)
        for e, row_id in zip(batch, ids, strict=True):
            _tell(e.on_durable, int(row_id))
        return True


def _failed_commit(batch: list[JournalEntry], attached: list[_AttachedRow], exc: Exception) -> str:
    """The log line of a failed transaction that held `batch` and `attached` (snapshots' tile rows,
    and the switches of a stopping service's last snapshots, the only things attached), saying what
    it held: one of tile rows or superseded rows' deletion alone was "journal commit failed (0 scans
    not durable)", a journal failure that lost nothing."""
    if batch:
        return f"journal commit failed ({len(batch)} scans not durable): {exc}"
    if attached:
        tiles = sum(1 for a in attached if a.row)
        rows = f"{tiles} tile row{'s' if tiles != 1 else ''}"
        switches = len(attached) - tiles  # (`DurableStore.snapshot(last=True)`)
        if switches:
            return f"storing {rows} and switching {switches} map(s) to their last snapshots failed: {exc}"
        return f"storing {rows} of a snapshot failed (the snapshot is retried): {exc}"
    return f"deleting journal rows a snapshot superseded failed (harmless: ignored, and deleted later): {exc}"


def _file_id(path: Path) -> tuple[int, int] | None:
    """(device, inode) of the file at `path`, None if there is none (it, or a directory on its path,
    is gone). Raises `OSError` if it cannot be looked at (no permission)."""
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    return st.st_dev, st.st_ino


def _tell(callback: Callable[[Any], None], value: object) -> None:
    """Call a durability callback on the writer thread; a bug in one is logged, and must not stop
    the thread every later scan waits on."""
    try:
        callback(value)
    except Exception:
        log.exception("journal callback %r failed", callback)
