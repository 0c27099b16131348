"""`DurableStore` in-process: what a snapshot leaves in the database and how the journal and the WAL
are kept small behind it (see docs/durability.md). The end-to-end crash test is test_durability.py."""

from __future__ import annotations

import sqlite3
import threading
import time
from pathlib import Path

import numpy as np

from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.persistence import DB_NAME, DurableStore, JournalWriter, scan_to_blob
from fleetmap.scan import Scan


def fan(x: float, n: int = 1081) -> Scan:
    return Scan.from_fan((x, 0.0, 0.0), -2.35, 4.7 / n, [3.0 + 0.001 * k for k in range(n)], 0.0, 30.0)


def counters() -> dict:
    return {"scans_integrated": 0, "scans_rejected": 0, "robots": {}}


def journal_rows(data_dir: Path, map_id: str = "m") -> list[int]:
    db = sqlite3.connect(data_dir / DB_NAME)
    try:
        return [r[0] for r in db.execute("SELECT id FROM journal WHERE map_id = ? ORDER BY id", (map_id,))]
    finally:
        db.close()


def journal(store: DurableStore, gmap: GridMap, scans: list[Scan], start: int = 0) -> None:
    """Apply and journal `scans` as the registry does, and wait until they are committed."""
    for k, scan in enumerate(scans):
        with gmap.lock:
            gmap.integrate(scan)
            store.journal("m", "r", start + k, 0.0, scan_to_blob(scan), lambda _row: None)
    store.writer.flush()


def wait_until(predicate, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_superseded_journal_rows_are_deleted_a_few_per_commit(tmp_path: Path, monkeypatch) -> None:
    """The switch only marks the snapshot's rows superseded; the writer deletes them TRIM_ROWS per
    transaction, also when no scan arrives, and rows after the snapshot are never touched."""
    monkeypatch.setattr(JournalWriter, "TRIM_ROWS", 7)
    store = DurableStore(tmp_path)
    try:
        gmap = GridMap(MapConfig())
        store.map_created("m", gmap).result()
        scans = [fan(0.01 * k, n=61) for k in range(40)]
        journal(store, gmap, scans)
        assert len(journal_rows(tmp_path)) == 40
        store.snapshot("m", gmap, counters)
        journal(store, gmap, scans[:5], start=40)  # rows after the snapshot stay
        wait_until(lambda: len(journal_rows(tmp_path)) == 5)
        assert store.writer.trimmed == 40
        assert not store.writer._trim
    finally:
        store.close()


def test_superseded_rows_left_by_a_crash_are_deleted_at_start(tmp_path: Path, monkeypatch) -> None:
    """A crash before the writer deleted them: the restarted store replays only the rows after the
    snapshot, and deletes the others."""
    monkeypatch.setattr(JournalWriter, "TRIM_IDLE", 3600.0)  # never trims by itself
    monkeypatch.setattr(JournalWriter, "TRIM_ROWS", 1)
    store = DurableStore(tmp_path)
    gmap = GridMap(MapConfig())
    store.map_created("m", gmap).result()
    scans = [fan(0.01 * k, n=61) for k in range(12)]
    journal(store, gmap, scans[:8])
    store.snapshot("m", gmap, counters)
    for k in range(8, 12):  # one commit each, and each deletes one superseded row
        journal(store, gmap, [scans[k]], start=k)
    assert len(journal_rows(tmp_path)) == 8  # 4 of the 8 superseded rows are still there
    # The crash: nothing closed. A new store on the same directory.
    again = DurableStore(tmp_path)
    try:
        [(map_id, restored, _counters, replay)] = again.load()
        assert map_id == "m" and [seq for _robot, seq, _stamp, _scan in replay] == [8, 9, 10, 11]
        assert len(journal_rows(tmp_path)) == 4
        window = gmap.known_bounds()
        assert window is not None
        for scan in (s for _r, _q, _t, s in replay):
            restored.integrate(scan)
        np.testing.assert_array_equal(restored.region("log_odds", *window), gmap.region("log_odds", *window))
    finally:
        again.close()


def test_the_wal_starts_over_after_each_snapshot(tmp_path: Path) -> None:
    """Under continuous journaling the WAL must not grow without bound. A passive checkpoint never
    catches up while rows keep arriving, so SQLite never rewinds the WAL by itself; after a
    snapshot's checkpoint the writer copies the tail and rewinds it."""
    store = DurableStore(tmp_path)
    stop = threading.Event()
    blob = scan_to_blob(fan(0.0))  # a 17 KB journal row

    def robot() -> None:  # rows arrive all the time, also while the snapshot checkpoints
        seq = 0
        while not stop.is_set():
            store.journal("m", "r", seq, 0.0, blob, lambda _row: None)
            seq += 1
            time.sleep(0.0005)

    try:
        gmap = GridMap(MapConfig())
        gmap.integrate(fan(0.0))
        store.map_created("m", gmap).result()
        wal = tmp_path / f"{DB_NAME}-wal"
        thread = threading.Thread(target=robot)
        thread.start()
        sizes = []
        for _round in range(5):
            time.sleep(0.4)
            store.writer.flush()
            store.snapshot("m", gmap, counters)
            sizes.append(wal.stat().st_size)
        stop.set()
        thread.join()
        # Each round writes several MB to the WAL; without the rewind it would hold all of them.
        assert sizes[-1] < 2 * sizes[0], sizes
    finally:
        stop.set()
        store.close()
