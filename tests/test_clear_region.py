"""Forgetting a region: `GridMap.clear_window` in the engine, its journal row, and `DELETE
/maps/{id}/region` against the real service (over HTTP, with tokens, through a crash and a restart)."""

from __future__ import annotations

import contextlib
import math
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from fleetmap_client.rest import FleetmapClient, FleetmapError, MapChanged
from service_process import ServiceProcess

from fleetmap.api.conditional import Preconditions, map_etag
from fleetmap.api.errors import ApiError
from fleetmap.api_models import RegionCleared, tile_windows
from fleetmap.codec import WireScan, decode, encode_json
from fleetmap.config import MapConfig
from fleetmap.database import BASE_LAYOUT, CLEARED_WINDOWS_LAYOUT, DB_NAME, StorageError
from fleetmap.export import Window
from fleetmap.grid_map import GridMap
from fleetmap.map_entry import IngestRejected, MapEntry
from fleetmap.registry import MapConflict, MapRegistry
from fleetmap.scan import Pose2D, Scan
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap.storage_format import cleared_window_to_blob, journal_row_from_blob, scan_to_blob
from fleetmap.wire import JSON_ENCODING

#: Small tiles, so that the window below crosses tile edges, on both sides of 0.
CONFIG = MapConfig(resolution=0.1, tile_size=32, layers=["occupancy", "counts", "tsdf"])
STORED = ("log_odds", "hits", "misses", "tsdf", "tsdf_weight")
#: Cells -40 <= i < 10, -20 <= j < 18: around the first poses, across the tiles' edges at -32 and 0.
WINDOW = Window(-40, -20, 10, 18)
READ, WRITE = "read-token-0123456789", "write-token-0123456789"


@pytest.fixture(scope="module")
def scans() -> list[Scan]:
    """Simulated scans moved by (-10, -7) m, so that the map spans negative and positive cells; as
    the service decodes them from JSON."""
    robot = SimulatedRobot(generate_floorplan(7, width_m=20.0, height_m=15.0), seed=11, num_beams=271)
    moved = []
    for k in range(14):
        s = robot.tick()
        pose = Pose2D(s.pose.x - 10.0, s.pose.y - 7.0, s.pose.theta)
        scan = Scan(pose, s.angles, s.ranges, s.range_min, s.range_max)
        moved.append(decode(encode_json(scan, k, 0.0), JSON_ENCODING).scan)
    return moved


def _layers(gmap: GridMap, window: Window) -> dict[str, np.ndarray]:
    return {name: gmap.region(name, window.i0, window.j0, window.i1, window.j1) for name in STORED}


def _observed(layers: dict[str, np.ndarray]) -> np.ndarray:
    return (
        ~np.isnan(layers["log_odds"])
        | (layers["hits"] > 0)
        | (layers["misses"] > 0)
        | (layers["tsdf_weight"] > 0)
    )


def _inside(extent: Window, window: Window) -> np.ndarray:
    """Which cells of `extent`'s arrays lie in `window`."""
    j, i = np.mgrid[extent.j0 : extent.j1, extent.i0 : extent.i1]
    return (i >= window.i0) & (i < window.i1) & (j >= window.j0) & (j < window.j1)


