"""Tests of `GridMap` and its tile store: coordinates (negative ones too), the layout of `region`,
sparse tile creation, tile versions, the all-or-nothing tile cap, reads of unknown cells, layer
availability, and that the compiled kernels release the GIL.
"""

from __future__ import annotations

import importlib
import itertools
import math
import subprocess
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from numba.core.dispatcher import Dispatcher

from fleetmap import update_plan
from fleetmap.config import MapConfig, OccupancyParams
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import (
    STATE_FREE,
    STATE_OCCUPIED,
    STATE_UNKNOWN,
    GridMap,
    IntegrationResult,
    LayerUnavailableError,
)
from fleetmap.kernels import integrate_scan
from fleetmap.kernels.tile_index import index_find
from fleetmap.kernels.traversal import EXACT, segment_cells
from fleetmap.scan import Scan, ScanError
from fleetmap.sim import SimulatedRobot, generate_floorplan
from fleetmap.tiles import TileLimitError, TileStore

ALL_READ_LAYERS = ("log_odds", "hits", "misses", "tsdf", "tsdf_weight")


def make_map(**config: object) -> GridMap:
    config.setdefault("resolution", 0.25)
    config.setdefault("tile_size", 16)
    return GridMap(MapConfig(**config))  # type: ignore[arg-type]


def one_beam(pose: tuple[float, float, float], angle: float, r: float | None) -> Scan:
    return Scan.from_angles(pose, [angle], [r])


def snapshot(m: GridMap, window: tuple[int, int, int, int]) -> dict[str, object]:
    """Everything observable about a map: every stored layer over a window, tiles and versions."""
    out: dict[str, object] = {
        layer: m.region(layer, *window) for layer in ALL_READ_LAYERS if m.config.has(_needs(layer))
    }
    out["keys"] = list(m.store.keys)
    out["versions"] = {k: m.store.version(k) for k in m.store.keys}
    out["clock"] = m.store.clock
    out["bounds"] = m.known_bounds()
    return out


def _needs(layer: str) -> str:
    return {"log_odds": "occupancy", "hits": "counts", "misses": "counts"}.get(layer, "tsdf")


def assert_same(a: dict[str, object], b: dict[str, object]) -> None:
    assert a.keys() == b.keys()
    for key, value in a.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, b[key], err_msg=key)
        else:
            assert value == b[key], key


# -- coordinates and region layout -------------------------------------------------------------------


def test_cell_index_half_open_and_negative() -> None:
    """Cell (i, j) covers [i*res, (i+1)*res) x [j*res, (j+1)*res), negative indices included."""
    m = make_map()
    assert m.cell_index(0.0, 0.0) == (0, 0)
    assert m.cell_index(0.5, -0.5) == (2, -2)
    assert m.cell_index(-0.01, -0.26) == (-1, -2)
    assert m.cell_index(0.2499, 0.25) == (0, 1)
    assert m.cell_index(-1e-12, 1e5) == (-1, 400_000)
    # floor(x / res) in binary: the decimal edge 0.15 of cell 3 at 0.05 m is 2.9999999999999996
    # cells, in cell 2 (the README says so).
    assert make_map(resolution=0.05).cell_index(0.15, -0.15) == (2, -3)


def test_negative_coordinates() -> None:
    """A beam entirely at negative coordinates: sensor at (-3.7, -2.2) looking along -x, return at
    1.33 m, i.e. at x = -5.03. The cells -15..-21 of row -9 are known, -21 (which holds (-5.03, -2.2))
    is the only hit, the tiles are (-1, -1) and (-2, -1), and point reads agree."""
    occ = OccupancyParams()
    m = make_map(layers=["occupancy"])
    m.integrate(one_beam((-3.7, -2.2, math.pi), 0.0, 1.33))
    a = m.region("log_odds", -30, -12, 0, 0)
    jj, ii = np.nonzero(~np.isnan(a))
    cells = sorted(zip((ii - 30).tolist(), (jj - 12).tolist(), strict=True))
    assert cells == [(i, -9) for i in range(-21, -14)]
    assert a[-9 + 12, -21 + 30] == pytest.approx(occ.l_hit)
    assert np.nanmax(np.delete(a[3], 9)) == pytest.approx(occ.l_miss)
    assert set(m.store.keys) == {(-1, -1), (-2, -1)}
    got = m.cells(np.array([[-5.03, -2.2], [-4.5, -2.2], [-3.7, -2.0]]))
    assert got["log_odds"][0] == pytest.approx(occ.l_hit)
    assert got["log_odds"][1] == pytest.approx(occ.l_miss)
    assert got["known"].tolist() == [True, True, False]
    assert m.known_bounds() == (-21, -9, -14, -8)


def test_region_layout_row_zero_is_lowest_y() -> None:
    """region() returns (j1 - j0, i1 - i0) with [j - j0, i - i0] holding cell (i, j): a hit in cell
    (5, -3) read over the window i in [3, 10), j in [-7, -1) is at [4, 2] of a (6, 7) array; a beam
    along +y fills one column from low rows to high rows."""
    occ = OccupancyParams()
    m = make_map(layers=["occupancy"])
    # Sensor in cell (5, -5), beam along +y ending at y = -0.6: cell (5, -3).
    m.integrate(one_beam((1.375, -1.125, math.pi / 2), 0.0, 0.525))
    a = m.region("log_odds", 3, -7, 10, -1)
    assert a.shape == (6, 7)
    assert a[4, 2] == pytest.approx(occ.l_hit)
    assert a[2, 2] == pytest.approx(occ.l_miss) and a[3, 2] == pytest.approx(occ.l_miss)
    known = ~np.isnan(a)
    assert known.sum() == 3 and known[:, 2].sum() == 3
    state = m.region("state", 3, -7, 10, -1)
    assert state[4, 2] == STATE_OCCUPIED and state[0, 0] == STATE_UNKNOWN
    # Empty and inverted windows give empty arrays.
    assert m.region("log_odds", 3, 3, 3, 9).shape == (6, 0)
    assert m.region("log_odds", 9, 9, 3, 3).shape == (0, 0)


def test_region_agrees_with_point_reads_across_tiles() -> None:
    """A 360-degree scan over many 16-cell tiles: every layer's region equals cell-by-cell reads via
    cells() at the cell centres, so the window assembly across tiles is right."""
    m = make_map()
    rng = np.random.default_rng(11)
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    m.integrate(Scan.from_angles((-0.3, 0.7, 0.2), angles, rng.uniform(0.5, 9.0, angles.size)))
    i0, j0, i1, j1 = -45, -40, 41, 44
    ii, jj = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1))
    pts = np.stack([(ii.ravel() + 0.5) * 0.25, (jj.ravel() + 0.5) * 0.25], axis=1)
    got = m.cells(pts)
    for layer in ALL_READ_LAYERS:
        np.testing.assert_array_equal(m.region(layer, i0, j0, i1, j1).ravel(), got[layer], err_msg=layer)
    assert got["known"].sum() > 500


