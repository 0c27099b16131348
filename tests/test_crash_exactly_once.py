"""Exactly once across crashes: the real durable service SIGKILLed at random moments (and once
stopped with SIGTERM) and restarted on the same data directory, several rounds, while robots publish
continuously with `ScanPublisher` (store and forward: each keeps its last 1000 scans, which every
new service process fetches) through a `FreezableProxy` that the restarted service is reached
through. Snapshots are taken every second (`--snapshot-interval`), so they race the kills, the
journal commits and the scans waiting in the ingest queue after each restart's history fetch.

At the end every scan must be integrated exactly once: each robot's `flush()` confirms all it
published (none lost), GET /maps/{id} counts exactly those scans, and each robot's own map equals
the engine's map of its scans in publish order, cell by cell. The shared map is checked by counts.
tests/test_store_forward.py checks one kill at a moment the test picks; scripts/chaos_service.py
counts `integrated = sent - dropped - rejected - duplicate`, which a scan refused as a duplicate
but never integrated passes.

What holds (asserted): no scan is integrated twice (each robot's integrated + lost = published, and
the service's counters say the same as its flush), the durable bookkeeping loses nothing at a
restart (a copy of the data directory after each kill, replayed offline, had no gap between a
robot's saved seq and its journal rows in 80 robot restores), and a robot that lost nothing is
confirmed by its flush, with its own map equal to the engine's cell by cell.

What it found: a restarted service took part of a robot's cache, then a later scan, and never the
rest (6 to 450 scans counted lost, none reported missed by zenoh-ext), in about half of the runs of
10 restarts: robots connected while the service's router waited 0.5 s in `zenoh.open` had their
caches fetched twice at once by the new scan subscriber, and zenoh-ext skipped part of them. The
router no longer waits (`scouting/delay` 0, fleetmap/zenoh_ingest.py). After that, 5 of 5 runs of 10
restarts passed, and 8 of 11 heavier runs (12 restarts, 40 scans/s, up to 4 s down). The losses left
were of two kinds, both found and fixed on 2026-11-27 (docs/protocol.md, "Delivery guarantees"):

- every robot lost scans at the same restart (541, 402, 81 ...): robots retried their connection
  with Zenoh's default backoff (again 1, 3, 7, 11 s ... after the loss, then every 4 s), so they met
  a restarted service up to 4 s after it listened and missed one that was up for less; five such in
  a row kept them away for 37 s, longer than 1000 scans last at 40 scans/s. Robots now retry every
  0.5 s at most (`connect/retry`, `fleetmap_client.zenoh_config.client_config`; measured with
  scripts/reconnect_timing.py: 0.1-0.45 s after the service listens, against up to 3.9 s).
- one robot lost 70 to 600 scans: a scan it put while its session was reconnecting (between the
  publisher's look at the link and the put) reached the restarted service live, before the service
  had fetched the robot's cache; zenoh-ext took it for the robot's first and dropped the cache
  before it as old. Traced by logging such puts: in each of the 4 instrumented runs with this loss,
  the service's first scan of the robot was the one put while connecting (1623, 1681, 2399, 841).
  `ScanPublisher` now hands Zenoh nothing while it knows it is disconnected (its own queue keeps
  those scans, sent after the reconnection's hold).

Heavier runs on 2026-11-27 (12 restarts, 40 scans/s, up to 4 s down, same seeds for each version,
run in turn so that each saw the same load on the shared 2-core machine): before both fixes 9 of 18
runs lost scans (every robot in 4, one robot as above in 4, and two not traced: two robots at the
live edge, and 21 scans in the middle of one robot's fetch); with the reconnect retry alone 3 of 18
(all of the one-robot kind); with both, 0 of 12, and on the day's final code 1 of 13 further runs
(its cause not captured). Traced that evening (logging, not kept, of every scan each service process
received, live or fetched, and of each robot's holds and puts), 11 runs of seeds 1-11 on that code
lost scans in two: seed 8, 3 scans of one robot, its 0.5 s hold over before a restarted service busy
with another robot's cache had queried this one's (its first scan there was a held one, seq 1190,
and 1187-1189, in the cache only, were dropped as old); and seed 5, 216 scans of 4 robots never
integrated, refused at the SIGTERM: Zenoh ran scan callbacks after the service's session closed, and
the closing registry counted them as a full queue's and saved their seqs. `ScanPublisher` now holds
until the service's query for its cache has come, and the closing registry takes nothing. Holding
only until the query (0.1-0.5 s), 2 of 46 runs (seeds 40 and 41) lost scans of a third kind, not
understood: a restarted service's fetch of a robot's cache began in its middle, unreported
(docs/protocol.md, "Delivery guarantees", for all three); so the hold also lasts 0.5 s at least
again. On that final code: 28 of 28 heavy runs clean (seeds 1-26, 40 and 41, traced, one at a time).
A loss of cached scans still ends the test as xfail (every other check holding), and anything else
fails it.

Longer or different runs (the defaults take about 30 s; `make soak` runs 12 restarts):

    FLEETMAP_SOAK_ROUNDS=12 FLEETMAP_SOAK_SEED=7 pytest tests/test_crash_exactly_once.py -n 0

`FLEETMAP_SOAK_ROUNDS` (restarts, default 4), `FLEETMAP_SOAK_SEED` (the kill moments and down
times; default random, printed in a failure), `FLEETMAP_SOAK_RATE` (scans/s per robot, default 30),
`FLEETMAP_SOAK_DOWN` (the longest time no service runs, seconds, default 2; scans published then
reach a new process as one burst, queued deep), `FLEETMAP_SOAK_BEAMS` (beams per scan, default 91;
more make integration slower, so scans wait longer in the queue while snapshots are taken).
"""

