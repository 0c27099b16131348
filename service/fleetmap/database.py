"""The SQLite database in the data directory: its tables, the checks before the service uses it,
and how every connection to it is opened (WAL, full fsync on commit)."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import pwd
import shutil
import sqlite3
import threading
from pathlib import Path

from fleetmap.wal_check import damaged_commits

DB_NAME = "fleetmap.db"
#: Held locked (a POSIX record lock) by the service that uses the data directory.
LOCK_NAME = "fleetmap.lock"
#: The database's layout (`PRAGMA user_version`): its tables, tile format 2, journal rows up to
#: version 3. A version that changes any of them in a way older ones cannot read raises it, so an
#: older service refuses the directory instead of misreading it or writing what the newer one
#: misreads. Directories written before it was recorded hold 0 and are this layout. (The journal's
#: `session` column came later within version 1: added to a database without it at start (`_migrate`),
#: and an older service, which names the columns it reads and writes, works on it as before. So did
#: the `tombstones` table, created at start where it is missing, which an older service ignores,
#: and its `forgotten` column, added at start where it is missing: an older service names the
#: columns it reads and writes, its rows get 0 there, and it takes a forgotten robot's stone for a
#: deleted map's, which ignores the same old scans; and its `plain_seq` and `plain_stamp` columns,
#: likewise: an older service writes NULL there, and does not cover such scans, as before; and the
#: journal's `refused` column, likewise: an older service writes NULL there, and its replay counts
#: the seqs refused before a row as lost, as before.)
#: Version 2 (`CLEARED_WINDOWS_LAYOUT`): a journal row may also be a window of cells cleared
#: (`storage_format.cleared_window_to_blob`, `DELETE /maps/{id}/region`), which a version 1
#: service would take for a corrupt row. The tables are the
#: same, so a database is raised to 2 only before its first such row (`DurableStore
#: .allow_cleared_windows`): until a region is cleared, an older service can still open it (a
#: rollback after an upgrade).
SCHEMA_VERSION = 2
#: The layout a new database is written as, and the least an opened one is raised to.
BASE_LAYOUT = 1
#: The layout whose journal may hold cleared windows.
CLEARED_WINDOWS_LAYOUT = 2
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
    scan BLOB NOT NULL,
    session INTEGER,  -- the publisher's session id (`ScanMessage.session`); NULL: it sent none
    refused TEXT  -- JSON [[seq, may be sent again], ...]: its session's scans refused before it; NULL: none
);
CREATE INDEX IF NOT EXISTS journal_map ON journal (map_id, id);
CREATE TABLE IF NOT EXISTS tombstones (  -- robots of deleted and replaced maps (`tombstones.py`)
    map_id TEXT NOT NULL,
    robot_id TEXT NOT NULL,
    deleted_at REAL NOT NULL,
    sessions TEXT NOT NULL,  -- JSON: publisher session id -> the last seq the service had
    forgotten INTEGER NOT NULL DEFAULT 0,  -- 1: forgotten by its map, which lives on
    plain_seq INTEGER,  -- the last seq and stamp the service had of its scans without a session id
    plain_stamp REAL,
    PRIMARY KEY (map_id, robot_id)
);
"""


def wal_path(path: Path) -> Path:
    """The write-ahead log of the database at `path`, where SQLite (WAL mode) commits first."""
    return path.with_name(path.name + "-wal")


class StorageError(RuntimeError):
    """The data directory cannot hold the maps (unwritable, full, corrupt, in use). The message says
    why."""


