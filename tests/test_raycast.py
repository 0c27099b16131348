"""Ray casting (`GridMap.cast_rays`, `POST /maps/{map_id}/raycast`, `FleetmapClient.raycast`).

The kernel is compared with a slow reference written here from the engine's public pieces only: the
cells of `segment_cells(..., EXACT)` in order, each classified by `GridMap.cells` (its `state`, or the
count model for a map without occupancy), the entry point computed from the cell boundary crossed.
On the Intel map, on synthetic maps painted cell by cell, and on random small maps (hypothesis).
The endpoint and the client run against the real service over HTTP and must answer what the library
answers for the same scans.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from fleetmap_client.rest import FleetmapClient, FleetmapError
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service_process import ServiceProcess
from test_api_support import room_scans

from fleetmap import GridMap, MapConfig
from fleetmap.codec import decode, encode_json
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import (
    MAX_RAY_CELLS,
    MAX_RAY_WALK,
    MAX_RAYS,
    RAY_MAX_RANGE,
    RAY_OCCUPIED,
    RAY_STATUS_NAMES,
    RAY_UNKNOWN,
    STATE_OCCUPIED,
    STATE_UNKNOWN,
    LayerUnavailableError,
    RaycastResult,
    RayLimitError,
)
from fleetmap.kernels.traversal import EXACT, segment_cells
from fleetmap.wire import JSON_ENCODING

# -- the reference ---------------------------------------------------------------------------------


def reference_ray(
    gmap: GridMap, origin: tuple[float, float], angle: float, max_range: float, unknown: str
) -> tuple[int, float, int, int]:
    """(status, range, i, j) of one ray, the slow and obvious way."""
    res = gmap.resolution
    ox, oy = origin
    ex, ey = ox + max_range * math.cos(angle), oy + max_range * math.sin(angle)
    u0, v0, u1, v1 = ox / res, oy / res, ex / res, ey / res
    cells = segment_cells(u0, v0, u1, v1, EXACT)
    values = gmap.cells((cells + 0.5) * res)  # each cell's centre: that cell, whatever the rounding
    assert np.array_equal(np.floor((cells + 0.5) * res / res).astype(np.int64), cells)
    if gmap.config.has("occupancy"):
        occupied = values["state"] == STATE_OCCUPIED
    else:
        total = values["hits"].astype(np.float64) + values["misses"]
        with np.errstate(invalid="ignore"):
            occupied = values["hits"] / total > gmap.config.occupancy.occupied_thresh
    known = values["known"]
    for k, (i, j) in enumerate(cells.tolist()):
        if occupied[k] or (unknown == "stop" and not known[k]):
            status = RAY_OCCUPIED if occupied[k] else RAY_UNKNOWN
            if k == 0:
                return status, 0.0, i, j
            pi, pj = cells[k - 1]
            # Entered across the line between the two columns, or else between the two rows.
            t = (max(pi, i) - u0) / (u1 - u0) if pi != i else (max(pj, j) - v0) / (v1 - v0)
            return status, t * max_range, i, j
    i, j = cells[-1].tolist()
    return RAY_MAX_RANGE, max_range, i, j


def assert_matches_reference(
    gmap: GridMap, origin: tuple[float, float], angles: np.ndarray, max_range: float, unknown: str
) -> RaycastResult:
    got = gmap.cast_rays(origin, angles, max_range, unknown)  # type: ignore[arg-type]
    assert all(len(a) == len(angles) for a in got)
    for r, angle in enumerate(angles.tolist()):
        status, distance, i, j = reference_ray(gmap, origin, angle, max_range, unknown)
        where = f"ray {r} at angle {angle!r} from {origin}, max_range {max_range}, unknown={unknown}"
        assert (int(got.status[r]), int(got.i[r]), int(got.j[r])) == (status, i, j), where
        assert got.range[r] == pytest.approx(distance, abs=1e-9 * max(1.0, max_range)), where
        assert got.x[r] == pytest.approx(origin[0] + distance * math.cos(angle), abs=1e-9), where
        assert got.y[r] == pytest.approx(origin[1] + distance * math.sin(angle), abs=1e-9), where
    return got


def paint(gmap: GridMap, cells: dict[tuple[int, int], float]) -> None:
    """Set cells by hand to log-odds `value` (NaN: unknown), and their counts to a hit and a miss
    plus `2 * value` more hits (value > 0) or misses (value < 0), rounded: p 0.5 for 0, 5 / 6 for
    WALL, none for NaN."""
    store = gmap.store
    keys = sorted({(i >> store.shift, j >> store.shift) for i, j in cells} - set(store.slots))
    store.create(keys)
    for (i, j), value in cells.items():
        slot, li, lj = store.slots[(i >> store.shift, j >> store.shift)], i & store.mask, j & store.mask
        if "log_odds" in store.pools:
            store.pools["log_odds"][slot, lj, li] = value
        if "hits" in store.pools:
            more = 0 if math.isnan(value) else round(2 * value)
            hits, misses = (0, 0) if math.isnan(value) else (1 + max(more, 0), 1 + max(-more, 0))
            store.pools["hits"][slot, lj, li] = hits
            store.pools["misses"][slot, lj, li] = misses


# -- synthetic maps ----------------------------------------------------------------------------------

FREE, WALL = -2.0, 2.0  # log-odds: p 0.12 and 0.88


def walled_map(layers: tuple[str, ...] = ("occupancy",)) -> GridMap:
    """A 0.1 m map of 16-cell tiles: free cells over [-40, 40) x [-40, 40) (negative ones too,
    several tiles each way), a wall column at i = 25 and a wall row at j = -30."""
    gmap = GridMap(MapConfig(resolution=0.1, tile_size=16, layers=list(layers)))  # type: ignore[arg-type]
    cells = {(i, j): FREE for i in range(-40, 40) for j in range(-40, 40)}
    cells.update({(25, j): WALL for j in range(-40, 40)})
    cells.update({(i, -30): WALL for i in range(-40, 40)})
    paint(gmap, cells)
    return gmap


def test_rays_stop_at_walls_across_tiles_and_at_negative_coordinates() -> None:
    gmap = walled_map()
    # Along the axes: +x meets the wall column, -y the wall row, -x and +y leave the observed area.
    r = gmap.cast_rays((0.05, 0.05), [0.0, -math.pi / 2, math.pi, math.pi / 2], 10.0)
    assert r.status.tolist() == [RAY_OCCUPIED, RAY_OCCUPIED, RAY_UNKNOWN, RAY_UNKNOWN]
    assert (r.i.tolist(), r.j.tolist()) == ([25, 0, -41, 0], [0, -30, 0, 40])
    assert r.range == pytest.approx([2.45, 2.95, 4.05, 3.95])
    assert r.x == pytest.approx([2.5, 0.05, -4.0, 0.05]) and r.y == pytest.approx([0.05, -2.9, 0.05, 4.0])
    # Diagonals through cell corners, and rays at all angles, against the reference.
    for origin in [(0.0, 0.0), (-1.0, -1.0), (0.05, 0.05), (-3.33, 1.27), (2.2, -2.7)]:
        for unknown in ("stop", "pass"):
            assert_matches_reference(gmap, origin, np.arange(8) * math.pi / 4, 10.0, unknown)
            assert_matches_reference(gmap, origin, np.linspace(-math.pi, math.pi, 97), 7.3, unknown)


def test_a_ray_starting_in_an_obstacle_hits_at_range_zero() -> None:
    gmap = walled_map()
    r = gmap.cast_rays((2.53, 0.77), [0.0, 1.0, math.pi], 5.0)
    assert r.status.tolist() == [RAY_OCCUPIED] * 3
    assert r.range.tolist() == [0.0] * 3 and r.x.tolist() == [2.53] * 3 and r.y.tolist() == [0.77] * 3
    assert r.i.tolist() == [25] * 3 and r.j.tolist() == [7] * 3


def test_unknown_cells_stop_or_pass() -> None:
    gmap = walled_map()
    # From outside the observed area towards the wall column: stop at once, or pass and hit it.
    stop = gmap.cast_rays((-6.0, 0.05), 0.0, 20.0)
    passed = gmap.cast_rays((-6.0, 0.05), 0.0, 20.0, unknown="pass")
    assert (int(stop.status[0]), float(stop.range[0]), int(stop.i[0])) == (RAY_UNKNOWN, 0.0, -60)
    assert (int(passed.status[0]), int(passed.i[0])) == (RAY_OCCUPIED, 25)
    assert float(passed.range[0]) == pytest.approx(8.5)
    # An empty map: unknown at the origin, or nothing at all up to max_range.
    empty = GridMap(MapConfig(resolution=0.05))
    r = empty.cast_rays((-1.0, -2.0), [0.3], 1.0)
    assert (int(r.status[0]), float(r.range[0])) == (RAY_UNKNOWN, 0.0)
    r = empty.cast_rays((-1.0, -2.0), [0.3], 1.0, unknown="pass")
    assert int(r.status[0]) == RAY_MAX_RANGE and float(r.range[0]) == 1.0
    assert r.x[0] == pytest.approx(-1.0 + math.cos(0.3)) and r.y[0] == pytest.approx(-2.0 + math.sin(0.3))
    assert (int(r.i[0]), int(r.j[0])) == (math.floor(r.x[0] / 0.05), math.floor(r.y[0] / 0.05))


def test_an_origin_on_a_cell_edge_walking_back_enters_the_next_cell_at_zero() -> None:
    """x = 1.0 is cell 10's left edge at 0.1 m: a ray going -x enters cell 9 at once, at +0.0."""
    gmap = walled_map()
    paint(gmap, {(9, 5): WALL})
    r = gmap.cast_rays((1.0, 0.55), [math.pi, 0.0], 5.0)
    assert r.status.tolist() == [RAY_OCCUPIED, RAY_OCCUPIED] and r.i.tolist() == [9, 25]
    assert r.range[0] == 0.0 and math.copysign(1.0, r.range[0]) == 1.0
    assert (r.x[0], r.y[0]) == (1.0, 0.55)