@pytest.mark.parametrize("model", [{}, {"update": "per_ray"}, {"sensor_model": "beam"}])
def test_tile_size_does_not_change_the_map(model: dict[str, str]) -> None:
    """The same scans in maps of 16-, 64- and 256-cell tiles (a scan spanning more than 256 tiles at
    16 takes the sparse marking path) give identical layers, for per-scan updates, ordered per-ray
    entries and the beam model, with the TSDF band's tiles merged into the plan's tile list."""
    rng = np.random.default_rng(5)
    scans = []
    for _ in range(4):
        angles = np.linspace(-math.pi, math.pi, 180, endpoint=False)
        ranges = rng.uniform(0.2, 60.0, angles.size)  # ~30 x 30 tiles of 16 cells: the sparse path
        ranges[rng.random(angles.size) < 0.1] = math.inf
        pose = (float(rng.uniform(-2, 2)), float(rng.uniform(-2, 2)), float(rng.uniform(-3, 3)))
        scans.append(Scan.from_angles(pose, angles, ranges))
    window = (-260, -260, 260, 260)
    reads = []
    for tile_size in (16, 64, 256):
        m = make_map(tile_size=tile_size, no_return_range=3.0, **model)
        for scan in scans:
            m.integrate(scan)
        reads.append({layer: m.region(layer, *window) for layer in ALL_READ_LAYERS})
    for other in reads[1:]:
        for layer in ALL_READ_LAYERS:
            np.testing.assert_array_equal(reads[0][layer], other[layer], err_msg=layer)


# -- tiles and versions ------------------------------------------------------------------------------


def test_tiles_created_only_where_touched() -> None:
    """A long diagonal beam through several 16-cell (4 m) tiles creates exactly the tiles of its
    traversal cells, and nothing is created by a scan without usable beams."""
    m = make_map(layers=["occupancy"])
    assert len(m.store) == 0
    result = m.integrate(one_beam((0.6, -3.1, 0.0), 0.9, 14.0))
    x1, y1 = 0.6 + 14.0 * math.cos(0.9), -3.1 + 14.0 * math.sin(0.9)
    cells = segment_cells(0.6 / 0.25, -3.1 / 0.25, x1 / 0.25, y1 / 0.25, EXACT)
    expected = {(int(i) >> 4, int(j) >> 4) for i, j in cells}
    assert set(m.store.keys) == expected
    assert result.tiles_created == len(expected) >= 4
    assert set(result.changed_tiles) == expected
    before = list(m.store.keys)
    empty = m.integrate(Scan.from_angles((40.0, 40.0, 0.0), [0.0, 1.0], [math.inf, math.nan]))
    assert empty.tiles_created == 0 and empty.changed_tiles == []
    assert m.store.keys == before


def test_versions_change_only_for_changed_tiles() -> None:
    """Each tile's version changes when one of its cells changes and not otherwise: a scan inside
    tile (0, 0) leaves tile (2, 0)'s version alone and vice versa; versions never repeat."""
    m = make_map()
    m.integrate(one_beam((0.5, 0.5, 0.0), 0.0, 1.0))  # tile (0, 0) only
    m.integrate(one_beam((9.0, 1.0, 0.0), 0.0, 1.5))  # tile (2, 0) only
    assert set(m.store.keys) == {(0, 0), (2, 0)}
    v_a, v_b = m.store.version((0, 0)), m.store.version((2, 0))
    assert v_a is not None and v_b is not None and v_a != v_b
    assert m.store.version((1, 0)) is None
    result = m.integrate(one_beam((9.0, 1.0, 0.0), 0.0, 1.5))
    assert result.changed_tiles == [(2, 0)]
    assert m.store.version((0, 0)) == v_a
    v_b2 = m.store.version((2, 0))
    assert v_b2 != v_b
    m.integrate(one_beam((0.5, 0.5, 0.0), 0.5, 2.0))
    assert m.store.version((0, 0)) not in (v_a, v_b, v_b2)
    assert m.store.version((2, 0)) == v_b2
    assert len(set(m.store.versions[: len(m.store)].tolist())) == len(m.store)


@pytest.mark.parametrize("layers", [["occupancy"], ["occupancy", "counts"]])
def test_a_saturated_map_reports_no_change(layers: list[str]) -> None:
    """The same dense fan again and again (its plan holds runs of misses as well as single cells,
    hits among them, across tile edges): while cells still move, the tiles they are in change
    version; once every log-odds value sits at its clamp, a scan changes nothing and no version
    moves. Counts never saturate in practice, so with them every scan changes its tiles."""
    m = make_map(layers=layers, tile_size=64)
    fan = Scan.from_fan((3.17, 3.11, 0.4), -2.3, 4.6 / 540, np.full(540, 4.0), range_max=30.0)
    plan = m.plan(fan)
    assert plan.runs.shape[1] > 0 and plan.cell.size > 0 and plan.num_tiles > 1
    for _ in range(12):  # the octomap preset clamps after 5 misses or 5 hits
        m.integrate(fan)
    before = m.store.versions[: len(m.store)].copy()
    result = m.integrate(fan)
    assert result.cell_updates == plan.cell.size + int(plan.runs[1].sum())
    if layers == ["occupancy"]:
        assert result.changed_tiles == []
        assert (m.store.versions[: len(m.store)] == before).all()
    else:
        assert len(result.changed_tiles) == plan.num_tiles
        assert (m.store.versions[: len(m.store)] != before).all()