def test_clear_window_forgets_exactly_the_window_in_every_layer(scans: list[Scan]) -> None:
    gmap = GridMap(CONFIG)
    for scan in scans:
        gmap.integrate(scan)
    bounds = gmap.known_bounds()
    assert bounds is not None
    extent = Window(bounds[0] - 3, bounds[1] - 3, bounds[2] + 3, bounds[3] + 3)
    assert (
        extent.i0 < WINDOW.i0 < 0 < WINDOW.i1 < extent.i1
        and extent.j0 < WINDOW.j0 < 0 < WINDOW.j1 < extent.j1
    )
    before = _layers(gmap, extent)
    versions = {key: gmap.store.version(key) for key in gmap.store.keys}
    inside = _inside(extent, WINDOW)
    observed = _observed(before) & inside
    j, i = np.nonzero(observed)
    expected_tiles = sorted(
        {((ii + extent.i0) >> 5, (jj + extent.j0) >> 5) for ii, jj in zip(i, j, strict=True)}
    )
    assert len(expected_tiles) >= 4  # the window crosses tile edges where the map has cells

    cleared = gmap.clear_window(WINDOW.i0, WINDOW.j0, WINDOW.i1, WINDOW.j1)

    assert cleared.cells == int(observed.sum()) > 1000
    assert sorted(cleared.changed_tiles) == expected_tiles
    after = _layers(gmap, extent)
    for name in STORED:  # outside the window: bit for bit as before
        np.testing.assert_array_equal(after[name][~inside], before[name][~inside], err_msg=name)
    assert np.isnan(after["log_odds"][inside]).all() and not _observed(after)[inside].any()
    assert np.isnan(after["tsdf"][inside]).all()  # a weight of 0 reads as unknown
    for key, version in versions.items():
        assert (gmap.store.version(key) > version) == (key in expected_tiles), key
    # Nothing left to forget: no cell, no tile, no version moved.
    clock = gmap.store.clock
    assert gmap.clear_window(WINDOW.i0, WINDOW.j0, WINDOW.i1, WINDOW.j1) == (0, [])
    assert gmap.clear_window(5, 5, 5, 9) == (0, []) and gmap.store.clock == clock
    # A later scan observes the cells again.
    gmap.integrate(scans[0])
    assert _observed(_layers(gmap, WINDOW)).any()


def test_a_cleared_window_is_a_journal_row_of_its_own(scans: list[Scan]) -> None:
    window = Window(-3, -(2**40), 5, 2**40)
    blob = cleared_window_to_blob(window)
    assert journal_row_from_blob(blob) == window
    row = journal_row_from_blob(scan_to_blob(scans[0]))  # scans' rows as before
    assert isinstance(row, Scan) and np.array_equal(row.ranges, scans[0].ranges, equal_nan=True)
    for damaged in (blob[:-1], blob + b"\0", blob[:5] + bytes([blob[5] ^ 1]) + blob[6:]):
        with pytest.raises(StorageError, match="corrupt journal entry"):
            journal_row_from_blob(damaged)


def _engine(scans: list[Scan], cleared_after: int) -> tuple[GridMap, tuple[int, list[list[int]]]]:
    """The map the service should hold: the scans, with WINDOW cleared after the first `cleared_after`."""
    gmap = GridMap(CONFIG)
    for scan in scans[:cleared_after]:
        gmap.integrate(scan)
    cleared = gmap.clear_window(WINDOW.i0, WINDOW.j0, WINDOW.i1, WINDOW.j1)
    for scan in scans[cleared_after:]:
        gmap.integrate(scan)
    return gmap, (cleared.cells, tile_windows(cleared.changed_tiles, CONFIG.tile_size))


def _layout(data: Path) -> int:
    with contextlib.closing(sqlite3.connect(data / DB_NAME)) as conn:
        return int(conn.execute("PRAGMA user_version").fetchone()[0])


def _assert_same_map(client: FleetmapClient, gmap: GridMap) -> None:
    bounds = gmap.known_bounds()
    assert bounds is not None
    res = CONFIG.resolution
    i0, j0, i1, j1 = bounds[0] - 2, bounds[1] - 2, bounds[2] + 2, bounds[3] + 2
    box = (
        (i0 + 0.5) * res,
        (j0 + 0.5) * res,
        (i1 + 0.5) * res,
        (j1 + 0.5) * res,
    )  # cell centres: exact floors
    for name in STORED:
        got = client.region("m", *box, layer=name)  # type: ignore[arg-type]
        np.testing.assert_array_equal(got, gmap.region(name, i0, j0, i1, j1), err_msg=name)