class DataDirLock:
    """The data directory's lock: one service at a time. Two services on one directory would each
    serve and journal their own copy of the maps into one database, snapshot over each other and
    delete each other's maps and journal rows, so a restart would serve a mix of both.

    It is a POSIX record lock (`fcntl.lockf`) on `fleetmap.lock`: the kernel drops it when the
    process ends, however it ends (kill -9 included), so a crash never leaves a stale lock. Such
    locks belong to a process, not to an open file: a second `DurableStore` in the same process
    (what in-process tests do to play a restart after a crash) is not refused.

    The directory itself is locked too (`flock`, `_lock_directory`): a lock file deleted while its
    service runs (an operator clearing "stale" lock files) took its lock with it, and a second
    service made a new one, locked it and ran beside the first on the same database."""

    def __init__(self, data_dir: Path) -> None:
        path = data_dir / LOCK_NAME
        try:
            self._fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise StorageError(f"data directory {data_dir} is not writable: {exc.strerror}") from None
        self._dir: tuple[int, int] | None = None
        try:
            self._dir = _lock_directory(data_dir)
            fcntl.lockf(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except (OSError, _DirectoryInUse) as exc:
            if isinstance(exc, OSError) and exc.errno not in (errno.EAGAIN, errno.EACCES):
                # Not held by anyone: the file system takes no POSIX locks (ENOLCK from an NFS
                # mount without its lock service, ENOSYS or EOPNOTSUPP from some FUSE file systems).
                # It said "in use by another fleetmap service (pid N)", naming whichever service
                # wrote the lock file last, long gone: an operator went looking for it, or deleted
                # the "stale" file, and was refused the same way again.
                self.release()
                raise StorageError(
                    f"data directory {data_dir} cannot be locked ({exc.strerror}): its file system "
                    "does not take the locks that keep a second service, and SQLite's own writers, "
                    "apart (some network and FUSE file systems do not): give --data-dir a directory "
                    "on a local disk"
                ) from None
            holder = os.pread(self._fd, 32, 0).decode(errors="replace").strip() or "unknown"
            self.release()
            raise StorageError(
                f"data directory {data_dir} is in use by another fleetmap service (pid {holder}); "
                "two services on one data directory would overwrite each other's maps: stop it, or "
                "give this one another --data-dir"
            ) from None
        # Only a message for whoever is refused next: the lock itself is what counts. A disk with no
        # room left fails the write (ENOSPC, EFBIG): that start was a traceback, exit 1; the check of
        # the directory's room that follows says what is wrong.
        pid = f"{os.getpid()}\n".encode()
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, pid, 0)

    def release(self) -> None:
        """Give the directory up (closing the file drops the lock); idempotent."""
        if self._fd >= 0:
            os.close(self._fd)  # drops the lock
            self._fd = -1
        if self._dir is not None:
            _unlock_directory(self._dir)
            self._dir = None


class _DirectoryInUse(Exception):
    """Another process holds the data directory's `flock` (`_lock_directory`)."""


#: This process's locks of data directories (`_lock_directory`): (device, inode) -> [descriptor,
#: holders]. A `flock` belongs to an open file, not to a process: a second `DurableStore` on the
#: same directory in this process (in-process tests play a restart after a crash so) shares the
#: first one's, as it shares its POSIX lock of `fleetmap.lock`.
_DIRECTORY_LOCKS: dict[tuple[int, int], list[int]] = {}
_DIRECTORY_LOCKS_GUARD = threading.Lock()