@pytest.mark.parametrize("preset", ["int8", "octomap"])
def test_a_per_ray_scan_whose_cells_end_as_they_began_changes_no_tile(preset: str) -> None:
    """Per-ray updates apply in order, so a cell may move and come back within one scan: at a clamp,
    moved off it by one ray and back by the next (int8 at -128: a hit, + 9, then a miss, - 9;
    OctoMap's at its upper clamp: a miss, then a hit that clamps). Its tile was as before the scan,
    yet it got a new version and was reported changed, which the service pushes to every viewer
    as a changed tile and a new ETag. A scan that does move a cell still changes its tile."""
    m = make_map(layers=["occupancy"], update="per_ray", occupancy={"preset": preset})
    sensor = (0.1, 0.1, 0.0)  # beams along row 0 from cell 0, 0.25 m cells: 2 m ends in cell 8

    def scan(*ranges: float) -> IntegrationResult:
        return m.integrate(Scan.from_angles(sensor, [0.0] * len(ranges), list(ranges)))

    # Cells 0-7 and 9-11 at the lower clamp, 8 and 12 at the upper.
    for ranges in [3.0] * 40 + [2.0] * 40:
        scan(ranges)
    before = m.region("log_odds", 0, 0, 16, 1)
    version = m.store.version((0, 0))
    # int8: cell 4 hit (by the 1 m beam), then missed (by the 2 m one). OctoMap: cell 8 missed (by
    # the 3 m beam), then hit back to the clamp (by the 2 m one).
    result = scan(*([1.0, 2.0] if preset == "int8" else [3.0, 2.0]))
    np.testing.assert_array_equal(m.region("log_odds", 0, 0, 16, 1), before)
    assert result.changed_tiles == [] and m.store.version((0, 0)) == version
    result = scan(1.0)  # cell 4 hit: off its clamp
    assert result.changed_tiles == [(0, 0)] and m.store.version((0, 0)) != version


def test_tile_cap_rejects_whole_scan() -> None:
    """max_tiles 2: after a scan in tile (0, 0), a scan that changes cells of tile (0, 0) AND needs
    two new tiles is refused with TileLimitError and leaves every layer, tile, version and the
    version clock exactly as they were; a scan needing one new tile is then accepted."""
    m = make_map(max_tiles=2)
    m.integrate(one_beam((0.5, 0.5, 0.0), 0.0, 1.0))
    window = (-20, -20, 60, 20)
    before = snapshot(m, window)
    # Beams 1 and 3 stay in tile (0, 0); beam 2 reaches tile (2, 0) through tile (1, 0).
    too_big = Scan.from_angles((0.5, 0.5, 0.0), [0.5, 0.0, -0.3], [2.0, 9.5, 1.0])
    with pytest.raises(TileLimitError):
        m.integrate(too_big)
    assert_same(snapshot(m, window), before)
    ok = m.integrate(one_beam((0.5, 0.5, 0.0), 0.0, 5.0))  # reaches tile (1, 0) only
    assert ok.tiles_created == 1
    assert set(m.store.keys) == {(0, 0), (1, 0)}
    with pytest.raises(TileLimitError):
        m.integrate(one_beam((-0.5, 0.5, 0.0), 0.0, 0.1))  # tile (-1, 0)
    assert set(m.store.keys) == {(0, 0), (1, 0)}


