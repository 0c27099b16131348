"""`wal_check.damaged_commits` against SQLite itself: a write-ahead log is damaged exactly when SQLite
would drop more committed transactions than a crash can tear (the last one)."""

from __future__ import annotations

import random
import shutil
import sqlite3
import struct
from pathlib import Path

from fleetmap.wal_check import damaged_commits

COMMITS = 30


def write_log(directory: Path, restart_after: int | None = None) -> Path:
    """A database of a table and COMMITS committed inserts (rows 1..COMMITS) whose write-ahead log still holds
    them all, as a crash leaves it: copied while the connection that wrote it is open (closing the
    last connection checkpoints the log and deletes it). `restart_after`: checkpointed after that
    many, so that the next commit starts the log over (new salts) and overwrites it from its start,
    the older frames left beyond the newer ones."""
    source = directory / "source"
    source.mkdir()
    conn = sqlite3.connect(source / "x.db", isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA wal_autocheckpoint=0")
    conn.execute("CREATE TABLE t (k INTEGER PRIMARY KEY, b BLOB)")
    rng = random.Random(3)
    for k in range(1, COMMITS + 1):
        conn.execute("INSERT INTO t VALUES (?, ?)", (k, rng.randbytes(rng.choice((10, 3000, 9000)))))
        if k == restart_after:
            assert conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()[0] == 0
    copy = directory / "copy"
    copy.mkdir()
    for name in ("x.db", "x.db-wal"):
        shutil.copy(source / name, copy / name)
    conn.close()
    return copy / "x.db-wal"


def commits_sqlite_reads(wal: Path) -> int:
    """The commits SQLite recovers from the database beside `wal` (on a copy: it rewrites the files):
    the table's creation and one per row."""
    copy = wal.parent.parent / "read"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(wal.parent, copy)
    conn = sqlite3.connect(copy / "x.db")
    try:
        tables = conn.execute("SELECT COUNT(*) FROM sqlite_master WHERE name = 't'").fetchone()[0]
        return tables + (conn.execute("SELECT COUNT(*) FROM t").fetchone()[0] if tables else 0)
    finally:
        conn.close()


def test_an_intact_log_and_one_torn_at_its_end_are_not_damaged(tmp_path: Path) -> None:
    wal = write_log(tmp_path)
    assert commits_sqlite_reads(wal) == 1 + COMMITS
    assert damaged_commits(wal) == 0
    whole = wal.read_bytes()
    # Torn anywhere in its last transaction (a power cut during its write), or cut short.
    for size in (len(whole) - 1, len(whole) - 5000, 32 + 10, 0):
        wal.write_bytes(whole[:size])
        assert damaged_commits(wal) == 0, size


def test_frames_of_an_earlier_generation_beyond_the_current_ones_are_not_damage(tmp_path: Path) -> None:
    """The service's log is overwritten from its start after a checkpoint, not truncated."""
    wal = write_log(tmp_path, restart_after=COMMITS - 3)
    assert commits_sqlite_reads(wal) == 1 + COMMITS
    assert damaged_commits(wal) == 0


def test_a_byte_changed_anywhere_counts_the_commits_sqlite_would_drop_beyond_the_last(tmp_path: Path) -> None:
    wal = write_log(tmp_path)
    whole = wal.read_bytes()
    frame = 24 + struct.unpack(">I", whole[8:12])[0]
    rng = random.Random(7)
    for offset in [*range(32), *rng.sample(range(32, len(whole)), 40)]:  # the header, and frames
        damaged = bytearray(whole)
        damaged[offset] ^= 0x5A
        wal.write_bytes(bytes(damaged))
        expected = max(0, 1 + COMMITS - commits_sqlite_reads(wal) - 1)
        # A frame whose own salts are damaged cannot be told from one of an earlier generation: it is
        # not counted (which errs towards starting).
        salts_damaged = offset >= 32 and 8 <= (offset - 32) % frame < 16
        allowed = {expected, max(0, expected - 1)} if salts_damaged else {expected}
        assert damaged_commits(wal) in allowed, offset