def test_a_cell_entered_before_max_range_counts() -> None:
    gmap = walled_map()
    # The wall column covers x in [2.5, 2.6): a ray ending at 2.55 enters it, one ending at 2.49 not.
    inside = gmap.cast_rays((0.05, 0.05), 0.0, 2.5)
    short = gmap.cast_rays((0.05, 0.05), 0.0, 2.44)
    assert (int(inside.status[0]), int(inside.i[0])) == (RAY_OCCUPIED, 25)
    assert float(inside.range[0]) == pytest.approx(2.45)
    assert (int(short.status[0]), int(short.i[0]), float(short.range[0])) == (RAY_MAX_RANGE, 24, 2.44)


def test_uncertain_cells_are_walked_through() -> None:
    """Only p > occupied_thresh stops a ray: a known cell between the thresholds does not."""
    gmap = walled_map()
    paint(gmap, {(10, 0): 0.0, (11, 0): 0.6, (12, 0): 0.62})  # p 0.5, 0.646, 0.650
    state = gmap.cells([[1.05, 0.05], [1.15, 0.05], [1.25, 0.05]])["state"]
    assert gmap.config.occupancy.occupied_thresh == 0.65
    assert state.tolist() == [STATE_UNKNOWN, STATE_UNKNOWN, STATE_OCCUPIED]
    r = gmap.cast_rays((0.05, 0.05), 0.0, 10.0)
    assert (int(r.status[0]), int(r.i[0])) == (RAY_OCCUPIED, 12)
    assert_matches_reference(gmap, (0.05, 0.05), np.array([0.0]), 10.0, "stop")