from __future__ import annotations

import os
import random
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from fleetmap_client.publisher import ScanPublisher
from robot_process import scans_for
from service_process import FreezableProxy, ServiceProcess
from test_e2e import assert_region_equal, map_stats
from test_store_forward import LAYERS, engine_map

from fleetmap.scan import Scan

ROUNDS = int(os.environ.get("FLEETMAP_SOAK_ROUNDS", "4"))
SEED = int(os.environ.get("FLEETMAP_SOAK_SEED", str(random.randrange(1 << 30))))
RATE = float(os.environ.get("FLEETMAP_SOAK_RATE", "30"))
MAX_DOWN = float(os.environ.get("FLEETMAP_SOAK_DOWN", "2"))
BEAMS = int(os.environ.get("FLEETMAP_SOAK_BEAMS", "91"))
#: Robots with a map each (whose map must equal the engine's), and robots sharing one map.
OWN_MAPS = 3
SHARED = 2
#: Scans made per robot: more than a run publishes (a round takes some 10 s at most), so `Robot`
#: does not reach the end of its list.
SCANS_PER_ROBOT = int(RATE * (10 * ROUNDS + 15))


class Robot:
    """A `ScanPublisher` publishing `scans` (seq k = scan k, stamp k) at `RATE` from a thread, through
    `proxy`, until `stop()`. Late (a publish blocked by a congested link), it catches up at once."""

    def __init__(self, proxy: FreezableProxy, map_id: str, robot_id: str, scans: list[Scan]) -> None:
        self.map_id, self.robot_id, self.scans = map_id, robot_id, scans
        self.pub = ScanPublisher(map_id, robot_id, connect=[proxy.endpoint], backlog=1000)
        self.sent = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        started = time.monotonic()
        for seq, scan in enumerate(self.scans):
            if self._stop.wait(max(0.0, started + seq / RATE - time.monotonic())):
                return
            assert self.pub.publish(scan, seq=seq, stamp=float(seq))
            self.sent = seq + 1

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(30)
        assert not self.thread.is_alive()


def robot_stats(http: httpx.Client, map_id: str, robot_id: str) -> dict[str, Any]:
    return dict(map_stats(http, map_id).get("robots", {}).get(robot_id, {}))


class LossWatch:
    """Polls the current service for each robot's `lost` count and notes when it grows (which
    service, how many seconds after it started, the robot's counters): where a failure began."""

    def __init__(self, robots: list[Robot]) -> None:
        self.robots = robots
        self.service: ServiceProcess | None = None
        self.started = 0.0
        self.number = 0
        self.seen: dict[tuple[str, str], int] = {}
        self.notes: list[str] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def follow(self, service: ServiceProcess) -> None:
        self.service, self.started, self.number = service, time.monotonic(), self.number + 1

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            service = self.service
            if service is None:
                continue
            try:
                with httpx.Client(base_url=service.base_url, timeout=1) as http:
                    for robot in self.robots:
                        state = robot_stats(http, robot.map_id, robot.robot_id)
                        key = (robot.map_id, robot.robot_id)
                        if state.get("lost", 0) > self.seen.get(key, 0):
                            self.seen[key] = state["lost"]
                            self.notes.append(
                                f"service #{self.number} +{time.monotonic() - self.started:.1f} s: {key} "
                                f"lost {state['lost']} last_seq {state['last_seq']} sent {robot.sent}"
                            )
            except httpx.HTTPError:
                continue

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(5)