def _lock_directory(data_dir: Path) -> tuple[int, int] | None:
    """Lock `data_dir` itself (`flock`, dropped by the kernel when the process ends), which no one
    can delete as a file; its key for `_unlock_directory`, or None where its file system takes no
    such lock (the lock file's alone guards it then). `_DirectoryInUse` if another process holds it."""
    try:
        fd = os.open(data_dir, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return None
    with _DIRECTORY_LOCKS_GUARD:
        stat = os.fstat(fd)
        key = (stat.st_dev, stat.st_ino)
        held = _DIRECTORY_LOCKS.get(key)
        if held is not None:
            os.close(fd)
            held[1] += 1
            return key
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise _DirectoryInUse() from None
        except OSError:  # not supported there (some network file systems)
            os.close(fd)
            return None
        _DIRECTORY_LOCKS[key] = [fd, 1]
        return key


def _unlock_directory(key: tuple[int, int]) -> None:
    """Give up one hold of the directory lock `key`; the last one closes it (dropping the lock)."""
    with _DIRECTORY_LOCKS_GUARD:
        held = _DIRECTORY_LOCKS[key]
        held[1] -= 1
        if held[1] == 0:
            del _DIRECTORY_LOCKS[key]
            os.close(held[0])


def open_database(data_dir: Path) -> tuple[Path, DataDirLock]:
    """Lock the data directory, check it can hold the maps and create the schema; return the
    database path and the lock, which the caller holds as long as it uses the database.

    Raises `StorageError` with a clear message when the directory cannot be created or written, the
    disk is (nearly) full, or another service uses it, so the service never runs silently in memory
    only, nor beside another one on the same maps."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        dangling = [p for p in (data_dir, *data_dir.parents) if p.is_symlink() and not p.exists()]
        if dangling:
            # A link (the directory's, or a folder's on its path) to a directory that is not there (a
            # disk not mounted, a volume gone) was "a file, not a directory". It is not made through
            # the link: on an unmounted disk's mount point, the maps would go to the disk beneath.
            link = dangling[0]
            if _link_loops(link):
                # (It was "a symbolic link to B, which does not exist: make that directory", of a link
                # to B, itself a link back to it: no directory can be made there.)
                raise StorageError(
                    f"data directory {data_dir}: {link} is a symbolic link that leads back to itself "
                    f"({link} -> {os.readlink(link)} -> ...): point it to a directory, or give --data-dir "
                    "another"
                ) from None
            raise StorageError(
                f"data directory {data_dir}: {link} is a symbolic link to {os.readlink(link)}, which "
                "does not exist (a disk not mounted?): make that directory, or give --data-dir another"
            ) from None
        # `--data-dir BACKUP/fleetmap.db`, the database rather than its directory, said "cannot
        # create data directory BACKUP/fleetmap.db: File exists".
        hint = f" (give the directory that holds {DB_NAME})" if data_dir.name == DB_NAME else ""
        raise StorageError(f"data directory {data_dir} is a file, not a directory{hint}") from None
    except OSError as exc:
        raise StorageError(f"cannot create data directory {data_dir}: {exc.strerror}") from None
    lock = DataDirLock(data_dir)
    try:
        return _check_and_create(data_dir), lock
    except BaseException:
        lock.release()
        raise


def _link_loops(link: Path) -> bool:
    """Whether following the symbolic link `link` never ends (it leads back to itself, at once or
    through other links)."""
    try:
        os.stat(link)
    except OSError as exc:
        return exc.errno == errno.ELOOP
    return False


def _check_and_create(data_dir: Path) -> Path:
    probe = data_dir / ".write-test"
    try:
        with open(probe, "wb") as f:
            f.write(b"\0" * 65536)
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            raise StorageError(
                f"data directory {data_dir} has no room to write ({exc.strerror}); at least "
                f"{MIN_FREE_BYTES // (1024 * 1024)} MiB must be free"
            ) from None
        raise StorageError(f"data directory {data_dir} is not writable: {exc.strerror}") from None
    finally:
        with contextlib.suppress(OSError):  # (a full disk failed the write, and left the file)
            probe.unlink()
    free = shutil.disk_usage(data_dir).free
    if free < MIN_FREE_BYTES:
        raise StorageError(
            f"data directory {data_dir} has only {free // (1024 * 1024)} MiB free; "
            f"at least {MIN_FREE_BYTES // (1024 * 1024)} MiB are needed"
        )
    path = data_dir / DB_NAME
    _refuse_unwritable(path)
    try:
        _refuse_orphaned_wal(path)
        _refuse_damaged_wal(path)
        _refuse_unknown_layout(path)
        conn = connect(path)
        try:
            conn.executescript(SCHEMA)
            _migrate(conn)
            (version,) = conn.execute("PRAGMA user_version").fetchone()
            if version < BASE_LAYOUT:
                conn.execute(f"PRAGMA user_version = {BASE_LAYOUT}")
        finally:
            conn.close()
    except sqlite3.DatabaseError as exc:
        raise StorageError(f"cannot open the map database {path}: {exc}") from None
    return path


def _refuse_unwritable(path: Path) -> None:
    """Raise `StorageError` if the database at `path`, or its write-ahead log or shared-memory file,
    exists but cannot be opened for writing: a file of another user (a backup copied in by root for a
    service that runs as its own user), read-only, or immutable. The directory's own check passed, so
    the start went on and the first write at load failed with SQLite's "attempt to write a readonly
    database", reported as a damaged database to restore from a backup or move aside, which would
    have thrown the maps away."""
    for file in (path, wal_path(path), path.with_name(path.name + "-shm")):
        try:
            fd = os.open(file, os.O_RDWR)
        except FileNotFoundError:
            continue
        except OSError as exc:
            if exc.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
                continue  # (a directory of that name, ...: SQLite says what is wrong next)
            user = user_name()
            raise StorageError(
                f"the map database file {file} cannot be written ({exc.strerror}): the database is not "
                f"damaged; give the user the service runs as ({user}) write access to it (chown, "
                "chmod; chattr -i if it is immutable)"
            ) from None
        os.close(fd)


def user_name() -> str:
    """The name of the user this process runs as (its uid if it has none)."""
    uid = os.geteuid()
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:  # (a uid with no name: a container's)
        return f"uid {uid}"


def _refuse_orphaned_wal(path: Path) -> None:
    """Raise `StorageError` if the database at `path` is missing (or empty) while its write-ahead
    log is not: the database file was deleted or moved (a restore of some of the files, a clean-up
    of `*.db`) and the log holds its latest commits, the journal of acknowledged scans among them.
    SQLite opened a new empty database there and dropped the log: the service started with no maps
    and the scans were gone for good. A crash never leaves this: the database is written first."""
    wal = wal_path(path)
    try:
        wal_size = wal.stat().st_size
        db_size = path.stat().st_size if path.exists() else 0
    except OSError:  # no log (the usual case), or one that cannot be read: SQLite says so next
        return
    if wal_size > 0 and db_size == 0:
        state = "empty" if path.exists() else "missing"
        raise StorageError(
            f"the map database {path} is {state}, but its write-ahead log {wal} holds {wal_size} bytes of "
            "its latest changes: the database file was deleted or moved. Put it back beside the log, "
            "or move the directory aside to start with no maps (this start would drop the log)"
        )


def _refuse_damaged_wal(path: Path) -> None:
    """Raise `StorageError` if the write-ahead log beside the database at `path` is damaged so that
    SQLite would drop committed transactions (`wal_check.damaged_commits`): it ends the log at the
    first bad frame without an error, so the service started on what was left, acknowledged scans of
    every map after that frame gone. Checked before any connection: the first one to close
    checkpoints what SQLite recovered and deletes the log, with what it dropped."""
    wal = wal_path(path)
    try:
        lost = damaged_commits(wal)
    except OSError:  # none (the usual case), or unreadable: SQLite says so next, more precisely
        return
    if lost:
        raise StorageError(
            f"the write-ahead log {wal} of the map database is damaged: at least {lost} committed "
            "transaction(s) after the damage would be dropped (a crash never leaves that). Restore the "
            "data directory from a backup; or, to keep only what precedes the damage, open "
            f"{path} once with the sqlite3 shell (it keeps the readable part of the log) and start again"
        )


def _refuse_unknown_layout(path: Path) -> None:
    """Raise `StorageError` for a database at `path` that this fleetmap must not write to: one a
    newer fleetmap wrote (a higher `user_version`), or one that is not a map database at all (tables,
    none of them fleetmap's `maps`: another program's file under this name). Looks without changing
    anything: `connect` would have turned the file to WAL mode and the schema added fleetmap's tables
    to it before it was refused as damaged."""
    if not path.exists():
        return
    conn = sqlite3.connect(path)  # reads only: no journal mode, no schema
    try:
        (version,) = conn.execute("PRAGMA user_version").fetchone()
        tables = {row[0] for row in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    finally:
        conn.close()
    if version > SCHEMA_VERSION:
        raise StorageError(
            f"the map database {path} was written by a newer fleetmap (schema version {version}; "
            f"this one reads up to {SCHEMA_VERSION}): run that version, or move the directory aside"
        )
    if tables and "maps" not in tables:
        listed = ", ".join(sorted(tables)[:5]) + (", ..." if len(tables) > 5 else "")
        raise StorageError(
            f"{path} is not a fleetmap map database (its tables: {listed}): move it aside, or give "
            "--data-dir a directory of fleetmap's own"
        )


def _migrate(conn: sqlite3.Connection) -> None:
    """Bring a database written before the journal had its `session` column up to date: its rows keep
    NULL there (no session: their restarts are told by their stamps, as when they were written),
    and its `refused` column (NULL: the row names no refusal); one written before tombstones had
    their `forgotten` column: its rows are all deleted maps' robots (0); and one written before
    their `plain_seq` and `plain_stamp` columns: NULL there (its scans without a session id were
    not remembered). Each column missing is added, all in one transaction: `conn` is in
    autocommit, where each ALTER TABLE committed alone, and a crash between `plain_seq` and
    `plain_stamp` left a database that had the one, so was taken for migrated, and failed every
    later start for want of the other."""
    wanted = {
        "journal": [("session", "INTEGER"), ("refused", "TEXT")],
        "tombstones": [
            ("forgotten", "INTEGER NOT NULL DEFAULT 0"),
            ("plain_seq", "INTEGER"),
            ("plain_stamp", "REAL"),
        ],
    }
    alters = []
    for table, columns in wanted.items():
        present = {row[1] for row in conn.execute(f"PRAGMA table_info({table})")}
        alters += [
            f"ALTER TABLE {table} ADD COLUMN {name} {kind}" for name, kind in columns if name not in present
        ]
    if not alters:  # (no write lock taken: a database another program holds must not fail here)
        return
    # (A failure leaves the transaction open: closing `conn`, as `open_database` does, rolls it back.)
    conn.execute("BEGIN IMMEDIATE")
    for alter in alters:
        conn.execute(alter)
    conn.execute("COMMIT")


#: Seconds a connection waits for a lock another connection (or program) holds on the database.
BUSY_TIMEOUT = 30.0


def connect(path: Path, synchronous: str = "FULL", autocheckpoint: bool = True) -> sqlite3.Connection:
    """A connection to the database at `path` as every part of the service opens one: WAL, autocommit
    (transactions are explicit BEGIN / COMMIT), usable from any thread, waiting up to `BUSY_TIMEOUT`
    for a lock. `synchronous` FULL makes a commit durable when it returns; `autocheckpoint=False`
    leaves WAL checkpoints to the caller."""
    conn = sqlite3.connect(path, timeout=BUSY_TIMEOUT, isolation_level=None, check_same_thread=False)
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