def test_delete_region_over_http_is_journaled_and_survives_a_crash(tmp_path: Path, scans: list[Scan]) -> None:
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"read {READ}\nwrite {WRITE}\n")
    args = ["--data-dir", str(tmp_path / "data"), "--auth-tokens", str(tokens)]
    res = CONFIG.resolution
    box = {"xmin": WINDOW.i0 * res + 0.05, "ymin": WINDOW.j0 * res + 0.05}
    box |= {"xmax": WINDOW.i1 * res + 0.05, "ymax": WINDOW.j1 * res + 0.05}
    expected, (cells, tiles) = _engine(scans, cleared_after=10)

    with ServiceProcess(tmp_path, args) as svc, FleetmapClient(svc.base_url, token=WRITE) as client:
        client.create_map("m", CONFIG)
        for k, scan in enumerate(scans[:10]):
            client.post_scan("m", "r1", scan, seq=k)
        with httpx.Client(base_url=svc.base_url) as http:
            # A writer's: none is 401, a reader's 403; bad windows 422; no map 404. Nothing changed.
            url, bearer = "/maps/m/region", {"Authorization": f"Bearer {READ}"}
            assert http.delete(url, params=box).status_code == 401
            assert http.delete(url, params=box, headers=bearer).status_code == 403
        with pytest.raises(FleetmapError) as partial:
            client._request("DELETE", "/maps/m/region", params={"xmin": 0.0, "ymin": 0.0, "xmax": 1.0})
        assert partial.value.status == 422 and "ymax" in partial.value.detail
        with pytest.raises(FleetmapError) as empty:
            client.clear_region("m", 1.0, 1.0, 1.0, 2.0)
        assert empty.value.status == 422 and "holds no cell" in empty.value.detail
        # A bound that is not a finite number is the client's ValueError before any request (an int
        # past float's range raised OverflowError; NaN went out, to come back as a 422).
        for bad in (math.nan, math.inf, 10**400):
            with pytest.raises(ValueError, match="finite"):
                client.clear_region("m", 0.0, 0.0, bad, 1.0)
            with pytest.raises(ValueError, match="finite"):
                client.region("m", bad, 0.0, 1.0, 1.0)
            with pytest.raises(ValueError, match="finite"):
                client.surface("m", 0.0, 0.0, 1.0, bad)
        with pytest.raises(FleetmapError) as missing:
            client.clear_region("no-such-map", 0.0, 0.0, 1.0, 1.0)
        assert missing.value.status == 404
        assert client.get_map("m").stats.scans_integrated == 10

        # If-Match: another map's tag is a 412 and nothing changes; the map's own passes (below).
        # The client's clear_region sends it as its other writes do (it had no if_match at all).
        info, etag = client.get_map_and_etag("m")
        with pytest.raises(MapChanged) as stale:
            client.clear_region("m", *box.values(), if_match='"map-0"')
        assert stale.value.status == 412 and stale.value.etag == etag
        # The database's layout is raised before the first cleared window's row, not before:
        # until a region is cleared, an older fleetmap can still open the directory.
        assert _layout(tmp_path / "data") == BASE_LAYOUT
        version = client.get_map("m").stats.version
        result = client.clear_region("m", *box.values(), if_match=etag)
        assert isinstance(result, RegionCleared)
        assert _layout(tmp_path / "data") == CLEARED_WINDOWS_LAYOUT
        assert info.stats.version == version
        assert result.window == [WINDOW.i0, WINDOW.j0, WINDOW.i1, WINDOW.j1]
        assert (result.cells_cleared, result.changed_tiles) == (cells, tiles) and cells > 1000
        # The tiles stay stored, as docs/api.md says: clearing frees no memory (deleting the map does).
        stats = client.get_map("m").stats
        assert (stats.tiles, stats.memory_bytes) == (info.stats.tiles, info.stats.memory_bytes)
        # Viewers are told: the changed tiles come in the event stream as a scan's would.
        stream = client.events("m", since=version)
        event, data = next(stream)
        stream.close()
        assert event == "tiles" and sorted(data["tiles"]) == tiles and data["version"] > version
        for k, scan in enumerate(scans[10:], start=10):  # observe part of it again
            client.post_scan("m", "r1", scan, seq=k)
        _assert_same_map(client, expected)
        assert svc.proc is not None
        svc.proc.kill()  # no final snapshot: the journal alone holds the clear, between the scans

    for crash in (True, False):  # replayed from the journal, then from the shutdown's snapshot
        with ServiceProcess(tmp_path, args) as svc, FleetmapClient(svc.base_url, token=READ) as client:
            _assert_same_map(client, expected)
            assert client.get_map("m").stats.scans_integrated == len(scans)
            if crash:
                assert svc.stop() == 0


