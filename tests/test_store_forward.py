"""Store and forward over real parts: the real service as a process, a robot's `ScanPublisher` (a real
Zenoh client session) reaching it through a TCP proxy with real sockets (`FreezableProxy`), which a
test cuts (a Wi-Fi dead zone) or points at a restarted service.

What a robot publishes while its link is down, or while the service is away, is kept in its
publisher's backlog (zenoh-ext's advanced publisher) and fetched by the service's advanced
subscriber when they meet again: integrated once, in order, so that the map equals the engine's map
of every scan. Without a backlog (`backlog=0`, the old behaviour) those scans are lost.

Plain publishers reaching the advanced subscriber are covered where they always were: the robots of
tests/test_ingest.py (`scan_publisher`) and tests/robot_process.py (tests/test_e2e.py) publish with
`session.declare_publisher`.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import fleetmap_client.publisher as publisher_module
import httpx
import pytest
import zenoh
from fleetmap_client.publisher import ScanPublisher
from prometheus_client.parser import text_string_to_metric_families
from robot_process import scans_for
from service_process import FreezableProxy, RestartingService, ServiceProcess, free_port, reaped, wait_for
from test_e2e import assert_region_equal, map_stats, wait_integrated

from fleetmap import codec
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan

LAYERS = ("log_odds", "hits", "misses", "tsdf", "tsdf_weight")
#: Scans published per second by the robots of these tests.
RATE = 25.0


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One `--in-memory` service for the module's tests that need no other: each publishes to maps
    of its own (ids no other test here uses) and counts the service-wide Zenoh counters from what
    they were when it began; none stops or restarts it (those tests keep their own)."""
    with ServiceProcess(tmp_path_factory.mktemp("store-forward"), ["--in-memory"]) as svc:
        yield svc


def engine_map(scans: list[Scan]) -> GridMap:
    """The engine's map of `scans` in order, each as the service decodes it (binary: float32 ranges)."""
    gmap = GridMap()
    for seq, scan in enumerate(scans):
        payload = codec.encode_binary(scan, seq, stamp=float(seq))
        gmap.integrate(codec.decode(payload, codec.BINARY_ENCODING).scan)
    return gmap


def robot_stats(http: httpx.Client, map_id: str, robot_id: str) -> dict[str, Any]:
    robot: dict[str, Any] = map_stats(http, map_id)["robots"][robot_id]
    return robot


def zenoh_counters(http: httpx.Client) -> tuple[int, float]:
    """(`/healthz` zenoh.unrecoverable, `/metrics` fleetmap_zenoh_scans_unrecoverable_total)."""
    healthz = http.get("/healthz").json()["zenoh"]["unrecoverable"]
    metric = next(
        sample.value
        for family in text_string_to_metric_families(http.get("/metrics").text)
        for sample in family.samples
        if sample.name == "fleetmap_zenoh_scans_unrecoverable_total"
    )
    return healthz, metric


def publish_then_cut(
    pub: ScanPublisher, proxy: FreezableProxy, http: httpx.Client, map_id: str, scans: list[Scan], first: int
) -> None:
    """Publish scans 0 .. `first` - 1 over a live link, wait until the service integrated them, then
    cut the link and wait until the robot notices: what it publishes next goes into the dead zone."""
    assert pub.wait_connected(20)
    for seq in range(first):
        pub.publish(scans[seq], seq=seq, stamp=float(seq))
    wait_integrated(http, map_id, first, timeout=20)
    proxy.cut()
    wait_for(lambda: not pub.connected, 15, 0.01, "the robot to notice the cut")