def test_every_scan_is_integrated_exactly_once_across_kills_and_restarts(tmp_path: Path) -> None:
    """ROUNDS restarts of the durable service (one by SIGTERM, the others SIGKILL, at random moments)
    under five store-and-forward robots; at the end every robot's scans are integrated exactly
    once (module docstring), or the known defect shows (xfail)."""
    rng = random.Random(SEED)
    why = f"FLEETMAP_SOAK_SEED={SEED}"
    data = ["--data-dir", str(tmp_path / "data"), "--snapshot-interval", "0.5"]
    service = ServiceProcess(tmp_path, data).start()
    services = [service]
    proxy = FreezableProxy(service.zenoh_port)
    robots = [Robot(proxy, f"own{k}", "r", scans_for(sim=20 + k, beams=BEAMS, count=SCANS_PER_ROBOT))
              for k in range(OWN_MAPS)]  # fmt: skip
    robots += [Robot(proxy, "shared", f"r{k}", scans_for(sim=30 + k, beams=BEAMS, count=SCANS_PER_ROBOT))
               for k in range(SHARED)]  # fmt: skip
    kills = []
    watch = LossWatch(robots)
    watch.follow(service)
    try:
        for robot in robots:
            assert robot.pub.wait_connected(20), robot.pub.last_connect_error
            robot.thread.start()
        sigterm_round = rng.randrange(ROUNDS)
        for round_no in range(ROUNDS):
            # From at once (scans of the history fetch still queued, snapshots of them) to seconds in.
            time.sleep(rng.uniform(0.05, 4.0))
            assert service.proc is not None and service.alive(), service.logs()
            if round_no == sigterm_round:
                assert service.stop() == 0, service.logs()
                kills.append("TERM")
            else:
                service.proc.kill()
                service.proc.wait(10)
                kills.append("KILL")
            watch.service = None
            time.sleep(rng.uniform(0.0, MAX_DOWN))  # the robots go on publishing into their caches
            service = ServiceProcess(tmp_path, data)
            services.append(service)
            proxy.target_port = service.zenoh_port
            service.start()
            watch.follow(service)
        time.sleep(rng.uniform(0.5, 2.0))
        for robot in robots:
            robot.stop()
        watch.stop()
        what = f"{why}, {kills}, sent {[r.sent for r in robots]}, losses {watch.notes}, {service.log_path}"
        lossy = []
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            for robot in robots:
                key = (robot.map_id, robot.robot_id)
                report = robot.pub.flush(timeout=60)
                # Every scan integrated, or counted lost (the known defect below): never twice.
                assert report.settled and report.refused == 0, (key, report, what)
                assert report.published == report.integrated + report.lost == robot.sent, (key, report, what)
                state = robot_stats(http, robot.map_id, robot.robot_id)
                counts = (state["scans_integrated"] + state["lost"], state["dropped"], state["last_seq"])
                assert counts == (robot.sent, 0, robot.sent - 1), (key, state, what)
                assert (state["scans_integrated"], state["lost"]) == (report.integrated, report.lost), what
                if report.lost:
                    lossy.append((key, report.lost, state["duplicates"]))
                    continue
                assert report.confirmed, (key, report, what)
                if robot.map_id != "shared":
                    assert map_stats(http, robot.map_id)["scans_integrated"] == robot.sent, what
                    assert_region_equal(http, robot.map_id, engine_map(robot.scans[: robot.sent]), LAYERS)
            shared = [robot_stats(http, "shared", r.robot_id)["scans_integrated"] for r in robots[OWN_MAPS:]]
            assert map_stats(http, "shared")["scans_integrated"] == sum(shared), what
        if lossy:
            pytest.xfail(f"scans lost before they were fetched (module docstring): {lossy}; {what}")
    finally:
        watch.stop()
        for robot in robots:
            robot._stop.set()
            robot.pub.close()
        proxy.close()
        for svc in services:
            svc.stop()