def test_counts_maps_use_the_count_model_and_tsdf_maps_cannot_cast() -> None:
    gmap = walled_map(("counts", "tsdf"))
    r = gmap.cast_rays((0.05, 0.05), [0.0, -math.pi / 2], 10.0)
    assert r.status.tolist() == [RAY_OCCUPIED, RAY_OCCUPIED] and r.i.tolist() == [25, 0]
    paint(gmap, {(5, 0): 0.0})  # one hit, one miss: p = 0.5, not occupied
    paint(gmap, {(6, 1): 3.0})  # seven hits, one miss
    for unknown in ("stop", "pass"):
        assert_matches_reference(gmap, (-0.37, 0.41), np.linspace(-3, 3, 61), 9.0, unknown)
    r = gmap.cast_rays((0.05, 0.15), 0.0, 10.0)
    assert int(r.i[0]) == 6
    tsdf_only = GridMap(MapConfig(layers=["tsdf"]))
    with pytest.raises(LayerUnavailableError, match="'occupancy' or the 'counts'"):
        tsdf_only.cast_rays((0.0, 0.0), [0.0], 1.0)
    # Said whatever the rays: they were judged first, so rays too long for the limits were a
    # RayLimitError (413), and the caller who shortened them met this refusal only next.
    for angles, max_range in (([0.0], 1e6), ([0.0] * (MAX_RAYS + 1), 1.0), ([0.0] * 1000, 900.0)):
        with pytest.raises(LayerUnavailableError, match="'occupancy' or the 'counts'"):
            tsdf_only.cast_rays((0.0, 0.0), angles, max_range)


def test_the_occupied_log_odds_edge_is_classify_s_own() -> None:
    """The kernel's log-odds threshold is the float32 where `classify` turns occupied, exactly."""
    for preset in ("octomap", "cartographer", "coursera", "int8"):
        gmap = GridMap(MapConfig(occupancy={"preset": preset}))  # type: ignore[arg-type]
        edge = np.float32(gmap._log_odds_occupied())
        below = np.nextafter(edge, np.float32(-np.inf))
        below_state, edge_state = gmap.classify(np.array([below, edge], dtype=np.float32)).tolist()
        assert below_state != STATE_OCCUPIED and edge_state == STATE_OCCUPIED, preset
        paint(gmap, {(3, 0): float(below), (4, 0): float(edge)})
        r = gmap.cast_rays((0.01, 0.01), 0.0, 1.0, unknown="pass")
        assert int(r.i[0]) == 4


def test_rays_from_many_origins_are_each_origin_s_own_rays() -> None:
    """`origin` of shape (n, 2): ray r starts at origin[r], and answers what a call from that origin
    alone answers (and the reference), in order; one origin of shape (1, 2) serves every ray."""
    gmap = walled_map()
    rng = np.random.default_rng(7)
    origins = np.concatenate([rng.uniform(-4.5, 4.5, (200, 2)), [[0.0, 0.0], [1.0, 0.55], [2.53, 0.77]]])
    angles = rng.uniform(-math.pi, math.pi, origins.shape[0])
    for unknown in ("stop", "pass"):
        many = gmap.cast_rays(origins, angles, 7.3, unknown)  # type: ignore[arg-type]
        expected = {RAY_OCCUPIED, RAY_MAX_RANGE} | ({RAY_UNKNOWN} if unknown == "stop" else set())
        assert {int(c) for c in many.status} == expected
        for r in range(origins.shape[0]):
            alone = gmap.cast_rays(origins[r], [angles[r]], 7.3, unknown)  # type: ignore[arg-type]
            assert [float(v[r]) for v in many] == [float(v[0]) for v in alone], (r, unknown)
        for r in range(0, origins.shape[0], 20):
            origin = (float(origins[r, 0]), float(origins[r, 1]))
            status, distance, i, j = reference_ray(gmap, origin, float(angles[r]), 7.3, unknown)
            assert (int(many.status[r]), int(many.i[r]), int(many.j[r])) == (status, i, j)
            assert many.range[r] == pytest.approx(distance, abs=1e-9 * 7.3)
    shared = gmap.cast_rays([[0.05, 0.05]], [0.0, -math.pi / 2], 10.0)
    assert shared.i.tolist() == [25, 0] and shared.j.tolist() == [0, -30]
    with pytest.raises(ValueError, match="3 origins for 2 angles"):
        gmap.cast_rays(np.zeros((3, 2)), [0.0, 1.0], 1.0)
    with pytest.raises(ValueError, match="one per ray"):
        gmap.cast_rays(np.zeros((2, 3)), [0.0, 1.0], 1.0)
    with pytest.raises(ValueError, match=r"finite.*got \[100000000.0, 0.0\]"):
        gmap.cast_rays([[0.0, 0.0], [1e8, 0.0]], [0.0, 1.0], 1.0)


