"""A fleet's recovered backlogs, sent at once, overflow the ingest queue: the scans it has no room
for are deferred and fetched again from the robots' Zenoh caches as it drains
(`fleetmap.backlog_refetch`), not dropped. Real Zenoh sessions (the service's ingest in this
process, robots' `ScanPublisher`s), a registry with a small queue so that the test is cheap."""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest
import zenoh
from fleetmap_client.publisher import DEFAULT_BACKLOG, ScanPublisher
from registry_idle import wait_idle
from service_process import free_port, reaped, wait_for
from test_ingest import client_session, sim_scans

from fleetmap import backlog_refetch, codec
from fleetmap.backlog_refetch import BacklogRefetch, Origin
from fleetmap.fair_queue import FULL_GROUP, FULL_SOURCE, FairQueue
from fleetmap.map_entry import MapEntry
from fleetmap.registry import MapRegistry
from fleetmap.scan import Scan
from fleetmap.wire import BINARY_ENCODING, SCAN_KEY
from fleetmap.zenoh_ingest import ZenohIngest

ROBOTS = 20
#: Scans each robot has queued while the service was away: its recovered backlog.
BACKLOG = 40


@dataclass
class Fleet:
    """A service's ingest in this process, on a registry whose queue is small, with map `m` made,
    and robots' `ScanPublisher`s (`r0`, `r1` ...) connecting to it (to the router it is a client
    of, with `router`) at `endpoint`."""

    registry: MapRegistry
    entry: MapEntry
    ingest: ZenohIngest
    pubs: list[ScanPublisher]
    endpoint: str


@contextlib.contextmanager
def fleet(
    robots: int,
    backlog: int,
    queue_per_robot: int,
    queue_total: int,
    router: bool = False,
    cache: int | None = None,
) -> Iterator[Fleet]:
    """A `Fleet` of `robots` publishers keeping `backlog` scans each (and `cache` in their Zenoh
    caches, by default the client's), its ingest not started (the robots queue their scans
    meanwhile); everything closed on the way out. With `router`, a Zenoh
    router (a Python session standing in for zenohd) listens, and the ingest is a client of it, as
    `fleetmap serve --zenoh-connect` is; the robots connect to the router."""
    registry = MapRegistry(workers=1, queue_per_robot=queue_per_robot, queue_total=queue_total)
    registry.start()
    entry, _ = registry.create("m")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with contextlib.ExitStack() as stack:
        stack.callback(registry.close)
        if router:
            stack.enter_context(router_session(endpoint))
            ingest = ZenohIngest(registry, connect=[endpoint])
        else:
            ingest = ZenohIngest(registry, listen=[endpoint])
        stack.callback(ingest.close)
        pubs = [
            ScanPublisher("m", f"r{k}", connect=[endpoint], backlog=backlog, cache=cache)
            for k in range(robots)
        ]
        for pub in pubs:
            stack.callback(pub.close)
        yield Fleet(registry, entry, ingest, pubs, endpoint)


@contextlib.contextmanager
def router_session(endpoint: str) -> Iterator[zenoh.Session]:
    """A Zenoh router listening on `endpoint`: a Python session in router mode, as zenohd (which is
    not installed here) would route, timestamping off as the service's own router has it."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("timestamping/enabled", '{"router": false}')
    session = zenoh.open(cfg)
    try:
        yield session
    finally:
        session.close()


@contextlib.contextmanager
def silent_robot(endpoint: str, robot_id: str) -> Iterator[Callable[[Scan, int], None]]:
    """A robot's advanced publisher whose link died silently once it sent its scans: its samples
    carry their source and sequence number as a `ScanPublisher`'s do, but its cache's queryable
    takes every query and answers none (its queries wait, unread, in a channel until the end).
    Yields `put(scan, sn)`, which returns once the service's subscriber matched."""
    key = SCAN_KEY.format(map_id="m", robot_id=robot_id)
    session = client_session(endpoint)
    try:
        publisher = session.declare_publisher(key, encoding=zenoh.Encoding(BINARY_ENCODING))
        source = publisher.id
        cache = session.declare_queryable(
            f"{key}/@adv/pub/{source.zid}/{source.eid}/**", zenoh.handlers.FifoChannel(1000)
        )
        wait_for(lambda: publisher.matching_status.matching, timeout=30, what="the service's subscriber")

        def put(scan: Scan, sn: int) -> None:
            publisher.put(
                codec.encode_binary(scan, sn, stamp=sn / 10.0), source_info=zenoh.SourceInfo(source, sn)
            )

        yield put
        cache.undeclare()
    finally:
        session.close()