@pytest.mark.parametrize("path", ["integrate", "plan-and-apply"])
def test_a_scan_touching_more_tiles_than_the_cap_allocates_no_trace_scratch(
    path: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scan that touches more tiles than `max_tiles` can never be integrated, so it is refused
    (TileLimitError, map unchanged) before the per-scan trace allocates a plane of scratch for each
    of those tiles: one 100 km beam at 5 cm (7813 tiles of 256 x 256) made a map of at most 4
    tiles allocate 512 MB, which its thread then kept for every later scan."""
    # A fresh per-thread scratch: one grown by an earlier test would hide the allocation.
    monkeypatch.setattr(update_plan, "_scratch", threading.local())
    m = GridMap(MapConfig(resolution=0.05, tile_size=256, max_tiles=4, layers=["occupancy"]))
    m.integrate(one_beam((0.5, 0.5, 0.0), 0.0, 2.0))
    window = (-10, -10, 60, 30)
    before = snapshot(m, window)
    far = Scan.from_angles((0.5, 0.5, 0.0), [0.0], [1e5], range_max=math.inf)
    tracemalloc.start()
    try:
        with pytest.raises(TileLimitError, match="max_tiles"):
            if path == "integrate":
                m.integrate(far)
            else:
                m.apply(m.plan(far))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20, f"{peak / 2**20:.0f} MiB allocated for a scan the map cannot hold"
    assert update_plan.trace_scratch(m.store.shift).nbytes < 64 << 20
    assert_same(snapshot(m, window), before)


# -- reads of unknown cells and unavailable layers ---------------------------------------------------


def test_cells_of_unknown_points() -> None:
    """cells() of never-observed points, in a missing tile or an existing one: known False,
    log-odds NaN, probability 0.5, state unknown, counts 0, tsdf NaN with weight 0."""
    m = make_map()
    empty = m.cells(np.array([[1.0, 1.0]]))
    m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 1.0))
    got = m.cells(np.array([[100.0, -100.0], [0.125, 1.125], [0.125, 0.125]]))
    for res, k in ((empty, 0), (got, 0), (got, 1)):
        assert not res["known"][k]
        assert math.isnan(res["log_odds"][k])
        assert res["probability"][k] == 0.5
        assert res["state"][k] == STATE_UNKNOWN
        assert res["hits"][k] == 0 and res["misses"][k] == 0
        assert math.isnan(res["tsdf"][k]) and res["tsdf_weight"][k] == 0
    assert got["known"][2]
    assert got["probability"][2] == pytest.approx(0.4)


@pytest.mark.parametrize("layer", ["tsdf_weight", "tsdf"])
def test_a_region_of_the_tsdf_holds_the_window_about_once(layer: str) -> None:
    """region("tsdf_weight") and region("tsdf") over a large window (what `fleetmap build` writes
    as tsdf_weight.npy and tsdf.npy) allocate about the answer's size. The weights made a NaN window
    and then a nan_to_num copy with masks, 3.3 times the answer (2.9 GB for the 0.9 GB weights of
    the Freiburg campus at 2 cm, the build's peak); the values made a window of the weights too, and
    a mask of it, 2.25 times. The values: the weights, 0 where unknown (in unknown cells and missing
    tiles), and the TSDF, NaN exactly there."""
    m = make_map(layers=["tsdf"], resolution=0.05, tile_size=64)
    m.integrate(Scan.from_angles((0.01, 0.01, 0.0), np.linspace(-3, 3, 400), np.full(400, 3.0)))
    window = (-1000, -1000, 1000, 1000)  # 2000 x 2000 cells: 16 MB of float32
    tracemalloc.start()
    try:
        base, _ = tracemalloc.get_traced_memory()
        values = m.region(layer, *window)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert values.dtype == np.float32 and values.shape == (2000, 2000)
    assert peak - base < 1.2 * values.nbytes, f"{(peak - base) / values.nbytes:.1f} times the answer"
    weight, tsdf = m.region("tsdf_weight", *window), m.region("tsdf", *window)
    assert (weight > 0).sum() > 1000 and not np.isnan(weight).any()
    np.testing.assert_array_equal(weight > 0, ~np.isnan(tsdf))
    assert np.nanmin(tsdf) < -0.5 < 0.5 < np.nanmax(tsdf)
    stored = m.store.pools["tsdf"][m.store.slots[(0, 0)]]  # the tile holding (0, 0)
    np.testing.assert_array_equal(tsdf[1000:1064, 1000:1064][weight[1000:1064, 1000:1064] > 0],
                                  stored[weight[1000:1064, 1000:1064] > 0])  # fmt: skip


@pytest.mark.parametrize(
    "layers", [["occupancy", "counts", "tsdf"], ["occupancy"], ["counts"], ["tsdf"], ["tsdf", "counts"]]
)
def test_cells_equal_one_cell_region_reads(layers: list[str]) -> None:
    """cells() (one gather per layer) gives at every point exactly what a 1 x 1 region() of its cell
    gives, for random points in observed cells, unobserved cells of existing tiles, missing tiles,
    negative coordinates, cell and tile boundaries, repeated and far-away points."""
    m = make_map(layers=layers)
    rng = np.random.default_rng(5)
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    poses = np.column_stack([rng.uniform(-6, 6, 30), rng.uniform(-6, 6, 30), rng.uniform(-3, 3, 30)])
    for x, y, theta in poses.tolist():
        ranges = rng.uniform(0.3, 5.0, angles.size)
        ranges[rng.random(angles.size) < 0.1] = np.inf  # some no-returns
        m.integrate(Scan.from_angles((x, y, theta), angles, ranges, 0.0, 6.0))
    res, tile = m.resolution, m.store.tile_size
    points = np.concatenate(
        [
            rng.uniform(-15, 15, (1500, 2)),  # inside and around the observed area
            np.arange(-8, 9)[:, None] * np.array([[res * tile, res]]),  # tile and cell boundaries
            -np.arange(-8, 9)[:, None] * np.array([[res, res * tile]]),
            [[1e6, -1e6], [-1e6, 1e6], [0.0, 0.0], [0.0, 0.0], [-1e-12, 1e-12]],  # far, repeated, edges
        ]
    )
    got = m.cells(points)
    assert 0 < got["known"].sum() < len(points)  # both kinds are in the sample
    for k, (x, y) in enumerate(points):
        i, j = m.cell_index(x, y)
        one = {layer: m.region(layer, i, j, i + 1, j + 1)[0, 0] for layer in ALL_READ_LAYERS + ("state",)
               if m.config.has(_needs(layer if layer != "state" else "log_odds"))}  # fmt: skip
        known = []  # `known` is the first kept layer's: occupancy, else counts, else tsdf
        if m.config.has("occupancy"):
            np.testing.assert_equal(got["log_odds"][k], one["log_odds"])
            assert got["state"][k] == one["state"]
            p = m.region("probability", i, j, i + 1, j + 1)[0, 0]
            assert got["probability"][k] == (0.5 if math.isnan(one["log_odds"]) else p)
            known.append(not math.isnan(one["log_odds"]))
        if m.config.has("counts"):
            assert (got["hits"][k], got["misses"][k]) == (one["hits"], one["misses"])
            known.append(one["hits"] + one["misses"] > 0)
        if m.config.has("tsdf"):
            np.testing.assert_equal(got["tsdf"][k], one["tsdf"])
            assert got["tsdf_weight"][k] == one["tsdf_weight"]
            known.append(one["tsdf_weight"] > 0)
        assert got["known"][k] == known[0], k


def test_cells_of_points_billions_of_tiles_apart() -> None:
    """Points too far apart for one int64 key per tile still find their cells (the pairwise path)."""
    m = make_map(layers=["counts"])
    m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 1.0))
    points = np.array([[1e11, -1e11], [0.125, 0.125], [-1e11, 1e11], [1.125, 0.125], [0.125, 0.125]])
    got = m.cells(points)
    assert got["known"].tolist() == [False, True, False, True, True]
    assert got["hits"].tolist() == [0, 0, 0, 1, 0] and got["misses"].tolist() == [0, 1, 0, 0, 1]


def test_cells_of_counts_whose_sum_passes_uint32_are_known() -> None:
    """A counts map's `known` was `hits + misses > 0` in uint32, which wraps: a cell of 2**32 - 1
    hits (where counts saturate) and one miss, or 2**31 of each (a snapshot may hold any counts),
    read as never observed."""
    m = make_map(layers=["counts"])
    m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 1.0))
    slot = m.store.slots[(0, 0)]
    m.store.pools["hits"][slot, 0, :2] = [2**32 - 1, 2**31]
    m.store.pools["misses"][slot, 0, :2] = [1, 2**31]
    got = m.cells(np.array([[0.125, 0.125], [0.375, 0.125], [0.125, 0.375]]))
    assert got["known"].tolist() == [True, True, False]


def test_state_thresholds() -> None:
    """state: p > 0.65 occupied, p < 0.196 free, in between unknown: one miss (p 0.4) is still
    'unknown', four misses (p 0.165) are free, one hit (p 0.7) is occupied."""
    m = make_map(layers=["occupancy"])
    m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 1.0))  # cells 0..3 of row 0 missed, 4 hit
    assert m.region("state", 0, 0, 5, 1)[0].tolist() == [STATE_UNKNOWN] * 4 + [STATE_OCCUPIED]
    for _ in range(3):
        m.integrate(one_beam((0.125, 0.125, math.pi / 2), 0.0, 1.0))  # misses the sensor cell again
    assert m.region("state", 0, 0, 5, 1)[0].tolist() == [STATE_FREE] + [STATE_UNKNOWN] * 3 + [STATE_OCCUPIED]


def test_state_follows_the_probability_the_map_reports() -> None:
    """`state` is `free` when p < free_thresh and `occupied` when p > occupied_thresh, for the p the
    map reports (a float32, in `cells`, the probability layer and JSON as that float32's exact
    value). The thresholds were rounded to float32 for the comparison (numpy compares a float32
    array with a Python float in float32): with p_min 0.19599999999 a missed cell reported
    p 0.19599999487 with free_thresh 0.196 and state `unknown`, and no cell of the map was ever
    free. Likewise a cell at p 0.97000003 was not occupied above occupied_thresh 0.97."""
    for occupancy, state in (
        ({"p_min": 0.19599999999}, STATE_FREE),
        ({"p_max": 0.9700000001, "occupied_thresh": 0.97}, STATE_OCCUPIED),
    ):
        m = make_map(layers=["occupancy"], occupancy=occupancy)
        for _ in range(8):  # the sensor cell missed to l_min, the end cell hit to l_max
            m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 1.0))
        got = m.cells(np.array([[0.125, 0.125], [1.125, 0.125]]))
        p, thresholds = got["probability"].astype(np.float64), m.config.occupancy
        expected = np.where(
            p > thresholds.occupied_thresh,
            STATE_OCCUPIED,
            np.where(p < thresholds.free_thresh, STATE_FREE, STATE_UNKNOWN),
        )
        assert state in expected.tolist()
        assert got["state"].tolist() == expected.tolist()
        assert m.region("state", 0, 0, 5, 1)[0, [0, 4]].tolist() == expected.tolist()
        assert m.classify(m.region("log_odds", 0, 0, 5, 1))[0, [0, 4]].tolist() == expected.tolist()


def test_layer_unavailable() -> None:
    """Reading a layer the map does not keep, or no layer at all, raises LayerUnavailableError;
    cells() reports only the kept layers."""
    m = make_map(layers=["occupancy"])
    m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 1.0))
    for layer in ("tsdf", "tsdf_weight", "hits", "misses", "bogus"):
        with pytest.raises(LayerUnavailableError):
            m.region(layer, 0, 0, 4, 4)
    with pytest.raises(LayerUnavailableError):
        m.surface(0, 0, 4, 4)
    assert set(m.cells(np.array([[0.1, 0.1]]))) == {"known", "log_odds", "probability", "state"}
    t = make_map(layers=["tsdf"])
    for layer in ("log_odds", "probability", "state", "hits"):
        with pytest.raises(LayerUnavailableError):
            t.region(layer, 0, 0, 4, 4)


def test_known_bounds() -> None:
    """known_bounds() is None for an empty map and the exclusive cell bounds of all observed cells."""
    m = make_map(layers=["occupancy", "counts"])
    assert m.known_bounds() is None
    m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 1.0))  # cells 0..4 of row 0
    assert m.known_bounds() == (0, 0, 5, 1)
    m.integrate(one_beam((-5.1, -9.9, math.pi / 2), 0.0, 0.7))  # cells (-21, -40..-37)
    assert m.known_bounds() == (-21, -40, 5, 1)


def test_known_bounds_independent_of_layer_order() -> None:
    """The same scan in maps keeping the same layers listed in a different order has the same
    known_bounds(), and those bounds contain every cell cells() calls known (here the sensor cell
    (0, 0) and the free cells up to the hit in cell 8)."""
    bounds = []
    for layers in (["occupancy", "tsdf"], ["tsdf", "occupancy"]):
        m = make_map(layers=layers)
        m.integrate(one_beam((0.125, 0.125, 0.0), 0.0, 2.0))
        assert m.cells(np.array([[0.125, 0.125]]))["known"][0]
        bounds.append(m.known_bounds())
    assert bounds[0] == (0, 0, 9, 1)
    assert bounds[1] == bounds[0]


# -- the GIL -----------------------------------------------------------------------------------------


def test_kernels_release_the_gil() -> None:
    """Every compiled kernel of fleetmap.kernels is compiled with nogil=True, so integration of
    different maps can run on several threads at once."""
    found = 0
    for name in ("traversal", "ray_model", "update", "tsdf", "beam_model", "tile_index", "integrate_scan"):
        module = importlib.import_module(f"fleetmap.kernels.{name}")
        for attr, value in vars(module).items():
            if isinstance(value, Dispatcher):
                found += 1
                assert value.targetoptions.get("nogil") is True, f"{name}.{attr} holds the GIL"
    assert found >= 10


@pytest.mark.parametrize(
    "config",
    [
        # The TSDF band of 100 000 beams, 256 cells deep, makes the one-call path's scan long.
        pytest.param(
            {"resolution": 0.05, "layers": ["occupancy", "tsdf"], "tsdf": {"truncation": 12.8}}, id="one-call"
        ),
        pytest.param(
            {"resolution": 0.02, "layers": ["occupancy"], "sensor_model": "beam", "beam": {"beta": 0.01}},
            id="plan-and-apply",
        ),
    ],
)
def test_python_runs_on_another_thread_while_a_long_scan_integrates(config: dict[str, object]) -> None:
    """The proof of "the integration releases the GIL" by behaviour, not by a compiler flag: while one
    `integrate` call runs for a second or more, a Python loop on another thread keeps running. Held,
    the GIL would stop that loop for the whole kernel call, so the loop's longest pause within the
    call would be about as long as the call itself (most of it, on the planned path)."""
    gmap = GridMap(MapConfig.model_validate({**config, "max_tiles": 100_000}))
    fan = {"pose": (0.0, 0.0, 0.0), "angle_min": -math.pi, "range_min": 0.0, "range_max": 100.0}
    beams, reach = (3_600, 30.0) if config.get("sensor_model") == "beam" else (40_000, 10.0)
    scan = Scan.from_fan(**fan, angle_increment=2 * math.pi / beams, ranges=[reach] * beams)
    # Once first: the kernels are compiled and the tiles exist, so that the timed call is one
    # kernel call on the one-call path (a scan needing new tiles there is planned instead).
    gmap.integrate(scan)
    # The loop's pauses longer than a millisecond, as (start, end); no list of every tick, which
    # would grow by millions a second.
    pauses: list[tuple[float, float]] = []
    running = threading.Event()
    stop = threading.Event()

    def python_loop() -> None:
        last = time.perf_counter()
        running.set()
        while not stop.is_set():
            now = time.perf_counter()
            if now - last > 1e-3:
                pauses.append((last, now))
            last = now

    looper = threading.Thread(target=python_loop)
    looper.start()
    try:
        running.wait()
        started = time.perf_counter()
        gmap.integrate(scan)
        ended = time.perf_counter()
    finally:
        stop.set()
        looper.join()
    took = ended - started
    # (0.43 s here; a faster machine still gives a pause bound well above a scheduler's time slice.)
    assert took > 0.15, f"the scan took {took:.2f} s: too short for the GIL to show"
    longest = max((min(end, ended) - max(start, started) for start, end in pauses), default=0.0)
    assert longest < 0.25 * took, f"a Python thread stopped for {longest:.2f} s of a {took:.2f} s integration"


def test_two_threads_integrate_two_maps() -> None:
    """Two threads integrating into two different maps at the same time both finish, each map equal
    to the same scans integrated sequentially."""
    rng = np.random.default_rng(2)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    scans = [
        Scan.from_angles((float(x), float(y), 0.0), angles, rng.uniform(0.5, 8.0, angles.size))
        for x, y in rng.uniform(-3, 3, (20, 2))
    ]
    maps = [make_map(tile_size=64), make_map(tile_size=64)]
    errors: list[BaseException] = []

    def work(m: GridMap, order: list[Scan]) -> None:
        try:
            for scan in order:
                m.integrate(scan)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(maps[0], scans)),
               threading.Thread(target=work, args=(maps[1], scans[::-1]))]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors and not any(t.is_alive() for t in threads)
    ref = make_map(tile_size=64)
    for scan in scans:
        ref.integrate(scan)
    window = (-60, -60, 60, 60)
    np.testing.assert_array_equal(maps[0].region("log_odds", *window), ref.region("log_odds", *window))
    # Counts commute, so the reversed order gives the same counts.
    for layer in ("hits", "misses"):
        np.testing.assert_array_equal(maps[1].region(layer, *window), ref.region(layer, *window))


# -- integration in one compiled call ----------------------------------------------------------------


def test_tile_index_finds_every_tile() -> None:
    """The kernels' tile index (`TileStore.index`) holds exactly the store's tiles with their slots,
    through batches of creations that regrow it, for negative and very distant tile keys."""
    rng = np.random.default_rng(4)
    store = TileStore(16, ["occupancy"], max_tiles=5000)
    keys = {(int(i), int(j)) for i, j in rng.integers(-40, 40, (700, 2))}
    keys |= {(int(i), int(j)) for i, j in rng.integers(-(2**35), 2**35, (300, 2))}
    ordered = sorted(keys)
    for lo in range(0, len(ordered), 97):
        store.create(ordered[lo : lo + 97])
    assert store.index[1].size >= 2 * len(store)  # at most half full
    for key, slot in store.slots.items():
        assert index_find(*store.index, *key) == slot
    for key in [(41, 0), (-41, 5), (2**35, 2**35), (0, -(2**36))]:
        assert key not in store.slots and index_find(*store.index, *key) == -1


def test_a_growing_store_holds_its_old_and_new_pools_one_array_at_a_time() -> None:
    """A store that outgrows its pools doubles them, and lets each old array go as soon as it is
    copied: the growth holds the new pools (twice the old) and at most one old array besides, not
    every old and every new pool at once (three times the old pools; a Freiburg campus build at 2 cm
    peaked at 4.7 GB for 2.2 GB of tiles). The cached `kernel_pools`, which every integration asks
    for, kept all the old ones to the end."""
    tracemalloc.start()  # before the pools are made, so that freeing them counts
    try:
        store = TileStore(64, ["occupancy", "counts", "tsdf"], max_tiles=10_000)
        keys = [(i, 0) for i in range(64)]
        store.create(keys[:1])
        while len(store) < store._capacity:  # fill the room made so far
            store.create([keys[len(store)]])
        store.kernel_pools()  # as every integration does before tiles are created
        sample = {a.name: store.pools[a.name][: len(store)].copy() for a in store.arrays}
        old_bytes = sum(store.pools[a.name].nbytes for a in store.arrays)
        largest = max(store.pools[a.name].nbytes for a in store.arrays)
        capacity = store._capacity
        tracemalloc.reset_peak()
        base, _ = tracemalloc.get_traced_memory()
        store.create([keys[len(store)]])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert store._capacity == 2 * capacity
    new_bytes = sum(store.pools[a.name].nbytes for a in store.arrays)
    grown = peak - base  # base holds the old pools
    assert grown < new_bytes - old_bytes + largest + (64 << 10), (
        f"the growth held {(grown + old_bytes) / old_bytes:.2f} times the old pools"
    )
    for name, values in sample.items():  # the tiles were kept
        np.testing.assert_array_equal(store.pools[name][: len(values)], values)
    assert all(p is store.pools[n] for p, n in zip(store.kernel_pools(), ALL_READ_LAYERS, strict=True))


def _fleet_scans(n: int) -> list[Scan]:
    """Scans of two simulated robots in a generated floor plan, plus a few with long no-return beams
    (a box too large for the dense window, and a scratch that must grow)."""
    plan = generate_floorplan(3)
    robots = [SimulatedRobot(plan, seed, noise_std=0.01) for seed in (1, 2)]
    scans = [robot.tick() for _ in range(n) for robot in robots]
    fan = np.linspace(-2.0, 2.0, 90)
    ranges = np.where(np.arange(fan.size) % 3 == 0, math.inf, 4.0)
    for k in (5, 25, 45):
        pose = scans[k].pose
        scans.insert(k, Scan.from_angles((pose.x, pose.y, pose.theta), fan, ranges, 0.0, 30.0))
    return scans


@pytest.mark.parametrize(
    "config",
    [
        {},
        {"layers": ["occupancy", "counts"]},
        {"layers": ["counts"]},
        {"traversal": "bresenham"},
        {"no_return_range": 25.0},
        {"no_return_range": 40.0, "occupancy": {"preset": "cartographer"}},  # past the 30 m range_max
        {"layers": ["occupancy", "counts", "tsdf"], "tsdf": {"truncation": 0.3, "max_weight": 5.0}},
        {"layers": ["counts", "tsdf"]},
    ],
)
def test_integrate_in_one_call_equals_plan_and_apply(
    config: dict[str, object], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`integrate` (one compiled call, which creates the tiles it needs while the pools have room)
    gives, scan by scan, the same result as `apply(plan(scan))`, and the same map: every layer,
    tile, version and the clock. The one-call path does most of the scans, creates tiles in some,
    and hands those that need a larger store back."""
    statuses: list[int] = []
    created_in_kernel = 0
    kernel = integrate_scan.integrate_ray_scan

    def counted(*args: object) -> tuple:
        nonlocal created_in_kernel
        out = kernel(*args)
        statuses.append(int(out[0]))
        created_in_kernel += int(out[0] == integrate_scan.INTEGRATED and out[5] > 0)
        return out

    monkeypatch.setattr(integrate_scan, "integrate_ray_scan", counted)
    # A fresh per-thread trace scratch, so that the long clearing beams must grow it here whatever
    # ran before in this process.
    monkeypatch.setattr(update_plan, "_scratch", threading.local())
    settings = {"resolution": 0.05, "tile_size": 64, "layers": ["occupancy"], **config}
    one_call, planned = GridMap(MapConfig(**settings)), GridMap(MapConfig(**settings))  # type: ignore[arg-type]
    for scan in _fleet_scans(30):
        got = one_call.integrate(scan)
        want = planned.apply(planned.plan(scan))
        assert got == want
    window = one_call.known_bounds()
    assert window is not None and window == planned.known_bounds()
    assert_same(snapshot(one_call, window), snapshot(planned, window))
    integrated = statuses.count(integrate_scan.INTEGRATED)
    assert integrated > len(statuses) // 2
    assert created_in_kernel > 0
    assert statuses.count(integrate_scan.NEEDS_TILES) > 0
    if config.get("no_return_range") == 40.0:
        assert statuses.count(integrate_scan.NEEDS_SCRATCH) > 0


def test_integrate_in_one_call_equals_plan_and_apply_on_the_intel_log(datasets_dir: Path) -> None:
    """The same equivalence on real scans: the Intel Research Lab log's first 300."""
    scans = list(itertools.islice(load_dataset(datasets_dir / "intel-corrected.log.gz"), 300))
    one_call, planned = GridMap(MapConfig()), GridMap(MapConfig())
    for scan in scans:
        assert one_call.integrate(scan) == planned.apply(planned.plan(scan))
    window = one_call.known_bounds()
    assert window is not None
    assert_same(snapshot(one_call, window), snapshot(planned, window))


def _parallel_beams(count: int, cells: int, resolution: float) -> Scan:
    """`count` beams along +x from a cell's centre, each ending `cells` cells away (walks of
    `cells + 3` cells each by `scan_rays`' count)."""
    r, centre = cells * resolution, resolution / 2
    return Scan.from_angles((centre, centre, 0.0), [0.0] * count, [r] * count, range_max=2 * r)


@pytest.mark.parametrize(
    ("config", "path"),
    [({}, "integrate"), ({}, "plan"), ({"layers": ["occupancy", "tsdf"]}, "integrate"),
     ({"layers": ["counts"], "update": "per_ray"}, "integrate")],
)  # fmt: skip
def test_a_scan_whose_beams_walk_too_many_cells_is_refused_before_it_is_traced(
    monkeypatch: pytest.MonkeyPatch, config: dict[str, object], path: str
) -> None:
    """The ray model's trace allocates for every cell its beams walk (before de-duplication), so
    their total is bounded (`update_plan.MAX_SCAN_CELLS`): a scan past it is a ScanError that
    changes nothing, at the limit it is integrated. The limit is lowered here to 4,096 cells so
    that the scans stay small; the real one refuses, at once, a scan the service's input limits
    allow and that took 13 s and 2.8 GB before (the next test)."""
    monkeypatch.setattr(update_plan, "MAX_SCAN_CELLS", 4096)
    m = make_map(resolution=0.05, tile_size=256, **config)
    m.integrate(Scan.from_angles((0.0, 0.0, 0.0), [0.0, 1.0], [2.0, 3.0]))
    window = (-300, -300, 1300, 300)
    before = snapshot(m, window)
    run = m.integrate if path == "integrate" else lambda scan: m.apply(m.plan(scan))
    with pytest.raises(ScanError, match="cross more than 4,096 cells in all"):
        run(_parallel_beams(5, 1020, 0.05))  # 5 x 1,023 cells
    assert_same(snapshot(m, window), before)
    result = run(_parallel_beams(4, 1020, 0.05))  # 4 x 1,023 = 4,092 cells: within
    assert result.cell_updates == (4 if config.get("update") == "per_ray" else 1) * 1021


def test_the_scan_cell_limit_refuses_what_the_service_allows_and_fits_real_lidars() -> None:
    """At the real limit: 16,384 beams of 300 m at 5 cm (within the service's default input limits)
    are refused; a 1,081-beam lidar's 30 m scan, and a TSDF-only map's long beams (the band is a
    few cells a return), are not."""
    angles = np.linspace(-math.pi, math.pi, 16_384, endpoint=False)
    m = make_map(resolution=0.05)
    with pytest.raises(ScanError, match="cells in all"):
        m.integrate(Scan.from_angles((0.0, 0.0, 0.0), angles, np.full(angles.size, 300.0), range_max=400.0))
    assert len(m.store.keys) == 0
    lidar = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 1081)
    assert m.integrate(Scan.from_angles((0.0, 0.0, 0.0), lidar, np.full(lidar.size, 30.0))).cell_updates > 0
    band = make_map(resolution=0.05, layers=["tsdf"])
    assert band.integrate(Scan.from_angles((0.0, 0.0, 0.0), angles, np.full(angles.size, 300.0),
                                           range_max=400.0)).tsdf_updates > 0  # fmt: skip


def test_a_beam_model_scan_whose_window_is_too_large_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """The beam model evaluates every cell of a square around the sensor reaching its longest beam:
    past `MAX_SCAN_CELLS` cells (lowered here) the scan is a ScanError that changes nothing (a
    1,000 m beam at 5 cm asked for 27 GB and failed with numba's bare MemoryError)."""
    monkeypatch.setattr(update_plan, "MAX_SCAN_CELLS", 100 * 100)
    m = make_map(resolution=0.05, sensor_model="beam")
    m.integrate(Scan.from_angles((0.0, 0.0, 0.0), [0.0, 0.5], [1.0, 1.0]))
    window = (-100, -100, 100, 100)
    before = snapshot(m, window)
    with pytest.raises(ScanError, match="beam model would evaluate more than 10,000 cells"):
        m.integrate(Scan.from_angles((0.0, 0.0, 0.0), [0.0, 0.5], [1.0, 2.5]))  # (2 * 50 + 4)**2 cells
    assert_same(snapshot(m, window), before)
    assert m.integrate(Scan.from_angles((0.0, 0.0, 0.0), [0.0, 0.5], [1.0, 2.3])).cell_updates > 0


@pytest.mark.parametrize(
    "config",
    [
        {},
        {"layers": ["occupancy", "tsdf"]},
        {"layers": ["tsdf"]},
        {"update": "per_ray"},
        {"sensor_model": "beam"},
    ],
)
def test_scans_beyond_the_index_range_or_too_wide_are_refused(config: dict[str, object]) -> None:
    """A pose or reach beyond +-2**40 cells, or a scan whose box spans more than 2**20 tiles, is
    refused with a clear ScanError and changes nothing, on every integration path (one call, plan
    and apply, per-ray entries, the beam model, the TSDF band alone: each numbers its tiles in a
    table over the box, which for per-ray updates asked for 13 GB before)."""
    m = make_map(resolution=0.05, tile_size=256, **config)
    m.integrate(Scan.from_angles((0.0, 0.0, 0.0), [0.0, 1.0], [2.0, 3.0]))
    window = (-100, -100, 100, 100)
    before = snapshot(m, window)
    far_pose = Scan.from_angles((6e10, 0.0, 0.0), [0.0], [1.0])
    far_reach = Scan.from_angles((0.0, 0.0, 0.0), [0.0], [6e10], range_max=math.inf)
    wide = Scan.from_angles((0.0, 0.0, 0.0), [0.0, math.pi / 2], [15_000.0, 15_000.0], range_max=math.inf)
    for scan, message in (
        (far_pose, "coordinate range"),
        (far_reach, "coordinate range"),
        (wide, "too large an area"),
    ):
        with pytest.raises(ScanError, match=message):
            m.integrate(scan)
        assert_same(snapshot(m, window), before)


def test_known_bounds_rescans_only_changed_tiles_and_never_loops_over_all() -> None:
    """`known_bounds` (every `GET /maps/{id}`, and viewers ask again as a map grows) looped over every
    tile in Python under the map's lock: 3.6 ms a call on a 1 km map of 6,400 tiles, however little
    changed. Now it rescans the tiles changed since its last call, combines the tiles' bounds in one
    vectorised pass, and answers at once when nothing changed; never a walk of the tile dict."""
    gmap = GridMap(MapConfig(resolution=0.1, tile_size=16, max_tiles=10_000))
    rng = np.random.default_rng(11)

    def scan_at(x: float, y: float) -> Scan:
        return Scan.from_fan((x, y, 0.0), -1.0, 0.05, rng.uniform(0.5, 4.0, 40), 0.0, 10.0)

    def brute_force() -> tuple[int, int, int, int] | None:
        lo, hi = [math.inf, math.inf], [-math.inf, -math.inf]
        t = gmap.store.tile_size
        for (ti, tj), slot in gmap.store.slots.items():
            seen = np.argwhere(gmap._observed(slot))
            if seen.size:
                lo = [min(lo[0], ti * t + seen[:, 1].min()), min(lo[1], tj * t + seen[:, 0].min())]
                hi = [max(hi[0], ti * t + seen[:, 1].max() + 1), max(hi[1], tj * t + seen[:, 0].max() + 1)]
        return None if lo[0] == math.inf else (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))

    assert gmap.known_bounds() is None
    gmap.store.create([(40, 40)])  # a tile with nothing observed counts for nothing
    assert gmap.known_bounds() is None
    scanned: list[int] = []
    observed = gmap._observed

    def counted(slot: int) -> np.ndarray:
        scanned.append(slot)
        return observed(slot)

    gmap._observed = counted  # type: ignore[method-assign]
    slots = gmap.store.slots
    seen = {key: int(gmap.store.versions[slot]) for key, slot in slots.items()}  # as of the last call
    for x, y in [(0.0, 0.0), (-3.0, 2.0), (5.0, -4.0), (5.0, -4.0)]:
        gmap.store.slots = slots
        gmap.integrate(scan_at(x, y))
        expected = brute_force()
        versions = {key: int(gmap.store.versions[slot]) for key, slot in slots.items()}
        changed = {slots[key] for key, version in versions.items() if seen.get(key) != version}
        seen = versions
        scanned.clear()
        gmap.store.slots = _NoWalk(slots)  # type: ignore[assignment]
        assert gmap.known_bounds() == expected
        assert sorted(scanned) == sorted(changed)
        scanned.clear()
        assert gmap.known_bounds() == expected and scanned == []  # nothing changed: no tile scanned
    gmap.store.slots = slots


