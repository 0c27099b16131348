"""The SQLite database in the data directory: its tables, the checks before the service uses it,
and how every connection to it is opened (WAL, full fsync on commit)."""

from __future__ import annotations

import os
import shutil
import sqlite3
from pathlib import Path

DB_NAME = "fleetmap.db"
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