def test_rays_read_under_the_map_lock() -> None:
    """A ray query waits while another thread holds the map's lock (a scan being applied)."""
    gmap = walled_map()
    answers: list[RaycastResult] = []
    reader = threading.Thread(target=lambda: answers.append(gmap.cast_rays((0.05, 0.05), [0.0], 5.0)))
    with gmap.lock:
        reader.start()
        reader.join(0.3)
        assert reader.is_alive() and not answers
    reader.join(10)
    assert [a.i.tolist() for a in answers] == [[25]]


def test_bad_arguments_are_refused() -> None:
    gmap = GridMap(MapConfig(resolution=0.05))
    for origin in [(math.nan, 0.0), (0.0, math.inf), (2e7, 0.0), (1.0,), "ab"]:
        with pytest.raises(ValueError, match="origin"):
            gmap.cast_rays(origin, [0.0], 1.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="angles must be finite"):
        gmap.cast_rays((0, 0), [0.0, math.nan], 1.0)
    with pytest.raises(ValueError, match="angles must be numbers"):
        gmap.cast_rays((0, 0), ["north"], 1.0)  # type: ignore[list-item]
    with pytest.raises(ValueError, match="one-dimensional"):
        gmap.cast_rays((0, 0), [[0.0, 1.0]], 1.0)
    with pytest.raises(RayLimitError, match=f"limit of {MAX_RAYS} per call"):
        gmap.cast_rays((0, 0), np.zeros(MAX_RAYS + 1), 0.05)
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="max_range must be a positive"):
            gmap.cast_rays((0, 0), [0.0], bad)
    with pytest.raises(RayLimitError, match=f"limit of {MAX_RAY_CELLS} cells"):
        gmap.cast_rays((0, 0), [0.0], MAX_RAY_CELLS * 0.05 * 1.001)
    # Just past the limit, the message does not round the cells down to the limit itself ("1000.01 m
    # is 20000 cells, more than the limit of 20000 cells"), and gives the limit in metres.
    with pytest.raises(RayLimitError) as just_past:
        gmap.cast_rays((0, 0), [0.0], 1000.01)
    assert "is 20000.2 cells" in str(just_past.value) and "20000 cells (1000 m)" in str(just_past.value)
    # Nor rounds what was sent, however little past the limit ("max_range 1000 m is 20000 cells").
    with pytest.raises(RayLimitError) as hair_past:
        gmap.cast_rays((0, 0), [0.0], 1000.0001)
    assert str(hair_past.value).startswith("max_range 1000.0001 m is 20000.002 cells"), hair_past.value
    rays = MAX_RAY_WALK // MAX_RAY_CELLS
    with pytest.raises(RayLimitError, match=f"{rays + 1} rays of 20000 cells .* limit of {MAX_RAY_WALK}"):
        gmap.cast_rays((0, 0), np.zeros(rays + 1), MAX_RAY_CELLS * 0.05)
    with pytest.raises(ValueError, match="'stop' or 'pass'"):
        gmap.cast_rays((0, 0), [0.0], 1.0, unknown="ignore")  # type: ignore[arg-type]
    # At the limits it works, and no ray at all is no answer.
    r = gmap.cast_rays((0, 0), np.zeros(rays), MAX_RAY_CELLS * 0.05, unknown="pass")
    assert (r.status == RAY_MAX_RANGE).all() and (r.i == MAX_RAY_CELLS).all()
    r = gmap.cast_rays(
        (0, 0), np.full(MAX_RAYS, math.pi / 2), MAX_RAY_WALK // MAX_RAYS * 0.05, unknown="pass"
    )
    assert (r.status == RAY_MAX_RANGE).all() and (r.j == MAX_RAY_WALK // MAX_RAYS).all()
    assert all(len(a) == 0 for a in gmap.cast_rays((0, 0), [], 1.0))


# -- random small maps ---------------------------------------------------------------------------------


@st.composite
def small_maps(draw: st.DrawFn) -> tuple[GridMap, tuple[float, float], np.ndarray, float, str]:
    resolution = draw(st.sampled_from([0.05, 0.1, 0.25, 1.0]))
    layers = draw(st.sampled_from([("occupancy",), ("counts",), ("occupancy", "counts")]))
    gmap = GridMap(MapConfig(resolution=resolution, tile_size=16, layers=list(layers)))  # type: ignore[arg-type]
    # Four tiles each way around the origin: free cells over a square of them (or none), then
    # anything anywhere.
    cells = {(i, j): FREE for i in range(-24, 24) for j in range(-24, 24)} if draw(st.booleans()) else {}
    cell = st.tuples(st.integers(-32, 31), st.integers(-32, 31))
    values = st.sampled_from([FREE, WALL, 0.0, 0.7, -0.3, 1.5, 3.0, -1.0, math.nan])
    cells.update(draw(st.dictionaries(cell, values, max_size=200)))
    paint(gmap, cells)
    coordinate = st.floats(-33 * resolution, 33 * resolution, allow_nan=False)
    # Cell corners and edges (exactly representable multiples of the resolution) as well as any point.
    on_grid = st.integers(-33, 33).map(lambda k: k * resolution)
    origin = (draw(st.one_of(coordinate, on_grid)), draw(st.one_of(coordinate, on_grid)))
    special = st.sampled_from([k * math.pi / 4 for k in range(-4, 5)])
    angles = draw(st.lists(st.one_of(st.floats(-7, 7, allow_nan=False), special), min_size=1, max_size=8))
    max_range = draw(st.floats(0.01, 70 * resolution))
    return gmap, origin, np.array(angles), max_range, draw(st.sampled_from(["stop", "pass"]))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(small_maps())
def test_random_small_maps_match_the_reference(
    case: tuple[GridMap, tuple[float, float], np.ndarray, float, str],
) -> None:
    assert_matches_reference(*case)


# -- the Intel map ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def intel_map(datasets_dir: Path) -> GridMap:
    """The Intel Research Lab at 0.05 m, from every 4th scan of its corrected log."""
    path = datasets_dir / "intel-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"{path} is missing")
    gmap = GridMap(MapConfig(resolution=0.05))
    dataset = load_dataset(path)
    for k in range(0, len(dataset), 4):
        gmap.integrate(dataset[k])
    return gmap


def test_the_intel_map_matches_the_reference(intel_map: GridMap) -> None:
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    statuses = set()
    # Poses of the robot (free space), a wall, outside the building (unknown), a far corner.
    for origin in [(0.0, 0.0), (-5.3, 2.1), (10.2, -12.9), (-30.0, 30.0), (5.0, 5.0)]:
        for unknown in ("stop", "pass"):
            got = assert_matches_reference(intel_map, origin, angles, 10.0, unknown)
            statuses |= set(got.status.tolist())
    assert statuses == {RAY_OCCUPIED, RAY_UNKNOWN, RAY_MAX_RANGE}


def test_a_ray_from_inside_a_wall_of_the_intel_map(intel_map: GridMap) -> None:
    r = intel_map.cast_rays((0.0, 0.0), np.linspace(0, 2 * math.pi, 36), 10.0)
    hit = np.flatnonzero(r.status == RAY_OCCUPIED)
    assert hit.size >= 30
    # From the centre of a wall cell a ray hit: every ray hits at once, in that cell.
    i, j = int(r.i[hit[0]]), int(r.j[hit[0]])
    res = intel_map.resolution
    inside = intel_map.cast_rays(((i + 0.5) * res, (j + 0.5) * res), [0.0, 1.0, -2.0], 5.0)
    assert inside.status.tolist() == [RAY_OCCUPIED] * 3 and inside.range.tolist() == [0.0] * 3
    assert (inside.i.tolist(), inside.j.tolist()) == ([i] * 3, [j] * 3)


# -- the endpoint and the client, on the real service --------------------------------------------------

ROOM = {"resolution": 0.05, "tile_size": 16}
#: Origins in the box room of `room_scans` (walls at x = +-3, y = +-2), on a wall, and outside it.
ORIGINS = [(0.0, 0.0), (-1.23, 0.77), (2.9, -1.9), (3.0, 0.4), (-5.0, 5.0)]


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One real service for the module's HTTP tests (each test uses its own map ids)."""
    with ServiceProcess(tmp_path_factory.mktemp("raycast"), ["--in-memory"]) as svc:
        yield svc


def room_maps(url: str, map_id: str, config: dict[str, object]) -> GridMap:
    """Make map `map_id` on the service from 12 room scans over HTTP; return the engine's map of the
    same scans as the service decoded them."""
    assert httpx.put(f"{url}/maps/{map_id}", json=config).status_code == 201
    gmap = GridMap(MapConfig.model_validate(config))
    for seq, scan in enumerate(room_scans(12, seed=5)):
        payload = encode_json(scan, seq)
        r = httpx.post(
            f"{url}/maps/{map_id}/scans",
            params={"robot_id": "r1"},
            content=payload,
            headers={"content-type": JSON_ENCODING},
        )
        assert r.status_code == 200 and r.json()["status"] == "integrated", r.text
        gmap.integrate(decode(payload, JSON_ENCODING).scan)
    return gmap


def raycast(url: str, map_id: str, body: dict[str, object]) -> httpx.Response:
    return httpx.post(f"{url}/maps/{map_id}/raycast", json=body, timeout=30)


def assert_same_answer(answer: dict[str, object], result: RaycastResult) -> None:
    """The JSON answer is the library's result, number for number."""
    assert answer == {
        "count": len(result.status),
        "status": [RAY_STATUS_NAMES[int(c)] for c in result.status],
        "range": result.range.tolist(),
        "x": result.x.tolist(),
        "y": result.y.tolist(),
        "i": result.i.tolist(),
        "j": result.j.tolist(),
    }


@pytest.mark.parametrize("layers", [["occupancy", "counts", "tsdf"], ["counts"]], ids=["occupancy", "counts"])
def test_the_endpoint_answers_what_the_library_answers(service: ServiceProcess, layers: list[str]) -> None:
    map_id = f"room-{len(layers)}"
    gmap = room_maps(service.base_url, map_id, {**ROOM, "layers": layers})
    angles = np.linspace(-math.pi, math.pi, 181).tolist()
    statuses = set()
    for origin in ORIGINS:
        for unknown in ("stop", "pass"):
            body = {"origin": list(origin), "angles": angles, "max_range": 6.5, "unknown": unknown}
            r = raycast(service.base_url, map_id, body)
            assert r.status_code == 200, r.text
            expected = gmap.cast_rays(origin, angles, 6.5, unknown)  # type: ignore[arg-type]
            assert_same_answer(r.json(), expected)
            statuses |= set(r.json()["status"])
    assert statuses == {"occupied", "unknown", "max_range"}
    # `unknown` defaults to "stop"; integers are numbers.
    r = raycast(service.base_url, map_id, {"origin": [0, 0], "angles": [0, 1], "max_range": 10})
    assert_same_answer(r.json(), gmap.cast_rays((0.0, 0.0), [0.0, 1.0], 10.0))
    assert r.json()["status"] == ["occupied", "occupied"]


def test_the_endpoint_casts_rays_from_many_origins(service: ServiceProcess) -> None:
    map_id = "room-origins"
    gmap = room_maps(service.base_url, map_id, ROOM)
    origins = [list(o) for o in ORIGINS for _ in range(37)]
    angles = np.linspace(-math.pi, math.pi, len(origins)).tolist()
    r = raycast(service.base_url, map_id, {"origins": origins, "angles": angles, "max_range": 6.5})
    assert r.status_code == 200, r.text
    assert_same_answer(r.json(), gmap.cast_rays(origins, angles, 6.5))
    assert set(r.json()["status"]) == {"occupied", "unknown"}
    # Each ray from its own origin, not all from the first one.
    first = gmap.cast_rays(origins[0], angles, 6.5)
    assert r.json()["range"] != first.range.tolist()
    url = service.base_url
    ok = {"origins": [[0.0, 0.0], [1.0, 1.0]], "angles": [0.0, 1.0], "max_range": 5.0}
    for change, words in [
        ({"origin": [0.0, 0.0]}, "not both"),
        ({"origins": None}, "give origin"),
        ({"origins": [[0.0, 0.0]]}, "1 origins for 2 angles"),
        ({"origins": [[0.0, 0.0], [0.0]]}, "origins"),
        ({"origins": [[0.0, 0.0], [0.0, 2e7]]}, "origins"),
        ({"origins": [[0.0, 0.0], "x"]}, "origins"),
    ]:
        r = raycast(url, map_id, {k: v for k, v in {**ok, **change}.items() if v is not None})
        assert r.status_code == 422, (change, r.text)
        assert words in r.json()["detail"], (change, r.json())
    many = MAX_RAYS + 1
    r = raycast(url, map_id, {**ok, "origins": [[0.0, 0.0]] * many, "angles": [0.0] * many})
    assert r.status_code == 413 and r.json()["detail"].startswith(f"{many} rays is more than the limit")


def test_bad_requests_are_refused_as_the_api_does(service: ServiceProcess) -> None:
    url = service.base_url
    room_maps(url, "bad", ROOM)
    ok = {"origin": [0.0, 0.0], "angles": [0.0], "max_range": 5.0}
    assert raycast(url, "bad", ok).status_code == 200
    r = raycast(url, "no-such-map", ok)
    assert r.status_code == 404 and r.json()["detail"] == "no map 'no-such-map'"
    for change, where in [
        ({"origin": [0.0]}, "origin"),
        ({"origin": [0.0, 0.0, 0.0]}, "origin"),
        ({"origin": [0.0, 2e7]}, "origin"),
        ({"origin": ["0", 0.0]}, "origin"),
        ({"angles": []}, "angles"),
        ({"angles": [0.0, "1"]}, "angles"),
        ({"angles": 0.0}, "angles"),
        ({"max_range": 0}, "max_range"),
        ({"max_range": -1.0}, "max_range"),
        ({"max_range": "5"}, "max_range"),
        ({"unknown": "ignore"}, "unknown"),
        ({"ignore_unknown": True}, "ignore_unknown"),
    ]:
        r = raycast(url, "bad", {**ok, **change})
        assert r.status_code == 422, (change, r.text)
        assert where in r.json()["detail"], (change, r.json())
    for missing in ok:
        r = raycast(url, "bad", {k: v for k, v in ok.items() if k != missing})
        assert r.status_code == 422 and missing in r.json()["detail"]
    r = httpx.post(f"{url}/maps/bad/raycast", content=b'{"origin": [0, 0], "angles": [NaN], "max_range": 1}',
                   headers={"content-type": "application/json"})  # fmt: skip
    assert r.status_code == 422
    r = httpx.post(f"{url}/maps/bad/raycast", content=b'{"origin": [0, 0], "angles": [0], "max_range": 1}')
    assert r.status_code == 415
    # Too much at once: 413, as for too many points.
    r = raycast(url, "bad", {**ok, "angles": [0.0] * (MAX_RAYS + 1)})
    assert r.status_code == 413 and r.json()["detail"] == (
        f"{MAX_RAYS + 1} rays is more than the limit of {MAX_RAYS} per request"
    )
    r = raycast(url, "bad", {**ok, "max_range": MAX_RAY_CELLS * 0.05 + 1})
    assert r.status_code == 413 and f"more than the limit of {MAX_RAY_CELLS} cells" in r.json()["detail"]
    r = raycast(url, "bad", {**ok, "angles": [0.0] * 1000, "max_range": 900.0})
    assert r.status_code == 413 and f"limit of {MAX_RAY_WALK} cells per call" in r.json()["detail"]
    assert raycast(url, "bad", {**ok, "angles": [0.0] * 838, "max_range": 1000.0}).status_code == 200
    # A map keeping only the TSDF has nothing to cast against: 422, as a layer the map does not keep.
    assert httpx.put(f"{url}/maps/tsdf-only", json={"layers": ["tsdf"]}).status_code == 201
    for change in ({}, {"max_range": MAX_RAY_CELLS * 0.05 + 1}, {"angles": [0.0] * 1000, "max_range": 900.0}):
        r = raycast(url, "tsdf-only", {**ok, **change})
        assert r.status_code == 422 and "'occupancy' or the 'counts' layer" in r.json()["detail"], r.text


def test_the_client_casts_rays(service: ServiceProcess) -> None:
    gmap = room_maps(service.base_url, "client", ROOM)
    angles = np.linspace(0, 2 * math.pi, 90)
    with FleetmapClient(service.base_url) as fm:
        got = fm.raycast("client", (0.4, -0.3), angles, 8.0)
        passed = fm.raycast("client", [-4.0, 0.1], 0.0, 8.0, unknown="pass")
        expected = gmap.cast_rays((0.4, -0.3), angles, 8.0)
        assert got["status"].tolist() == [RAY_STATUS_NAMES[int(c)] for c in expected.status]
        for name in ("range", "x", "y", "i", "j"):
            assert got[name].dtype == getattr(expected, name).dtype
            np.testing.assert_array_equal(got[name], getattr(expected, name))
        # From outside the room through the unknown to its wall at x = -3 (the cell of -3.0 or the one
        # before: where the beams ended, rounded).
        wall = gmap.cast_rays((-4.0, 0.1), [0.0], 8.0, unknown="pass")
        assert passed["status"].tolist() == ["occupied"] and passed["i"].tolist() in ([-60], [-61])
        assert passed["range"].tolist() == wall.range.tolist() and 0.9 <= passed["range"][0] <= 1.0
        with pytest.raises(ValueError, match="finite"):
            fm.raycast("client", (math.nan, 0.0), [0.0], 1.0)
        with pytest.raises(ValueError, match="angles must be finite"):
            fm.raycast("client", (0.0, 0.0), [math.inf], 1.0)
        with pytest.raises(ValueError, match="pair"):
            fm.raycast("client", (0.0, 0.0, 0.0), [0.0], 1.0)
        # Angles of two dimensions are refused, as the engine refuses them: not flattened into 6 rays
        # and paired with 6 origins in an order the caller never chose.
        with pytest.raises(ValueError, match="one-dimensional"):
            gmap.cast_rays((0.0, 0.0), np.zeros((2, 3)), 1.0)
        with pytest.raises(ValueError, match="one-dimensional"):
            fm.raycast("client", (0.0, 0.0), np.zeros((2, 3)), 1.0)
        with pytest.raises(ValueError, match="one-dimensional"):
            fm.raycast("client", np.zeros((6, 2)), np.zeros((2, 3)), 1.0)
        # Complex numbers are refused, not cut to their real parts (with numpy's warning only).
        with pytest.raises(ValueError, match="complex"):
            fm.raycast("client", (0.0, 0.0), np.exp(1j * angles), 1.0)
        with pytest.raises(ValueError, match="complex"):
            fm.raycast("client", np.array([0.4 + 0j, -0.3]), [0.0], 1.0)
        with pytest.raises(ValueError, match="complex"):
            fm.cells("client", np.array([0.4 - 0.3j, 1.0 + 0.5j]))
        # So are ints beyond float's range (OverflowError, no ValueError, escaped), before any request.
        huge = 10**400
        for args in [((huge, 0.0), [0.0], 1.0), ((0.0, 0.0), [huge], 1.0), ((0.0, 0.0), [0.0], huge)]:
            with pytest.raises(ValueError):
                fm.raycast("client", *args)  # type: ignore[arg-type]
        with pytest.raises(ValueError):
            fm.cells("client", [[huge, 0.0]])
        with pytest.raises(ValueError, match="finite"):
            fm.cell("client", huge, 0.0)
        # No rays answer no rays, as the engine does (the service, 1 to 10 000 a request, refuses
        # none: it is not asked); a range that is not positive is refused before any request.
        none = fm.raycast("client", (0.4, -0.3), [], 8.0)
        empty = gmap.cast_rays((0.4, -0.3), [], 8.0)
        assert set(none) == {"status", "range", "x", "y", "i", "j"}
        for name in ("range", "x", "y", "i", "j"):
            assert none[name].shape == (0,) and none[name].dtype == getattr(empty, name).dtype
        assert none["status"].shape == (0,) and none["status"].dtype.kind == "U"
        assert fm.raycast("client", np.zeros((0, 2)), np.zeros(0), 8.0)["range"].shape == (0,)
        for bad_range in (0.0, -1.0):
            with pytest.raises(ValueError, match="max_range must be a positive"):
                fm.raycast("client", (0.0, 0.0), [0.0], bad_range)
            with pytest.raises(ValueError, match="max_range must be a positive"):
                fm.raycast("client", (0.0, 0.0), [], bad_range)
        with pytest.raises(FleetmapError) as err:
            fm.raycast("nothing-here", (0.0, 0.0), [0.0], 1.0)
        assert err.value.status == 404


def engine_rays(gmap: GridMap, origin: tuple[float, float], angles: np.ndarray, max_range: float,
                unknown: str = "stop") -> dict[str, list[object]]:  # fmt: skip
    """The engine's answer for any number of rays, cast 1000 at a time (its own limits are the
    service's), as lists per field: each ray's answer depends on that ray alone."""
    out: dict[str, list[object]] = {name: [] for name in ("status", "range", "x", "y", "i", "j")}
    for k in range(0, len(angles), 1000):
        part = gmap.cast_rays(origin, angles[k : k + 1000], max_range, unknown)  # type: ignore[arg-type]
        out["status"] += [RAY_STATUS_NAMES[int(c)] for c in part.status]
        for name in ("range", "x", "y", "i", "j"):
            out[name] += getattr(part, name).tolist()
    return out


def test_the_client_splits_rays_past_the_services_limits(service: ServiceProcess) -> None:
    """The service casts at most MAX_RAYS rays, and MAX_RAY_WALK cells of rays x max_range, a
    request (413 past either); the client passed the 413 on, as `cells` once did for points. It now
    casts them in several requests and joins the answers in the order of the angles. A ray longer
    than MAX_RAY_CELLS cannot be split: still a 413."""
    gmap = room_maps(service.base_url, "split", ROOM)
    rng = np.random.default_rng(3)
    many = rng.uniform(-math.pi, math.pi, 2 * MAX_RAYS + 7)  # three requests by count
    cells_long = 2000  # 9000 rays x 2000 cells is over MAX_RAY_WALK: two requests by the walk
    long_range = cells_long * gmap.resolution
    long = rng.uniform(-math.pi, math.pi, 9000)
    assert len(long) * cells_long > MAX_RAY_WALK and len(long) <= MAX_RAYS
    with FleetmapClient(service.base_url) as fm:
        for angles, max_range, unknown in ((many, 8.0, "stop"), (long, long_range, "pass")):
            got = fm.raycast("split", (0.4, -0.3), angles, max_range, unknown=unknown)  # type: ignore[arg-type]
            expected = engine_rays(gmap, (0.4, -0.3), angles, max_range, unknown)
            assert {name: values.tolist() for name, values in got.items()} == expected
            assert len(set(expected["range"])) > 100  # the rays differ: a mixed-up order would show
        with pytest.raises(FleetmapError) as err:
            fm.raycast("split", (0.0, 0.0), [0.0, 1.0], (MAX_RAY_CELLS + 10) * gmap.resolution)
        assert err.value.status == 413 and "cells" in err.value.detail


def test_the_client_casts_rays_from_many_origins(service: ServiceProcess) -> None:
    """An origin per ray, sent as `origins`, split past the service's limits with the origins kept
    beside their angles."""
    gmap = room_maps(service.base_url, "client-origins", ROOM)
    rng = np.random.default_rng(11)
    origins = rng.uniform(-2.8, 2.8, (MAX_RAYS + 50, 2))  # two requests
    angles = rng.uniform(-math.pi, math.pi, len(origins))
    with FleetmapClient(service.base_url) as fm:
        got = fm.raycast("client-origins", origins, angles, 6.0)
        half = len(origins) // 2  # the engine's own limit is the service's
        parts = [gmap.cast_rays(origins[k : k + half], angles[k : k + half], 6.0) for k in (0, half)]
        for name in ("status", "range", "x", "y", "i", "j"):
            expected = np.concatenate([getattr(part, name) for part in parts])
            if name == "status":
                expected = np.array([RAY_STATUS_NAMES[int(c)] for c in expected])
            np.testing.assert_array_equal(got[name], expected)
        assert len(set(got["range"].tolist())) > 1000  # each ray from its own origin
        with pytest.raises(ValueError, match="3 origins for 2 angles"):
            fm.raycast("client-origins", np.zeros((3, 2)), [0.0, 1.0], 1.0)
        with pytest.raises(ValueError, match="finite"):
            fm.raycast("client-origins", [[0.0, 0.0], [math.nan, 0.0]], [0.0, 1.0], 1.0)
