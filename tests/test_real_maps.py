"""The engine against the pure-Python reference mapper (`reference.py`), on synthetic segments and on
maps of the real laser logs in ../shared/datasets.

The reference finds each ray's cells by column clipping instead of the engine's boundary stepping
and keeps its map in dicts; on real data the two must agree cell by cell: the same set of known
cells, log-odds equal to 1e-5 (exactly for presets whose steps float32 adds exactly), and identical
hit / miss counts. The same holds for the Bresenham traversal, every occupancy preset and explicit
parameters, the beam sensor model (against a brute-force table 9.2), and the TSDF layer (values to
TSDF_ATOL, weights exactly); and the service's plan-then-apply path builds the very map, tile
versions and per-scan results of the one-call `GridMap.integrate`. To keep the pure-Python
references to a few seconds per case, the maps use a subset of the scans, a 5 to 25 cm grid and a
shorter range_max (longer readings become no-returns).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from reference import BeamReferenceMap, ReferenceMap, ReferenceTsdf, bresenham_cells
from reference import segment_cells as reference_cells

from fleetmap.config import MapConfig
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import GridMap, IntegrationResult
from fleetmap.kernels.traversal import BRESENHAM, EXACT, segment_cells
from fleetmap.scan import Scan

DATASETS = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"


def engine_cells(x0: float, y0: float, x1: float, y1: float) -> set[tuple[int, int]]:
    return {(int(i), int(j)) for i, j in segment_cells(x0, y0, x1, y1, EXACT)}


# -- the reference's traversal against the engine's ----------------------------------------------------


def test_reference_traversal_matches_engine_on_generic_segments() -> None:
    """On segments through no grid vertex except possibly their start (random floats, starts on grid
    vertices and grid lines, runs along grid lines, zero length) both traversals give the same
    cells."""
    rng = np.random.default_rng(12)
    segs: list[tuple[float, float, float, float]] = []
    for _ in range(1500):
        segs.append(tuple(rng.uniform(-30, 30, 4)))  # type: ignore[arg-type]
        vx, vy = (float(v) for v in rng.integers(-9, 9, 2))
        ex, ey = (float(v) for v in rng.uniform(-20, 20, 2))
        segs.append((vx, vy, ex, ey))  # from a grid vertex
        segs.append((vx, float(rng.uniform(-9, 9)), ex, ey))  # from a vertical grid line
        segs.append((ex, vy, float(rng.uniform(-20, 20)), vy))  # along a horizontal grid line
        segs.append((vx, ey, vx, float(rng.uniform(-20, 20))))  # along a vertical grid line
        segs.append((ex, ey, ex, ey))
    for seg in segs:
        assert reference_cells(*seg) == engine_cells(*seg), seg


def test_reference_traversal_at_vertex_passes() -> None:
    """Through interior grid vertices (quarter-cell coordinates) the two traversals may pick
    different side cells (the engine's choice depends on rounding of its boundary parameters), but
    they have the same size and differ only in cells beside a vertex the segment passes through."""
    rng = np.random.default_rng(4)
    differ = 0
    for _ in range(3000):
        x0, y0 = (float(v) for v in rng.integers(-40, 40, 2) / 4.0)
        k = int(rng.integers(-12, 13))
        sx, sy = [(1, 1), (1, -1), (-1, 1), (-1, -1), (2, 1), (1, -2), (3, 2)][int(rng.integers(0, 7))]
        seg = (x0, y0, x0 + sx * k, y0 + sy * k)
        ref, eng = reference_cells(*seg), engine_cells(*seg)
        assert len(ref) == len(eng), seg
        if ref != eng:
            differ += 1
            sides = set()
            for x in range(math.ceil(min(seg[0], seg[2])), math.floor(max(seg[0], seg[2])) + 1):
                y = seg[1] + (x - seg[0]) * sy / sx
                if y == math.floor(y):
                    sides |= {(x - 1, int(y)), (x, int(y) - 1), (x - 1, int(y) - 1), (x, int(y))}
            assert ref ^ eng <= sides, seg
    assert differ < 3000


def test_reference_bresenham_matches_engine() -> None:
    """The reference's Bresenham line (`bresenham_cells`: nearest cells, ties away from the start)
    and the engine's error-term walk give the same cells on random segments, also between cells whose
    lines have exact ties (end points on half-cells, every direction)."""
    rng = np.random.default_rng(7)
    for n in range(4000):
        x0, y0, x1, y1 = (float(v) for v in rng.uniform(-25, 25, 4))
        if n % 2:  # integer cell offsets: ties are common
            x0, y0, x1, y1 = (math.floor(v) + 0.5 for v in (x0, y0, x1, y1))
        got = {(int(i), int(j)) for i, j in segment_cells(x0, y0, x1, y1, BRESENHAM)}
        assert bresenham_cells(x0, y0, x1, y1) == got, (x0, y0, x1, y1)


def test_reference_map_by_hand() -> None:
    """The reference itself on a hand-checked scan: two beams from the centre of cell (0, 0) at
    0.25 m resolution, one to cell 4 of row 0 and one straight up to cell (0, 2): hits at both ends,
    one miss at the shared sensor cell (per scan)."""
    ref = ReferenceMap(0.25, 1.0, -0.5, -100.0, 100.0)
    ref.integrate((0.125, 0.125, 0.0), np.array([0.0, math.pi / 2]), np.array([1.0, 0.5]), 0.0, math.inf)
    assert ref.log_odds == {(0, 0): -0.5, (1, 0): -0.5, (2, 0): -0.5, (3, 0): -0.5, (4, 0): 1.0,
                            (0, 1): -0.5, (0, 2): 1.0}  # fmt: skip
    assert ref.misses[(0, 0)] == 1


# -- real logs -----------------------------------------------------------------------------------------


def logit(p: float) -> float:
    """Log-odds of probability p, written here rather than taken from the engine's config, so that the
    presets below are checked against their documented values."""
    return math.log(p / (1.0 - p))


#: (l_hit, l_miss, l_min, l_max) of the occupancy presets, as their sources state them (config.py).
OCTOMAP = (logit(0.7), logit(0.4), logit(0.12), logit(0.97))
CARTOGRAPHER = (logit(0.55), logit(0.49), logit(0.1), logit(0.9))
COURSERA = (1.0, -0.5, -100.0, 100.0)
INT8 = (9.0, -9.0, -128.0, 127.0)


def load(file: str, range_max: float | None) -> list[Scan]:
    """The scans of one of the shared logs, with `range_max` (None: the log's own); the test is
    skipped (with the reason shown) when the shared datasets are not there."""
    path = DATASETS / file
    if not path.is_file():
        pytest.skip(f"real datasets not found at {DATASETS}: {file} is missing")
    return list(load_dataset(path, range_max=range_max))


def scan_args(scan: Scan) -> tuple[tuple[float, float, float], np.ndarray, np.ndarray, float, float]:
    """A scan as the references take it: pose, bearings, ranges, range_min, range_max."""
    pose = (scan.pose.x, scan.pose.y, scan.pose.theta)
    return pose, scan.angles, scan.ranges, scan.range_min, scan.range_max


def dense(
    values: Mapping[tuple[int, int], float], bounds: tuple[int, int, int, int], fill: float, dtype: type
) -> np.ndarray:
    """A reference's dict of cells as a region array (row = j - j0, column = i - i0)."""
    i0, j0, i1, j1 = bounds
    out: np.ndarray = np.full((j1 - j0, i1 - i0), fill, dtype=dtype)
    for (i, j), value in values.items():
        out[j - j0, i - i0] = value
    return out


def assert_known_cells_equal(
    got: np.ndarray, expected: np.ndarray, bounds: tuple[int, int, int, int]
) -> None:
    """The same cells are known (not NaN) in both arrays; the message names a few that are not."""
    diff = np.argwhere(np.isnan(got) != np.isnan(expected))
    assert diff.size == 0, (
        f"{len(diff)} cells known in only one map, e.g. cells "
        f"{[(int(c) + bounds[0], int(r) + bounds[1]) for r, c in diff[:5]]}"
    )


def assert_occupancy_matches(
    m: GridMap, ref: ReferenceMap, bounds: tuple[int, int, int, int], atol: float
) -> np.ndarray:
    """The engine's log-odds, hits and misses over `bounds` equal the reference's: the same known
    cells, log-odds within `atol`, counts exactly. Returns the reference's log-odds (NaN unknown)."""
    expected = dense(ref.log_odds, bounds, np.nan, np.float64)
    got = m.region("log_odds", *bounds).astype(np.float64)
    assert_known_cells_equal(got, expected, bounds)
    known = ~np.isnan(expected)
    np.testing.assert_allclose(got[known], expected[known], rtol=0, atol=atol)
    np.testing.assert_array_equal(m.region("hits", *bounds), dense(ref.hits, bounds, 0, np.int64))
    np.testing.assert_array_equal(m.region("misses", *bounds), dense(ref.misses, bounds, 0, np.int64))
    return expected


#: How far an engine TSDF value may be from the reference's. Both keep the running average as
#: float32 after every sample (a float32 step is 6e-8 just below 1), but the engine rounds each
#: sample to float32 before fusing it and finds a beam's direction by rotating (cos, sin) of its
#: bearing by the heading rather than as cos(heading + bearing): a last-bit difference in a sample
#: can move the stored average to a neighbouring float32 now and then, and each later fusion shrinks
#: an earlier difference by W / (W + 1) rather than adding to it. On the cases below the largest
#: difference is 2.4e-7 (a few float32 steps; a fifth to a third of the cells differ at all); 1e-6 leaves
#: room for that, and is far below any real fault in the fusion (a sample (z - d) / t moves by
#: 2.5e-2 per millimetre at the narrowest truncation here, 4 cm, and by 1e-3 at the widest, 1 m).
TSDF_ATOL = 1e-6


def assert_tsdf_matches(m: GridMap, ref: ReferenceTsdf, bounds: tuple[int, int, int, int]) -> np.ndarray:
    """The engine's TSDF over `bounds` equals the reference's: the same observed cells, weights
    exactly, values within TSDF_ATOL. Returns the reference's values (NaN unobserved)."""
    expected = dense(ref.tsdf, bounds, np.nan, np.float64)
    got = m.region("tsdf", *bounds).astype(np.float64)
    assert_known_cells_equal(got, expected, bounds)
    np.testing.assert_array_equal(
        m.region("tsdf_weight", *bounds), dense(ref.weight, bounds, 0.0, np.float32)
    )
    known = ~np.isnan(expected)
    np.testing.assert_allclose(got[known], expected[known], rtol=0, atol=TSDF_ATOL)
    return expected


# -- the ray model: traversals, update modes and occupancy parameters ------------------------------------


@dataclass(frozen=True)
class Case:
    file: str
    every: int  # use every n-th scan
    resolution: float
    range_max: float
    no_return_range: float = 0.0
    update: Literal["per_scan", "per_ray"] = "per_scan"
    traversal: Literal["exact", "bresenham"] = "exact"
    #: The map's `occupancy` section (a preset or parameters) and what it must mean, (l_hit, l_miss,
    #: l_min, l_max) as documented: the reference uses these, not the engine's resolved values.
    occupancy: tuple[tuple[str, object], ...] = ()
    log_odds: tuple[float, float, float, float] = OCTOMAP
    #: Tolerance on log-odds: 1e-5 for float32 sums of irrational steps; 0 where every step and
    #: clamp is a small multiple of 1/2, which float32 adds exactly.
    atol: float = 1e-5
    #: Whether some cells must have reached each clamp (so that the clamps are exercised).
    clamps: bool = False
    name: str = ""

    @property
    def id(self) -> str:
        return "-".join(filter(None, (self.file.split(".")[0], self.update, self.name)))


CASES = [
    Case("intel-corrected.log.gz", every=6, resolution=0.05, range_max=8.0),
    Case("freiburg-campus-corrected.log.gz", every=30, resolution=0.1, range_max=20.0),
    # Scan 0 of the CSAIL log is at (0, 0): rays start exactly on a grid vertex.
    Case("csail-robotlaser.log.gz", every=8, resolution=0.1, range_max=10.0, no_return_range=2.0),
    Case("intel-corrected.log.gz", every=15, resolution=0.1, range_max=10.0, update="per_ray"),
    # Bresenham lines, per scan and per ray (with no-return clearing).
    Case(
        "csail-robotlaser.log.gz",
        every=12,
        resolution=0.05,
        range_max=12.0,
        traversal="bresenham",
        name="bresenham",
    ),
    Case(
        "freiburg-campus-corrected.log.gz",
        every=40,
        resolution=0.2,
        range_max=40.0,
        update="per_ray",
        no_return_range=20.0,
        traversal="bresenham",
        name="bresenham",
    ),
    # The other presets, and parameters given partly as probabilities, partly as log-odds. Per ray,
    # a cell gets several updates a scan, so the clamps are reached within a subset of the scans.
    Case(
        "intel-corrected.log.gz",
        every=10,
        resolution=0.1,
        range_max=8.0,
        update="per_ray",
        occupancy=(("preset", "cartographer"),),
        log_odds=CARTOGRAPHER,
        clamps=True,
        name="cartographer",
    ),
    Case(
        "freiburg-campus-corrected.log.gz",
        every=40,
        resolution=0.2,
        range_max=30.0,
        no_return_range=5.0,
        occupancy=(("preset", "coursera"),),
        log_odds=COURSERA,
        atol=0.0,
        name="coursera",
    ),
    Case(
        "csail-robotlaser.log.gz",
        every=10,
        resolution=0.2,
        range_max=15.0,
        update="per_ray",
        no_return_range=2.0,
        occupancy=(("preset", "int8"),),
        log_odds=INT8,
        atol=0.0,
        clamps=True,
        name="int8",
    ),
    Case(
        "intel-corrected.log.gz",
        every=10,
        resolution=0.1,
        range_max=12.0,
        update="per_ray",
        no_return_range=5.0,
        occupancy=(("p_hit", 0.9), ("l_miss", -0.1), ("p_min", 0.01), ("l_max", 2.0)),
        log_odds=(logit(0.9), -0.1, logit(0.01), 2.0),
        clamps=True,
        name="custom",
    ),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_real_log_matches_reference(case: Case) -> None:
    """A map of a real log built by the engine equals the reference map cell by cell: the same known
    cells (and known_bounds), log-odds within the case's tolerance (the engine stores float32), and
    the same hit and miss counts, for per-scan and per-ray updates, with no-return clearing, with
    the exact and the Bresenham traversal, and with each occupancy preset and explicit parameters
    (the reference takes the parameters as documented, so a wrong preset fails too)."""
    scans = load(case.file, case.range_max)[:: case.every]
    config = MapConfig(
        resolution=case.resolution,
        layers=["occupancy", "counts"],
        no_return_range=case.no_return_range,
        update=case.update,
        traversal=case.traversal,
        occupancy=dict(case.occupancy),
    )
    traversal = bresenham_cells if case.traversal == "bresenham" else reference_cells
    ref = ReferenceMap(
        case.resolution, *case.log_odds, no_return_range=case.no_return_range,
        per_ray=case.update == "per_ray", traversal=traversal,
    )  # fmt: skip
    m = GridMap(config)
    for scan in scans:
        ref.integrate(*scan_args(scan))
        m.integrate(scan)
    assert len(scans) >= 50 and sum(int(s.no_return_mask().sum()) for s in scans) > 0

    bounds = ref.bounds()
    assert m.known_bounds() == bounds
    expected = assert_occupancy_matches(m, ref, bounds, case.atol)
    values = expected[~np.isnan(expected)]
    assert values.size == len(ref.log_odds) > 10_000
    # The maps are not trivial: both free and occupied cells exist.
    assert (values > 0).sum() > 1000 and (values < 0).sum() > 10_000
    if case.clamps:
        l_min, l_max = case.log_odds[2:]
        assert (values == l_min).sum() > 20 and (values == l_max).sum() > 20
    if case.traversal != "exact":
        # The option took effect: the same scans traced exactly miss a different set of cells.
        exact = GridMap(config.model_copy(update={"traversal": "exact"}))
        for scan in scans:
            exact.integrate(scan)
        assert (exact.region("misses", *bounds) != m.region("misses", *bounds)).sum() > 1000


# -- the beam model ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BeamCase:
    file: str
    every: int
    resolution: float
    range_max: float
    alpha: float = 0.1
    beta: float = 0.0175
    no_return_range: float = 0.0


BEAM_CASES = [
    BeamCase("intel-corrected.log.gz", every=30, resolution=0.1, range_max=8.0),
    # Wider cones than the beam spacing, thicker obstacles, and no-returns cleared to 3 m (10 m).
    BeamCase(
        "csail-robotlaser.log.gz",
        every=35,
        resolution=0.1,
        range_max=10.0,
        alpha=0.2,
        beta=0.05,
        no_return_range=3.0,
    ),
    BeamCase(
        "freiburg-campus-corrected.log.gz",
        every=130,
        resolution=0.25,
        range_max=30.0,
        alpha=0.5,
        beta=0.02,
        no_return_range=10.0,
    ),
]


@pytest.mark.parametrize("case", BEAM_CASES, ids=lambda c: c.file.split(".")[0])
def test_beam_model_real_log_matches_reference(case: BeamCase) -> None:
    """The beam sensor model (Probabilistic Robotics table 9.2) on a real log equals the brute-force
    reference that evaluates every cell around the sensor against every beam: the same known cells,
    log-odds within 1e-5, the same hit and miss counts. The engine culls cells by bearing bins and
    finds the nearest beam by binary search; the reference does neither."""
    scans = load(case.file, case.range_max)[:: case.every]
    config = MapConfig(
        resolution=case.resolution, layers=["occupancy", "counts"], sensor_model="beam",
        beam={"alpha": case.alpha, "beta": case.beta}, no_return_range=case.no_return_range,
    )  # fmt: skip
    ref = BeamReferenceMap(
        case.resolution, *OCTOMAP, alpha=case.alpha, beta=case.beta, no_return_range=case.no_return_range
    )
    m = GridMap(config)
    for scan in scans:
        ref.integrate(*scan_args(scan))
        m.integrate(scan)
    no_returns = sum(int(s.no_return_mask().sum()) for s in scans)
    assert len(scans) >= 15 and no_returns > 0

    bounds = ref.bounds()
    assert m.known_bounds() == bounds
    expected = assert_occupancy_matches(m, ref, bounds, 1e-5)
    values = expected[~np.isnan(expected)]
    assert values.size > 10_000 and (values > 0).sum() > 1000 and (values < 0).sum() > 10_000
    if case.no_return_range > 0:
        # Some cells were cleared only by no-returns: without them the reference leaves them unknown.
        ref_returns = BeamReferenceMap(case.resolution, *OCTOMAP, alpha=case.alpha, beta=case.beta)
        for scan in scans:
            ref_returns.integrate(*scan_args(scan))
        assert len(ref.log_odds.keys() - ref_returns.log_odds.keys()) > 100


# -- the TSDF layer ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TsdfCase:
    file: str
    every: int
    resolution: float
    truncation: float
    range_max: float | None = None  # the log's own (80 m): its max-range readings are no-returns
    max_weight: float = 1000.0


TSDF_CASES = [
    TsdfCase("intel-corrected.log.gz", every=10, resolution=0.05, truncation=0.2),
    # A band narrower than a cell.
    TsdfCase("csail-robotlaser.log.gz", every=3, resolution=0.1, truncation=0.04),
    # A wide band whose weights reach a low cap.
    TsdfCase("freiburg-campus-corrected.log.gz", every=25, resolution=0.2, truncation=1.0, max_weight=5.0),
]


@pytest.mark.parametrize("case", TSDF_CASES, ids=lambda c: c.file.split(".")[0])
def test_tsdf_real_log_matches_reference(case: TsdfCase) -> None:
    """The TSDF layer of a real log equals the reference's band-by-band fusion: the same observed
    cells, weights exactly (with the cap), values within TSDF_ATOL; no-returns add nothing."""
    scans = load(case.file, case.range_max)[:: case.every]
    config = MapConfig(
        resolution=case.resolution, layers=["tsdf"],
        tsdf={"truncation": case.truncation, "max_weight": case.max_weight},
    )  # fmt: skip
    ref = ReferenceTsdf(case.resolution, case.truncation, case.max_weight)
    m = GridMap(config)
    for scan in scans:
        ref.integrate(*scan_args(scan))
        m.integrate(scan)
    assert len(scans) >= 50 and sum(int(s.no_return_mask().sum()) for s in scans) > 0

    bounds = ref.bounds()
    assert m.known_bounds() == bounds
    expected = assert_tsdf_matches(m, ref, bounds)
    values = expected[~np.isnan(expected)]
    assert values.size > 10_000 and (values > 0.5).sum() > 1000 and (values < -0.5).sum() > 1000
    samples = np.array(list(ref.samples.values()))
    assert (samples > 1).sum() > 1000  # cells fused from several samples
    if case.max_weight < 1000:
        assert (samples > case.max_weight).sum() > 1000  # the cap binds


# -- plan then apply against the one-call integration --------------------------------------------------------


@dataclass(frozen=True)
class PlanCase:
    file: str
    every: int
    resolution: float
    range_max: float
    tile_size: int
    no_return_range: float = 0.0
    truncation: float = 0.2


PLAN_CASES = [
    PlanCase("intel-corrected.log.gz", every=8, resolution=0.05, range_max=8.0, tile_size=16),
    PlanCase(
        "csail-robotlaser.log.gz",
        every=10,
        resolution=0.1,
        range_max=10.0,
        tile_size=32,
        no_return_range=2.0,
        truncation=0.3,
    ),
]


@pytest.mark.parametrize("case", PLAN_CASES, ids=lambda c: c.file.split(".")[0])
def test_plan_then_apply_matches_integrate_on_real_log(case: PlanCase) -> None:
    """`GridMap.plan` + `GridMap.apply` (the service's path) and the one-call `GridMap.integrate`
    build the same map of a real log with every layer: the same IntegrationResult for each scan
    (updates, changed tiles in order, tiles created), the same tiles with the same versions and
    version clock, identical cells in every layer, and both equal to the references. Small tiles
    make scans create tiles, in the one-call kernel and, when the store must grow, by its fallback
    to plan and apply."""
    scans = load(case.file, case.range_max)[:: case.every]
    config = MapConfig(
        resolution=case.resolution, tile_size=case.tile_size, max_tiles=100_000,
        no_return_range=case.no_return_range, tsdf={"truncation": case.truncation},
    )  # fmt: skip
    one_call, planned = GridMap(config), GridMap(config)
    in_place = 0  # scans the one-call kernel integrated itself
    integrate_in_place = one_call._integrate_in_place

    def counting(scan: Scan) -> IntegrationResult | None:
        nonlocal in_place
        result = integrate_in_place(scan)
        in_place += result is not None
        return result

    one_call._integrate_in_place = counting  # type: ignore[method-assign]
    occ = ReferenceMap(case.resolution, *OCTOMAP, no_return_range=case.no_return_range)
    tsdf = ReferenceTsdf(case.resolution, case.truncation, 1000.0)
    created = 0
    for k, scan in enumerate(scans):
        expected = one_call.integrate(scan)
        assert planned.apply(planned.plan(scan)) == expected, f"scan {k}"
        created += expected.tiles_created
        occ.integrate(*scan_args(scan))
        tsdf.integrate(*scan_args(scan))
    assert len(scans) >= 50 and created > 100
    assert len(scans) // 2 < in_place < len(scans)  # both ways of creating tiles were taken

    store_a, store_b = one_call.store, planned.store
    assert store_a.keys == store_b.keys
    assert store_a.clock == store_b.clock
    assert [store_a.version(k) for k in store_a.keys] == [store_b.version(k) for k in store_b.keys]
    bounds = one_call.known_bounds()
    assert bounds is not None and bounds == planned.known_bounds()
    for layer in ("log_odds", "hits", "misses", "tsdf", "tsdf_weight"):
        np.testing.assert_array_equal(one_call.region(layer, *bounds), planned.region(layer, *bounds))
    # The union of the occupancy and the TSDF layers' cells.
    (a0, b0, a1, b1), (c0, d0, c1, d1) = occ.bounds(), tsdf.bounds()
    assert bounds == (min(a0, c0), min(b0, d0), max(a1, c1), max(b1, d1))
    assert_occupancy_matches(one_call, occ, bounds, 1e-5)
    assert_tsdf_matches(one_call, tsdf, bounds)
