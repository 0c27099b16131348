"""The shared memory budget (`--max-memory`): maps' tiles stay within it, a scan that needs more is
refused whole with its map unchanged, freed maps give their bytes back, and the real service
answers such a scan 507 and goes on serving."""

from __future__ import annotations

import contextlib
import gc
import json
import random
import re
from typing import Any

import httpx
import numpy as np
import pytest
from service_process import ServiceProcess

from fleetmap.codec import WireScan, encode_json
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.map_entry import IngestRejected
from fleetmap.memory_budget import MemoryBudget, MemoryBudgetError, UploadReservation, format_size, parse_size
from fleetmap.persistence import DurableStore
from fleetmap.registry import MapRegistry
from fleetmap.robot_state import MAX_SESSIONS
from fleetmap.scan import Scan
from fleetmap.tiles import SLOT_OVERHEAD

#: Small tiles (0.8 m) and one layer, so that a few scans need many tiles of 1416 bytes each (their
#: cells, version and bookkeeping).
SMALL = MapConfig(tile_size=16, layers=("occupancy",))
TILE_BYTES = 16 * 16 * 4 + 8 + SLOT_OVERHEAD


def scan_at(x: float) -> Scan:
    return Scan.from_fan((x, 0.0, 0.0), -1.5, 0.1, [2.0] * 31, 0.0, 30.0)


def state(gmap: GridMap) -> tuple:
    """Everything a refused scan must leave as it was."""
    bounds = gmap.known_bounds()
    cells = None if bounds is None else gmap.region("log_odds", *bounds).tobytes()
    return len(gmap.store), gmap.store.clock, bounds, cells, gmap.memory_bytes()


def test_parse_size() -> None:
    assert parse_size("512MiB") == 512 * 2**20
    assert parse_size("2G") == parse_size("2 gib") == parse_size("2GB") == 2 * 2**30
    assert parse_size("1.5M") == 3 * 2**19
    assert parse_size("none") is None
    assert parse_size("auto") > 0  # type: ignore[operator]
    for bad in ("12x", "-1G", "", "100"):
        with pytest.raises(ValueError):
            parse_size(bad)