class Robot:
    """A robot publishing `scans` (seq k = scan k, stamp k) at `RATE` from a thread, through `proxy`."""

    def __init__(self, proxy: FreezableProxy, map_id: str, scans: list[Scan], backlog: int) -> None:
        self.scans = scans
        self.pub = ScanPublisher(map_id, "r1", connect=[proxy.endpoint], backlog=backlog)
        self.sent = 0  # scans published so far
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> Robot:
        assert self.pub.wait_connected(20), self.pub.last_connect_error
        self.thread.start()
        return self

    def _run(self) -> None:
        started = time.monotonic()
        for seq, scan in enumerate(self.scans):
            time.sleep(max(0.0, started + seq / RATE - time.monotonic()))
            self.pub.publish(scan, seq=seq, stamp=float(seq))
            self.sent = seq + 1

    def wait_sent(self, n: int) -> None:
        wait_for(lambda: self.sent >= n, 30, 0.01, f"{n} scans published")

    def finish(self) -> None:
        self.thread.join(60)
        assert not self.thread.is_alive()


@pytest.mark.parametrize("backlog", [1000, 0])
def test_a_dead_zone_loses_no_scan(service: ServiceProcess, backlog: int) -> None:
    """The robot's link is cut for 2 s (new connections refused too) while it keeps publishing at
    25 Hz: with its backlog, every scan is integrated once, none lost, and the map is the engine's
    map of all of them. Without (`backlog=0`), the scans of the dead zone are gone: that is what the
    backlog changes."""
    scans = scans_for(sim=3, count=150)
    proxy = FreezableProxy(service.zenoh_port)
    map_id = f"dz-{backlog}"  # each case a map of its own, on the module's service
    robot = Robot(proxy, map_id, scans, backlog)
    with httpx.Client(base_url=service.base_url, timeout=10) as http:
        counted_before = zenoh_counters(http)  # the module's earlier tests' count
    try:
        robot.start()
        robot.wait_sent(40)
        assert proxy.cut() >= 1
        time.sleep(2.0)  # 50 scans published into the dead zone, some 5 more until Zenoh reconnects
        proxy.restore()
        robot.finish()
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            if backlog:
                wait_integrated(http, map_id, len(scans), timeout=30)
                state = robot_stats(http, map_id, "r1")
                assert (state["scans_integrated"], state["lost"], state["dropped"]) == (len(scans), 0, 0)
                assert state["last_seq"] == len(scans) - 1 and state["restarts"] == 0
                assert robot.pub.dropped == 0
                assert_region_equal(http, map_id, engine_map(scans), LAYERS)
                assert zenoh_counters(http) == counted_before
            else:
                wait_for(lambda: robot_stats(http, map_id, "r1")["last_seq"] == len(scans) - 1, 30, 0.05)
                state = robot_stats(http, map_id, "r1")
                assert robot.pub.dropped >= 40, robot.pub.dropped  # given up while disconnected
                assert state["lost"] >= 40 and state["scans_integrated"] == len(scans) - state["lost"], state
    finally:
        robot.pub.close()
        proxy.close()


def test_the_service_killed_and_restarted_integrates_every_scan_once(tmp_path: Path) -> None:
    """SIGKILL of a durable service while the robot publishes, a new service on the same data (the
    robot reconnects to it through the proxy): the new service fetches the robot's backlog, which
    holds scans the killed one had integrated and journaled (ignored as duplicates: the seq
    bookkeeping is restored from the journal) and scans it never integrated or journaled, or that
    were published while no service ran (integrated). Afterwards every scan is integrated exactly
    once: the robot's counters say so and the map equals the engine's, cell by cell."""
    data = ["--data-dir", str(tmp_path / "data")]
    scans = scans_for(sim=4, count=200)
    services = RestartingService(tmp_path, data)
    proxy = services.proxy
    robot = Robot(proxy, "restart", scans, 1000)
    try:
        robot.start()
        robot.wait_sent(60)
        services.kill()  # no snapshot, no goodbye: what was not journaled is gone from the service
        second = services.restart()  # the robot published on meanwhile: its backlog grew
        robot.finish()
        with httpx.Client(base_url=second.base_url, timeout=10) as http:
            wait_integrated(http, "restart", len(scans), timeout=30)
            time.sleep(0.5)  # nothing more may come (a double integration would show now)
            state = robot_stats(http, "restart", "r1")
            assert (state["scans_integrated"], state["lost"], state["dropped"]) == (len(scans), 0, 0), state
            assert state["restarts"] == 0 and state["last_seq"] == len(scans) - 1
            assert state["duplicates"] > 0  # the history fetch replayed what the first one had
            assert map_stats(http, "restart")["scans_integrated"] == len(scans)
            assert_region_equal(http, "restart", engine_map(scans), LAYERS)
    finally:
        robot.pub.close()
        services.close()


