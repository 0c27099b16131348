"""What one OccupancyGrid of a big map costs the ROS 2 map publisher (`fleetmap.ros.map_publisher`).

    PYTHONPATH=service:clients/python .venv/bin/python benchmarks/bench_ros_map.py [--side 2000] [--reps 5]

Builds a map whose observed extent is `side` x `side` cells at 0.05 m (2000: 100 x 100 m, 4 M cells),
every cell observed (scans from a grid of poses in a room of that size), then times, best and median
of `--reps`, the steps one publication takes:

* check: what a period costs when the map did not change (registry look-up, the tile clock): the
  cost of an unchanged map;
* window: `export.known_window` (tile bounds cached by version: cheap after the first call);
* cells: `occupancy_grid.grid_cells` (the strips copied under the map lock, the probabilities, the
  export's classification, the int8 values);
* encode: the CDR bytes (`encode_occupancy_grid`);
* publish: `RosMapPublisher.publish_changed` after a change, the whole path (window, cells, encode,
  put), measured on a real router session with an rmw_zenoh-style subscriber connected over
  loopback TCP, and the time until that subscriber has the whole sample;
* lock: the longest single hold of the map's lock during one publication (the integration workers
  wait at most that long);
* update: the same after a scan that changes one storage tile (a pillar seen 1.5 m all round):
  `publish_changed` then finds the tiles changed since the last grid and puts an
  OccupancyGridUpdate of them on `<topic>_updates` instead of the grid; its bytes beside the grid's,
  the time until a subscriber of the updates has it, and the longest lock hold.
"""

from __future__ import annotations

import argparse
import math
import statistics
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh
import zenoh.ext

from fleetmap.config import MapConfig
from fleetmap.export import known_window
from fleetmap.registry import MapRegistry
from fleetmap.ros.map_publisher import MapTopic, RosMapOptions, RosMapPublisher
from fleetmap.ros.occupancy_grid import GridInfo, encode_occupancy_grid, grid_cells
from fleetmap.scan import Scan


def room_scan(x: float, y: float, size: float, beams: int = 2000) -> Scan:
    angles = np.linspace(-math.pi, math.pi, beams, endpoint=False)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (size - x) / c, np.where(c < 0, -x / c, np.inf))
        ty = np.where(s > 0, (size - y) / s, np.where(s < 0, -y / s, np.inf))
    return Scan.from_angles((x, y, 0.0), angles, np.minimum(tx, ty), 0.0, 2 * size)


def timed(fn: Callable[[], object], reps: int) -> tuple[float, float, object]:
    times, result = [], None
    for _ in range(reps):
        started = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - started)
    return min(times), statistics.median(times), result