def test_a_fleets_backlogs_past_the_queue_are_all_integrated_once() -> None:
    """Twenty robots queue 40 scans each while the service is away (`ScanPublisher`'s backlog), then
    send them at once when it comes up, into a queue whose map share holds 24 scans, while the map
    is locked (nothing integrates). Before, every scan past the 24 was dropped (`queue_full`: 775
    of 800 refused, the robots' flushes said so). Now each is deferred and fetched again from its
    robot's cache once the queue has room: every scan integrated, exactly once, none dropped,
    refused or lost."""
    # The map's share of the queue: 24.
    with fleet(ROBOTS, BACKLOG + 10, queue_per_robot=16, queue_total=48) as f:
        check_backlogs_integrated_once(f, sim_scans(3, BACKLOG, beams=61), queued=24)


def test_deferral_and_refetch_work_through_a_zenoh_router() -> None:
    """The service a client of a Zenoh router (`fleetmap serve --zenoh-connect`), the robots clients
    of that router too: the fetches of deferred scans are routed to the robots' caches and their
    replies back, and the backlogs past the queue are integrated once all the same."""
    with fleet(4, 30, queue_per_robot=4, queue_total=16, router=True) as f:  # the map's share: 8
        assert f.ingest.connect == [f.endpoint]
        check_backlogs_integrated_once(f, sim_scans(6, 20, beams=61), queued=8)
        assert f.ingest.mode == "client" and f.ingest.status()["routers"] == 1


def check_backlogs_integrated_once(f: Fleet, scans: list[Scan], queued: int) -> None:
    """Every robot of `f` queues `scans` while the ingest is not started, then sends them at once
    when it starts, with the map locked, into a queue whose map share holds `queued`: afterwards
    every scan is integrated, exactly once, in order, none dropped, refused or lost, and no
    publisher is left behind."""
    registry, entry, ingest, pubs = f.registry, f.entry, f.ingest, f.pubs
    robots, backlog = len(pubs), len(scans)
    for pub in pubs:
        for scan in scans:
            assert pub.publish(scan)
    assert sum(pub.pending for pub in pubs) == robots * backlog
    with entry.gmap.lock:  # nothing integrates: the bursts overflow the queue for certain
        ingest.start()
        wait_for(
            lambda: ingest.status()["messages_received"] == robots * backlog,
            timeout=60, what="every robot's backlog delivered while the map is locked",
        )  # fmt: skip
    reports = [pub.flush(60) for pub in pubs]
    assert [r.integrated for r in reports] == [backlog] * robots, reports
    assert all(r.confirmed for r in reports), reports
    assert wait_idle(registry)
    status = ingest.status()
    # The queue held its share and the worker 1: the rest were deferred, and fetched again.
    assert min(status["deferred"], status["refetched"]) >= robots * backlog - queued - 1, status
    assert status["rejected"] == {} and status["unrecoverable"] == 0, status
    for k in range(robots):
        robot = entry.robots[f"r{k}"]
        counts = (robot.scans_integrated, robot.dropped, robot.lost, robot.duplicates, robot.last_seq)
        assert counts == (backlog, 0, 0, 0, backlog - 1), (k, counts)
    assert entry.scans_integrated == robots * backlog
    assert ingest._refetch.behind() == 0