def _integrate(registry: MapRegistry, robot_id: str, seq: int, scan: Scan) -> None:
    """Integrate `scan` as seq `seq` of robot `robot_id` into map "m" of `registry`, and wait for it."""
    done = registry.submit("m", robot_id, WireScan(seq=seq, stamp=0.0, scan=scan), wait=True)
    assert done is not None and done.result(30).cell_updates > 0


@contextlib.contextmanager
def _registry_whose_map_went(scans: list[Scan]) -> Iterator[tuple[MapRegistry, MapEntry]]:
    """A started registry whose map "m" took a scan of robot "r" and was then deleted: yields it and
    that map's entry, gone; closed after."""
    registry = MapRegistry(workers=1)
    registry.start()
    try:
        entry, _ = registry.create("m", CONFIG)
        _integrate(registry, "r", 0, scans[0])
        registry.delete("m", wait=True)
        yield registry, entry
    finally:
        registry.close()


def test_a_condition_on_a_map_replaced_meanwhile_is_compared_with_the_map_there_now(
    scans: list[Scan],
) -> None:
    """The route looks the map up, then clears under its lock: a map replaced in between failed its
    `If-Match` as "there is no map 'm'", without an `ETag`, though a map was there. The 412 says what
    the map is now and carries its tag, as every write's does (docs/api.md, "Conditional writes");
    with that tag the clear is refused as computed for another map (409). Nothing is cleared."""
    with _registry_whose_map_went(scans) as (registry, entry):
        now, _ = registry.create("m", CONFIG)
        _integrate(registry, "r2", 0, scans[0])
        before = _layers(now.gmap, WINDOW)
        stale = Preconditions(if_match=[map_etag(entry)]).expectation("m")
        with pytest.raises(ApiError) as refused:
            registry.clear_window(entry, WINDOW, stale)
        assert refused.value.status == 412
        assert refused.value.headers == {"ETag": map_etag(now)}
        assert f"its ETag is now {map_etag(now)}" in refused.value.detail, refused.value.detail
        fresh = Preconditions(if_match=[map_etag(now)]).expectation("m")
        with pytest.raises(MapConflict, match="deleted or replaced meanwhile; nothing was cleared"):
            registry.clear_window(entry, WINDOW, fresh)
        after = _layers(now.gmap, WINDOW)
        assert all(np.array_equal(before[k], after[k], equal_nan=True) for k in STORED)


def test_no_window_is_cleared_in_a_map_that_replaced_the_one_it_was_computed_for(
    scans: list[Scan],
) -> None:
    """The route computes the window with the map's resolution, then clears: a map deleted, or replaced
    by one of another resolution, in between is refused (409), not cleared with the wrong cells."""
    with _registry_whose_map_went(scans) as (registry, entry):
        registry.create("m", MapConfig(resolution=0.05))
        with pytest.raises(MapConflict, match="deleted or replaced meanwhile; nothing was cleared"):
            registry.clear_window(entry, WINDOW)
        assert registry.clear_window(registry.get("m"), WINDOW) == (0, [])  # the new map: nothing yet
        entry = registry.get("m")
        _integrate(registry, "r", 1, scans[0])
    # Once the registry closes (the final snapshot, the journal's close), nothing is cleared.
    with pytest.raises(IngestRejected, match="shutting down: nothing was cleared") as closing:
        registry.clear_window(entry, Window(-1000, -1000, 1000, 1000))
    assert closing.value.status == 503 and entry.gmap.known_bounds() is not None
