"""A deleted or replaced map stays so: the registry remembers its robots' publisher sessions
(`Tombstones`), in memory and in the database, so that copies of their old scans (a robot's cache,
fetched again after a restart) and their liveliness tokens do not bring it back.

The registry runs in the test process here, on a real `DurableStore` (SQLite in a temporary data
directory): "a restart" is a second registry on the same directory after the first closed.
tests/test_store_forward.py runs the same story end to end (the real service, a robot's real cache).
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest
from fleetmap_client.delivery import delivery_report
from registry_idle import wait_idle
from robot_process import scans_for

from fleetmap import persistence, tombstones
from fleetmap.codec import WireScan
from fleetmap.config import MapConfig
from fleetmap.database import DB_NAME
from fleetmap.grid_map import GridMap
from fleetmap.map_entry import IngestRejected
from fleetmap.persistence import DurableStore
from fleetmap.registry import MapRegistry, NotDurable
from fleetmap.robot_state import MAX_SESSIONS, RobotState
from fleetmap.tombstones import MAX_BURIED_SESSIONS, BuriedSessions, Tombstone, Tombstones

SESSION = 7_000_000_000_123  # a publisher session id (64-bit, as `ScanPublisher` makes them)
SCANS = scans_for(sim=3, beams=61, count=12)


def wire(seq: int, session: int | None = SESSION) -> WireScan:
    return WireScan(seq, float(seq), SCANS[seq % len(SCANS)], session)


@pytest.fixture
def data(tmp_path: Path) -> Path:
    return tmp_path / "data"


def registry(data: Path) -> MapRegistry:
    reg = MapRegistry(durable=DurableStore(data))
    reg.start()
    return reg


@pytest.fixture
def restarted(data: Path) -> Iterator[MapRegistry]:
    """A registry that fed map `m` scans 0-4 of robot `r` (session `SESSION`) and `other`'s scan 0
    without a session, deleted it, closed; then a new registry on the same data directory."""
    first = registry(data)
    for seq in range(5):
        first.submit("m", "r", wire(seq))
    first.submit("m", "other", wire(0, session=None))
    assert wait_idle(first)
    first.delete("m", wait=True)
    first.close()
    again = registry(data)
    yield again
    again.close()


def refusal(reg: MapRegistry, map_id: str, robot_id: str, scan: WireScan) -> IngestRejected:
    with pytest.raises(IngestRejected) as caught:
        reg.submit(map_id, robot_id, scan)
    return caught.value


def test_old_scans_of_a_deleted_map_are_ignored_after_a_restart(restarted: MapRegistry) -> None:
    for seq in range(5):
        refused = refusal(restarted, "m", "r", wire(seq))
        assert refused.status == 200 and refused.kind == "duplicate"
        assert "from before map 'm' was deleted or replaced" in refused.reason
        assert "had seq 4" in refused.reason
    assert "m" not in restarted.maps  # no scan of them created the map again


def test_a_new_scan_or_session_or_a_scan_without_session_makes_a_new_map(restarted: MapRegistry) -> None:
    restarted.submit("m", "r", wire(5))  # newer than what the service had
    assert wait_idle(restarted)
    robot = restarted.get("m").robots["r"]
    assert (robot.scans_integrated, robot.last_seq, robot.lost) == (1, 5, 0)
    refused = refusal(restarted, "m", "r", wire(3))  # the old ones stay ignored beside the new map
    assert refused.status == 200
    assert restarted.get("m").robots["r"].duplicates == 1  # counted on the robot, which exists now
    restarted.submit("m", "r", wire(0, session=SESSION + 1))  # the robot's process restarted
    restarted.submit("m", "other", WireScan(0, 5.0, SCANS[0], None))  # its robot restarted: a later stamp
    assert wait_idle(restarted)
    assert restarted.get("m").scans_integrated == 3


def test_old_scans_without_a_session_id_of_a_deleted_map_are_ignored_after_a_restart(data: Path) -> None:
    """A `ScanPublisher(send_session_id=False)` keeps its cache as any other, and the service fetches
    it again after a restart: its scans, carrying no session id, were not covered by the robot's
    tombstone, so they made the deleted map again with its old scans (seen on the real service: a
    map deleted after 20 such scans came back after a SIGTERM and a restart, 20 scans integrated).
    A copy carries its old stamp: one at or below the last seq with a stamp no later than the last
    scan's is ignored, seq 0 too (the cache's first scan: taken for a restart, as a live map takes
    seq 0, it made the map again); a robot that started its sequence again with a later stamp, or
    without a clock (stamp 0), makes a new map, whose own bookkeeping then tells its copies. The
    same holds for a robot a full map forgot."""
    first = registry(data)
    for seq in range(5):
        first.submit("m", "plain", WireScan(seq, 10.0 + seq, SCANS[seq], None))
    assert wait_idle(first)
    first.delete("m", wait=True)
    first.close()
    again = registry(data)
    try:
        for seq in range(5):
            refused = refusal(again, "m", "plain", WireScan(seq, 10.0 + seq, SCANS[seq], None))
            assert refused.status == 200 and "had seq 4" in refused.reason, refused.reason
        assert "m" not in again.maps  # no copy made the map again
        again.submit("m", "plain", WireScan(2, 99.0, SCANS[2], None))  # restarted: a later stamp
        assert wait_idle(again)
        assert again.get("m").robots["plain"].scans_integrated == 1
        again.delete("m", wait=True)
        for seq in range(3):  # a robot without a clock, restarted: its run goes on below the stone
            again.submit("m", "plain", WireScan(seq, 0.0, SCANS[seq], None))
        assert wait_idle(again)
        assert again.get("m").scans_integrated == 3
        with pytest.raises(IngestRejected, match="duplicate seq 2"):  # the map's own copy rule
            again.submit("m", "plain", WireScan(2, 0.0, SCANS[2], None))
    finally:
        again.close()
    # A robot a full map forgets: its copies are not integrated twice into the map, which lives on.
    full = MapRegistry(max_robots_per_map=1)
    full.start()
    try:
        for seq in range(1, 4):
            full.submit("f", "plain", WireScan(seq, 10.0 + seq, SCANS[seq], None))
        assert wait_idle(full)
        full.submit("f", "next", wire(0))  # forgets "plain", offline and idle, to make room
        assert wait_idle(full)
        refused = refusal(full, "f", "plain", WireScan(2, 12.0, SCANS[2], None))
        assert refused.status == 200 and "forgot robot 'plain'" in refused.reason, refused.reason
        assert full.get("f").scans_integrated == 4
    finally:
        full.close()


def test_a_cache_without_session_ids_fetched_again_after_the_new_map_integrates_nothing_twice(
    data: Path,
) -> None:
    """A robot without session ids goes on publishing after its map was deleted: its next scan (seq
    5) makes the new map. Its cache, fetched again after a restart of the service, holds its scans
    from before the deletion and that one. Once the robot was on the new map the tombstone was no
    longer asked, and the map's own bookkeeping took the cache's first scan, the copy of seq 0, for
    a restart (the new map's run has no seq 0 of its own to tell a copy by): it and every copy
    after it were integrated into the new map, which had not held them, and seq 5 a second time."""
    first = registry(data)
    for seq in range(5):
        first.submit("m", "plain", WireScan(seq, 10.0 + seq, SCANS[seq], None))
    assert wait_idle(first)
    first.delete("m", wait=True)
    first.submit("m", "plain", WireScan(5, 15.0, SCANS[5], None))  # the robot goes on: a new map
    assert wait_idle(first)
    first.close()
    again = registry(data)
    try:
        for seq in range(6):  # the robot's cache, fetched again
            refused = refusal(again, "m", "plain", WireScan(seq, 10.0 + seq, SCANS[seq], None))
            assert refused.status == 200 and refused.kind == "duplicate", (seq, refused.reason)
        assert wait_idle(again)
        robot = again.get("m").robots["plain"]
        assert (robot.scans_integrated, robot.restarts, robot.duplicates) == (1, 0, 6)
        again.submit("m", "plain", WireScan(6, 16.0, SCANS[6], None))  # its next scan goes on
        again.submit("m", "plain", WireScan(0, 100.0, SCANS[0], None))  # restarted: a later stamp
        again.submit("m", "plain", WireScan(0, 0.0, SCANS[1], None))  # restarted without a clock
        assert wait_idle(again)
        assert (robot.scans_integrated, robot.restarts) == (4, 2)
    finally:
        again.close()


def test_old_scans_of_negative_stamps_of_a_deleted_map_are_ignored(data: Path) -> None:
    """Stamps are of any epoch, so some are negative; only 0 says "no clock". A stone covered a copy
    only with a stamp above 0: the copies of a robot whose stamps are negative, ignored as
    duplicates by the live map, made the deleted map again with its old scans."""
    reg = registry(data)
    try:
        for seq in range(5):
            reg.submit("m", "plain", WireScan(seq, -1000.0 + seq, SCANS[seq], None))
        assert wait_idle(reg)
        with pytest.raises(IngestRejected, match="duplicate seq 2"):  # the live map's copy rule
            reg.submit("m", "plain", WireScan(2, -998.0, SCANS[2], None))
        reg.delete("m", wait=True)
        for seq in range(5):
            refused = refusal(reg, "m", "plain", WireScan(seq, -1000.0 + seq, SCANS[seq], None))
            assert refused.status == 200 and "had seq 4" in refused.reason, refused.reason
        assert "m" not in reg.maps
        reg.submit("m", "plain", WireScan(2, -10.0, SCANS[2], None))  # restarted: a later stamp
        assert wait_idle(reg)
        assert reg.get("m").robots["plain"].scans_integrated == 1
    finally:
        reg.close()


def test_a_token_of_a_buried_robot_creates_no_map_but_another_robots_does(restarted: MapRegistry) -> None:
    restarted.set_online("m", "r", True)  # seen again: the service restarted, or its link came back
    restarted.set_online("m", "other", True)  # buried too, though it sent no session id
    assert "m" not in restarted.maps
    restarted.set_online("m", "new", True)
    assert restarted.get("m").robots["new"].online
    restarted.submit("m", "r", wire(6))  # the buried robot is shown online once its map exists again
    assert wait_idle(restarted)
    assert restarted.get("m").robots["r"].scans_integrated == 1


def test_the_robots_of_a_replaced_map_are_buried(data: Path) -> None:
    reg = registry(data)
    try:
        for seq in range(3):
            reg.submit("m", "r", wire(seq))
        assert wait_idle(reg)
        uploaded = reg.get("m").gmap  # (any map will do: the old one, installed again)
        reg.replace("m", uploaded, wait=True)
        assert refusal(reg, "m", "r", wire(2)).status == 200
        assert "r" not in reg.get("m").robots
    finally:
        reg.close()
    again = registry(data)
    try:
        assert refusal(again, "m", "r", wire(1)).status == 200
        assert again.get("m").scans_integrated == 0
    finally:
        again.close()


def test_a_map_deleted_twice_remembers_every_session_and_the_higher_seq(data: Path) -> None:
    reg = registry(data)
    try:
        for seq in range(4):
            reg.submit("m", "r", wire(seq))
        assert wait_idle(reg)
        reg.delete("m", wait=True)
        reg.submit("m", "r", wire(8))  # the robot goes on: a new map
        reg.submit("m", "r", wire(0, session=SESSION + 1))  # and another process of it
        assert wait_idle(reg)
        reg.delete("m", wait=True)
        assert reg.tombstones.covers("m", "r", SESSION, 8) is not None
        assert reg.tombstones.covers("m", "r", SESSION, 9) is None
        assert reg.tombstones.covers("m", "r", SESSION + 1, 0) is not None
    finally:
        reg.close()
    db = sqlite3.connect(data / DB_NAME)
    rows = db.execute("SELECT map_id, robot_id, sessions FROM tombstones").fetchall()
    db.close()
    assert rows == [("m", "r", f'{{"{SESSION}": 8, "{SESSION + 1}": 0}}')]


def test_tombstones_past_their_days_are_forgotten_at_start(data: Path) -> None:
    DurableStore(data).close()  # the schema
    now = time.time()
    db = sqlite3.connect(data / DB_NAME)
    db.executemany(
        "INSERT INTO tombstones (map_id, robot_id, deleted_at, sessions) VALUES (?, ?, ?, ?)",
        [
            ("old", "r", now - (tombstones.TOMBSTONE_DAYS + 1) * 86400, f'{{"{SESSION}": 9}}'),
            ("recent", "r", now - (tombstones.TOMBSTONE_DAYS - 1) * 86400, f'{{"{SESSION}": 9}}'),
        ],
    )
    db.commit()
    db.close()
    reg = registry(data)
    try:
        assert reg.tombstones.covers("old", "r", SESSION, 9) is None
        assert reg.tombstones.covers("recent", "r", SESSION, 9) is not None
        reg.submit("old", "r", wire(9))  # its map comes back: a month is what the docs promise
        assert wait_idle(reg)
    finally:
        reg.close()
    db = sqlite3.connect(data / DB_NAME)
    assert [r[0] for r in db.execute("SELECT map_id FROM tombstones")] == ["recent"]
    db.close()


def test_at_most_max_tombstones_are_kept_the_oldest_forgotten(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tombstones, "MAX_TOMBSTONES", 3)
    state = RobotState()
    state.accept(4, 4.0, SESSION)
    stones = Tombstones()
    for k in range(5):
        stones.bury(f"m{k}", {"r": state}, now=1000.0 + k)
    assert len(stones) == 3
    assert [stones.buried(f"m{k}", "r") for k in range(5)] == [False, False, True, True, True]
    loaded = Tombstones(
        [Tombstone(f"m{k}", "r", 1000.0 + k, BuriedSessions([(SESSION, 4)])) for k in (4, 0, 2, 1, 3)],
        now=1005.0,
    )
    assert [loaded.buried(f"m{k}", "r") for k in range(5)] == [False, False, True, True, True]


@pytest.mark.parametrize("then", ["created by PUT", "created by another robot's scan"])
def test_a_deletion_not_stored_keeps_its_tombstones_when_a_new_map_of_its_id_supersedes_it(
    data: Path, monkeypatch: pytest.MonkeyPatch, then: str
) -> None:
    """A DELETE whose commit fails (a failing disk: 503) is retried by the journal writer, but a later
    change of the same map id (the map created again) supersedes it, rewriting the map whole. The
    tombstones that rode in the deletion's transaction must ride in that one: they were dropped
    with it, and after a restart robot r's cached scans went into the new map."""
    reg = registry(data)
    try:
        for seq in range(5):
            reg.submit("m", "r", wire(seq))
        assert wait_idle(reg, 60)
        failing = [True]
        bury = persistence._bury

        def failing_bury(conn: sqlite3.Connection, buried: Sequence[Tombstone]) -> None:
            if failing[0]:
                raise sqlite3.OperationalError("disk I/O error")
            bury(conn, buried)

        monkeypatch.setattr(persistence, "_bury", failing_bury)
        with pytest.raises(NotDurable):
            reg.delete("m", wait=True)
        failing[0] = False  # the disk works again, before the retry
        if then == "created by PUT":
            reg.create("m", wait=True)
        else:
            reg.submit("m", "x", wire(0, session=SESSION + 9))
            assert wait_idle(reg, 60)
        assert reg.durable is not None and reg.durable.writer.unstored == ()
    finally:
        reg.close()
    again = registry(data)
    try:
        refused = refusal(again, "m", "r", wire(3))  # from robot r's cache
        assert refused.status == 200 and "from before map 'm' was deleted" in refused.reason
    finally:
        again.close()


@pytest.mark.parametrize("how", ["deleted", "replaced"])
def test_a_scan_the_full_queue_refused_before_its_map_went_is_integrated_when_sent_again(how: str) -> None:
    """A REST client answered 503 (queue full) is told to retry the scan later with its seq, which is
    then integrated (docs/api.md; `RobotState.refused`). Its map deleted or replaced meanwhile, the
    retry was ignored as "from before the deletion", though the service never had that scan: lost
    although its sender did as told. (The scan queued before it, which the service had, stays ignored.)"""
    reg = MapRegistry(queue_per_robot=1)  # workers not started: nothing drains
    try:
        reg.submit("m", "r", wire(0))
        with pytest.raises(IngestRejected) as full:
            reg.submit("m", "r", wire(1))
        assert full.value.status == 503
        if how == "deleted":
            reg.delete("m")
        else:
            reg.replace("m", GridMap(MapConfig()))
        reg.start()
        retried = reg.submit("m", "r", wire(1), wait=True)
        assert retried is not None and retried.result(60).cell_updates > 0
        assert refusal(reg, "m", "r", wire(1)).status == 200  # integrated once: a copy is a duplicate
        assert refusal(reg, "m", "r", wire(0)).status == 200
        assert reg.get("m").robots["r"].scans_integrated == 1
    finally:
        reg.close()


def test_a_robot_buried_again_and_again_keeps_its_most_recent_sessions_only() -> None:
    """A map deleted every day (a scratch map reset each night), its robot's process restarted every
    day: each burial merged the robot's sessions into its tombstone, whose time each burial renews,
    so the tombstone (memory, and its JSON in the database) grew by a session a day without end.
    It keeps the `MAX_BURIED_SESSIONS` heard most recently, as many as the live bookkeeping tells
    apart."""
    stones = Tombstones()
    for day in range(3 * MAX_BURIED_SESSIONS):
        state = RobotState()
        state.accept(100, 100.0, SESSION + day)
        stones.bury("m", {"r": state}, now=1000.0 + day * 86400)
    last = 3 * MAX_BURIED_SESSIONS - 1
    covered = [stones.covers("m", "r", SESSION + day, 100) is not None for day in range(last + 1)]
    assert covered == [day > last - MAX_BURIED_SESSIONS for day in range(last + 1)]
    state = RobotState()  # one heard long ago, heard again: kept, as recent
    state.accept(7, 7.0, SESSION + last - MAX_BURIED_SESSIONS + 1)
    state.accept(200, 200.0, SESSION + 1000)
    stones.bury("m", {"r": state}, now=1000.0 + (last + 1) * 86400)
    assert stones.covers("m", "r", SESSION + last - MAX_BURIED_SESSIONS + 1, 100) is not None
    assert stones.covers("m", "r", SESSION + last - MAX_BURIED_SESSIONS + 2, 100) is None  # the oldest then


def test_a_deleted_maps_robot_with_more_sessions_than_its_recent_ones_stays_deleted(data: Path) -> None:
    """More robots under one robot id than `MAX_SESSIONS` (a fleet started from one image with its
    default id) push each other's sessions out of the robot's recent ones, which its bookkeeping
    still tells apart (`RobotState.pushed_out`). The tombstone kept the recent ones only: after a
    deletion and a restart, the copies of a pushed-out session's scans (its cache fetched again)
    made the deleted map again with them (seen on the real service: ten `ScanPublisher`s under one
    id, the map deleted, the service restarted: back with 6 scans), and the delivery query told that
    session's flush `no_map` and nothing of its scans, which it then waited for until its timeout."""
    from fleetmap.delivery import delivery_status

    count = MAX_SESSIONS + 2
    first = registry(data)
    for seq in range(3):
        for k in range(count):
            first.submit("m", "r", wire(seq, session=SESSION + k))
    assert wait_idle(first)
    assert len(first.get("m").robots["r"].sessions) == MAX_SESSIONS  # two pushed out of them
    first.delete("m", wait=True)
    first.close()
    again = registry(data)
    try:
        for k in range(count):
            for seq in range(3):
                refused = refusal(again, "m", "r", wire(seq, session=SESSION + k))
                assert refused.status == 200 and refused.kind == "duplicate", (k, refused.reason)
        assert "m" not in again.maps
        status = delivery_status(again, "m", "r", SESSION)  # a pushed-out session's flush asks
        assert status.status == "no_map"
        assert [(b.session, b.last_seq) for b in status.buried] == [(SESSION, 2)]
        listed = delivery_status(again, "m", "r").buried  # unasked, the recent ones, as on a live map
        assert [b.session for b in listed] == [SESSION + k for k in range(2, count)]
    finally:
        again.close()


@pytest.mark.parametrize(
    "sessions", ["[1, 2]", '{"x": 1}', '{"1": "two"}', "not json", "null", '{"1": 1e30}', f'{{"{2**64}": 1}}']
)
def test_a_damaged_tombstone_is_a_clear_error_at_start(data: Path, sessions: str) -> None:
    """A `tombstones` row whose sessions are not a JSON object of session ids and seqs (a damaged
    or hand-edited database) stops the start with the database's clear error, naming the file, as
    any other unreadable row does: not an AttributeError's traceback."""
    from fleetmap.database import StorageError

    DurableStore(data).close()  # the schema
    db = sqlite3.connect(data / DB_NAME)
    db.execute(
        "INSERT INTO tombstones (map_id, robot_id, deleted_at, sessions) VALUES ('m', 'r', ?, ?)",
        (time.time(), sessions),
    )
    db.commit()
    db.close()
    store = DurableStore(data)
    try:
        with pytest.raises(StorageError, match=DB_NAME):
            store.load_tombstones()
    finally:
        store.close()


def test_a_robot_that_waited_for_room_on_a_deleted_map_brings_it_back_neither_by_token_nor_by_cache(
    data: Path,
) -> None:
    """A map full of online robots (`--max-robots-per-map 1`) has no room for robot b: its token and
    scans are refused (429). The map is deleted; after a restart, b's token, seen again, made the
    map again, and its cache, fetched again, put its refused scans from before the deletion in it.
    It is buried with the map: its token makes none, its old scans are ignored, a new one makes the
    map as any robot's does, and its flush still says its old scans were refused, not gone."""
    from fleetmap.delivery import delivery_status

    first = MapRegistry(durable=DurableStore(data), max_robots_per_map=1)
    first.start()
    first.set_online("m", "a", True)
    first.submit("m", "a", wire(0))
    assert first.set_online("m", "b", True) is not None  # no room: not on the map
    for seq in range(3):
        assert refusal(first, "m", "b", wire(seq, session=SESSION + 1)).status == 429
    assert wait_idle(first)
    first.delete("m", wait=True)
    report = delivery_report(delivery_status(first, "m", "b", SESSION + 1), SESSION + 1, 0, 2)
    assert (report.settled, report.refused, report.gone) == (True, 3, 0), report
    first.close()
    again = MapRegistry(durable=DurableStore(data), max_robots_per_map=1)
    again.start()
    try:
        assert again.set_online("m", "b", True) is not None  # buried: no map made
        for seq in range(3):
            assert refusal(again, "m", "b", wire(seq, session=SESSION + 1)).status == 200
        assert "m" not in again.maps
        again.submit("m", "b", wire(3, session=SESSION + 1))  # newer than the deletion: a new map
        assert wait_idle(again)
        assert again.get("m").scans_integrated == 1
    finally:
        again.close()


# -- robots a full map forgot -------------------------------------------------------------------------


def forgetting_registry(data: Path | None = None, max_robots: int = 1) -> MapRegistry:
    """A started registry (durable on `data` if given) whose maps hold at most `max_robots` robots."""
    durable = DurableStore(data) if data is not None else None
    reg = MapRegistry(durable=durable, max_robots_per_map=max_robots)
    reg.start()
    return reg


def feed_then_forget(reg: MapRegistry) -> None:
    """Robot r's scans 0-4 (session `SESSION`) integrated into map `m`, then robot x's scan 0: the
    map, which holds one robot, forgets r (offline, nothing waiting) to make room for x."""
    for seq in range(5):
        reg.submit("m", "r", wire(seq))
    assert wait_idle(reg)
    reg.submit("m", "x", wire(0, session=SESSION + 50))
    assert wait_idle(reg)
    assert sorted(reg.get("m").robots) == ["x"]


def assert_old_scans_ignored(reg: MapRegistry, integrated: int) -> None:
    """Robot r's scans 0-4, sent again from its cache, are duplicates (200); map `m` still holds
    `integrated` scans."""
    for seq in range(5):
        refused = refusal(reg, "m", "r", wire(seq))
        assert refused.status == 200 and refused.kind == "duplicate", refused.reason
        assert "forgot robot 'r'" in refused.reason and "had seq 4" in refused.reason
    assert wait_idle(reg)
    assert reg.get("m").scans_integrated == integrated


def test_a_forgotten_robots_cached_scans_are_not_integrated_twice() -> None:
    """A full map forgets an idle robot to make room for a new one, and with it the seqs of its
    sessions: its cache, fetched again (the service restarted, its link came back past the lease),
    was integrated a second time into the map that held those scans. Now they are duplicates; its
    newer scans, a new session of it, and scans without a session id go through as before."""
    reg = forgetting_registry()
    try:
        feed_then_forget(reg)
        assert_old_scans_ignored(reg, integrated=6)
        assert "r" not in reg.get("m").robots  # an ignored scan brings it back no more than any refusal
        reg.set_online("m", "x", True)  # (x online: r may not make room for a third robot)
        reg.set_online("m", "x", False)
        reg.submit("m", "r", wire(5))  # newer than what the map had: r starts afresh with it
        assert wait_idle(reg)
        robot = reg.get("m").robots["r"]
        assert (robot.scans_integrated, robot.last_seq, robot.lost, robot.restarts) == (1, 5, 0, 0)
        assert refusal(reg, "m", "r", wire(3)).status == 200
        assert robot.duplicates == 1  # counted on the robot, which exists again
        reg.submit("m", "r", wire(0, session=SESSION + 1))  # its process restarted: a new session
        reg.submit("m", "r", wire(1, session=None))  # never re-delivered: never covered
        assert wait_idle(reg)
        assert reg.get("m").scans_integrated == 9
    finally:
        reg.close()


def test_the_delivery_query_calls_a_forgotten_robots_scans_gone_only_once_its_map_went() -> None:
    """The delivery query lists a deleted map's robots' sessions in `buried`, and the robot's flush
    counts those scans as gone with the map. A robot merely forgotten by a live map must not be
    listed: its scans are in the map. Its token brings it back as any robot's does; once the map is
    deleted, its scans did go with it, and its stone is a deleted map's."""
    reg = forgetting_registry()
    try:
        feed_then_forget(reg)
        status = reg.delivery_status("m", "r", SESSION)
        assert (status.status, status.buried) == ("no_robot", [])
        assert reg.tombstones.covers("m", "r", SESSION, 4) is not None
        reg.set_online("m", "r", True)  # its token on the live map: shown online (x makes room)
        assert reg.get("m").robots["r"].online
        assert reg.delivery_status("m", "r").buried == []
        reg.set_online("m", "r", False)
        reg.submit("m", "x", wire(1, session=SESSION + 50))  # r forgotten again (merged, still forgotten)
        assert wait_idle(reg)
        assert "r" not in reg.get("m").robots
        reg.delete("m")
        status = reg.delivery_status("m", "r", SESSION)
        assert status.status == "no_map"
        assert [(b.session, b.last_seq) for b in status.buried] == [(SESSION, 4)]
        reg.set_online("m", "r", True)  # its map was deleted under it: its token creates none
        assert "m" not in reg.maps
        assert refusal(reg, "m", "r", wire(4)).reason.startswith("seq 4 is from before map 'm' was deleted")
    finally:
        reg.close()


def test_a_robot_forgotten_while_running_stays_forgotten_after_a_restart(data: Path) -> None:
    """The tombstone of a robot the map forgot is stored (by the map's next snapshot, here the one
    at close, in the transaction that drops the robot's row), so that the cache a restarted service
    fetches is not integrated twice."""
    reg = forgetting_registry(data)
    try:
        feed_then_forget(reg)
    finally:
        reg.close()
    db = sqlite3.connect(data / DB_NAME)
    stored = db.execute("SELECT map_id, robot_id, sessions, forgotten FROM tombstones").fetchall()
    robots = [row[0] for row in db.execute("SELECT robot_id FROM robots")]
    db.close()
    assert stored == [("m", "r", f'{{"{SESSION}": 4}}', 1)] and robots == ["x"]
    again = forgetting_registry(data)
    try:
        stone = again.tombstones.get("m", "r")
        assert stone is not None and stone.forgotten
        assert_old_scans_ignored(again, integrated=6)
        assert again.delivery_status("m", "r", SESSION).buried == []
    finally:
        again.close()


def test_a_crash_leaves_a_forgotten_robots_seqs_or_its_tombstone_in_storage(data: Path) -> None:
    """Storage stops holding a forgotten robot's seqs (its row) in the snapshot that stores its
    tombstone: a crash before that snapshot restores the robot itself, one after it the tombstone.
    Either way its cached scans are duplicates. (A crash: a second registry on the same directory,
    the first never closed.)"""
    reg = forgetting_registry(data)
    crashed: list[MapRegistry] = []
    try:
        feed_then_forget(reg)
        before = forgetting_registry(data, max_robots=2)  # crashed before any snapshot
        crashed.append(before)
        assert sorted(before.get("m").robots) == ["r", "x"]
        for seq in range(5):
            assert refusal(before, "m", "r", wire(seq)).status == 200
        reg.snapshot_all(every_map=True)
        after = forgetting_registry(data)  # crashed after it
        crashed.append(after)
        assert sorted(after.get("m").robots) == ["x"]
        assert_old_scans_ignored(after, integrated=6)
    finally:
        for other in crashed:
            other.close()
        reg.close()


def test_a_robot_forgotten_at_restore_is_remembered_across_restarts(data: Path) -> None:
    """A map restored with more robots than it may hold (a lower --max-robots-per-map, or robots
    first heard since the snapshot replayed from the journal) forgets the ones heard from least
    recently: their old scans must not be integrated again either, in this process or the next."""
    reg = forgetting_registry(data, max_robots=3)
    try:
        for seq in range(5):
            reg.submit("m", "r", wire(seq))
        assert wait_idle(reg)
        for robot_id in ("a", "b"):
            reg.submit("m", robot_id, wire(0, session=SESSION + 60))
        assert wait_idle(reg)
    finally:
        reg.close()
    for _restart in range(2):
        again = forgetting_registry(data, max_robots=2)
        try:
            assert sorted(again.get("m").robots) == ["a", "b"]
            assert_old_scans_ignored(again, integrated=7)
        finally:
            again.close()


def test_forgotten_robots_stones_become_a_deleted_maps_only_with_their_own_map() -> None:
    """`Tombstones.forget` keeps a robot of a live map (covered, not `buried`); `bury` of that map,
    deleted or replaced, makes its forgotten robots' stones ordinary ones of that moment, and leaves
    other maps' alone. A robot with none of its scans in the map (every one refused) has nothing
    to remember; one without a session id has its last seq and stamp (`Tombstone.plain`)."""
    state = RobotState()
    state.accept(4, 4.0, SESSION)
    stones = Tombstones()
    assert stones.forget("m", "r", state, now=999.0) is None  # its scan refused: nothing in the map
    state.scans_integrated = 1
    forgotten = stones.forget("m", "r", state, now=1000.0)
    assert forgotten is not None and forgotten.forgotten and dict(forgotten.sessions) == {SESSION: 4}
    assert stones.forget("other", "r", state, now=1001.0) is not None
    no_session = RobotState()
    no_session.accept(9, 9.0, None)
    no_session.scans_integrated = 1
    plain = stones.forget("m", "plain", no_session, now=1002.0)
    assert plain is not None and plain.plain == (9, 9.0) and not plain.sessions
    assert (
        stones.covers("m", "plain", None, 9, 9.0) is plain
        and stones.covers("m", "plain", None, 9, 9.5) is None
    )
    assert stones.covers("m", "r", SESSION, 4) is forgotten and not stones.buried("m", "r")
    live = RobotState()
    live.accept(2, 2.0, SESSION + 1)
    made = stones.bury("m", {"live": live}, now=2000.0)
    assert [(s.robot_id, s.deleted_at, s.forgotten) for s in made] == [
        ("live", 2000.0, False), ("plain", 2000.0, False), ("r", 2000.0, False),
    ]  # fmt: skip
    assert stones.buried("m", "r") and stones.covers("m", "r", SESSION, 4) is not None
    other = stones.get("other", "r")
    assert other is not None and other.forgotten and not stones.buried("other", "r")


def test_a_forgotten_robot_keeps_what_an_earlier_deletion_buried_and_the_bounds_hold(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A robot buried with a deleted map that fed the new map of its id and was forgotten by it has
    one stone covering both, a forgotten one (its newer scans are in the live map). Forgotten robots
    count towards `MAX_TOMBSTONES` like the rest, the oldest going first."""
    monkeypatch.setattr(tombstones, "MAX_TOMBSTONES", 2)
    old, new = RobotState(), RobotState()
    old.accept(4, 4.0, SESSION)
    new.accept(9, 9.0, SESSION + 1)
    new.scans_integrated = 1
    stones = Tombstones()
    stones.bury("m", {"r": old}, now=1000.0)
    stone = stones.forget("m", "r", new, now=1001.0)
    assert stone is not None and stone.forgotten
    assert dict(stone.sessions) == {SESSION: 4, SESSION + 1: 9}
    stones.forget("m", "s", new, now=1002.0)
    stones.forget("m", "t", new, now=1003.0)
    assert len(stones) == 2 and stones.get("m", "r") is None
    assert [s.robot_id for s in stones.bury("m", {}, now=1004.0)] == ["s", "t"]


def _older_services_database(data: Path, schema: str) -> None:
    """A database in `data` made with an older service's `schema`, holding the tombstone of robot r
    of map m as such a service writes it: the four columns it knows."""
    db = sqlite3.connect(data / DB_NAME)
    db.executescript(schema)
    db.execute(
        "INSERT INTO tombstones (map_id, robot_id, deleted_at, sessions) VALUES ('m', 'r', ?, ?)",
        (time.time(), f'{{"{SESSION}": 4}}'),
    )
    db.commit()
    db.close()


def test_a_database_from_before_forgotten_robots_gets_the_column_at_start(data: Path) -> None:
    """A data directory written before tombstones had their `forgotten` column gets it at start, its
    rows deleted maps' robots; an older service, which names the four columns it writes, still
    writes rows a newer one reads."""
    from fleetmap.database import SCHEMA

    data.mkdir()
    old_schema = SCHEMA.replace(
        "    forgotten INTEGER NOT NULL DEFAULT 0,  -- 1: forgotten by its map, which lives on\n", ""
    )
    assert old_schema != SCHEMA
    _older_services_database(data, old_schema)
    reg = registry(data)
    try:
        stone = reg.tombstones.get("m", "r")
        assert stone is not None and not stone.forgotten and reg.tombstones.buried("m", "r")
    finally:
        reg.close()
    db = sqlite3.connect(data / DB_NAME)
    db.execute(  # as an older service writes one
        "INSERT OR REPLACE INTO tombstones (map_id, robot_id, deleted_at, sessions) VALUES ('n', 'r', ?, ?)",
        (time.time(), f'{{"{SESSION}": 4}}'),
    )
    db.commit()
    db.close()
    store = DurableStore(data)
    try:
        assert sorted((s.map_id, s.forgotten) for s in store.load_tombstones()) == [
            ("m", False),
            ("n", False),
        ]
    finally:
        store.close()


def test_a_forgotten_robots_stone_whose_map_an_older_service_deleted_is_a_deleted_maps(data: Path) -> None:
    """An older service, which knows no `forgotten` column, deletes a map and leaves its forgotten
    robots' rows as they were: at start they are deleted maps' robots (their token creates no map,
    the delivery query says their scans went with it). Those of a stored map stay forgotten."""
    DurableStore(data).close()  # the schema
    db = sqlite3.connect(data / DB_NAME)
    db.executemany(
        "INSERT INTO tombstones (map_id, robot_id, deleted_at, sessions, forgotten) VALUES (?, 'r', ?, ?, 1)",
        [(map_id, time.time(), f'{{"{SESSION}": 4}}') for map_id in ("gone", "live")],
    )
    db.execute(
        "INSERT INTO maps (id, config, created_at) VALUES ('live', ?, ?)",
        (MapConfig().model_dump_json(), 1.0),
    )
    db.commit()
    db.close()
    reg = registry(data)
    try:
        assert reg.tombstones.buried("gone", "r") and not reg.tombstones.buried("live", "r")
        reg.set_online("gone", "r", True)
        assert "gone" not in reg.maps
        assert [b.last_seq for b in reg.delivery_status("gone", "r").buried] == [4]
    finally:
        reg.close()


def test_forgotten_robots_churning_never_push_a_deleted_maps_robots_out(
    data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Anyone who can publish scans under made-up robot ids into a full map makes the map forget
    robot after robot, each with a tombstone. Evicted oldest first among all of them, those pushed
    out every deleted map's robots past `MAX_TOMBSTONES` (100,000 scans: minutes), and their cached
    scans brought the deleted maps back. Past the bound a forgotten robot's stone goes first, in
    memory and in the cut at start: the merge that added them must not weaken what was promised."""
    monkeypatch.setattr(tombstones, "MAX_TOMBSTONES", 3)
    monkeypatch.setattr(persistence, "MAX_TOMBSTONES", 3)
    reg = forgetting_registry(data)
    try:
        reg.submit("gone", "r", wire(0))
        assert wait_idle(reg)
        reg.delete("gone", wait=True)
        for k in range(6):  # each new id makes live map `m` forget the previous one
            reg.submit("m", f"a{k}", wire(0, session=SESSION + 100 + k))
            assert wait_idle(reg)
        assert len(reg.tombstones) == 3
        assert reg.tombstones.buried("gone", "r")
        assert [reg.tombstones.get("m", f"a{k}") is not None for k in range(5)] == [False] * 3 + [True] * 2
        refused = refusal(reg, "gone", "r", wire(0))
        assert refused.status == 200 and "gone" not in reg.maps
    finally:
        reg.close()
    db = sqlite3.connect(data / DB_NAME)  # more rows than the bound: the cut at start
    db.executemany(
        "INSERT INTO tombstones (map_id, robot_id, deleted_at, sessions, forgotten) VALUES ('m', ?, ?, ?, 1)",
        [(f"b{k}", time.time() + k, f'{{"{SESSION}": 4}}') for k in range(3)],
    )
    db.commit()
    db.close()
    again = forgetting_registry(data)
    try:
        assert again.tombstones.buried("gone", "r")
        kept = [robot for robot in ("b0", "b1", "b2") if again.tombstones.get("m", robot)]
        assert kept == ["b1", "b2"]
        assert refusal(again, "gone", "r", wire(0)).status == 200 and "gone" not in again.maps
    finally:
        again.close()


def test_a_snapshot_that_fails_storing_a_forgotten_robots_stone_is_retried_and_the_journal_goes_on(
    data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The snapshot transaction that drops a forgotten robot's row and stores its tombstone fails
    (a failing disk): nothing of it is stored (a crash now restores the robot itself), the stone
    stays pending and the next snapshot stores it. The failed transaction was left open on the
    journal writer's connection: the next group commit failed ("cannot start a transaction within a
    transaction") and its scans were answered 503 as not durable, though storage worked again."""
    reg = forgetting_registry(data)
    crashed: list[MapRegistry] = []
    try:
        feed_then_forget(reg)
        bury = persistence._bury

        def failing_bury(conn: sqlite3.Connection, buried: Sequence[Tombstone]) -> None:
            if buried:
                raise sqlite3.OperationalError("disk I/O error")
            bury(conn, buried)

        monkeypatch.setattr(persistence, "_bury", failing_bury)
        reg.snapshot_all(every_map=True)  # logged, retried at the next one
        assert list(reg.get("m").unstored_stones) == ["r"]
        monkeypatch.setattr(persistence, "_bury", bury)  # the disk works again
        integrated = reg.submit("m", "x", wire(1, session=SESSION + 50), wait=True)
        assert integrated is not None and integrated.result(60).cell_updates > 0
        before = forgetting_registry(data, max_robots=2)  # a crash now: the robot's row is stored
        crashed.append(before)
        assert sorted(before.get("m").robots) == ["r", "x"]
        reg.snapshot_all(every_map=True)
        assert reg.get("m").unstored_stones == {}
        after = forgetting_registry(data)  # a crash after the retry: its stone is
        crashed.append(after)
        assert sorted(after.get("m").robots) == ["x"]
        assert_old_scans_ignored(after, integrated=7)
    finally:
        for other in crashed:
            other.close()
        reg.close()


def test_forgotten_robots_stones_waiting_for_a_failing_disk_stay_within_the_bound(
    data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """While the snapshots that store forgotten robots' stones fail (a failing disk), the map kept
    every stone it was waiting to store, also those `Tombstones` had pruned: a sender cycling
    through robot ids grew that without bound. It keeps the ones the service still remembers, and
    stores those once the disk works."""
    monkeypatch.setattr(tombstones, "MAX_TOMBSTONES", 3)
    reg = forgetting_registry(data)
    try:
        bury = persistence._bury

        def failing_bury(conn: sqlite3.Connection, buried: Sequence[Tombstone]) -> None:
            if buried:
                raise sqlite3.OperationalError("disk I/O error")
            bury(conn, buried)

        monkeypatch.setattr(persistence, "_bury", failing_bury)
        for k in range(8):
            reg.submit("m", f"a{k}", wire(0, session=SESSION + 100 + k))
            assert wait_idle(reg)
            reg.snapshot_all(every_map=True)
        assert sorted(reg.get("m").unstored_stones) == ["a4", "a5", "a6"]
        monkeypatch.setattr(persistence, "_bury", bury)
        reg.snapshot_all(every_map=True)
        assert reg.get("m").unstored_stones == {}
    finally:
        reg.close()
    db = sqlite3.connect(data / DB_NAME)
    assert sorted(row[0] for row in db.execute("SELECT robot_id FROM tombstones")) == ["a4", "a5", "a6"]
    db.close()


@pytest.mark.parametrize("missing", [("plain_seq", "plain_stamp"), ("plain_stamp",)])
def test_a_database_without_the_plain_columns_gets_them_at_start(
    data: Path, missing: tuple[str, ...]
) -> None:
    """A data directory written before tombstones had their `plain_seq` and `plain_stamp` columns
    gets them at start, NULL in its rows (an older service did not cover scans without a session id);
    so does one that has only the first: each column is a transaction of its own in autocommit, and
    a crash (kill -9, a power cut) between the two left that, which then stopped every later start
    with "no such column: plain_stamp"."""
    from fleetmap.database import SCHEMA

    data.mkdir()
    old_schema = SCHEMA
    for column in missing:
        lines = old_schema.split("\n")
        old_schema = "\n".join(line for line in lines if not line.lstrip().startswith(column))
    assert old_schema.count("plain_") == 2 - len(missing)
    _older_services_database(data, old_schema)
    reg = registry(data)
    try:
        stone = reg.tombstones.get("m", "r")
        assert stone is not None and stone.plain is None and dict(stone.sessions) == {SESSION: 4}
        reg.submit("n", "p", wire(3, session=None))
        wait_idle(reg)
        reg.delete("n", wait=True)
    finally:
        reg.close()
    store = DurableStore(data)
    try:
        stones = {s.map_id: s for s in store.load_tombstones()}
        assert sorted(stones) == ["m", "n"] and stones["n"].plain is not None and stones["n"].plain[0] == 3
    finally:
        store.close()
