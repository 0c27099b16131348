"""The map registry and its fair queue: order per robot, fairness, seq accounting, refusals."""

from __future__ import annotations

import contextlib
import gc
import json
import logging
import os
import re
import sqlite3
import threading
import time
import tracemalloc
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from registry_idle import wait_idle

from fleetmap import persistence
from fleetmap import registry as registry_module
from fleetmap.codec import WireScan
from fleetmap.config import MapConfig
from fleetmap.fair_queue import FairQueue
from fleetmap.grid_map import GridMap
from fleetmap.journal import JournalWriter
from fleetmap.map_entry import IngestRejected
from fleetmap.persistence import DurableStore
from fleetmap.pushed_out import PushedOutRows
from fleetmap.registry import InvalidId, MapConflict, MapNotFound, MapRegistry
from fleetmap.robot_state import (
    CONFLICT_SHOWN,
    MAX_SESSIONS,
    MAX_SESSIONS_PUSHED_OUT,
    PUSHED_OUT_EXPIRY,
    RobotState,
)
from fleetmap.scan import Scan


def scan_at(x: float, r: float = 2.0, n: int = 30) -> Scan:
    return Scan.from_fan((x, 0.0, 0.0), -0.5, 1.0 / n, [r] * n, 0.0, 30.0)


@pytest.fixture
def registry():
    reg = MapRegistry(workers=2)
    reg.start()
    yield reg
    reg.close()


def test_fair_queue_round_robin_and_one_in_flight_per_source() -> None:
    q: FairQueue[str, int] = FairQueue(per_source=100, total=1000)
    for k in range(5):
        q.put("flood", k)
    q.put("quiet", 100)
    first = q.get(0.1)
    second = q.get(0.1)
    assert {first[0], second[0]} == {"flood", "quiet"}  # the quiet source is not starved
    assert q.get(0.05) is None  # flood has an item in flight: nothing else of it is handed out
    q.done("flood")
    assert q.get(0.1) == ("flood", 1)  # and its order is kept


def test_fair_queue_refuses_past_the_source_limit_without_blocking() -> None:
    q: FairQueue[str, int] = FairQueue(per_source=3, total=100)
    assert all(q.put("a", k) for k in range(3))
    started = time.monotonic()
    assert q.put("a", 3) is False
    assert time.monotonic() - started < 0.5
    assert q.put("b", 0) is True  # another source still gets in


def test_fair_queue_keeps_room_for_other_groups() -> None:
    """A sender under many robot ids of one map filled the whole queue, and another map's robot lost
    a third of its scans: a group (a map) holds at most `per_group` items."""
    q: FairQueue[tuple[str, int], int] = FairQueue(
        per_source=3, total=10, group=lambda source: source[0], per_group=5
    )
    admitted = [q.put(("flood", k), k) for k in range(10)]
    assert admitted == [True] * 5 + [False] * 5
    assert q.put(("quiet", 0), 0) and q.depth() == 6
    assert len(q._fifos) == 6  # a refused new source leaves no empty FIFO behind
    source, _ = q.get(0.1)  # type: ignore[misc]
    q.done(source)
    assert q.put(("flood", 99), 99)  # its group has room again
    q.drop_source(lambda s: s[0] == "flood")
    assert all(q.put(("flood", k), k) for k in range(5))


def test_fair_queue_bounds_the_bytes_it_holds() -> None:
    """Queued scans are held decoded: 8192 of 16,384 beams took 2.6 GB, outside the memory budget.
    With `size_of`, the queue refuses what would pass `max_bytes`, and takes again once items left."""
    q: FairQueue[str, int] = FairQueue(per_source=100, total=100, size_of=lambda item: item, max_bytes=100)
    assert q.put("a", 60) and q.put("b", 30)
    assert not q.put("c", 20)  # 110 bytes: refused, though the counts have room
    assert q.put("c", 10)
    source, _ = q.get(0.1)  # type: ignore[misc]
    q.done(source)
    assert q.put("c", 50)  # 60 went: room again
    q.drop_source(lambda s: True)
    assert q.put("d", 100) and not q.put("e", 1)


def test_the_registry_queue_counts_a_scans_beams() -> None:
    reg = MapRegistry(queue_bytes=2 * 30 * 16)  # two scans of 30 beams (bearings and ranges, 8 bytes)
    for seq in range(2):
        reg.submit("m", "r", WireScan(seq, 0.0, scan_at(0.0)))
    with pytest.raises(IngestRejected) as full:
        reg.submit("m", "r2", WireScan(0, 0.0, scan_at(0.0)))
    assert full.value.status == 503 and reg.get("m").robots["r2"].dropped == 1


def test_each_robot_is_integrated_in_seq_order(registry: MapRegistry) -> None:
    """Per-robot order is kept across two workers: the map equals the engine fed in seq order.
    The octomap clamp makes the order matter, so a reordering would show."""
    scans = [scan_at(0.1 * k, r=1.0 + 0.37 * (k % 5)) for k in range(60)]
    for k, s in enumerate(scans):
        registry.submit("m", "r1", WireScan(k, 0.0, s))
    assert wait_idle(registry)
    ref = GridMap(MapConfig())
    for s in scans:
        ref.integrate(s)
    got = registry.get("m").gmap
    b = ref.known_bounds()
    np.testing.assert_array_equal(got.region("log_odds", *b), ref.region("log_odds", *b))
    assert registry.get("m").robots["r1"].scans_integrated == 60


