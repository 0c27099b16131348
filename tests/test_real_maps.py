"""The engine against the pure-Python reference mapper (`reference.py`), on synthetic segments and on
maps of the real laser logs in ../shared/datasets.

The reference finds each ray's cells by column clipping instead of the engine's boundary stepping
and keeps its map in dicts; on real data the two must agree cell by cell: the same set of known
cells, log-odds equal to 1e-5, and identical hit / miss counts. To keep the pure-Python reference to
a few seconds per log, the maps use a subset of the scans, a 5 or 10 cm grid and a shorter
range_max (longer readings become no-returns).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from reference import ReferenceMap
from reference import segment_cells as reference_cells

from fleetmap.config import MapConfig
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import GridMap
from fleetmap.kernels.traversal import EXACT, segment_cells

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


@dataclass(frozen=True)
class Case:
    file: str
    every: int  # use every n-th scan
    resolution: float
    range_max: float
    no_return_range: float = 0.0
    update: str = "per_scan"


CASES = [
    Case("intel-corrected.log.gz", every=6, resolution=0.05, range_max=8.0),
    Case("freiburg-campus-corrected.log.gz", every=30, resolution=0.1, range_max=20.0),
    # Scan 0 of the CSAIL log is at (0, 0): rays start exactly on a grid vertex.
    Case("csail-robotlaser.log.gz", every=8, resolution=0.1, range_max=10.0, no_return_range=2.0),
    Case("intel-corrected.log.gz", every=15, resolution=0.1, range_max=10.0, update="per_ray"),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c.file.split('.')[0]}-{c.update}")
def test_real_log_matches_reference(case: Case) -> None:
    """A map of a real log built by the engine equals the reference map cell by cell: the same known
    cells (and known_bounds), log-odds within 1e-5 (the engine stores float32), and the same hit and
    miss counts, for per-scan and per-ray updates and with no-return clearing."""
    path = DATASETS / case.file
    if not path.is_file():
        pytest.skip(f"real datasets not found at {DATASETS}: {case.file} is missing")
    ds = load_dataset(path, range_max=case.range_max)
    config = MapConfig(
        resolution=case.resolution,
        layers=["occupancy", "counts"],
        no_return_range=case.no_return_range,
        update=case.update,  # type: ignore[arg-type]
    )
    occ = config.occupancy
    ref = ReferenceMap(
        case.resolution, occ.l_hit, occ.l_miss, occ.l_min, occ.l_max,
        no_return_range=case.no_return_range, per_ray=case.update == "per_ray",
    )  # fmt: skip
    m = GridMap(config)
    n = 0
    no_returns = 0
    for k in range(0, len(ds), case.every):
        scan = ds[k]
        ref.integrate((scan.pose.x, scan.pose.y, scan.pose.theta), scan.angles, scan.ranges,
                      scan.range_min, scan.range_max)  # fmt: skip
        m.integrate(scan)
        n += 1
        no_returns += int(scan.no_return_mask().sum())
    assert n >= 50 and no_returns > 0

    bounds = ref.bounds()
    assert m.known_bounds() == bounds
    i0, j0, i1, j1 = bounds
    expected = np.full((j1 - j0, i1 - i0), np.nan)
    exp_hits = np.zeros(expected.shape, dtype=np.int64)
    exp_misses = np.zeros(expected.shape, dtype=np.int64)
    for (i, j), value in ref.log_odds.items():
        expected[j - j0, i - i0] = value
    for (i, j), count in ref.hits.items():
        exp_hits[j - j0, i - i0] = count
    for (i, j), count in ref.misses.items():
        exp_misses[j - j0, i - i0] = count

    got = m.region("log_odds", *bounds).astype(np.float64)
    known_got, known_exp = ~np.isnan(got), ~np.isnan(expected)
    assert known_exp.sum() == len(ref.log_odds) > 10_000
    diff = np.argwhere(known_got != known_exp)
    assert diff.size == 0, (
        f"{len(diff)} cells known in only one map, e.g. cells "
        f"{[(int(c) + i0, int(r) + j0) for r, c in diff[:5]]}"
    )
    np.testing.assert_allclose(got[known_exp], expected[known_exp], rtol=0, atol=1e-5)
    np.testing.assert_array_equal(m.region("hits", *bounds), exp_hits)
    np.testing.assert_array_equal(m.region("misses", *bounds), exp_misses)
    # The maps are not trivial: both free and occupied cells exist.
    assert (expected[known_exp] > 0).sum() > 1000 and (expected[known_exp] < 0).sum() > 10_000