#: Seconds within which a robot must be connected again once a restarted service is reachable: its
#: retry period is at most 0.5 s (`RECONNECT_PERIOD_MAX_MS`), the rest is margin for a loaded machine.
#: Zenoh's own default retries every 4 s by then, and took 4.0 s here.
RECONNECT_BOUND_S = 2.0


def test_a_service_restarted_between_two_looks_at_the_link_gets_the_cache_first(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A robot that never saw its link down (it publishes rarely, or its watcher thread was starved
    while the service was killed and restarted) is connected to a new service process, with a new
    Zenoh id. Its next scan must wait for the reconnection's hold, as after a link seen down, so that
    the new service fetches the cache first: a live scan first would make zenoh-ext drop the cache
    as old. Its watcher is slowed to a minute here so that it cannot look in between; the scan was
    sent live (published, not held) before the publisher compared the routers' ids."""
    data = ["--data-dir", str(tmp_path / "data")]
    scans = scans_for(sim=5, beams=91, count=12)
    with RestartingService(tmp_path, data) as services:
        pub = ScanPublisher("between", "r1", connect=[services.proxy.endpoint], backlog=100)
        try:
            assert pub.wait_connected(20), pub.last_connect_error
            for seq in range(10):
                pub.publish(scans[seq], seq=seq, stamp=float(seq))
            monkeypatch.setattr(publisher_module, "WATCH_INTERVAL_S", 60.0)
            time.sleep(0.3)  # the watcher's current 50 ms wait ends; its next one is a minute
            services.kill()
            second = services.restart()
            wait_for(lambda: pub.connected and pub.subscribed, 20, 0.01, "the robot to meet the new service")
            published, backlogged = pub.published, pub.backlogged
            pub.publish(scans[10], seq=10, stamp=10.0)
            assert (pub.published, pub.backlogged) == (published, backlogged + 1), "sent live, not held"
            time.sleep(0.6)  # past the hold: the next publish sends the held scan first, then itself
            pub.publish(scans[11], seq=11, stamp=11.0)
            report = pub.flush(30)
            assert report.confirmed and report.integrated == 12, report
            with httpx.Client(base_url=second.base_url, timeout=10) as http:
                assert map_stats(http, "between")["scans_integrated"] == 12
        finally:
            pub.close()


def test_a_restarted_service_slow_to_fetch_the_cache_still_gets_it_before_the_held_scans(
    tmp_path: Path,
) -> None:
    """A new service process that hears of a reconnected robot (its liveliness token) only 2 s after
    the robot's link is up: the robot's queued scans must wait for the service's query for its cache,
    not for a fixed time. zenoh-ext takes the first scan of a publisher it does not know for its
    first (and drops as old what the fetch brings after it), so a held scan sent before the query
    cost the cache: in a heavy run of tests/test_crash_exactly_once.py the restarted service took
    0.6 s to query a robot's cache (its Zenoh thread waited while another robot's 1000 cached scans
    went through the scan callback), and the robot had sent its held scans after 0.5 s. Here the
    proxy delays what the robot sends to the new service by 2 s (`delay_after_handshake`); the new
    service has its own data directory, so it must take seqs 0-9 from the cache, 10-19 held."""
    scans = scans_for(sim=6, beams=91, count=20)
    first = ServiceProcess(tmp_path).start()
    proxy = FreezableProxy(first.zenoh_port)
    second = ServiceProcess(tmp_path)
    pub = ScanPublisher("slow", "r1", connect=[proxy.endpoint], backlog=100)
    try:
        assert pub.wait_connected(20), pub.last_connect_error
        for seq in range(10):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        assert pub.flush(30).confirmed  # in the cache too
        assert first.proc is not None
        first.proc.kill()
        first.proc.wait(10)
        wait_for(lambda: not pub.connected, 20, 0.01, "the robot to see its link down")
        for seq in range(10, 20):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        assert pub.pending == 10
        proxy.delay_after_handshake(2.0)
        proxy.target_port = second.zenoh_port
        second.start()
        report = pub.flush(30)
        with httpx.Client(base_url=second.base_url, timeout=10) as http:
            state = robot_stats(http, "slow", "r1")
        assert report.confirmed and report.integrated == 20, (report, state)
        assert (state["scans_integrated"], state["lost"]) == (20, 0), state
    finally:
        pub.close()
        proxy.close()
        first.stop()
        second.stop()


def test_a_robot_meets_a_restarted_service_within_a_second_of_it_listening(tmp_path: Path) -> None:
    """The durable service SIGKILLed, away for 6 s, started again: the robot's client session is
    connected to it, and sees its scan subscriber, within `RECONNECT_BOUND_S` of the service becoming
    reachable. The proxy refuses connections until just after one of the robot's attempts failed, so
    the time measured is the robot's wait for its next attempt, whatever the service's start took.
    With Zenoh's default `connect/retry` (1 s, growing to 4 s) it was about 4 s: a service that came
    back for less than that was never met, and five such in a row kept the robots of
    tests/test_crash_exactly_once.py away for 37 s, longer than their backlogs lasted."""
    data = ["--data-dir", str(tmp_path / "data")]
    services = RestartingService(tmp_path, data)
    proxy = services.proxy
    pub = ScanPublisher("back", "r1", connect=[proxy.endpoint])
    try:
        assert pub.wait_connected(20), pub.last_connect_error
        services.kill()
        proxy.cut()  # refused from now on, and counted: the robot's attempts
        away = time.monotonic()
        wait_for(lambda: not pub.connected, 15, 0.01, "the robot to notice the service left")
        services.restart()
        # Past the backoff's first steps (Zenoh's default tries again 1, 3, 7, 11 s after the loss).
        time.sleep(max(0.0, away + 6.0 - time.monotonic()))
        attempts = len(proxy.refused)
        wait_for(lambda: len(proxy.refused) > attempts, 10, 0.002, "a connection attempt of the robot")
        proxy.restore()
        reachable = time.monotonic()
        wait_for(lambda: pub.connected and pub.subscribed, 20, 0.01, "the robot to meet the new service")
        took = time.monotonic() - reachable
        tries = [round(t - away, 2) for t in proxy.refused]
        assert took < RECONNECT_BOUND_S, (
            f"connected {took:.2f} s after the service was reachable; attempts at {tries}"
        )
    finally:
        pub.close()
        services.close()


def test_a_burst_of_1000_recovered_scans_fits_the_ingest_queue(service: ServiceProcess) -> None:
    """1000 scans published into a dead zone (as fast as possible), then the link comes back: they
    arrive as one burst at network speed, far faster than they integrate, and the robot's queue
    (1024 scans by default; it was 64) holds them all: none dropped."""
    scans = scans_for(sim=5, beams=181, count=1010)
    proxy = FreezableProxy(service.zenoh_port)
    pub = ScanPublisher("burst", "r1", connect=[proxy.endpoint], backlog=1000)
    try:
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            queue_full = (
                http.get("/healthz").json()["zenoh"]["rejected"].get("queue_full", 0)
            )  # earlier tests'
            publish_then_cut(pub, proxy, http, "burst", scans, 10)
            for seq in range(10, len(scans)):
                assert pub.publish(scans[seq], seq=seq, stamp=float(seq))
            assert pub.backlogged == 1000 and pub.dropped == 0
            proxy.restore()
            wait_integrated(http, "burst", len(scans), timeout=60)
            state = robot_stats(http, "burst", "r1")
            assert (state["scans_integrated"], state["lost"], state["dropped"]) == (len(scans), 0, 0), state
            assert http.get("/healthz").json()["zenoh"]["rejected"].get("queue_full", 0) == queue_full
    finally:
        pub.close()
        proxy.close()


def test_scans_past_the_backlog_of_a_dead_zone_are_counted_as_lost(service: ServiceProcess) -> None:
    """A dead zone longer than the backlog: 50 scans published into it with a backlog of 10. They
    wait in the publisher's queue (nothing goes to Zenoh while it knows it is disconnected); the
    last 10 arrive, the 40 before them were pushed out: given up by the robot (`dropped`) and counted
    as lost by the service. Zenoh's cache had none of them, so zenoh-ext reports nothing missed."""
    scans = scans_for(sim=6, beams=181, count=60)
    proxy = FreezableProxy(service.zenoh_port)
    pub = ScanPublisher("miss", "r1", connect=[proxy.endpoint], backlog=10)
    try:
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            counted_before = zenoh_counters(http)  # the module's earlier tests' count
            publish_then_cut(pub, proxy, http, "miss", scans, 10)
            for seq in range(10, 60):
                assert pub.publish(scans[seq], seq=seq, stamp=float(seq))
            assert (pub.pending, pub.backlogged, pub.dropped) == (10, 10, 40)
            proxy.restore()
            wait_integrated(http, "miss", 20, timeout=30)
            state = robot_stats(http, "miss", "r1")
            assert (state["scans_integrated"], state["lost"], state["last_seq"]) == (20, 40, 59), state
            assert zenoh_counters(http) == counted_before
    finally:
        pub.close()
        proxy.close()


def test_scans_past_the_cache_of_a_silently_dead_link_are_counted_as_unrecoverable(
    service: ServiceProcess,
) -> None:
    """A link that dies without notice (frozen: to the robot it looks alive until Zenoh's lease runs
    out): the 50 scans published into it go to Zenoh, and its cache keeps the last 10 (`cache`).
    When the robot has reconnected, the service fetches those 10; the 40 before them were pushed out
    of the cache: the service counts them as unrecoverable (`/healthz` zenoh.unrecoverable,
    `/metrics`) and as lost on the robot."""
    scans = scans_for(sim=6, beams=181, count=60)
    proxy = FreezableProxy(service.zenoh_port)
    pub = ScanPublisher("unrecoverable", "r1", connect=[proxy.endpoint], backlog=10, cache=10)
    try:
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            healthz, metric = zenoh_counters(http)  # the module's earlier tests' count
            assert pub.wait_connected(20)
            for seq in range(10):
                pub.publish(scans[seq], seq=seq, stamp=float(seq))
            wait_integrated(http, "unrecoverable", 10, timeout=20)
            assert proxy.freeze(refuse_new=True) >= 1
            for seq in range(10, 60):
                assert pub.publish(scans[seq], seq=seq, stamp=float(seq))
            assert pub.pending == 0  # handed to Zenoh: the robot did not know
            proxy.restore()  # the frozen link stays silent until Zenoh gives up on it
            wait_integrated(http, "unrecoverable", 20, timeout=60)
            wait_for(
                lambda: zenoh_counters(http) == (healthz + 40, metric + 40),
                10,
                0.05,
                "40 unrecoverable scans",
            )
            state = robot_stats(http, "unrecoverable", "r1")
            assert (state["scans_integrated"], state["lost"], state["last_seq"]) == (20, 40, 59), state
    finally:
        pub.close()
        proxy.close()


def test_a_peer_robot_sends_its_queued_scans_before_newer_ones(tmp_path: Path) -> None:
    """A robot in peer mode: its session opens with nothing connected (a peer does not wait for its
    endpoints). The scans published before it opened wait in the publisher's queue, and so do those
    published after it opened, still disconnected; all leave in order once it is connected. (When
    the latter went to the advanced publisher's cache while the former stayed queued until the hold
    ended, the older ones reached the service after the newer ones, which took them for
    duplicates.)"""
    scans = scans_for(sim=7, beams=181, count=10)
    proxy = FreezableProxy(free_port())  # nothing listens there yet: every connection is closed
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    pub = ScanPublisher("peer", "r1", connect=[proxy.endpoint], zenoh_config=config)
    service: ServiceProcess | None = None
    try:
        for seq in range(5):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        assert pub.pending == 5  # the peer's session is still trying its endpoint (about 1 s)
        wait_for(pub._opened.is_set, 15, 0.01, "the peer session to open")
        assert not pub.connected
        for seq in range(5, 10):
            assert pub.publish(scans[seq], seq=seq, stamp=float(seq))
        assert (pub.published, pub.backlogged, pub.dropped, pub.pending) == (0, 10, 0, 10)
        service = ServiceProcess(tmp_path, ["--in-memory"]).start()
        proxy.target_port = service.zenoh_port
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            wait_for(lambda: map_stats(http, "peer").get("robots", {}).get("r1", {}).get("last_seq") == 9, 30)
            time.sleep(1.0)  # the queued scans would follow the hold (0.5 s) and count as duplicates
            state = robot_stats(http, "peer", "r1")
            assert (state["scans_integrated"], state["lost"], state["duplicates"]) == (10, 0, 0), state
            assert_region_equal(http, "peer", engine_map(scans), LAYERS)
    finally:
        pub.close()
        proxy.close()
        if service is not None:
            service.stop()


@pytest.mark.parametrize("how", ["deleted", "replaced"])
def test_a_deleted_map_stays_deleted_when_the_restarted_service_fetches_the_robots_cache(
    tmp_path: Path, how: str
) -> None:
    """A robot publishes 40 scans, which the service integrates; the map is deleted (or replaced by
    an upload of an empty map), the robot's publisher stays open with those scans in its cache, and
    the service restarts. The new service fetches the cache (history of a publisher it has not
    heard): those 40 scans are from before the deletion and are ignored, and the robot's liveliness
    token, seen again, creates nothing, so the map stays deleted (or as uploaded). Without the
    tombstones the deleted map came back with its 40 old scans. The robot's next scans go through:
    a new map of just those."""
    data = ["--data-dir", str(tmp_path / "data")]
    scans = scans_for(sim=8, beams=181, count=50)
    services = RestartingService(tmp_path, data)
    first, proxy = services.service, services.proxy
    pub = ScanPublisher("gone", "r1", connect=[proxy.endpoint], backlog=1000)
    try:
        assert pub.wait_connected(20)
        for seq in range(40):
            pub.publish(scans[seq], seq=seq, stamp=float(seq))
        with httpx.Client(base_url=first.base_url, timeout=10) as http:
            wait_integrated(http, "gone", 40, timeout=30)
            if how == "deleted":
                assert http.delete("/maps/gone").status_code == 204
            else:  # the map replaced by an upload of itself: the same cells, its robots gone
                snapshot = http.get("/maps/gone/snapshot").content
                put = http.put("/maps/gone/snapshot", content=snapshot)
                assert put.status_code == 200, put.text
        assert first.stop() == 0
        second = services.restart()
        with httpx.Client(base_url=second.base_url, timeout=10) as http:

            def refused() -> int:
                return int(http.get("/healthz").json()["zenoh"]["rejected"].get("duplicate", 0))

            wait_for(lambda: refused() >= 40, 30, 0.05, "the 40 cached scans fetched and ignored")
            time.sleep(0.5)  # (what the fetch brought in would be integrated by now)
            if how == "deleted":
                assert http.get("/maps/gone").status_code == 404, http.get("/maps").json()
            else:
                stats = map_stats(http, "gone")
                # (the robot is shown, online by its token, with none of its old scans)
                assert stats["scans_integrated"] == 0 and stats["robots"]["r1"]["last_seq"] is None, stats
                assert_region_equal(http, "gone", engine_map(scans[:40]), LAYERS)
            for seq in range(40, 50):
                pub.publish(scans[seq], seq=seq, stamp=float(seq))
            wait_integrated(http, "gone", 10, timeout=30)
            state = robot_stats(http, "gone", "r1")
            assert (state["scans_integrated"], state["last_seq"]) == (10, 49), state
            if how == "deleted":  # a new map of the 10 new scans only
                assert_region_equal(http, "gone", engine_map(scans[40:]), LAYERS)
    finally:
        pub.close()
        services.close()


def rest_scan(seq: int) -> dict[str, Any]:
    """A small JSON scan at the origin (a robot posting over REST)."""
    return {
        "seq": seq, "pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "angle_min": -1.0, "angle_increment": 0.5,
        "range_max": 10.0, "ranges": [2.0] * 5,
    }  # fmt: skip


@pytest.mark.parametrize("how", ["stopped", "killed"])
def test_a_robot_a_full_map_forgot_is_not_integrated_twice_from_its_cache(tmp_path: Path, how: str) -> None:
    """A map that holds two robots (`--max-robots-per-map 2`): r1 publishes 30 scans (its publisher's
    cache keeps them), its link goes, and r2 and r3 post a scan each, so the map forgets r1. The
    service restarts, stopped (its last snapshot stored r1's tombstone and dropped its row) or
    killed (r1's rows still in the journal: the restored map, one robot too many, forgets r1 again),
    and fetches r1's cache when r1 reconnects: those 30 scans are the map's already and must be
    ignored as duplicates, not integrated a second time as they were. r1's next scans go through."""
    data = ["--data-dir", str(tmp_path / "data"), "--max-robots-per-map", "2"]
    scans = scans_for(sim=9, beams=181, count=40)
    services = RestartingService(tmp_path, data)
    first, proxy = services.service, services.proxy
    pub = ScanPublisher("full", "r1", connect=[proxy.endpoint], backlog=1000)
    try:
        with httpx.Client(base_url=first.base_url, timeout=10) as http:
            publish_then_cut(pub, proxy, http, "full", scans, 30)
            wait_for(lambda: not robot_stats(http, "full", "r1")["online"], 15, 0.05, "r1 shown offline")
            for robot_id in ("r2", "r3"):  # r3 makes the map forget r1 (offline, nothing waiting)
                posted = http.post("/maps/full/scans", params={"robot_id": robot_id}, json=rest_scan(0))
                assert posted.status_code == 200, posted.text
            stats = map_stats(http, "full")
            assert (sorted(stats["robots"]), stats["scans_integrated"]) == (["r2", "r3"], 32), stats
        if how == "killed":
            services.kill()
        else:
            assert first.stop() == 0
        second = services.restart()
        proxy.restore()
        with httpx.Client(base_url=second.base_url, timeout=10) as http:

            def duplicates() -> int:
                return int(http.get("/healthz").json()["zenoh"]["rejected"].get("duplicate", 0))

            def fetched() -> int:  # r1's cached scans the service has seen, ignored or integrated
                robot = map_stats(http, "full")["robots"].get("r1", {})
                return duplicates() + int(robot.get("scans_integrated", 0))

            wait_for(lambda: fetched() >= 30, 30, 0.05, "r1's 30 cached scans fetched")
            time.sleep(0.5)  # (what the fetch brought in would be integrated by now)
            stats = map_stats(http, "full")
            assert stats["scans_integrated"] == 32, stats  # 62: r1's scans integrated twice
            assert duplicates() == 30 and stats["robots"]["r1"]["scans_integrated"] == 0, stats
            for seq in range(30, 40):
                pub.publish(scans[seq], seq=seq, stamp=float(seq))
            wait_integrated(http, "full", 42, timeout=30)
            state = robot_stats(http, "full", "r1")
            assert (state["scans_integrated"], state["last_seq"], state["lost"]) == (10, 39, 0), state
    finally:
        pub.close()
        services.close()


def test_close_while_a_publish_is_blocked_on_a_frozen_link_closes_the_session(
    service: ServiceProcess,
) -> None:
    """A robot thread inside `publish`, blocked by congestion control BLOCK on a frozen link, while
    another thread closes the publisher (the robot shutting down): `close()` must close the session
    without raising. zenoh-python holds the publisher borrowed during the put, so undeclaring it
    then raised RuntimeError ("Already borrowed") out of close(), which left the session open; the
    blocked thread then gets `PublisherClosed` (or False: its scan given up)."""
    scans = scans_for(sim=6, beams=50_000, count=1)
    proxy = FreezableProxy(service.zenoh_port)
    pub = ScanPublisher("frozen-close", "r1", connect=[proxy.endpoint])
    outcome: list[object] = []

    def publish_until_closed() -> None:
        try:
            while True:
                pub.publish(scans[0])
        except Exception as exc:  # noqa: BLE001 - what the thread ended with is the test's finding
            outcome.append(exc)

    sender = threading.Thread(target=publish_until_closed, daemon=True)
    try:
        assert pub.wait_connected(20)
        session = pub._session
        assert session is not None
        proxy.freeze()
        sender.start()
        # Blocked: nothing more is handed to Zenoh (a 200 kB scan fills the socket buffers at once).
        counted = [-1]

        def stalled() -> bool:
            before, counted[0] = counted[0], pub.published
            return counted[0] == before

        wait_for(stalled, 10, 0.5, "publish blocked on the frozen link")
        pub.close()  # raised RuntimeError: Already borrowed
        assert session.is_closed()
        sender.join(20)
        assert not sender.is_alive()
        assert [type(exc) for exc in outcome] == [publisher_module.PublisherClosed], outcome
    finally:
        pub.close()
        proxy.close()


#: A robot program whose daemon thread publishes big scans while the main thread ends (argv: the
#: endpoint): its publisher is closed at the exit (atexit) while that thread is blocked in Zenoh.
_EXIT_WHILE_BLOCKED = """
import sys, threading, time
from fleetmap.scan import Scan
from fleetmap_client.publisher import ScanPublisher
scan = Scan.from_fan((0.0, 0.0, 0.0), -3.0, 6.0 / 50_000, [3.0] * 50_000, 0.1, 10.0)
pub = ScanPublisher("frozen", "r1", connect=[sys.argv[1]])
assert pub.wait_connected(20)
print("connected", flush=True)
sys.stdin.readline()  # the link is frozen now
threading.Thread(target=lambda: [pub.publish(scan) for _ in iter(int, 1)], daemon=True).start()
time.sleep(2)  # blocked by then: the socket buffers hold a few 200 kB scans
"""


def test_a_program_that_ends_while_a_publish_is_blocked_on_a_frozen_link_exits_cleanly(
    service: ServiceProcess,
) -> None:
    """The atexit close of a publisher left open, while a daemon thread's `publish` is blocked by
    BLOCK on a frozen link, raised "Already borrowed" in the atexit callback, and the interpreter
    then finalized with that thread inside Zenoh's put: the process died of SIGABRT ("FATAL:
    exception not rethrown") instead of exiting 0."""
    proxy = FreezableProxy(service.zenoh_port)
    child = subprocess.Popen(
        [sys.executable, "-c", _EXIT_WHILE_BLOCKED, proxy.endpoint], stdin=subprocess.PIPE,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        with reaped(child):
            assert child.stdout is not None and child.stdin is not None
            assert child.stdout.readline().strip() == "connected"
            proxy.freeze()
            child.stdin.write("frozen\n")
            child.stdin.flush()
            out, _ = child.communicate(timeout=60)
        assert "Already borrowed" not in out and "FATAL" not in out, out
        assert child.returncode == 0, out
    finally:
        proxy.close()