def test_a_robot_whose_link_died_silently_does_not_hold_up_the_others_fetches(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A robot whose scans were deferred and whose link then died silently answers no fetch: each
    waits `REFETCH_TIMEOUT_S` (2 s; here 100 s, so that the wait cannot pass unnoticed). Fetched one
    at a time, every other robot's scans waited for it, and 3 fetches of it, about 6 s, before it
    was given up; here the two other robots were stuck for the 100 s. Now the fetches run side by
    side: the others' deferred scans are all integrated, exactly once, while the silent robot's
    fetch still waits."""
    monkeypatch.setattr(backlog_refetch, "REFETCH_TIMEOUT_S", 100.0)
    scans = sim_scans(7, 12, beams=61)
    with fleet(2, 30, queue_per_robot=4, queue_total=16) as f:  # the map's share: 8
        registry, entry, ingest, pubs = f.registry, f.entry, f.ingest, f.pubs
        ingest.start()
        for pub in pubs:
            assert pub.wait_connected(30)
        with silent_robot(f.endpoint, "silent") as put:
            with entry.gmap.lock:  # nothing integrates: the queue fills
                # The silent robot first: its FIFO fills, the rest of its scans are deferred, and
                # its publisher is the first behind.
                for sn, scan in enumerate(scans):
                    put(scan, sn)
                wait_for(lambda: ingest.status()["messages_received"] == 12, timeout=60, what="its scans")
                for pub in pubs:
                    for scan in scans:
                        assert pub.publish(scan)
                wait_for(lambda: ingest.status()["messages_received"] == 36, timeout=60, what="the others'")
                assert ingest._refetch.behind() == 3
            # The map integrates: the queue drains, and the fetches begin.
            reports = [pub.flush(45) for pub in pubs]
            assert [r.integrated for r in reports] == [12, 12], reports
            for k in range(2):
                robot = entry.robots[f"r{k}"]
                counts = (robot.scans_integrated, robot.dropped, robot.lost, robot.duplicates, robot.last_seq)
                assert counts == (12, 0, 0, 0, 11), (k, counts)
            # Its FIFO's 4 integrated (and the one the worker took, if it took one of its first),
            # the rest wait for its cache, which answers nothing.
            assert wait_idle(registry)
            assert entry.robots["silent"].scans_integrated in (4, 5)
            assert ingest._refetch.behind() == 1


#: A robot as its own process (so that the test can stop it, SIGSTOP: its link up and silent): a
#: `ScanPublisher` with a backlog that publishes argv[2] scans to map `m` through argv[1] once
#: connected, says "published", and closes when stdin does.
STOPPABLE_ROBOT = """
import sys
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap_client.publisher import ScanPublisher
plan = generate_floorplan(0, width_m=20.0, height_m=15.0)
robot = SimulatedRobot(plan, 8, num_beams=61, range_max=10.0, scan_rate=5.0)
with ScanPublisher("m", "stopped", connect=[sys.argv[1]], backlog=100) as pub:
    assert pub.wait_connected(30)
    for _ in range(int(sys.argv[2])):
        assert pub.publish(robot.tick())
    print("published", flush=True)
    sys.stdin.read()
"""


def test_a_robot_silent_for_a_while_keeps_its_deferred_scans(monkeypatch: pytest.MonkeyPatch) -> None:
    """A robot whose scans wait to be fetched again, and whose link then goes silent for a while
    (its session alive to Zenoh, within its lease; here the process is stopped): the fetches that
    time out say nothing of its cache. Counted as empty ones, they gave the robot up after 4 of them
    (some 8 s, before Zenoh's 10 s lease ended the session), and its deferred scans, still in its
    cache, were counted unrecoverable: 15 of these 20, though the robot came back. Now a fetch
    that timed out is only asked again: once the robot answers, every scan is integrated once.
    (A robot that is gone for good answers fetches at once, with nothing: those give it up.)"""
    monkeypatch.setattr(backlog_refetch, "REFETCH_TIMEOUT_S", 0.3)
    ended: list[int] = []
    real_ended = BacklogRefetch._ended

    def counting_ended(self: BacklogRefetch, fetch: backlog_refetch._Fetch) -> None:
        ended.append(fetch.got)
        real_ended(self, fetch)

    monkeypatch.setattr(BacklogRefetch, "_ended", counting_ended)
    with fleet(0, 10, queue_per_robot=4, queue_total=16) as f:
        registry, entry, ingest = f.registry, f.entry, f.ingest
        ingest.start()
        robot = subprocess.Popen(
            [sys.executable, "-c", STOPPABLE_ROBOT, f.endpoint, "20"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        with reaped(robot):
            assert robot.stdout is not None and robot.stdin is not None
            with entry.gmap.lock:  # its FIFO fills (4), the rest is deferred
                assert robot.stdout.readline().strip() == "published"
                wait_for(lambda: ingest.status()["messages_received"] == 20, timeout=60, what="its scans")
                robot.send_signal(signal.SIGSTOP)
            # Fetches of it time out, more than gave it up before, well within its lease (or it is
            # given up).
            wait_for(lambda: len(ended) >= 5 or ingest._refetch.behind() == 0, 60, what="its fetches to end")
            robot.send_signal(signal.SIGCONT)
            wait_for(lambda: ingest._refetch.behind() == 0, timeout=60, what="its scans fetched again")
            assert wait_idle(registry)
            state = entry.robots["stopped"]
            counts = (state.scans_integrated, state.dropped, state.lost, state.duplicates, state.last_seq)
            assert counts == (20, 0, 0, 0, 19), (counts, ingest.status())
            assert ingest.status()["unrecoverable"] == 0
            robot.stdin.close()
            assert robot.wait(30) == 0


def test_a_publisher_whose_cache_never_answers_is_given_up_in_the_end(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A fetch that times out is asked again (the test above), but not for ever: a publisher whose
    session lives on and whose cache answers no query (one Zenoh does not end: a peer that is
    alive, its queryable never reached) would hold its later scans back for good. Past
    `REFETCH_SILENCE_S` of fetches timing out (here 1 s), they count as empty ones, and it is given
    up as a gone robot is: its scans not fetched counted unrecoverable, its later ones taken."""
    monkeypatch.setattr(backlog_refetch, "REFETCH_TIMEOUT_S", 0.2)
    monkeypatch.setattr(backlog_refetch, "REFETCH_SILENCE_S", 1.0)
    scans = sim_scans(9, 12, beams=61)
    with fleet(0, 10, queue_per_robot=4, queue_total=16) as f:
        registry, entry, ingest = f.registry, f.entry, f.ingest
        ingest.start()
        with silent_robot(f.endpoint, "mute") as put:
            with entry.gmap.lock:
                for sn, scan in enumerate(scans):
                    put(scan, sn)
                wait_for(lambda: ingest.status()["messages_received"] == 12, timeout=60, what="its scans")
                assert ingest._refetch.behind() == 1
            wait_for(lambda: ingest._refetch.behind() == 0, timeout=30, what="the mute publisher given up")
            assert wait_idle(registry)
            integrated = entry.robots["mute"].scans_integrated
            assert integrated in (4, 5)  # its FIFO's, and the one the worker took
            assert ingest.status()["unrecoverable"] == 12 - integrated
            put(scans[0], 12)  # its next scan is taken again
            wait_for(lambda: entry.robots["mute"].scans_integrated == integrated + 1, 30, what="its next")
            assert entry.robots["mute"].lost == 12 - integrated


def test_the_gate_holds_a_behind_publishers_later_samples_until_its_next_is_taken() -> None:
    """The gate's bookkeeping alone: a publisher is behind from its deferred sample on; its later
    samples are held back (noted to be fetched), only its next one passes, and once every sample
    seen is taken it is not behind any more. Other publishers pass throughout."""
    gate = BacklogRefetch(
        lambda key, promised: 0, lambda key, sample, origin: None, lambda count, source: None
    )

    def origin(sn: int, eid: int = 1) -> Origin:
        return Origin("fleetmap/m/r/scan", "ab", eid, sn)

    assert gate.admit(origin(5))
    gate.taken(origin(5), deferred=True)  # the full queue deferred it
    assert gate.behind() == 1
    assert not gate.admit(origin(6)) and not gate.admit(origin(7))  # held back: after it
    assert gate.admit(origin(9, eid=2))  # another publisher
    assert gate.admit(origin(4))  # before it: taken already (a duplicate at most)
    assert gate.admit(origin(5))  # fetched again
    gate.taken(origin(5), deferred=True)  # deferred again: still behind from 5
    assert not gate.admit(origin(6))
    for sn in (5, 6):
        assert gate.admit(origin(sn))
        gate.taken(origin(sn), deferred=False)
    assert gate.behind() == 1  # 7 arrived and was held back: still to fetch
    assert gate.admit(origin(7))
    gate.taken(origin(7), deferred=False)
    assert gate.behind() == 0
    assert gate.admit(origin(8))


def test_fair_queue_says_its_room_and_what_would_refuse_without_queuing() -> None:
    """`room` and `refusal`, which the refetch and `submit(defer_when_full=True)` ask, agree with
    what `offer` does, and queue nothing."""
    q: FairQueue[tuple[str, int], int] = FairQueue(
        per_source=3, total=10, group=lambda source: source[0], per_group=4
    )
    assert q.room(("a", 1)) == 3 and q.refusal(("a", 1), 0) is None
    for item in range(3):
        assert q.offer(("a", 1), item) is None
    assert q.room(("a", 1)) == 0 and q.refusal(("a", 1), 9) == FULL_SOURCE == q.offer(("a", 1), 9)
    assert q.room(("a", 2)) == 1
    assert q.offer(("a", 2), 0) is None
    assert q.room(("a", 3)) == 0 and q.refusal(("a", 3), 0) == FULL_GROUP
    assert q.room(("b", 1)) == 3
    assert q.depth() == 4
    # Items promised to come (the refetch's fetches in flight) count as queued: their source's,
    # their group's and the whole queue's room is left to them.
    assert q.room(("a", 2), {("a", 2): 1}) == 0 and q.room(("b", 1), {("a", 2): 1}) == 3
    assert q.room(("b", 1), {("b", 2): 2}) == 2 and q.room(("b", 2), {("b", 2): 2}) == 1
    assert q.room(("c", 1), {("b", 1): 3, ("b", 2): 1}) == 2  # the total: 10 - 4 queued - 4 promised
    assert q.depth() == 4


def test_deferred_scans_pushed_out_of_a_robots_cache_meanwhile_are_given_up_not_the_rest() -> None:
    """Robots that publish on while the queue is full push their deferred scans out of their caches
    (a cache holds a publisher's last `cache` samples, here only as many as its backlog). A fetch
    for the first of them then brings nothing: the service asks for every one missing instead,
    takes what the cache still holds from where it begins and counts the rest unrecoverable. It
    gave the whole robot up after three empty fetches (an early version): 8,342 of 42,000 scans of
    40 robots unrecoverable where their caches had lost 2,000 at most."""
    cache = 30
    scans = sim_scans(4, 2 * cache, beams=61)
    with fleet(4, cache, queue_per_robot=8, queue_total=16, cache=cache) as f:  # the map's share: 8
        registry, entry, ingest, pubs = f.registry, f.entry, f.ingest, f.pubs
        for pub in pubs:
            for scan in scans[:cache]:
                assert pub.publish(scan)
        with entry.gmap.lock:
            ingest.start()
            wait_for(
                lambda: ingest.status()["messages_received"] == 4 * cache, timeout=60, what="the backlogs"
            )
            for pub in pubs:  # live, and into the caches: the backlogs' scans leave them
                for scan in scans[cache:]:
                    assert pub.publish(scan)
            wait_for(lambda: ingest.status()["messages_received"] == 8 * cache, timeout=60, what="the rest")
        reports = [pub.flush(60) for pub in pubs]
        assert wait_idle(registry)
        status = ingest.status()
        integrated = [entry.robots[f"r{k}"].scans_integrated for k in range(4)]
        # What a cache still held (its last 30) is in; what it had lost is counted, nothing else.
        assert all(n >= cache for n in integrated), (integrated, status)
        assert status["unrecoverable"] == 4 * 2 * cache - sum(integrated) > 0, (integrated, status)
        assert all(r.settled and r.integrated + r.lost + r.unsettled == 2 * cache for r in reports), reports
        assert ingest._refetch.behind() == 0


def test_robots_publishing_on_while_their_backlogs_wait_keep_them_in_their_caches() -> None:
    """The same robots with the client's default cache, twice their backlog: a robot whose whole
    backlog went out when the service came up may publish as many scans again before the first of
    them leaves its cache, so the queue's full delay costs none of them. With a cache as large as
    the backlog (until 2026-11-29), each scan a robot published meanwhile pushed one of its
    deferred scans out (40 robots x 1050 scans on one map: 50 to 740 unrecoverable; here 35 of
    these 80)."""
    backlog = 10
    scans = sim_scans(4, 2 * backlog, beams=61)
    with fleet(4, backlog, queue_per_robot=4, queue_total=8) as f:  # the map's share: 4
        registry, entry, ingest, pubs = f.registry, f.entry, f.ingest, f.pubs
        assert [pub.cache for pub in pubs] == [2 * backlog] * 4
        for pub in pubs:
            for scan in scans[:backlog]:
                assert pub.publish(scan)
        with entry.gmap.lock:
            ingest.start()
            wait_for(
                lambda: ingest.status()["messages_received"] == 4 * backlog, timeout=60, what="the backlogs"
            )
            for pub in pubs:  # live, and into the caches, behind the backlogs
                for scan in scans[backlog:]:
                    assert pub.publish(scan)
            wait_for(lambda: ingest.status()["messages_received"] == 8 * backlog, timeout=60, what="the rest")
        reports = [pub.flush(60) for pub in pubs]
        assert [r.integrated for r in reports] == [2 * backlog] * 4, reports
        assert wait_idle(registry)
        assert ingest.status()["unrecoverable"] == 0, ingest.status()
        for k in range(4):
            robot = entry.robots[f"r{k}"]
            counts = (robot.scans_integrated, robot.dropped, robot.lost, robot.duplicates, robot.last_seq)
            assert counts == (2 * backlog, 0, 0, 0, 2 * backlog - 1), (k, counts)
        assert ingest._refetch.behind() == 0


def test_a_robot_gone_with_its_deferred_scans_is_given_up_and_its_scans_counted() -> None:
    """A robot that closes while its scans wait to be fetched again takes its cache with it: the
    service's fetches bring nothing, and after `REFETCH_ATTEMPTS` of them it gives the robot up,
    counting what it could not fetch as unrecoverable, and forgets it (nothing left behind)."""
    with fleet(1, DEFAULT_BACKLOG, queue_per_robot=4, queue_total=8) as f:
        registry, entry, ingest, (pub,) = f.registry, f.entry, f.ingest, f.pubs
        ingest.start()
        assert pub.wait_connected(30)
        with entry.gmap.lock:
            for scan in sim_scans(5, 20, beams=61):
                assert pub.publish(scan)
            wait_for(lambda: ingest.status()["messages_received"] == 20, timeout=60, what="the scans")
            pub.close()
        wait_for(lambda: ingest._refetch.behind() == 0, timeout=60, what="the robot given up")
        assert wait_idle(registry)
        integrated = entry.robots["r0"].scans_integrated
        # The queue's 4, the worker's 1, and any the thread fetched again before the robot closed.
        assert 4 <= integrated < 20
        assert ingest.status()["unrecoverable"] == 20 - integrated