@pytest.mark.parametrize(
    ("tile_size", "layers", "tiles"),
    [
        (16, ("occupancy",), 400),  # a first growth: capacity = tiles
        (16, ("occupancy",), 33_000),  # the index just doubled (4 entries a tile)
        (16, ("occupancy", "counts", "tsdf"), 200_000),
        (64, ("counts",), 4_100),
        (256, ("tsdf",), 65),
    ],
)
def test_memory_bytes_counts_what_a_map_of_any_tile_size_holds(
    tile_size: int, layers: tuple, tiles: int
) -> None:
    """The budget counted only the pools and versions: the tiles' keys, the kernels' index and the
    per-slot bounds, ~300 bytes a tile, were not counted, 30 % more than `memory_bytes` said in a map
    of 16-cell tiles (a service at `--max-memory 256MiB` held 100 MB of them uncounted). Everything
    a map's tiles make it hold, as tracemalloc sees it (numpy's arrays included), is within what it
    counts, and each slot of capacity counts `SLOT_OVERHEAD` bytes more than its cells and version."""
    import tracemalloc

    from fleetmap.tiles import layer_arrays, tile_bytes

    warm = GridMap(MapConfig(tile_size=tile_size, layers=layers))
    warm.store.create([(0, 0), (3, 3)])
    warm.known_bounds()
    del warm
    gmap = GridMap(MapConfig(tile_size=tile_size, layers=layers, max_tiles=1_000_000))
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        side = 1000
        for first in range(0, tiles, 400):  # past the small-int cache, as a map's far tiles are
            gmap.store.create(
                [(300 + k % side, 300 + k // side) for k in range(first, min(tiles, first + 400))]
            )
        assert gmap.known_bounds() is None  # no cell observed, but each tile's bounds are kept
        gc.collect()
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    capacity = len(gmap.store.versions)
    assert gmap.memory_bytes() == capacity * (tile_bytes(tile_size, layer_arrays(layers)) + 8 + SLOT_OVERHEAD)
    assert held <= gmap.memory_bytes(), (held - gmap.memory_bytes()) / tiles


@pytest.mark.parametrize("gib", [1, 2, 4, 16])
def test_auto_leaves_room_for_what_the_budget_does_not_count(
    monkeypatch: pytest.MonkeyPatch, gib: int
) -> None:
    """`auto` was 75 % of the memory the service may use, whatever that was: in a container of 1 GiB,
    768 MiB of tiles beside the 250-400 MB the service holds without them (and the rendered tiles'
    caches, up to 384 MiB) passed the container's limit, so the service was killed where the budget
    should have refused scans with 507. It leaves `RESERVED` (1 GiB) now (in less than 4/3 GiB, a
    quarter of the memory for the tiles), and is 75 % of 4 GiB or more as before."""
    import fleetmap.memory_budget as memory_budget

    monkeypatch.setattr(memory_budget, "available_memory", lambda: gib << 30)
    auto = parse_size("auto")
    assert auto is not None
    assert auto == max(gib << 28, min(3 * (gib << 28), (gib << 30) - (1 << 30)))
    if gib >= 2:
        assert (gib << 30) - auto >= 1 << 30  # room for the fixed overhead (README) and the caches
    assert auto >= gib << 28


def test_empty_maps_hold_nothing_and_big_tiles_grow_one_at_a_time() -> None:
    """Four empty maps of 4096-cell tiles were charged 16 tiles (5.4 GB) each, and every other map's
    growth was then refused. Empty maps now hold no pool, a first growth holds the tiles a scan
    needs (the one tile of 64 MiB here), and the pools double from there."""
    budget = MemoryBudget(100 << 20)
    big = [GridMap(MapConfig(tile_size=4096, layers=("occupancy",))) for _ in range(4)]
    for gmap in big:
        gmap.store.charge(budget)
    assert budget.used == 0
    small = GridMap(SMALL)
    small.store.charge(budget)
    for k in range(8):
        small.integrate(scan_at(0.5 * k))  # grows freely
    assert budget.used == small.memory_bytes() < 2 * len(small.store) * TILE_BYTES
    inside_one_tile = Scan.from_fan((100.0, 100.0, 0.0), -1.5, 0.1, [2.0] * 31, 0.0, 30.0)
    big[0].integrate(inside_one_tile)  # 64 MiB a tile: room for the one tile it needs
    assert len(big[0].store) == 1 and big[0].memory_bytes() == 4096 * 4096 * 4 + 8 + SLOT_OVERHEAD
    with pytest.raises(MemoryBudgetError):  # a second 64 MiB tile does not fit beside the first
        big[1].integrate(inside_one_tile)
    assert big[1].memory_bytes() == 0


def test_maps_share_the_budget_and_a_refused_scan_changes_nothing() -> None:
    a, b = GridMap(SMALL), GridMap(SMALL)
    assert a.memory_bytes() == 0  # an empty map holds no pool
    start = 16 * TILE_BYTES
    budget = MemoryBudget(2 * start + 24 * TILE_BYTES)
    a.store.charge(budget)
    b.store.charge(budget)
    assert budget.used == 0
    b.integrate(scan_at(-1.0))  # b's first tiles: room for them, no more
    assert budget.used == b.memory_bytes() == len(b.store) * TILE_BYTES
    refused = None
    for k in range(200):
        before = state(a)
        try:
            a.integrate(scan_at(0.5 * k))
        except MemoryBudgetError as exc:
            refused = k
            assert "memory budget" in str(exc) and "--max-memory" in str(exc)
            assert state(a) == before  # the scan was refused whole
            break
        assert budget.used <= budget.limit  # type: ignore[operator]
        assert budget.used == a.memory_bytes() + b.memory_bytes()
    assert refused is not None and refused > 2
    # The pools stopped growing short of doubling, at what the budget allowed.
    assert a.memory_bytes() < 2 * 2 * start
    # Another map can not grow either; freeing one gives its bytes back to the others.
    with pytest.raises(MemoryBudgetError):
        for k in range(40):
            b.integrate(scan_at(-0.5 * k))
    held_by_b = b.memory_bytes()
    del b
    gc.collect()
    assert budget.used == a.memory_bytes()
    a.integrate(scan_at(0.5 * refused))  # fits now
    assert budget.used == a.memory_bytes() and a.memory_bytes() <= budget.limit + held_by_b  # type: ignore[operator]


def _send(registry: MapRegistry, map_id: str, k: int, session: int | None) -> Any:
    """Robot "r"'s scan `k` (seq k, at x = 0.5 k: farther scans need new tiles) of publisher session
    `session`: its IntegrationResult, or the IngestRejected that refused it (a duplicate: 200)."""
    stamp = 0.0 if session is None else float(k)
    try:
        future = registry.submit(map_id, "r", WireScan(k, stamp, scan_at(0.5 * k), session), wait=True)
        assert future is not None
        return future.result(10)
    except IngestRejected as exc:
        return exc


def test_the_registry_refuses_past_the_budget_with_507_and_counts_it() -> None:
    """...and the refused scan, sent again with its seq once memory is freed, is integrated: its seq
    was recorded when it was accepted into the queue, so the retry was a "duplicate", never
    integrated, though 507 is the service's state and not the scan's fault."""
    registry = MapRegistry(SMALL, memory_budget=MemoryBudget(60 * TILE_BYTES))
    registry.start()

    def send(map_id: str, k: int) -> Any:
        return _send(registry, map_id, k, None)

    try:
        assert not isinstance(send("other", 0), IngestRejected)  # holds the budget's first tiles
        for k in range(100):
            refused = send("m", k)
            if isinstance(refused, IngestRejected):
                break
        assert isinstance(refused, IngestRejected) and refused.status == 507, refused
        assert "memory budget" in refused.reason and "--max-memory" in refused.reason
        # What is missing, in units that show it: in MiB alone, tiles of a kilobyte made "this scan
        # needs 0.0 MiB more" and "1.0 MiB used up (0.0 MiB held)" of every refusal here.
        budget = registry.memory_budget
        assert budget is not None and budget.limit is not None
        free = budget.limit - budget.used
        assert 0 <= free < 16 * TILE_BYTES
        shown_free = f"{free} bytes" if free < 1024 else f"{free / 1024:.1f} KiB"
        assert f"{60 * TILE_BYTES / 1024:.1f} KiB (`fleetmap serve --max-memory`), has {shown_free} free" in (
            refused.reason
        ), refused.reason
        needed = re.search(r"the scan needs ([0-9.]+) KiB more", refused.reason)
        assert needed is not None and float(needed.group(1)) * 1024 > free, refused.reason
        robot = registry.get("m").robots["r"]
        assert robot.scans_rejected == 1 and "memory budget" in (robot.last_error or "")
        integrated = robot.scans_integrated
        registry.delete("other", wait=True)  # its tiles' bytes go back to the budget
        again = send("m", k)
        assert not isinstance(again, IngestRejected) and again.cell_updates > 0, again
        assert robot.scans_integrated == integrated + 1 and robot.lost == 0
        stale = send("m", k - 1)  # an older seq is still a duplicate
        assert isinstance(stale, IngestRejected) and stale.status == 200 and "duplicate" in stale.reason
    finally:
        registry.close()


def test_several_scans_refused_507_are_each_integrated_when_sent_again() -> None:
    """A robot (with a session id, as `FleetmapClient` and `ScanPublisher` send) whose scans kept
    coming while the budget was full got 507 for several of them; once memory is freed it sends each
    again, as docs/api.md tells it to. Only the last refused one was remembered as refused: the others
    were answered 200 "duplicate" and never integrated."""
    registry = MapRegistry(SMALL, memory_budget=MemoryBudget(60 * TILE_BYTES))
    registry.start()

    def send(map_id: str, k: int) -> Any:
        return _send(registry, map_id, k, 7)

    try:
        assert not isinstance(send("other", 0), IngestRejected)  # holds the budget's first tiles
        for k in range(100):
            if isinstance(send("m", k), IngestRejected):
                break
        refused = [k, k + 1, k + 2]
        for seq in refused[1:]:  # farther on: new tiles again
            result = send("m", seq)
            assert isinstance(result, IngestRejected) and result.status == 507, result
        robot = registry.get("m").robots["r"]
        integrated = robot.scans_integrated
        registry.delete("other", wait=True)  # its tiles' bytes go back to the budget
        for seq in refused:
            again = send("m", seq)
            assert not isinstance(again, IngestRejected) and again.cell_updates > 0, (seq, again)
        assert robot.scans_integrated == integrated + 3 and robot.lost == 0
        ledger = robot.sessions[7].ledger
        assert (ledger.refused, ledger.integrated) == (0, integrated + 3), ledger
        for seq in refused:  # each once: a second copy is a duplicate
            copy = send("m", seq)
            assert isinstance(copy, IngestRejected) and copy.status == 200 and "duplicate" in copy.reason
    finally:
        registry.close()


def test_a_scan_refused_507_is_integrated_when_sent_again_after_its_session_was_pushed_out() -> None:
    """A robot's scan refused 507, sent again once memory is freed, after more than MAX_SESSIONS
    other sessions under its id were heard (robots sharing one id, each sending scans): its session
    was pushed out of the robot's recent ones, the re-send's receipt was opened among those, and
    the submit failed with a KeyError (a 500 over REST, an error in the Zenoh callback) instead of
    integrating it. So too when its session was forgotten meanwhile: its re-send is a new session's."""
    registry = MapRegistry(SMALL, memory_budget=MemoryBudget(60 * TILE_BYTES))
    registry.start()
    try:
        assert not isinstance(_send(registry, "other", 0, None), IngestRejected)  # the first tiles
        for k in range(100):
            if isinstance(_send(registry, "m", k, 7), IngestRejected):
                break
        for session in range(100, 100 + MAX_SESSIONS):  # within the map's tiles: integrated
            assert not isinstance(_send(registry, "m", 0, session), IngestRejected)
        robot = registry.get("m").robots["r"]
        assert 7 not in robot.sessions and robot.session_seqs(7) is not None
        integrated = robot.scans_integrated
        registry.delete("other", wait=True)  # its tiles' bytes go back to the budget
        again = _send(registry, "m", k, 7)
        assert not isinstance(again, IngestRejected) and again.cell_updates > 0, again
        assert robot.scans_integrated == integrated + 1 and (robot.lost, robot.restarts) == (0, MAX_SESSIONS)
        ledger = robot.sessions[7].ledger
        assert (ledger.refused, ledger.integrated, ledger.settled) == (0, k + 1, k), ledger

        robot.note_refused(3, 9)  # the re-send of a scan of a session forgotten since: a new one's
        again = _send(registry, "m", 3, 9)
        assert not isinstance(again, IngestRejected), again
        assert robot.sessions[9].ledger.integrated == 1 and robot.restarts == MAX_SESSIONS + 1
    finally:
        registry.close()


def test_the_service_answers_507_past_max_memory_and_keeps_serving(tmp_path) -> None:
    """A real service with a budget of 24 MiB (18 tiles of the default map: 3 layers, 1.3 MiB a
    tile): small maps hold what their tiles take, so several fit; a robot roaming far needs more
    and is refused; the map and the service stay as they were, and /metrics shows the budget."""
    with ServiceProcess(tmp_path, ["--in-memory", "--max-memory", "24MiB"]) as svc:
        url = svc.base_url
        # Maps of a tile or two each. A map's first tiles made room for 16 (21 MiB here), all
        # charged to the budget though never used: the second map got what was left, the third was
        # refused 507 while the service held 3 tiles (at the default 75 % of 4 GiB, 140 such maps).
        small = Scan.from_fan((0.5, 0.5, 0.0), -1.5, 0.1, [1.0] * 31, 0.0, 30.0)  # two tiles
        for k in range(6):
            body = json.loads(encode_json(small, 0))
            r = httpx.post(f"{url}/maps/small{k}/scans", params={"robot_id": "r"}, json=body, timeout=30)
            assert r.status_code == 200, (k, r.text)
            stats = httpx.get(f"{url}/maps/small{k}", timeout=10).json()["stats"]
            assert stats["tiles"] == 2 and stats["memory_bytes"] <= 2 * 1.3 * 2**20, stats
        for k in range(6):  # 12 tiles held, 15.6 MiB: room for 6 more
            assert httpx.delete(f"{url}/maps/small{k}", timeout=10).status_code == 204
        statuses = []
        for k in range(12):
            scan = Scan.from_fan((40.0 * k, 0.0, 0.0), -1.5, 0.1, [2.0] * 31, 0.0, 30.0)
            r = httpx.post(
                f"{url}/maps/far/scans",
                params={"robot_id": "r"},
                json=json.loads(encode_json(scan, k)),
                timeout=30,
            )
            statuses.append(r.status_code)
            if r.status_code != 200:
                assert r.status_code == 507 and "memory budget" in r.json()["detail"], r.text
                break
        assert statuses[0] == 200 and statuses[-1] == 507
        info = httpx.get(f"{url}/maps/far", timeout=10).json()["stats"]
        assert info["scans_integrated"] == len(statuses) - 1 and info["scans_rejected"] == 1
        metrics = httpx.get(f"{url}/metrics", timeout=10).text
        samples = dict(
            line.rsplit(" ", 1) for line in metrics.splitlines() if line.startswith("fleetmap_memory_")
        )
        assert float(samples["fleetmap_memory_limit_bytes"]) == 24 * 2**20
        assert float(samples["fleetmap_memory_used_bytes"]) == info["memory_bytes"] <= 24 * 2**20
        # The 507 is counted among the robot's rejected scans, and the series says it may be: its
        # HELP called every one of them "refused as invalid", which a scan the budget refused is not.
        assert 'fleetmap_scans_rejected_total{map="far",robot="r"} 1.0' in metrics
        help_line = next(
            line for line in metrics.splitlines() if line.startswith("# HELP fleetmap_scans_rejected")
        )
        assert "memory budget" in help_line, help_line
        # Still serving: a scan near what is mapped needs no new tile and is integrated.
        near = Scan.from_fan((0.0, 0.0, 0.0), -1.5, 0.1, [1.0] * 31, 0.0, 30.0)
        r = httpx.post(
            f"{url}/maps/far/scans",
            params={"robot_id": "r"},
            json=json.loads(encode_json(near, 100)),
            timeout=30,
        )
        assert r.status_code == 200 and r.json()["status"] == "integrated"
        assert np.isfinite(
            np.array(
                httpx.get(f"{url}/maps/far/cell", params={"x": 0.5, "y": 0.0}, timeout=10).json()["log_odds"]
            )
        )
        # A snapshot upload is held to the budget too, before anything is allocated: a copy of the
        # map fits in its own place (its bytes go back), but not beside it.
        snapshot = httpx.get(f"{url}/maps/far/snapshot", timeout=30).content
        put = {"content": snapshot, "headers": {"content-type": "application/zip"}, "timeout": 30}
        r = httpx.put(f"{url}/maps/copy/snapshot", **put)  # type: ignore[arg-type]
        assert r.status_code == 507 and "memory budget" in r.json()["detail"], r.text
        assert httpx.get(f"{url}/maps/copy", timeout=10).status_code == 404  # nothing installed
        r = httpx.put(f"{url}/maps/far/snapshot", **put)  # type: ignore[arg-type]
        assert r.status_code == 200, r.text  # replaced, not created


def test_scans_refused_507_are_integrated_when_sent_again_after_a_restart_that_raised_the_budget(
    tmp_path,
) -> None:
    """A scan answered 507 is to be sent again with its seq once memory is freed (docs/api.md), and
    the way an operator frees memory is often a restart with a larger `--max-memory`. The service
    forgot across its restart which seqs it had refused so: the snapshot of its clean shutdown saved
    them as the robots' last seqs, and the re-sends were answered 200 "duplicate", never integrated.
    Robot "r" sends a session id (as `FleetmapClient` does), "plain" none: each re-send goes in
    once, a second copy is a duplicate."""
    data = ["--data-dir", str(tmp_path / "data")]
    # The default map: 1.3 MiB a tile, so 3 MiB holds two tiles, and 64 MiB plenty.
    near = Scan.from_fan((5.0, 5.0, 0.0), -1.5, 0.1, [1.0] * 31, 0.0, 30.0)
    far = [Scan.from_fan((50.0 * k, 50.0, 0.0), -1.5, 0.1, [1.0] * 31, 0.0, 30.0) for k in (1, 2)]
    sent = [("r", 1, far[0], 7), ("r", 2, far[1], 7), ("plain", 1, far[0], None)]

    def post(
        url: str, robot: str, seq: int, scan: Scan, session: int | None, map_id: str = "m"
    ) -> httpx.Response:
        body = json.loads(encode_json(scan, seq, stamp=float(seq), session=session))
        return httpx.post(f"{url}/maps/{map_id}/scans", params={"robot_id": robot}, json=body, timeout=30)

    with ServiceProcess(tmp_path, [*data, "--max-memory", "3MiB"]) as svc:
        for robot, session in (("r", 7), ("plain", None)):
            r = post(svc.base_url, robot, 0, near, session)
            assert r.json()["status"] == "integrated", r.text
        assert post(svc.base_url, "r", 0, near, None, "other").status_code == 200  # the second tile
        for robot, seq, scan, session in sent:
            r = post(svc.base_url, robot, seq, scan, session)
            assert r.status_code == 507 and "memory budget" in r.json()["detail"], r.text
        assert svc.stop() == 0  # a clean shutdown: its final snapshot saves the robots
    with ServiceProcess(tmp_path, [*data, "--max-memory", "64MiB"]) as svc:
        for robot, seq, scan, session in sent:
            r = post(svc.base_url, robot, seq, scan, session)
            assert r.status_code == 200 and r.json()["status"] == "integrated", (robot, seq, r.text)
        for robot, seq, scan, session in sent:  # each once
            r = post(svc.base_url, robot, seq, scan, session)
            assert r.status_code == 200 and r.json()["status"] == "duplicate", (robot, seq, r.text)
        robots = httpx.get(f"{svc.base_url}/maps/m", timeout=10).json()["stats"]["robots"]
        assert (robots["r"]["scans_integrated"], robots["plain"]["scans_integrated"]) == (3, 2), robots
        assert robots["r"]["lost"] == robots["plain"]["lost"] == 0, robots


def test_a_budget_that_holds_no_tile_of_the_default_map_is_warned_of_at_start(tmp_path) -> None:
    """`--max-memory 1MiB` was taken without a word, though it holds no tile of the default map
    (3 layers of 256 x 256 cells, 1.3 MiB): every robot's scan was then refused 507. It is still
    taken (maps of smaller tiles fit), with a warning at start that says so."""
    with ServiceProcess(tmp_path, ["--in-memory", "--max-memory", "1MiB"]) as svc:
        url = svc.base_url
        scan = Scan.from_fan((0.5, 0.5, 0.0), -1.5, 0.1, [1.0] * 31, 0.0, 30.0)
        r = httpx.post(
            f"{url}/maps/m/scans", params={"robot_id": "r"}, json=json.loads(encode_json(scan, 0)), timeout=30
        )
        assert r.status_code == 507, r.text
        assert httpx.put(f"{url}/maps/small", json={"tile_size": 64}, timeout=10).status_code == 201
        r = httpx.post(
            f"{url}/maps/small/scans", params={"robot_id": "r"}, json=json.loads(encode_json(scan, 0)),
            timeout=30,
        )  # fmt: skip
        assert r.status_code == 200, r.text
        logs = svc.logs()
    warning = (
        "WARNING fleetmap.server: --max-memory 1.0 MiB holds no tile of the default map configuration "
        "(--config; 1.3 MiB a tile: 256 x 256 cells of occupancy, counts, tsdf)"
    )
    assert warning in logs, logs


def test_a_restart_restores_maps_past_the_budget_and_then_refuses_growth(tmp_path) -> None:
    """The journal's scans were accepted: replaying them at start is never refused, even when the
    restored maps hold more than the (new, smaller) budget; they are counted, and growth waits."""
    scans = [scan_at(0.5 * k) for k in range(12)]
    first = MapRegistry(SMALL, durable=DurableStore(tmp_path))
    first.start()
    try:
        for k, scan in enumerate(scans):
            future = first.submit("m", "r", WireScan(k, 0.0, scan), wait=True)
            assert future is not None
            future.result(10)
        held, tiles = first.get("m").gmap.memory_bytes(), len(first.get("m").gmap.store)
    finally:
        # As a crash would leave it: every scan journaled, no snapshot, so the restart replays them.
        first.queue.close()
        first.durable.close()  # type: ignore[union-attr]
    budget = MemoryBudget(held // 2)
    again = MapRegistry(SMALL, durable=DurableStore(tmp_path), memory_budget=budget)
    again.start()
    try:
        gmap = again.get("m").gmap
        assert again.get("m").scans_integrated == len(scans)
        assert len(gmap.store) == tiles
        assert budget.used == gmap.memory_bytes() > budget.limit  # type: ignore[operator]
        future = again.submit("m", "r", WireScan(100, 0.0, scan_at(-50.0)), wait=True)
        assert future is not None
        with pytest.raises(IngestRejected) as refused:
            future.result(10)
        assert refused.value.status == 507
    finally:
        again.close()


def test_a_deleted_maps_bytes_go_back_to_the_budget_at_once_though_a_reader_still_holds_it() -> None:
    """A map deleted (or replaced) gives its bytes back when its DELETE is answered, not when the
    last reader lets go of it: an event stream holds its map until its next poll, a snapshot
    download or a region read until it ends, and meanwhile a scan retried after the 204 that freed
    the room was refused 507 again. A map that is gone never grows again, so its bytes are free as
    soon as those readers finish."""
    registry = MapRegistry(SMALL, memory_budget=MemoryBudget(60 * TILE_BYTES))
    registry.start()

    def send(map_id: str, k: int) -> Any:
        try:
            future = registry.submit(map_id, "r", WireScan(k, 0.0, scan_at(0.5 * k)), wait=True)
            assert future is not None
            return future.result(10)
        except IngestRejected as exc:
            return exc

    try:
        for remove in ("delete", "replace"):
            assert not isinstance(send("other", 0), IngestRejected)
            reader = registry.get("other")  # what an event stream or a download holds
            for k in range(100):
                refused = send("m", k)
                if isinstance(refused, IngestRejected):
                    break
            assert isinstance(refused, IngestRejected) and refused.status == 507, refused
            if remove == "delete":
                registry.delete("other", wait=True)
            else:
                registry.replace("other", GridMap(SMALL), wait=True)
            again = send("m", k)
            assert not isinstance(again, IngestRejected), (remove, again)
            assert reader.gmap.memory_bytes() > 0  # still held: the reader goes on reading it
            del reader
            registry.delete("m", wait=True)
            if remove == "replace":
                registry.delete("other", wait=True)
            assert registry.memory_budget is not None and registry.memory_budget.used == 0
    finally:
        registry.close()


def test_an_upload_reservation_becomes_its_maps_charge_or_goes_back() -> None:
    """An upload's reservation (`MapRegistry.upload_reservation`) is taken before the map's tiles
    are allocated, and the store's growth to them draws on it: counted once, before and after the
    map is installed. An upload that ends otherwise gives it back as it ends, though its map is
    still referenced (a traceback, a reader thread of a cancelled request), and cannot be installed."""
    registry = MapRegistry(SMALL, memory_budget=MemoryBudget(30 * TILE_BYTES))
    budget = registry.memory_budget
    assert budget is not None
    keys = [(k, 0) for k in range(20)]
    with registry.upload_reservation(None) as reservation:
        assert reservation is not None
        gmap = GridMap(SMALL)
        reservation.charge(gmap.store, len(keys))
        assert budget.used == 20 * TILE_BYTES and gmap.memory_bytes() == 0  # reserved, not yet allocated
        gmap.store.create(keys, fill=False)
        assert budget.used == gmap.memory_bytes() == 20 * TILE_BYTES  # drawn on, not counted again
        registry.replace("m", gmap, reservation=reservation)
        assert budget.used == 20 * TILE_BYTES
    assert budget.used == 20 * TILE_BYTES  # installed: the map's own charge now
    with pytest.raises(RuntimeError), registry.upload_reservation(None) as refused:
        assert refused is not None
        other = GridMap(SMALL)
        need, free = (re.escape(format_size(n * TILE_BYTES)) for n in (20, 10))
        shown = rf"need {need}, and the service's memory budget .* has {free} free"
        with pytest.raises(MemoryBudgetError, match=shown):
            refused.charge(other.store, 20)  # does not fit beside "m": nothing reserved
        assert budget.used == 20 * TILE_BYTES
        refused.charge(other.store, 10)
        other.store.create(keys[:10])
        assert budget.used == 30 * TILE_BYTES
        raise RuntimeError("the upload failed")
    assert budget.used == 20 * TILE_BYTES and other.memory_bytes() == 10 * TILE_BYTES  # given back at once
    with pytest.raises(MemoryBudgetError, match="ended"):
        registry.replace("n", other, reservation=refused)
    assert [entry.id for entry in registry.list()] == ["m"] and budget.used == 20 * TILE_BYTES


def test_a_replaced_maps_bytes_are_lent_once_and_the_loan_ends_with_either_side() -> None:
    """The bytes of a map being replaced count as free for the uploads replacing it, once: two
    uploads at once share them, and a scan meanwhile gets none of them. The loan ends when the map
    goes (deleted, or replaced by another upload): its bytes are then free for everyone, not twice."""
    budget = MemoryBudget(30 * TILE_BYTES)
    old = GridMap(SMALL)
    old.store.charge(budget)
    old.store.create([(k, 0) for k in range(20)])
    assert budget.used == 20 * TILE_BYTES and budget._free() == 10 * TILE_BYTES
    first, second = UploadReservation(budget, old.store), UploadReservation(budget, old.store)
    new = [GridMap(SMALL) for _ in range(3)]
    first.charge(new[0].store, 20)  # 10 free, 10 of the old map's
    assert budget.used == 40 * TILE_BYTES and budget.lent == 10 * TILE_BYTES and budget._free() == 0
    lendable = re.escape(format_size(10 * TILE_BYTES))
    with pytest.raises(
        MemoryBudgetError, match=rf"has 0 bytes free \(and {lendable} of the map it replaces\)"
    ):
        second.charge(new[1].store, 11)  # the old map has 10 tiles' bytes left to lend
    assert budget.used == 40 * TILE_BYTES
    second.charge(new[1].store, 10)
    assert budget.used == 50 * TILE_BYTES and budget.lent == 20 * TILE_BYTES and budget._free() == 0
    with pytest.raises(MemoryBudgetError):  # a scan's growth: what is lent is no one else's
        new[2].store.charge(budget)
        new[2].store.create([(0, 0)])
    old.store.uncharge()  # the old map is deleted: both loans end with it, and its bytes go back
    assert budget.used == 30 * TILE_BYTES and budget.lent == 0 and budget._free() == 0
    second.release()
    assert budget.used == 20 * TILE_BYTES and budget._free() == 10 * TILE_BYTES
    first.install(new[0].store)
    first.release()  # installed: kept
    assert budget.used == 20 * TILE_BYTES == new[0].store.charged.bytes  # type: ignore[union-attr]


#: The steps of `test_any_sequence_of_scans_uploads_and_deletions_keeps_the_budget_exact`, drawn
#: alike: scans thrice (they make the maps that uploads replace), uploads opened and charged twice.
STEPS = ("scan",) * 3 + ("delete",) + ("open", "charge") * 2 + ("install", "release", "collect")


@pytest.mark.parametrize("seed", range(40))
def test_any_sequence_of_scans_uploads_and_deletions_keeps_the_budget_exact(seed: int) -> None:
    """The budget's claims, after every step of a random sequence (seeded: the same each run) of
    scans (growing the old map during an upload that borrows its bytes, and the new map right after
    its install), uploads (reserved, allocated, installed or given up, interleaved: two replacing
    one map, one replacing a map another then replaces or that is deleted meanwhile), deletions and
    garbage collections on a real registry: `used` is exactly the live maps' pools plus the open
    uploads' reservations (never a byte twice, nor none), `lent` exactly the open uploads' loans,
    `used <= limit + lent`, and once no upload is open, `lent` is 0 and `used` the live maps' pools.
    (A guard: it found nothing wrong when it was written.)"""
    rng = random.Random(seed)
    limit = rng.randint(16, 64) * TILE_BYTES
    registry = MapRegistry(SMALL, memory_budget=MemoryBudget(limit))
    budget = registry.memory_budget
    assert budget is not None
    # Open uploads: each its reservation, the context that releases it, its map id, its map once charged.
    uploads: list[tuple[UploadReservation, contextlib.ExitStack, str, list[GridMap]]] = []
    with contextlib.ExitStack() as closing:
        for step in range(80):
            what, map_id = rng.choice(STEPS), rng.choice("ab")
            entry = next((e for e in registry.list() if e.id == map_id), None)
            with contextlib.suppress(MemoryBudgetError):
                if what == "scan":  # as a worker applies one: to the map of that id, unless retired
                    entry = entry or registry.create(map_id)[0]
                    with entry.gmap.lock:
                        if not entry.retired:
                            entry.gmap.apply(entry.gmap.plan(scan_at(rng.uniform(-40.0, 40.0))))
                elif what == "delete" and entry is not None:
                    registry.delete(map_id)
                elif what == "open":
                    stack = closing.enter_context(contextlib.ExitStack())
                    reservation = stack.enter_context(registry.upload_reservation(entry))
                    assert reservation is not None
                    uploads.append((reservation, stack, map_id, []))
                elif uploads:
                    upload = rng.choice(uploads)
                    reservation, stack, upload_id, built = upload
                    if what == "charge" and not built:  # as a reader does, and then allocates
                        built.append(GridMap(SMALL))
                        tiles = rng.randint(0, 48)
                        reservation.charge(built[0].store, tiles)
                        built[0].store.create([(k, 0) for k in range(tiles)], fill=False)
                    elif what == "install" and built:
                        uploads.remove(upload)
                        with stack:
                            registry.replace(upload_id, built[0], reservation=reservation)
                    elif what == "release":
                        uploads.remove(upload)
                        stack.close()
                elif what == "collect":
                    gc.collect()
            live = sum(e.gmap.memory_bytes() for e in registry.list())
            charges = [c for _, _, _, built in uploads if built and (c := built[0].store.charged) is not None]
            assert budget.used == live + sum(c.bytes for c in charges), (seed, step)
            assert budget.lent == sum(c.borrowed for c in charges), (seed, step)
            assert budget.used <= limit + budget.lent, (seed, step)
            for e in registry.list():  # an installed map's reservation is its charge, drawn on whole
                charged = e.gmap.store.charged
                assert charged is not None and charged.bytes == e.gmap.memory_bytes(), (seed, step)
    assert budget.lent == 0
    assert budget.used == sum(e.gmap.memory_bytes() for e in registry.list())


def test_a_map_whose_one_tile_is_more_than_the_whole_budget_is_refused_when_made(tmp_path) -> None:
    """`PUT /maps/{id}` made a map of any configuration, even one whose single tile needs more than
    all of `--max-memory` (1024-cell tiles of the three layers: 20 MiB, in a budget of 16): 201, and
    every scan of it was then refused 507, to be "sent again once memory is freed", though no
    deletion could ever make room. Such a PUT is refused 507 now, saying so, and makes no map; a
    configuration whose tiles fit is made as before."""
    with ServiceProcess(tmp_path, ["--in-memory", "--max-memory", "16MiB"]) as svc:
        url = svc.base_url
        r = httpx.put(f"{url}/maps/huge", json={"tile_size": 1024}, timeout=30)
        assert r.status_code == 507, r.text
        assert "20.0 MiB" in r.json()["detail"] and "16.0 MiB" in r.json()["detail"], r.text
        assert httpx.get(f"{url}/maps/huge", timeout=10).status_code == 404
        fits = {"tile_size": 1024, "layers": ["occupancy"]}  # 4 MiB a tile
        assert httpx.put(f"{url}/maps/fits", json=fits, timeout=30).status_code == 201
        scan = Scan.from_fan((0.5, 0.5, 0.0), -1.5, 0.1, [1.0] * 31, 0.0, 30.0)
        r = httpx.post(
            f"{url}/maps/fits/scans",
            params={"robot_id": "r"},
            json=json.loads(encode_json(scan, 0)),
            timeout=30,
        )
        assert r.status_code == 200, r.text