class LockProbe:
    """Wraps a map's RLock to record its longest hold."""

    def __init__(self, lock: object) -> None:
        self.lock = lock
        self.longest = 0.0
        self._since = 0.0
        self._depth = 0

    def __enter__(self) -> None:
        self.lock.__enter__()  # type: ignore[attr-defined]
        if self._depth == 0:
            self._since = time.perf_counter()
        self._depth += 1

    def __exit__(self, *exc: object) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.longest = max(self.longest, time.perf_counter() - self._since)
        self.lock.__exit__(*exc)  # type: ignore[attr-defined]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--side", type=int, default=2000, help="cells per side of the map (default 2000)")
    parser.add_argument("--reps", type=int, default=5)
    args = parser.parse_args()
    res = 0.05
    size = args.side * res
    registry = MapRegistry(MapConfig(resolution=res), workers=1)
    registry.start()
    entry, _ = registry.create("big", MapConfig(resolution=res))
    gmap = entry.gmap
    started = time.perf_counter()
    step = max(size / 8, 1.0)
    for x in np.arange(step / 2, size, step):
        for y in np.arange(step / 2, size, step):
            for _ in range(3):
                gmap.integrate(room_scan(float(x), float(y), size))
    window = known_window(gmap)
    assert window is not None
    ny, nx = window.shape
    built = time.perf_counter() - started
    print(f"map: {nx} x {ny} cells observed ({nx * ny / 1e6:.1f} M), built in {built:.0f} s")

    row = "{:<8} best {:9.3f} ms   median {:9.3f} ms{}"
    b, m, _ = timed(lambda: known_window(gmap), args.reps)
    print(row.format("window", 1000 * b, 1000 * m, ""))
    b, m, cells = timed(lambda: grid_cells(gmap, window), args.reps)
    assert isinstance(cells, np.ndarray)
    print(
        row.format(
            "cells", 1000 * b, 1000 * m, f"   ({np.count_nonzero(cells != -1) / cells.size:.0%} known)"
        )
    )
    info = GridInfo("map", time.time_ns(), res, window.origin(res))
    b, m, payload = timed(lambda: encode_occupancy_grid(cells, info), args.reps)
    assert isinstance(payload, bytes)
    print(row.format("encode", 1000 * b, 1000 * m, f"   ({len(payload) / 2**20:.2f} MiB)"))

    # The whole path on a real session, with a subscriber over loopback TCP.
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", '["tcp/127.0.0.1:27499"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(cfg)
    options = RosMapOptions((MapTopic("big"),), period=3600.0, full_grid_interval=3600.0)
    publisher = RosMapPublisher(registry, router, options)
    topic = publisher.topics[0]
    ccfg = zenoh.Config()
    ccfg.insert_json5("mode", '"client"')
    ccfg.insert_json5("connect/endpoints", '["tcp/127.0.0.1:27499"]')
    ccfg.insert_json5("scouting/multicast/enabled", "false")
    client = zenoh.open(ccfg)
    got = threading.Event()
    arrived: list[float] = []

    def on_sample(sample: zenoh.Sample) -> None:
        arrived.append(time.perf_counter())
        got.set()

    sub = zenoh.ext.declare_advanced_subscriber(
        client,
        topic.grid.key,
        on_sample,
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        recovery=zenoh.ext.RecoveryConfig(heartbeat=True),
    )
    updates_sub = zenoh.ext.declare_advanced_subscriber(client, topic.updates.key, on_sample)
    # Closed whatever happens: a Zenoh session left open keeps the interpreter from exiting.
    try:
        publisher.start()  # publishes once at start
        got.wait(30)
        time.sleep(1.0)
        probe = LockProbe(gmap.lock)
        gmap.lock = probe  # type: ignore[assignment]

        def publication(scan: Scan, sent_by: Any) -> tuple[float, float, float]:
            """Integrate `scan`, then one check, which must put one message by `sent_by` (the grid's
            publisher or the updates'): (its time, the longest map lock hold, the time until the
            subscriber has it)."""
            gmap.integrate(scan)
            got.clear()
            probe.longest = 0.0
            count = sent_by.published
            started = time.perf_counter()
            assert publisher.publish_changed() == 1
            took = time.perf_counter() - started
            assert sent_by.published == count + 1
            assert got.wait(30)
            return took, probe.longest, arrived[-1] - started

        def report(name: str, times: list[float], note: str) -> None:
            print(row.format(name, 1e3 * min(times), 1e3 * statistics.median(times), f"   ({note})"))

        checks, grids = [], []
        for k in range(args.reps):
            started = time.perf_counter()
            publisher.publish_changed()  # unchanged: nothing to do
            checks.append(time.perf_counter() - started)
            # A scan seen across the whole map: every tile changes, the whole grid goes.
            grids.append(publication(room_scan(size / 2 + 0.01 * k, size / 2, size, beams=360), topic.grid))
        report("check", checks, "map unchanged")
        report("publish", [g[0] for g in grids], "window+cells+encode+put")
        report("received", [g[2] for g in grids], "by the subscriber")
        report("lock", [g[1] for g in grids], "longest map lock hold")

        # A scan that changes one storage tile: an update of that tile instead of the grid.
        angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
        t = gmap.store.tile_size * res
        updates = []
        for k in range(args.reps):
            # Near the centre of one tile inside the map (the window does not grow), 1.5 m from its
            # edges at least: an update carries every tile changed since the last grid, so the
            # pillars stay in one tile.
            pillar = (t * 0.5 + 0.01 * k, t * 0.5, 0.0)
            updates.append(
                publication(Scan.from_angles(pillar, angles, np.full(360, 1.5), 0.0, 20.0), topic.updates)
            )
        update_bytes, grid_bytes = int(topic.updates.last["bytes"]), int(topic.grid.last["bytes"])
        report(
            "update",
            [u[0] for u in updates],
            f"changed tiles+cells+encode+put: {update_bytes / 2**10:.0f} KiB, "
            f"{update_bytes / grid_bytes:.1%} of the grid's {grid_bytes / 2**20:.2f} MiB",
        )
        report("received", [u[2] for u in updates], "the update, by the subscriber")
        report("lock", [u[1] for u in updates], "longest hold, update")
    finally:
        updates_sub.undeclare()
        sub.undeclare()
        publisher.close()
        client.close()
        router.close()
        registry.close()


if __name__ == "__main__":
    main()