def test_seq_duplicates_gaps_and_restart(registry: MapRegistry) -> None:
    registry.submit("m", "r", WireScan(5, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected) as dup:
        registry.submit("m", "r", WireScan(5, 0.0, scan_at(0)))
    assert dup.value.status == 200 and "duplicate" in dup.value.reason
    registry.submit("m", "r", WireScan(9, 0.0, scan_at(0)))  # 6, 7, 8 lost
    registry.submit("m", "r", WireScan(0, 0.0, scan_at(0)))  # a restarted robot
    registry.submit("m", "r", WireScan(1, 0.0, scan_at(0)))
    assert wait_idle(registry)
    robot = registry.get("m").robots["r"]
    assert (robot.duplicates, robot.lost, robot.scans_integrated, robot.last_seq) == (1, 3, 4, 1)


def test_a_late_copy_of_seq_0_is_a_duplicate_and_a_restart_at_seq_0_is_not(tmp_path: Path) -> None:
    """docs/protocol.md, Sequence numbers: a copy of seq 0 (its original stamp, not 0) that arrives
    after later scans is a copy, without a session id too: it was taken for a restart and integrated
    again, and so was every copy after it. A `ScanPublisher(send_session_id=False)`'s cache, fetched
    again after a restart of the service, starts so while it holds the robot's first scans: a
    routine SIGTERM and restart integrated its 20 scans a second time (40, seen on the real
    service). Seq 0 of another stamp (a clock that started again earlier), or of none (0), is
    still a restart; and the service knows the run's seq 0 across its own restart."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    try:
        for seq, stamp in ((0, 5.0), (1, 6.0), (2, 7.0)):
            registry.submit("m", "plain", WireScan(seq, stamp, scan_at(0)))
            registry.submit("m", "session", WireScan(seq, stamp, scan_at(0), session=7))
        assert wait_idle(registry)
    finally:
        registry.close()
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    try:
        for seq, stamp in ((0, 5.0), (1, 6.0), (2, 7.0)):  # the robots' caches, fetched again
            for robot, session in (("plain", None), ("session", 7)):
                with pytest.raises(IngestRejected, match="duplicate"):
                    registry.submit("m", robot, WireScan(seq, stamp, scan_at(0), session=session))
        registry.submit("m", "plain", WireScan(0, 1.0, scan_at(0)))  # restarted, its clock too
        registry.submit("m", "plain", WireScan(1, 1.5, scan_at(0)))
        registry.submit("m", "plain", WireScan(0, 0.0, scan_at(0)))  # restarted again, without a clock
        assert wait_idle(registry)
        plain, session = registry.get("m").robots["plain"], registry.get("m").robots["session"]
        assert (plain.scans_integrated, plain.restarts, plain.duplicates, plain.last_seq) == (6, 2, 3, 0)
        assert (session.scans_integrated, session.restarts, session.duplicates) == (3, 0, 3)
    finally:
        registry.close()


def test_queue_full_refuses_newest_and_counts_it() -> None:
    reg = MapRegistry(workers=1, queue_per_robot=2)  # workers not started: nothing drains
    reg.submit("m", "r", WireScan(0, 0.0, scan_at(0)))
    reg.submit("m", "r", WireScan(1, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected) as full:
        reg.submit("m", "r", WireScan(2, 0.0, scan_at(0)))
    assert full.value.status == 503
    robot = reg.get("m").robots["r"]
    assert robot.dropped == 1 and robot.lost == 0
    reg.submit("m", "other", WireScan(0, 0.0, scan_at(0)))  # other robots are not affected


def test_a_scan_the_full_queue_refuses_is_told_which_bound_refused_it() -> None:
    """A robot (and a REST client's 503) was told "ingest queue full: scan dropped" alone, whether
    its own queue was full (it sends faster than it is integrated) or other robots filled its map's
    share or the whole queue (nothing it can change by sending slower): the reason now says which,
    in `last_error` too."""
    reg = MapRegistry(queue_per_robot=2, queue_total=6, queue_bytes=1 << 30)  # workers not started
    for seq in range(2):
        reg.submit("m", "r", WireScan(seq, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected) as own:
        reg.submit("m", "r", WireScan(2, 0.0, scan_at(0)))
    assert own.value.status == 503 and "ingest queue full" in own.value.reason
    assert "the robot's queue holds 2 scans waiting" in own.value.reason, own.value.reason
    assert reg.get("m").robots["r"].last_error == f"scan seq 2: {own.value.reason}"
    reg.submit("m", "s", WireScan(0, 0.0, scan_at(0)))  # map m holds its half: 3 of 6
    with pytest.raises(IngestRejected) as share:
        reg.submit("m", "t", WireScan(0, 0.0, scan_at(0)))
    assert "map 'm''s share of the queue, 3 scans of all its robots, is full" in share.value.reason
    for k in range(3):
        reg.submit(f"other{k}", "r", WireScan(0, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected) as total:
        reg.submit("another", "r", WireScan(0, 0.0, scan_at(0)))
    assert "the queue holds 6 scans of all maps' robots waiting" in total.value.reason, total.value.reason
    small = MapRegistry(queue_bytes=30 * 16)  # one scan of 30 beams (bearings and ranges, 8 bytes)
    small.submit("m", "r", WireScan(0, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected) as size:
        small.submit("n", "r", WireScan(0, 0.0, scan_at(0)))
    assert "the queue holds 480 bytes of all maps' scans waiting" in size.value.reason, size.value.reason


def test_a_scan_the_full_queue_refused_is_integrated_when_sent_again() -> None:
    """A REST client answered 503 (queue full) is told to retry later. The refused scan's seq was
    recorded (so that it is not also counted as lost), and its retry was ignored as a duplicate of
    itself: a scan the service never integrated, lost although its sender did as told."""
    reg = MapRegistry(queue_bytes=30 * 16)  # one scan of 30 beams: others' scans fill the queue
    reg.submit("m", "other", WireScan(0, 0.0, scan_at(0.0)))
    for session in (None, 77):
        with pytest.raises(IngestRejected) as full:
            reg.submit("m", f"r{session}", WireScan(4, 1.0, scan_at(1.0), session), wait=True)
        assert full.value.status == 503
    reg.start()
    try:
        assert wait_idle(reg)
        for session in (None, 77):
            retry = reg.submit("m", f"r{session}", WireScan(4, 1.0, scan_at(1.0), session), wait=True)
            assert retry is not None and retry.result(10).cell_updates > 0
            with pytest.raises(IngestRejected) as again:  # integrated once: a copy is a duplicate
                reg.submit("m", f"r{session}", WireScan(4, 1.0, scan_at(1.0), session))
            assert again.value.status == 200
            robot = reg.get("m").robots[f"r{session}"]
            counts = (robot.scans_integrated, robot.dropped, robot.duplicates, robot.lost, robot.restarts)
            assert counts == (1, 1, 1, 0, 0) and robot.last_seq == 4
    finally:
        reg.close()


def test_tile_cap_rejects_the_scan_and_counts_it(registry: MapRegistry) -> None:
    registry.create("small", MapConfig(max_tiles=1, tile_size=16, resolution=0.1))
    fut = registry.submit("small", "r", WireScan(0, 0.0, scan_at(0.0, r=20.0)), wait=True)
    with pytest.raises(IngestRejected, match="max_tiles"):
        fut.result(5)
    entry = registry.get("small")
    assert entry.scans_rejected == 1 and "max_tiles" in entry.robots["r"].last_error
    assert len(entry.gmap.store) == 0


def test_map_lifecycle_and_errors(registry: MapRegistry) -> None:
    entry, created = registry.create("a", MapConfig(resolution=0.1))
    assert created and registry.create("a", MapConfig(resolution=0.1)) == (entry, False)
    with pytest.raises(MapConflict):
        registry.create("a", MapConfig(resolution=0.2))
    with pytest.raises(InvalidId):
        registry.create("bad/id")
    registry.delete("a")
    with pytest.raises(MapNotFound):
        registry.get("a")
    off = MapRegistry(auto_create=False)
    with pytest.raises(IngestRejected) as missing:
        off.submit("nope", "r", WireScan(0, 0.0, scan_at(0)))
    assert missing.value.status == 404


def test_submit_never_blocks_while_a_map_is_locked(registry: MapRegistry) -> None:
    """A reader holding the map lock delays integration, never the (Zenoh callback) caller."""
    registry.submit("m", "r", WireScan(0, 0.0, scan_at(0)))
    assert wait_idle(registry)
    entry = registry.get("m")
    with entry.gmap.lock:
        started = time.monotonic()
        for k in range(1, 30):
            registry.submit("m", "r", WireScan(k, 0.0, scan_at(0)))
        assert time.monotonic() - started < 1.0
    assert wait_idle(registry)
    assert entry.robots["r"].scans_integrated == 30


def test_readers_never_see_half_a_scan() -> None:
    """While scans integrate, every read of the hit counts sees a whole number of scans' hits."""
    registry = MapRegistry(workers=2, queue_per_robot=256)
    registry.start()
    n = 40
    s = scan_at(0.0, r=3.0, n=n)
    registry.submit("m", "r", WireScan(0, 0.0, s))
    assert wait_idle(registry)
    gmap = registry.get("m").gmap
    b = gmap.known_bounds()
    per_scan = int(gmap.region("hits", *b).sum())
    stop = threading.Event()
    seen: list[int] = []

    def read() -> None:
        while not stop.is_set():
            seen.append(int(gmap.region("hits", *b).sum()))
            time.sleep(0.0002)  # a viewer reads now and then; a reader spinning on the lock starves writers

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        # Batches of scans until the reader has read often enough: on a busy machine (two test
        # processes on two cores) 200 scans were integrated before it had read ten times.
        seq, deadline = 1, time.monotonic() + 30
        while (seq < 200 or len(seen) <= 10) and time.monotonic() < deadline:
            for _ in range(100):
                registry.submit("m", "r", WireScan(seq, 0.0, s))
                seq += 1
            assert wait_idle(registry, 30)
    finally:
        stop.set()
        reader.join(5)
        registry.close()
    assert len(seen) > 10
    assert all(v % per_scan == 0 for v in seen)


def test_scans_create_at_most_max_auto_maps() -> None:
    """Made-up map ids cannot create maps without end; PUT-style creation still works."""
    reg = MapRegistry(max_auto_maps=3)
    for k in range(3):
        reg.submit(f"m{k}", "r", WireScan(0, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected, match="PUT") as refused:
        reg.submit("m3", "r", WireScan(0, 0.0, scan_at(0)))
    assert refused.value.status == 404
    reg.set_online("m4", "r", True)
    assert len(reg.list()) == 3
    reg.create("m5")
    assert len(reg.list()) == 4
    # Maps made with PUT count too: the refusal names the limit, not the maps held as if it were.
    with pytest.raises(IngestRejected) as refused:
        reg.submit("m6", "r", WireScan(0, 0.0, scan_at(0)))
    assert refused.value.status == 404
    assert "holds 4 maps" in refused.value.reason and "fewer than 3" in refused.value.reason, refused.value


def test_robot_ids_per_map_are_capped() -> None:
    reg = MapRegistry(max_robots_per_map=2)
    reg.submit("m", "a", WireScan(0, 0.0, scan_at(0)))
    reg.submit("m", "b", WireScan(0, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected) as refused:
        reg.submit("m", "c", WireScan(0, 0.0, scan_at(0)))
    assert refused.value.status == 429
    reg.reject("m", "d", "garbage")
    reg.set_online("m", "e", True)
    entry = reg.get("m")
    assert sorted(entry.robots) == ["a", "b"] and entry.scans_rejected == 2  # the 429 and the garbage


def test_robots_that_only_sent_garbage_give_their_place_to_real_ones() -> None:
    """Undecodable messages under 1023 made-up robot ids filled a map's robot slots for good: a real
    new robot was then refused (429). A robot with no accepted scan that is not online now makes
    room first; online robots, or robots with scans waiting, never do (a robot whose scans were
    integrated makes room once it is offline: see test_ingest)."""
    reg = MapRegistry(max_robots_per_map=3)
    reg.submit("m", "real", WireScan(0, 0.0, scan_at(0)))
    reg.set_online("m", "alive", True)
    reg.reject("m", "junk-1", "garbage")
    reg.reject("m", "junk-2", "garbage")  # junk-1 makes room
    entry = reg.get("m")
    assert sorted(entry.robots) == ["alive", "junk-2", "real"] and entry.scans_rejected == 2
    reg.submit("m", "new", WireScan(0, 0.0, scan_at(0)))  # junk-2 makes room
    assert sorted(entry.robots) == ["alive", "new", "real"]
    with pytest.raises(IngestRejected) as refused:  # nobody left who may make room
        reg.submit("m", "another", WireScan(0, 0.0, scan_at(0)))
    assert refused.value.status == 429 and entry.scans_rejected == 3


def test_a_token_going_away_for_a_robot_the_map_does_not_hold_changes_nothing() -> None:
    """A liveliness token withdrawn for a robot the map does not hold (forgotten to make room, or
    never seen: any Zenoh peer can declare and drop tokens) made room for it: an idle robot was
    forgotten, its counters gone, and an offline robot with no scan took its place."""
    reg = MapRegistry(max_robots_per_map=2)
    reg.start()
    try:
        for robot in ("a", "b"):  # integrated, so idle: either could be forgotten to make room
            future = reg.submit("m", robot, WireScan(0, 0.0, scan_at(0)), wait=True)
            assert future is not None
            future.result(timeout=30)
        entry = reg.get("m")
        reg.set_online("m", "stranger", False)
        assert sorted(entry.robots) == ["a", "b"]
        assert entry.robots["a"].scans_integrated == entry.robots["b"].scans_integrated == 1
        reg.set_online("m", "a", True)
        reg.set_online("m", "a", False)  # a robot the map holds still goes offline
        assert not entry.robots["a"].online
    finally:
        reg.close()


def test_a_restored_map_is_stored_outside_the_registry_lock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Encoding a restored map's tiles for storage takes about 1.5 ms a tile, seconds for a big map,
    while scans and every request need the registry's lock: `replace` encodes them before taking
    it. With `wait`, it returns once the map and all its tiles are committed."""
    gmap = GridMap(MapConfig(tile_size=16))
    for x in (0.0, 1.0, 2.0):
        gmap.integrate(scan_at(x, r=3.0))
    assert len(gmap.store) > 10
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    lock_free: list[bool] = []
    encode = persistence.tile_to_blob

    def encode_and_probe(*args: Any) -> bytes:
        def probe() -> None:  # another thread, as a scan's submit would be
            got = registry.lock.acquire(blocking=False)
            if got:
                registry.lock.release()
            lock_free.append(got)

        prober = threading.Thread(target=probe)
        prober.start()
        prober.join()
        return encode(*args)

    monkeypatch.setattr(persistence, "tile_to_blob", encode_and_probe)
    try:
        registry.replace("m", gmap, wait=True)
        with sqlite3.connect(registry.durable.path) as conn:
            stored = conn.execute("SELECT COUNT(*) FROM tiles WHERE map_id = 'm'").fetchone()[0]
    finally:
        registry.close()
    assert len(lock_free) == len(gmap.store) and all(lock_free)
    assert stored == len(gmap.store)


class StalledPlan:
    """Holds the planning of one map's scans until `release` is set: the scan being planned is then
    in flight (off the queue, no lock held), and the test arranges what happens meanwhile. `started`
    is set once a scan is being planned."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, gmap: GridMap) -> None:
        self.started = threading.Event()
        self.release = threading.Event()
        plan = gmap.plan

        def stalled(scan: Scan) -> Any:
            self.started.set()
            assert self.release.wait(10), "the test never released the stalled plan"
            return plan(scan)

        monkeypatch.setattr(gmap, "plan", stalled)


def test_scans_queued_for_a_deleted_or_replaced_map_are_answered_at_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """DELETE (or a snapshot PUT) throws the map's queued scans away: their callers learn it at once
    (404, or 409 when a map of that id exists again), instead of waiting out their timeout for a
    scan that will never be integrated. One worker, held by robot r's first scan: with a second one
    (the `registry` fixture's), robot s's scan stayed queued only until that worker took it (and
    stalled on it too), which it did before the DELETE whenever this thread lost the GIL in between:
    the test failed whenever a garbage collection of the whole file's run fell there.
    """
    registry = MapRegistry(workers=1)
    registry.start()
    try:
        for stamp, remove in enumerate(("delete", "replace")):
            # (Stamps that move on, as a robot's do: the same seq and stamp after the deletion would be
            # a copy of the deleted map's scan, which its tombstone ignores.)
            entry, _ = registry.create("m")
            stall = StalledPlan(monkeypatch, entry.gmap)
            first = registry.submit("m", "r", WireScan(0, float(stamp), scan_at(0)), wait=True)
            assert stall.started.wait(5)
            queued = [
                registry.submit("m", rid, WireScan(1, float(stamp), scan_at(0)), wait=True)
                for rid in ("r", "s")
            ]
            assert registry.backlog()[0] == 2
            if remove == "delete":
                registry.delete("m")
            else:
                registry.replace("m", GridMap(MapConfig()))
            for future in queued:
                with pytest.raises(IngestRejected) as gone:
                    future.result(2)
                status, says = (404, "deleted before the scan") if remove == "delete" else (409, "replaced")
                assert gone.value.status == status and says in gone.value.reason
            assert registry.backlog()[0] == 0
            stall.release.set()
            first.exception(5)  # answered too (what it says: test_a_scan_in_flight_...)
            assert wait_idle(registry)
            if remove == "replace":
                assert registry.get("m").robots == {}  # the new map never saw these scans
                registry.delete("m")
    finally:
        registry.close()


def test_a_scan_in_flight_when_its_map_is_replaced_reaches_neither_map(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scan being planned (no lock held) while its map is deleted and created again: it is applied
    to neither map, leaves no journal row (which the new map would replay after a restart), and its
    caller gets 409. `test_durability.py` checks the same through a kill -9 of the real service."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    try:
        old, _ = registry.create("m", wait=True)
        stall = StalledPlan(monkeypatch, old.gmap)
        future = registry.submit("m", "old-robot", WireScan(0, 0.0, scan_at(0.0)), wait=True)
        assert stall.started.wait(5)
        registry.delete("m", wait=True)
        new, _ = registry.create("m", MapConfig(resolution=0.1), wait=True)
        stall.release.set()
        with pytest.raises(IngestRejected) as gone:
            future.result(5)
        assert gone.value.status == 409 and "not integrated" in gone.value.reason
        assert wait_idle(registry)
        assert (new.robots, new.scans_integrated, len(new.gmap.store)) == ({}, 0, 0)
        assert len(old.gmap.store) == 0  # not applied to the old one either
        with sqlite3.connect(registry.durable.path) as conn:
            assert conn.execute("SELECT COUNT(*) FROM journal").fetchone()[0] == 0
    finally:
        registry.close()
    again = MapRegistry(durable=DurableStore(tmp_path))
    again.start()
    try:
        restored = again.get("m")
        assert (restored.config.resolution, restored.robots, len(restored.gmap.store)) == (0.1, {}, 0)
    finally:
        again.close()


def test_a_map_created_by_a_refused_scan_is_removed_again(tmp_path: Path) -> None:
    """A scan to a new map id creates the map; when the scan is refused (here 422, past max_tiles),
    the map, holding nothing, is removed again, from storage too: a refused message changes no map.
    A map that another robot's scan reached meanwhile, or that a PUT or a liveliness token claimed,
    stays. Every scan is queued while this test holds the registry's lock, which a worker needs
    before it looks at a scan, so no interleaving decides the outcome. (Queuing them before
    `start` instead raced with its restore: a map the journal writer had stored meanwhile came back
    as a new map, and its scan was answered 409, "replaced".)"""
    small = MapConfig(max_tiles=1, tile_size=16, resolution=0.1)
    too_big = WireScan(0, 0.0, scan_at(0.0, r=20.0))
    fits = WireScan(0, 0.0, Scan.from_fan((0.5, 0.8, 0.0), -0.5, 0.1, [0.5] * 10, 0.0, 30.0))
    registry = MapRegistry(default_config=small, durable=DurableStore(tmp_path))
    registry.start()
    try:
        with registry.lock:
            alone = registry.submit("alone", "r", too_big, wait=True)
            shared = registry.submit("shared", "a", too_big, wait=True)
            registry.submit("shared", "b", fits)
            registry.submit("put", "r", too_big)
            registry.create("put", small)  # a PUT of the same configuration: asked for by name
            registry.submit("token", "r", too_big)
            registry.set_online("token", "r", True)  # the robot's liveliness token would create it anyway
        for future in (alone, shared):
            with pytest.raises(IngestRejected) as refused:
                future.result(5)
            assert refused.value.status == 422 and "max_tiles" in refused.value.reason
        assert wait_idle(registry)
        assert sorted(entry.id for entry in registry.list()) == ["put", "shared", "token"]
        assert "removed again" in alone.exception().reason and "removed" not in shared.exception().reason
        robots = registry.get("shared").robots
        assert (robots["a"].scans_rejected, robots["b"].scans_integrated) == (1, 1)
        with sqlite3.connect(registry.durable.path) as conn:
            assert sorted(row[0] for row in conn.execute("SELECT id FROM maps")) == ["put", "shared", "token"]
    finally:
        registry.close()


def test_a_map_created_by_a_scan_the_full_queue_refuses_is_removed_again() -> None:
    reg = MapRegistry(queue_total=1)  # workers not started: the first scan fills the queue
    reg.submit("first", "r", WireScan(0, 0.0, scan_at(0)))
    with pytest.raises(IngestRejected) as full:
        reg.submit("second", "r", WireScan(0, 0.0, scan_at(0)))
    assert [entry.id for entry in reg.list()] == ["first"]
    assert full.value.status == 503 and "removed again" in full.value.reason


def test_robot_counters_survive_a_crash_and_a_shutdown_with_no_scan_since_the_snapshot(
    tmp_path: Path,
) -> None:
    """After a crash the journal's replay counts a robot's seq gaps as lost again (they came back as
    0); a clean shutdown snapshots a map even when only refused messages arrived since its last
    snapshot (its duplicates and rejected counts went back to 0)."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    for seq in (0, 1, 5):  # 3 and 4 and 2 never arrive: 3 lost
        registry.submit("m", "r", WireScan(seq, 0.0, scan_at(0.1 * seq)), wait=True).result(10)  # type: ignore[union-attr]
    assert registry.get("m").robots["r"].lost == 3
    registry.queue.close()  # a crash: no snapshot, only the journal
    for t in registry._workers:
        t.join(5)
    registry.durable.close()  # type: ignore[union-attr]
    crashed = MapRegistry(durable=DurableStore(tmp_path))
    crashed.start()
    robot = crashed.get("m").robots["r"]
    assert (robot.scans_integrated, robot.last_seq, robot.lost) == (3, 5, 3)
    crashed.close()  # snapshots: the counters are now in the snapshot

    again = MapRegistry(durable=DurableStore(tmp_path))
    again.start()
    with pytest.raises(IngestRejected):
        again.submit("m", "r", WireScan(4, 0.0, scan_at(0.0)))  # a duplicate: no journal row
    again.reject("m", "r", "garbage")
    again.close()
    last = MapRegistry(durable=DurableStore(tmp_path))
    last.start()
    try:
        robot = last.get("m").robots["r"]
        assert (robot.duplicates, robot.scans_rejected, robot.lost, robot.last_error) == (1, 1, 3, "garbage")
    finally:
        last.close()


def test_a_live_robot_shows_online_in_its_map_created_again() -> None:
    """A robot whose liveliness token stayed up showed offline (and was missing) in its map deleted
    and created again, until its next scan: the registry remembers the tokens present."""
    reg = MapRegistry()
    reg.set_online("m", "r", True)  # the token creates the map
    assert reg.get("m").robots["r"].online
    reg.delete("m")
    created, _ = reg.create("m")
    assert created.robots["r"].online
    reg.set_online("m", "r", False)
    reg.delete("m")
    assert "r" not in reg.create("m")[0].robots  # a token gone is forgotten


def _crash(registry: MapRegistry) -> None:
    """Stop `registry` as a crash would: no snapshot, only the journal."""
    registry.queue.close()
    for t in registry._workers:
        t.join(5)
    registry.durable.close()  # type: ignore[union-attr]


@contextlib.contextmanager
def _restarted(data_dir: Path) -> Iterator[MapRegistry]:
    """A registry started again on `data_dir` (its maps restored), closed after the block."""
    registry = MapRegistry(durable=DurableStore(data_dir))
    registry.start()
    try:
        yield registry
    finally:
        registry.close()


def test_a_scan_submitted_while_the_registry_closes_is_not_taken_and_the_next_process_takes_it(
    tmp_path: Path,
) -> None:
    """A scan submitted after `close` began (Zenoh runs scan callbacks for a moment after the
    ingest's session closed) is refused as `shutting_down`, and nothing of it is recorded: the
    closing snapshot does not save its seq, so when the robot's cache sends it again to the next
    process it is integrated, not ignored as a duplicate. Counted as a full queue's instead, its
    seq was saved as settled (refused), and the scan was never integrated anywhere
    (tests/test_crash_exactly_once.py lost 56 scans of a robot so, at a SIGTERM during a fetch)."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    scans = [WireScan(seq, 10.0 + seq, scan_at(0.1 * seq), session=7) for seq in range(4)]
    for wire in scans[:3]:
        registry.submit("m", "r", wire, wait=True).result(10)  # type: ignore[union-attr]
    refusals: list[IngestRejected] = []
    close_queue = registry.queue.close

    def close_then_a_scan_arrives() -> None:
        close_queue()
        with pytest.raises(IngestRejected) as refused:
            registry.submit("m", "r", scans[3])
        refusals.append(refused.value)

    registry.queue.close = close_then_a_scan_arrives  # type: ignore[method-assign]
    registry.close()  # its final snapshot
    assert [(r.kind, r.status) for r in refusals] == [("shutting_down", 503)]
    robot = registry.get("m").robots["r"]
    assert (robot.last_seq, robot.dropped, robot.lost, robot.last_error) == (2, 0, 0, None)
    with _restarted(tmp_path) as again:
        assert again.get("m").robots["r"].last_seq == 2
        again.submit("m", "r", scans[3], wait=True).result(10)  # type: ignore[union-attr]
        robot = again.get("m").robots["r"]
        assert (robot.scans_integrated, robot.duplicates, robot.dropped, robot.lost) == (4, 0, 0, 0)
        assert again.delivery_status("m", "r", 7).session(7).integrated == 4  # type: ignore[union-attr]


def test_a_database_and_snapshot_from_before_session_ids_still_load(tmp_path: Path) -> None:
    """A data directory written before session ids: journal rows without the `session` column and
    robots saved without `sessions`. It loads, the column is added, and the robot's scans (which
    carried no session id) go on as before: a gap is lost, seq 0 with stamp 0 is a restart, a copy
    of the last scan a duplicate."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    for seq in (0, 1, 2):
        registry.submit("m", "r", WireScan(seq, 10.0 + seq, scan_at(0.1 * seq)), wait=True).result(10)  # type: ignore[union-attr]
    registry.close()  # snapshotted
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    for seq in (3, 5):
        registry.submit("m", "r", WireScan(seq, 10.0 + seq, scan_at(0.1 * seq)), wait=True).result(10)  # type: ignore[union-attr]
    _crash(registry)
    with sqlite3.connect(registry.durable.path) as conn:  # type: ignore[union-attr]
        conn.execute("ALTER TABLE journal DROP COLUMN session")
        for robot_id, state in conn.execute("SELECT robot_id, state FROM robots").fetchall():
            old = {
                k: v for k, v in json.loads(state).items() if k not in RobotState.SAVED[-3:] + ("sessions",)
            }
            conn.execute("UPDATE robots SET state = ? WHERE robot_id = ?", (json.dumps(old), robot_id))
    with _restarted(tmp_path) as again:
        robot = again.get("m").robots["r"]
        assert (robot.scans_integrated, robot.last_seq, robot.lost, robot.restarts) == (5, 5, 1, 0)
        with pytest.raises(IngestRejected, match="duplicate"):
            again.submit("m", "r", WireScan(5, 15.0, scan_at(0.0)))
        again.submit("m", "r", WireScan(0, 0.0, scan_at(0.0)), wait=True).result(10)  # type: ignore[union-attr]
        assert (robot.duplicates, robot.restarts, robot.last_seq) == (1, 1, 0)
        with sqlite3.connect(again.durable.path) as conn:  # type: ignore[union-attr]
            assert "session" in {row[1] for row in conn.execute("PRAGMA table_info(journal)")}


def test_a_robots_sessions_stay_bounded_and_survive_its_saved_state() -> None:
    """A sender that makes up a session id per scan holds at most MAX_SESSIONS of them; the saved
    state (JSON, as in the snapshot) gives back the same bookkeeping."""
    robot = RobotState()
    for k in range(3 * MAX_SESSIONS):
        assert not robot.is_duplicate(0, 0.0, 1000 + k)
        robot.accept(0, 0.0, 1000 + k, now=1.0)
    assert len(robot.sessions) == MAX_SESSIONS
    assert (robot.restarts, robot.id_conflicts) == (3 * MAX_SESSIONS - 1, 0)
    restored = RobotState.from_saved(json.loads(json.dumps(robot.saved())))
    assert restored.sessions == robot.sessions and restored.saved() == robot.saved()
    assert restored.is_duplicate(0, 0.0, 1000 + 3 * MAX_SESSIONS - 1)
    assert not restored.in_conflict(1.0)


def test_many_robots_under_one_id_stay_told_apart_in_bounded_memory_and_saved_state() -> None:
    """136 sessions under one robot id, each pushed out by the others before it comes back, are
    all still known: one conflict each but the first, nothing restarted or lost, a copy of a scan
    of the session pushed out longest ago a duplicate, counted in its ledger; so after the saved
    state is read back (the sessions pushed out were not saved: their copies, a robot's cache
    fetched again after a restart of the service, were new). A session more pushes the oldest out
    for good, as does the robot's PUSHED_OUT_EXPIRY-th scan since a session's last: each comes back
    as a new session (a restart). Their rows hold the memory the docs say."""
    crowd = MAX_SESSIONS + MAX_SESSIONS_PUSHED_OUT
    robot = RobotState()
    for seq in range(3):
        for session in range(1, crowd + 1):
            assert not robot.is_duplicate(seq, float(seq), session)
            robot.accept(seq, float(seq), session, now=1.0)
    assert (robot.restarts, robot.lost, robot.id_conflicts) == (0, 0, crowd - 1)
    assert len(robot.pushed_out) == MAX_SESSIONS_PUSHED_OUT and not robot.settling
    saved = json.loads(json.dumps(robot.saved()))
    restored = RobotState.from_saved(saved)
    assert restored.pushed_out == robot.pushed_out and restored.saved() == robot.saved()
    row = saved["pushed_out"][0]
    for damaged in (
        "x",
        [row[:-1]],
        [[*row[:-1], "1"]],
        [[row[0], 1.5, *row[2:]]],
        [[2**63, *row[1:]]],
        [[*row[:4], -1, *row[5:]]],
    ):
        with pytest.raises(ValueError, match="pushed_out|wrong shape"):
            RobotState.from_saved({**saved, "pushed_out": damaged})
    for state in (robot, restored):
        assert state.is_duplicate(1, 1.0, 1)
        assert state.count_duplicate(1).ledger.duplicates == 1
        seqs = state.session_seqs(1)
        assert seqs is not None and (seqs.last_seq, seqs.ledger.integrated, seqs.ledger.duplicates) == (
            2,
            0,
            1,
        )
        assert not state.is_duplicate(3, 3.0, 1)
        state.accept(3, 3.0, 1, now=2.0)  # back from the oldest row: no restart, no conflict more
        assert (state.restarts, state.lost, state.id_conflicts) == (0, 0, crowd - 1)

    robot.accept(0, 9.0, crowd + 1, now=3.0)  # one more: session 2, pushed out longest ago, goes
    assert 2 not in robot.pushed_out and len(robot.pushed_out) == MAX_SESSIONS_PUSHED_OUT
    assert not robot.is_duplicate(2, 2.0, 2)
    assert 3 in robot.pushed_out
    robot.accepted += PUSHED_OUT_EXPIRY  # (a million scans of sessions heard since)
    robot.accept(0, 9.0, crowd + 2, now=3.0)  # pushes one out: every row expired
    assert not robot.pushed_out and len(robot.sessions) == MAX_SESSIONS
    assert not robot.is_duplicate(2, 2.0, 3)
    restarts = robot.restarts
    robot.accept(3, 3.0, 3, now=3.0)
    assert robot.restarts == restarts + 1

    saved = json.loads(json.dumps(restored.saved()))  # (with session 1's last scan, 3)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        with_rows = RobotState.from_saved(saved)
        gc.collect()  # (what it holds, not garbage waiting for a collection)
        middle = tracemalloc.get_traced_memory()[0]
        without = RobotState.from_saved({**saved, "pushed_out": []})
        gc.collect()
        rows = (middle - before) - (tracemalloc.get_traced_memory()[0] - middle)
    finally:
        tracemalloc.stop()
    assert len(with_rows.pushed_out) == MAX_SESSIONS_PUSHED_OUT and not without.pushed_out
    assert 10_000 < rows < 16_000  # about 14 kB (docs/security.md)


def test_a_robots_scans_read_no_row_of_its_sessions_pushed_out_unless_one_comes_back(monkeypatch) -> None:
    """A robot that restarted 139 times holds 128 sessions of its past in rows: each scan of its
    current session looked at all of them (decoded whole, 5 µs a row) for sessions heard since,
    0.7 ms a scan under the registry's lock, where none can be (each was pushed out as the least
    recently heard). Its scans read no row now; a session that comes back from them reads only the
    column of when each was heard, and decodes the rows a conflict changes."""
    robot = RobotState()
    for session in range(1, 140):  # restarts: one scan each
        robot.accept(0, 1.0, session, now=1.0)
    assert len(robot.pushed_out) == MAX_SESSIONS_PUSHED_OUT
    decoded: list[int] = []
    real_row = PushedOutRows._row
    monkeypatch.setattr(
        PushedOutRows, "_row", lambda rows, index: decoded.append(index) or real_row(rows, index)
    )
    for seq in range(1, 100):
        robot.accept(seq, 1.0, 139, now=1.0)
    assert decoded == []
    robot.accept(1, 1.0, 100, now=1.0)  # back, beside 101 to 139: its row, and the rows of 101-131
    assert len(decoded) == 1 + (139 - MAX_SESSIONS) - 100 and robot.id_conflicts == 139 - 100


def test_a_session_whose_lost_count_passes_64_bits_is_pushed_out_all_the_same() -> None:
    """Scans without a session id that restart at seqs near 2**63 (a seq below the last, a later
    stamp) each add their seq to the session's `lost`: past what a pushed-out session's row holds,
    the scan of a ninth session that pushed it out failed (struct.error under the registry's lock)."""
    robot = RobotState()
    for stamp, seq in enumerate([2**63 - 1, 2**63 - 2, 2**63 - 3, *range(MAX_SESSIONS)]):
        session = None if seq > MAX_SESSIONS else 1 + seq
        robot.accept(seq, float(stamp), session, now=1.0)
        ledger = robot.sessions[session or 0].ledger
        ledger.settle(ledger.open(seq), integrated=True)
    plain = robot.session_seqs(None)
    assert 0 in robot.pushed_out and plain is not None and plain.ledger.lost == 2**63 - 1
    assert robot.lost == (2**63 - 2) + (2**63 - 3) + sum(range(MAX_SESSIONS))  # (unclamped)


def test_a_robots_scans_refused_for_the_services_sake_survive_its_saved_state() -> None:
    """The scans refused for the service's sake (a full queue, the memory budget) that the robot may
    send again are saved with it, in order, so that a re-send after a restart is still new
    (tests/test_memory_budget.py runs it through the real service); a damaged list is refused."""
    robot = RobotState()
    for seq, session in [(0, 7), (1, 7), (2, 7), (0, None)]:
        robot.accept(seq, float(seq), session, now=1.0)
    robot.note_refused(2, 7)
    robot.note_refused(1, 7)
    saved = json.loads(json.dumps(robot.saved()))
    restored = RobotState.from_saved(saved)
    assert list(restored.refused_scans) == [(7, 2), (7, 1)]
    assert not restored.is_duplicate(1, 1.0, 7) and restored.is_duplicate(0, 0.0, 7)
    for damaged in ({"7": 1}, [[7]], [[7, "1"]], [[7, True]], [[7, 1.5]]):
        with pytest.raises(ValueError, match="refused_scans"):
            RobotState.from_saved({**saved, "refused_scans": damaged})


def test_interleaved_sessions_are_a_conflict_shown_for_a_minute_and_a_late_copy_is_not() -> None:
    """Two publishers under one id: each one's seqs counted apart (no duplicate, lost or restart
    from switching), one conflict; a third joins: one more, its restart withdrawn too. The conflict
    shows until CONFLICT_SHOWN after the last interleaved scan. A late copy of an ended session's
    scan after a restart is a duplicate, not a conflict."""
    robot = RobotState()
    for seq, session in [(0, 1), (0, 2), (1, 1), (1, 2), (3, 1), (2, 2), (0, 3), (4, 1), (3, 2)]:
        assert not robot.is_duplicate(seq, 0.0, session)
        robot.accept(seq, 0.0, session, now=100.0)
    assert (robot.lost, robot.restarts, robot.duplicates, robot.id_conflicts) == (1, 0, 0, 2)
    assert robot.is_duplicate(3, 0.0, 1) and not robot.is_duplicate(5, 0.0, 1)
    assert robot.in_conflict(100.0 + CONFLICT_SHOWN - 1) and not robot.in_conflict(100.0 + CONFLICT_SHOWN)

    # The service's clock stepped back an hour (NTP) after the last interleaved scan: not shown for
    # the hour and a minute until the clock is back there (`conflict_at` is wall-clock time, saved).
    assert not robot.in_conflict(100.0 - 3600.0)

    restarted = RobotState()
    for k in range(3):
        restarted.accept(k, 50.0 + k, 7, now=1.0)
    assert not restarted.is_duplicate(0, 0.0, 8)  # a new session at seq 0, clock at 0: a restart
    restarted.accept(0, 0.0, 8, now=2.0)
    assert restarted.is_duplicate(2, 52.0, 7)  # a late copy of the old run's scan
    # Within a session, stamps say nothing: a copy of seq 0, or with a later stamp, is a duplicate.
    assert restarted.is_duplicate(0, 50.0, 7) and restarted.is_duplicate(1, 99.0, 7)
    assert (restarted.restarts, restarted.id_conflicts, restarted.in_conflict(2.0)) == (1, 0, False)


@pytest.mark.parametrize("session", [None, 7])
def test_a_crash_replays_scans_queued_at_the_snapshot_without_a_restart(
    tmp_path: Path, session: int | None
) -> None:
    """Scans accepted before a snapshot but applied after it are in the snapshot's counters (their
    seqs accepted) and in the journal after it. Replaying them after a crash must not count them
    again: it counted a restart and their seq as lost for a robot that sends no session id.

    In-process rather than through the service: the test holds the map's lock so that the scans
    wait in the queue while the snapshot is taken, which a process cannot be made to do."""
    registry = MapRegistry(workers=1, durable=DurableStore(tmp_path))
    registry.start()
    for seq in (0, 1):
        registry.submit("m", "r", WireScan(seq, 10.0 + seq, scan_at(0.1 * seq), session), wait=True).result(
            10
        )  # type: ignore[union-attr]
    entry = registry.get("m")
    with entry.gmap.lock:  # the worker waits for it to apply 2 and 3
        queued = [
            registry.submit("m", "r", WireScan(seq, 10.0 + seq, scan_at(0.1 * seq), session), wait=True)
            for seq in (2, 3)
        ]
        registry.snapshot_all(every_map=True)  # counters with seq 3 accepted, journal up to seq 1
    for future in queued:
        future.result(10)  # type: ignore[union-attr]
    _crash(registry)
    with _restarted(tmp_path) as again:
        robot = again.get("m").robots["r"]
        assert (robot.scans_integrated, robot.last_seq, robot.lost, robot.restarts) == (4, 3, 0, 0)
        with pytest.raises(IngestRejected, match="duplicate"):
            again.submit("m", "r", WireScan(3, 13.0, scan_at(0.0), session))


def test_an_integration_bug_is_counted_every_time_and_its_traceback_logged_rate_limited(
    registry: MapRegistry, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A bug that makes every scan's integration raise (here the engine's `plan`, replaced) must not
    kill the workers, and each scan is refused and counted; but its traceback used to be logged for
    every scan, hundreds a second under a fleet. It is logged once per kind and place per 5 s, with
    the count of those held back on the next line."""

    def broken(self: GridMap, scan: Scan) -> None:
        raise KeyError("a bug")

    registry.create("m", MapConfig())  # not one its first scan makes: that one goes with the refusal
    monkeypatch.setattr(GridMap, "plan", broken)
    caplog.set_level(logging.ERROR, logger="fleetmap.registry")
    for seq in range(40):
        registry.submit("m", "r", WireScan(seq, 0.0, scan_at(0.0)))
    assert wait_idle(registry)
    robot = registry.get("m").robots["r"]
    assert robot.scans_rejected == 40 and robot.scans_integrated == 0
    assert "internal error: 'a bug'" in (robot.last_error or "")
    bugs = [r for r in caplog.records if "integration of m/r seq" in r.getMessage()]
    assert len(bugs) == 1, [r.getMessage() for r in bugs]
    assert bugs[0].exc_info is not None and "KeyError" in bugs[0].getMessage()


def test_a_snapshot_pass_never_stores_a_map_replaced_after_it_listed_the_maps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`snapshot_all` lists the maps, then snapshots them one after the other (seconds, for big
    maps). A map deleted and created again (or replaced by an upload) meanwhile must not be stored
    from the old map's entry: that snapshot passed the incarnation check (the id's current creation
    time was read from the old entry's turn), so the new map's stored snapshot got the old map's
    tiles and counters, and its snapshot clock, so that later snapshots skipped the new map's own
    tiles. After a restart the new map held the deleted map's cells and lost its own."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    try:
        registry.create("a", wait=True)
        old, _ = registry.create("m", wait=True)
        for map_id, x in (("a", 0.0), ("m", 0.0)):
            registry.submit(map_id, "r", WireScan(0, 0.0, scan_at(x)), wait=True).result(5)
        old.gmap.integrate(scan_at(200.0))  # (more of the old map's tiles; journaled or not is no matter)
        snapshot = registry.durable.snapshot  # type: ignore[union-attr]
        replaced: list[str] = []

        def snapshot_then_replace(map_id: str, *args: Any, **kwargs: Any) -> int:
            # The pass listed both maps; while it stores "a", "m" is deleted and created again, and
            # the new map takes a scan of its own far from the old one's.
            if map_id == "a" and not replaced:
                replaced.append(map_id)
                registry.delete("m", wait=True)
                registry.create("m", wait=True)
                registry.submit("m", "s", WireScan(0, 0.0, scan_at(-100.0)), wait=True).result(5)
            return snapshot(map_id, *args, **kwargs)

        monkeypatch.setattr(registry.durable, "snapshot", snapshot_then_replace)
        registry.snapshot_all()
        assert replaced
        monkeypatch.undo()
        new = registry.get("m")
        assert new is not old
        registry.submit("m", "s", WireScan(1, 0.0, scan_at(-100.5)), wait=True).result(5)
        want = _tiles(new.gmap)
        want_robots = set(new.robots)
    finally:
        registry.close()  # its final snapshot stores the new map
    with _restarted(tmp_path) as again:
        restored = again.get("m")
        got = _tiles(restored.gmap)
        assert set(got) == set(want)  # none of the old map's tiles
        for key, arrays in want.items():
            for name, array in arrays.items():
                np.testing.assert_array_equal(got[key][name], array)
        assert set(restored.robots) == want_robots == {"s"}


def _tiles(gmap: GridMap) -> dict[tuple[int, int], dict[str, np.ndarray]]:
    """Copies of every tile of `gmap`: key -> array name -> cells."""
    store = gmap.store
    with gmap.lock:
        return {
            key: {a.name: store.pools[a.name][slot].copy() for a in store.arrays}
            for key, slot in store.slots.items()
        }


def test_a_map_created_again_right_after_a_snapshot_switch_keeps_its_own_snapshot_state(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The snapshot thread records what a snapshot stored (the map's clock, its journal rows counted
    from zero) once the writer has committed the switch. A map deleted and created again in between
    got the OLD map's clock recorded as its own: its next snapshots skipped every tile of its own
    whose version was below it, while the journal rows those tiles came from were trimmed, so a
    restart lost them."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    durable = registry.durable
    assert durable is not None
    try:
        registry.create("m", wait=True)
        for seq in range(3):  # the old map's clock: above the new map's first versions
            registry.submit("m", "r", WireScan(seq, 0.0, scan_at(0.1 * seq)), wait=True).result(5)
        run = durable.writer.run
        recreated: list[bool] = []

        def run_then_recreate(op: Any) -> Any:
            result = run(op)
            if getattr(op, "__name__", "") == "switch" and not recreated:
                # Committed; the snapshot thread has not recorded it yet.
                recreated.append(True)
                registry.delete("m", wait=True)
                registry.create("m", wait=True)
            return result

        monkeypatch.setattr(durable.writer, "run", run_then_recreate)
        registry.snapshot_all()
        monkeypatch.undo()
        assert recreated
        registry.submit("m", "s", WireScan(0, 0.0, scan_at(-100.0)), wait=True).result(5)
        registry.snapshot_all()  # stores the new map's tile, and trims its journal row
        want = _tiles(registry.get("m").gmap)
        assert want
    finally:
        _crash(registry)
    with _restarted(tmp_path) as again:
        got = _tiles(again.get("m").gmap)
        assert set(got) == set(want)
        for key, arrays in want.items():
            for name, array in arrays.items():
                np.testing.assert_array_equal(got[key][name], array)


def test_a_put_that_finds_the_map_answers_once_the_maps_creation_is_stored(tmp_path: Path) -> None:
    """Two PUT /maps/{id} at once (or a PUT right after a robot's first scan created the map): the
    one that finds the map created answers 200 "exists". It answered at once, while the creation
    still waited for the journal writer, so a crash right after that answer lost the map the client
    was told exists. Now it answers once the creation is committed, as the creating PUT does."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    durable = registry.durable
    assert durable is not None
    held, go = threading.Event(), threading.Event()
    try:

        def busy(_conn: sqlite3.Connection) -> None:
            held.set()
            assert go.wait(10)

        durable.writer.submit(busy)  # the writer is busy: the creation waits behind this
        assert held.wait(5)
        first: list[bool] = []
        creating = threading.Thread(target=lambda: first.append(registry.create("m", wait=True)[1]))
        creating.start()
        while "m" not in registry.maps:
            time.sleep(0.001)
        second: list[bool] = []
        finding = threading.Thread(target=lambda: second.append(registry.create("m", wait=True)[1]))
        finding.start()
        finding.join(0.3)
        assert finding.is_alive() and not second  # not answered while the map is not stored
        go.set()
        creating.join(5)
        finding.join(5)
        assert (first, second) == ([True], [False])
    finally:
        go.set()
        registry.close()


def test_a_restored_or_uploaded_maps_bounds_are_read_before_it_is_served(tmp_path: Path) -> None:
    """The first `GET /maps/{id}` of a map after a start or an upload read every tile for its bounds
    under the map's lock (0.2-0.5 s for a 1 km map of 6,400 tiles, ingest of the map waiting). They
    are read before the map is installed now: the first bounds asked for read no tile."""
    gmap = GridMap(MapConfig(tile_size=16))
    for x in (0.0, 1.0, 2.0):
        gmap.integrate(scan_at(x, r=3.0))
    expected = GridMap.known_bounds(gmap)
    gmap._bounds_answer = ((-1, -1), None)  # forget it, as a freshly loaded map has nothing
    gmap._bounds_version[:] = -1
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    try:
        entry = registry.replace("m", gmap, wait=True)
        read: list[int] = []
        observed = entry.gmap._observed
        entry.gmap._observed = lambda slot: read.append(slot) or observed(slot)  # type: ignore[method-assign]
        assert entry.gmap.known_bounds() == expected and read == []
    finally:
        registry.close()
    restarted = MapRegistry(durable=DurableStore(tmp_path))
    restarted.start()
    try:
        gmap = restarted.maps["m"].gmap
        read = []
        observed = gmap._observed
        gmap._observed = lambda slot: read.append(slot) or observed(slot)  # type: ignore[method-assign]
        assert gmap.known_bounds() == expected and read == []
    finally:
        restarted.close()


def test_robots_whose_every_scan_broke_the_input_limits_give_their_place_first() -> None:
    """A well-formed scan that breaks the input limits (a pose outside the world bound), with a
    session id, is settled as refused with its seq recorded (for the delivery query): a robot that
    sent only such scans had a seq, so it no longer made room first, and scans under made-up robot
    ids made a full map forget its real offline robots (their counters), as only valid scans could;
    and each such robot forgotten took a tombstone (the database's, and pushing real forgotten
    robots' out), though none of its scans is in the map to keep from being integrated twice."""
    reg = MapRegistry(max_robots_per_map=2)
    reg.start()
    try:
        future = reg.submit("m", "real", WireScan(0, 0.0, scan_at(0), 5), wait=True)
        assert future is not None
        future.result(timeout=120)
        for k in range(1, 4):
            reason = "scan seq 0 refused: pose (1e+06, 0) is outside the world bound of +-100000 m"
            reg.reject("m", f"junk-{k}", reason, (0, 0.0, 1000 + k))
        entry = reg.get("m")
        assert sorted(entry.robots) == ["junk-3", "real"]
        assert [reg.tombstones.get("m", f"junk-{k}") for k in (1, 2)] == [None, None]
    finally:
        reg.close()


def _snapshot_generations(data: Path) -> dict[str, int]:
    """Each stored map's snapshot generation, which every snapshot of the map moves on."""
    with contextlib.closing(sqlite3.connect(f"file:{data / 'fleetmap.db'}?mode=ro", uri=True)) as conn:
        return dict(conn.execute("SELECT id, snapshot_gen FROM maps").fetchall())


def test_a_clean_stop_snapshots_only_the_maps_with_something_unsaved(tmp_path: Path) -> None:
    """The stop's last pass snapshotted every map, also one with nothing new since its last
    snapshot: a writer round trip and a synced transaction each, about 5 ms a map, so a service of
    5,000 idle maps took 27 s to stop (Docker kills after 10 s by default). It snapshots the maps the
    periodic pass would: journaled scans, or counts and tombstones that only a snapshot stores."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    for map_id in ("idle", "scanned", "refused"):
        registry.create(map_id, wait=True)
    registry.submit("refused", "r", WireScan(0, 0.0, scan_at(0.0)), wait=True).result(10)  # type: ignore[union-attr]
    registry.close()
    before = _snapshot_generations(tmp_path)

    again = MapRegistry(durable=DurableStore(tmp_path))
    again.start()
    again.submit("scanned", "r", WireScan(0, 0.0, scan_at(0.0)), wait=True).result(10)  # type: ignore[union-attr]
    with pytest.raises(IngestRejected):
        again.submit("refused", "r", WireScan(0, 0.0, scan_at(0.0)))  # a duplicate: no journal row
    again.close()
    after = _snapshot_generations(tmp_path)
    assert after["idle"] == before["idle"], "a map with nothing new was snapshotted again"
    assert after["scanned"] != before["scanned"] and after["refused"] != before["refused"]

    last = MapRegistry(durable=DurableStore(tmp_path))
    last.start()
    try:
        assert last.get("scanned").robots["r"].scans_integrated == 1
        assert last.get("refused").robots["r"].duplicates == 1
    finally:
        last.close()


def test_the_last_snapshot_of_a_stop_is_not_paced(tmp_path: Path) -> None:
    """Snapshots pace themselves (`DurableStore.snapshot_pace`: a sleep after each tile) so that the
    workers integrating scans keep the cores; the stop's last snapshot slept as much, though no
    worker runs by then, and 61,000 changed tiles took 22 s to store where they need 10 (Docker
    kills after 10 s by default). A pace that would sleep for hours shows it: the stop still ends."""
    registry = MapRegistry(durable=DurableStore(tmp_path, snapshot_interval=3600.0, snapshot_pace=1e7))
    registry.start()
    registry.submit("m", "r", WireScan(0, 0.0, scan_at(0.0)), wait=True).result(10)  # type: ignore[union-attr]
    stopping = threading.Thread(target=registry.close, daemon=True)  # (daemon: a hung one is left behind)
    stopping.start()
    stopping.join(120)
    assert not stopping.is_alive(), "the stop's last snapshot slept its pace"
    with contextlib.closing(sqlite3.connect(tmp_path / "fleetmap.db")) as conn:
        assert conn.execute("SELECT COUNT(*) FROM tiles WHERE map_id = 'm'").fetchone()[0] > 0


def _crashed_with_maps(data_dir: Path, scans: dict[str, int]) -> None:
    """Leave in `data_dir` the maps of `scans` (map id -> scans of robot r) as a crash leaves them:
    created and journaled, never snapshotted."""
    registry = MapRegistry(durable=DurableStore(data_dir))
    registry.start()
    for map_id, count in scans.items():
        registry.create(map_id, MapConfig(tile_size=16), wait=True)
        for seq in range(count):
            registry.submit(map_id, "r", WireScan(seq, 0.0, scan_at(0.1 * seq)), wait=True).result(10)  # type: ignore[union-attr]
    registry.queue.close()  # a crash: no snapshot, only the journal
    for t in registry._workers:
        t.join(5)
    registry.durable.close()  # type: ignore[union-attr]


#: Maps of the stop after a crash restore below; `FLEETMAP_STOP_MAPS=5000` makes it the one seen
#: taking 33-41 s (its seconds printed: `pytest -s`).
STOP_MAPS = int(os.environ.get("FLEETMAP_STOP_MAPS", "24"))


def test_a_stop_after_a_crash_restore_snapshots_its_maps_in_a_few_transactions(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After a crash every restored map has journal rows, so a stop snapshots every map, and each
    map's last snapshot took about five synced transactions of its own (its tile rows, its switch,
    its checkpoint's, the deletion of its journal rows) after waiting `ATTACH_WAIT` for a group
    commit that no scan would make: 5,000 maps took 33-41 s to stop, past `docker stop`'s 10 s,
    whose SIGKILL made the next start a crash restore again. Now the last snapshots share
    transactions. `ATTACH_WAIT` is made an hour here: a stop that waits for it does not end."""
    maps = {f"m{i}": 3 for i in range(STOP_MAPS)}
    _crashed_with_maps(tmp_path, maps)
    monkeypatch.setattr(JournalWriter, "ATTACH_WAIT", 3600.0)
    registry = MapRegistry(durable=DurableStore(tmp_path, snapshot_interval=3600.0))
    registry.start()
    want = {map_id: _tiles(registry.get(map_id).gmap) for map_id in maps}
    before = _snapshot_generations(tmp_path)
    commits: list[str] = []
    registry.durable.writer._conn.set_trace_callback(  # type: ignore[union-attr]
        lambda sql: commits.append(sql) if sql == "COMMIT" else None
    )
    stopping = threading.Thread(target=registry.close, daemon=True)  # (daemon: a hung one is left behind)
    started = time.monotonic()
    stopping.start()
    stopping.join(120)
    assert not stopping.is_alive(), "the stop's last snapshots waited for a group commit"
    print(f"stopped after restoring {len(maps)} maps in {time.monotonic() - started:.1f} s")
    assert len(commits) <= len(maps) // 4, f"{len(commits)} transactions to stop {len(maps)} maps"
    after = _snapshot_generations(tmp_path)
    assert all(after[map_id] != before[map_id] for map_id in maps), "a map was not snapshotted"
    with contextlib.closing(sqlite3.connect(tmp_path / "fleetmap.db")) as conn:
        assert conn.execute("SELECT COUNT(*) FROM journal").fetchone()[0] == 0
    with _restarted(tmp_path) as again:
        for map_id, count in maps.items():
            entry = again.get(map_id)
            assert entry.robots["r"].scans_integrated == count and entry.robots["r"].last_seq == count - 1
            got = _tiles(entry.gmap)
            assert got.keys() == want[map_id].keys()
            for key, arrays in want[map_id].items():
                for name, array in arrays.items():
                    np.testing.assert_array_equal(got[key][name], array)


def test_a_stop_does_not_wait_for_the_periodic_pass_to_snapshot_every_map_one_by_one(tmp_path: Path) -> None:
    """A stop waits for the periodic snapshot pass under way (`stop_periodic`), and the pass went on
    through every map it listed, one synced snapshot after another: a stop during the first full
    pass after a crash restore of 5,000 maps (every one with journal rows) took 52 s. The pass now
    ends with the map under way once the service stops, and the stop's last pass, whose snapshots
    share transactions, takes the others."""
    maps = {f"m{i}": 1 for i in range(12)}
    _crashed_with_maps(tmp_path, maps)
    registry = MapRegistry(durable=DurableStore(tmp_path, snapshot_interval=0.0))  # a full pass a second
    durable = registry.durable
    assert durable is not None
    closing = threading.Thread(target=registry.close, daemon=True)  # (daemon: a hung one is left behind)
    begun: list[bool] = []  # per periodic snapshot: whether the service was stopping as it began
    # Set once the stop is under way: the first snapshot appends to `begun` before it starts the
    # stop, so a wait for `begun` alone could join the closing thread before it was started.
    stopping = threading.Event()
    snapshot = durable.snapshot

    def observed(*args: Any, **kwargs: Any) -> int:
        begun.append(durable._stop.is_set())
        if len(begun) == 1:  # the pass is under way: the service stops now
            closing.start()
            stopping.set()
            assert durable._stop.wait(60)
        return snapshot(*args, **kwargs)

    durable.snapshot = observed  # type: ignore[method-assign]
    registry.start()
    assert stopping.wait(60), "no periodic snapshot began"
    closing.join(120)
    assert not closing.is_alive()
    assert begun == [False], f"the pass went on through {begun.count(True)} more maps after the stop began"
    with contextlib.closing(sqlite3.connect(tmp_path / "fleetmap.db")) as conn:
        assert conn.execute("SELECT COUNT(*) FROM journal").fetchone()[0] == 0  # the last pass took them
    with _restarted(tmp_path) as again:
        assert all(again.get(map_id).robots["r"].scans_integrated == 1 for map_id in maps)


def test_snapshot_failures_held_back_at_the_stop_are_counted_in_the_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full disk fails every map's last snapshot at a stop. The log wrote the first failure and
    held the others back, to be counted by the next line of their kind, which never came: the
    service stopped. Now the stop's pass ends with one line counting them."""
    registry = MapRegistry(durable=DurableStore(tmp_path))
    registry.start()
    maps = ["a", "b", "c", "d"]
    for map_id in maps:
        registry.create(map_id, MapConfig(tile_size=16), wait=True)
        registry.submit(map_id, "r", WireScan(0, 0.0, scan_at(0.0)), wait=True).result(10)  # type: ignore[union-attr]
    durable = registry.durable
    assert durable is not None

    def full_disk(*args: Any, **kwargs: Any) -> Future[int]:
        failed: Future[int] = Future()
        failed.set_exception(sqlite3.OperationalError("database or disk is full"))
        return failed

    monkeypatch.setattr(durable, "last_snapshot", full_disk)
    caplog.set_level(logging.ERROR, logger="fleetmap.registry")
    registry.close()
    lines = [r.getMessage() for r in caplog.records]
    failed = [line for line in lines if line.startswith("snapshot of map ")]
    assert len(failed) == 1, lines  # the first one; the others within the log's interval are held
    counted = [line for line in lines if "more snapshot failures at the stop" in line]
    assert counted == [
        f"{len(maps) - 1} more snapshot failures at the stop, not logged one by one (the last line names "
        "the maps storage failed to keep)"
    ], lines


def test_the_restore_logs_totals_not_a_line_per_map(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A start logged a line per restored map: 5,000 lines for 5,000 maps. Now one line of totals
    (maps, tiles, journal scans replayed); each map's own line is at debug level. The maps are
    restored as before."""
    _crashed_with_maps(tmp_path, {"a": 3, "b": 0, "c": 2})
    caplog.set_level(logging.INFO, logger="fleetmap.registry")
    again = MapRegistry(durable=DurableStore(tmp_path))
    again.start()
    try:
        tiles = sum(len(again.get(m).gmap.store) for m in "abc")
        assert tiles > 0
        assert [again.get(m).scans_integrated for m in "abc"] == [3, 0, 2]
    finally:
        again.close()
    lines = [r.getMessage() for r in caplog.records if "restor" in r.getMessage()]
    assert len(lines) == 1, lines
    assert re.fullmatch(
        rf"restored 3 map\(s\) in [0-9.]+ s: {tiles} tiles, 5 journal scans replayed", lines[0]
    )


def test_a_long_restore_reports_its_progress_in_the_maps(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """While maps are restored, the log says every RESTORE_REPORT seconds how many of them are done
    (as it says how far a long journal's replay is), and a map whose replay reported its progress
    gets its own closing line."""
    _crashed_with_maps(tmp_path, {"a": 2, "b": 0, "c": 1})
    monkeypatch.setattr(registry_module, "RESTORE_REPORT", 0.0)  # every step reports
    caplog.set_level(logging.INFO, logger="fleetmap.registry")
    again = MapRegistry(durable=DurableStore(tmp_path))
    again.start()
    try:
        tiles = {m: len(again.get(m).gmap.store) for m in "ac"}
    finally:
        again.close()
    lines = [r.getMessage() for r in caplog.records if "restor" in r.getMessage()]
    assert [re.sub(r" \(\d+ s\)$", "", line) for line in lines[:-1]] == [
        "restoring maps: 0 of 3 restored",
        "restoring map a: 0 of 2 journal scans replayed",
        "restoring map a: 1 of 2 journal scans replayed",
        f"restored map a: {tiles['a']} tiles, 2 journal scans replayed",
        "restoring maps: 1 of 3 restored",
        "restoring maps: 2 of 3 restored",
        "restoring map c: 0 of 1 journal scans replayed",
        f"restored map c: {tiles['c']} tiles, 1 journal scans replayed",
    ], lines
    assert lines[-1].startswith("restored 3 map(s) in "), lines