class _NoWalk(dict):
    """A tile dict that refuses to be walked whole."""

    def items(self):  # type: ignore[no-untyped-def]
        raise AssertionError("walked every tile")

    def __iter__(self):  # type: ignore[no-untyped-def]
        raise AssertionError("walked every tile")

    def values(self):  # type: ignore[no-untyped-def]
        raise AssertionError("walked every tile")


#: A map of 16-cell tiles applies the plan of a map of 256-cell tiles; the process's exit status and
#: what it prints tell what happened.
_FOREIGN_PLAN = """
import numpy as np
from fleetmap import GridMap, MapConfig, Scan
scan = Scan.from_fan((0.5, 0.5, 0.3), -3.0, 0.02, np.full(300, 9.0), 0.05, 10.0)
small = GridMap(MapConfig(tile_size=16))
large = GridMap(MapConfig(tile_size=256))
try:
    small.apply(large.plan(scan))
except ValueError as exc:
    print("refused:", exc)
"""


@pytest.mark.parametrize(
    "other",
    [{"tile_size": 16}, {"resolution": 0.1}, {"layers": ["tsdf"]}, {"traversal": "bresenham"}],
)
def test_a_plan_applies_only_to_a_map_configured_as_its_own(other: dict[str, object]) -> None:
    """`apply` took a plan made by any map: one of another tile size wrote its cells into other tiles
    and cells (a 9 m fan became a map 300 m across, or crashed the process: a segmentation fault
    when the plan's tiles were larger than the map's), one of another resolution or sensor model a
    map of another scan. A plan made under another configuration is refused (ValueError), the map
    unchanged; one of a map configured alike applies as the map's own plan."""
    scan = Scan.from_fan((0.5, 0.5, 0.3), -3.0, 0.02, np.full(300, 9.0), 0.05, 10.0)
    gmap = GridMap(MapConfig(tile_size=256))
    with pytest.raises(ValueError, match="made under another map configuration"):
        gmap.apply(GridMap({"tile_size": 256, **other}).plan(scan))
    assert len(gmap.store) == 0 and gmap.known_bounds() is None
    alike = GridMap({"tile_size": 256, "layers": ["tsdf", "counts", "occupancy"]})
    reference = GridMap(MapConfig(tile_size=256))
    assert gmap.apply(alike.plan(scan)) == reference.integrate(scan)
    bounds = reference.known_bounds()
    assert bounds is not None and gmap.known_bounds() == bounds
    for layer in ALL_READ_LAYERS:
        np.testing.assert_array_equal(gmap.region(layer, *bounds), reference.region(layer, *bounds))


def test_a_plan_of_larger_tiles_does_not_crash_the_process() -> None:
    """The segmentation fault, in a process of its own."""
    result = subprocess.run([sys.executable, "-c", _FOREIGN_PLAN], capture_output=True, text=True)
    assert result.returncode == 0, f"exit status {result.returncode}: {result.stderr[-2000:]}"
    assert result.stdout.startswith("refused: ") and "made under another map configuration" in result.stdout
