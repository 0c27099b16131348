"""Property tests of the grid traversals in `fleetmap.kernels.traversal` (coordinates in CELL units).

`exact` (Amanatides-Woo) must visit every cell the segment crosses and only cells that touch it, as a
4-connected chain of `|di| + |dj| + 1` distinct cells from the start cell to the end cell.
`bresenham` must be the classic 8-connected line of `max(|di|, |dj|) + 1` cells between the start and
end cells. Each property is checked on random segments, including negative coordinates, axis-aligned
and zero-length segments, integer and half-integer end points and segments through cell corners.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fleetmap import update_plan
from fleetmap.config import MapConfig
from fleetmap.kernels.fan_rows import trace_fan_rows
from fleetmap.kernels.scan_geometry import beam_layout, scan_rays
from fleetmap.kernels.traversal import BRESENHAM, EXACT, cell_count, cells, exact_starts, segment_cells
from fleetmap.scan import Scan
from fleetmap.update_plan import plan_scan, ray_trace_inputs

#: Slack for "touches": a visited cell's closed square may miss the segment by at most this much
#: (floating-point rounding in the walk's boundary parameters).
EPS = 1e-9

Point = tuple[float, float]
Segment = tuple[float, float, float, float]

# -- strategies --------------------------------------------------------------------------------------

_free = st.floats(-60.0, 60.0, allow_nan=False, allow_infinity=False)
_grid = st.integers(-40, 40).map(float)  # exactly on grid lines
_half = st.integers(-80, 80).map(lambda k: k / 2.0)  # grid lines and cell centres
_quarter = st.integers(-160, 160).map(lambda k: k / 4.0)
coord = st.one_of(_free, _grid, _half, _quarter)


@st.composite
def segments(draw: st.DrawFn) -> Segment:
    """Random segments, biased towards the degenerate cases a traversal gets wrong."""
    x0, y0 = draw(coord), draw(coord)
    kind = draw(st.sampled_from(["free", "free", "horizontal", "vertical", "zero", "diagonal", "short"]))
    if kind == "horizontal":
        return x0, y0, draw(coord), y0
    if kind == "vertical":
        return x0, y0, x0, draw(coord)
    if kind == "zero":
        return x0, y0, x0, y0
    if kind == "diagonal":
        # Slope +-1 (or +-2, +-1/2) from a point: passes through cell corners when x0, y0 are
        # centres or corners.
        k = draw(st.integers(-30, 30))
        sx, sy = draw(st.sampled_from([(1, 1), (1, -1), (-1, 1), (-1, -1), (2, 1), (1, 2), (-2, 1)]))
        return x0, y0, x0 + sx * k, y0 + sy * k
    if kind == "short":
        dx = draw(st.floats(-1.5, 1.5, allow_nan=False))
        dy = draw(st.floats(-1.5, 1.5, allow_nan=False))
        return x0, y0, x0 + dx, y0 + dy
    return x0, y0, draw(coord), draw(coord)


# -- geometric helpers (independent of the engine) ---------------------------------------------------


def segment_touches_square(seg: Segment, i: int, j: int, eps: float = EPS) -> bool:
    """Whether the segment meets the closed square `[i, i+1] x [j, j+1]` grown by `eps` (Liang-Barsky)."""
    x0, y0, x1, y1 = seg
    t0, t1 = 0.0, 1.0
    slabs = ((x1 - x0, i - eps - x0, i + 1 + eps - x0), (y1 - y0, j - eps - y0, j + 1 + eps - y0))
    for p, q_lo, q_hi in slabs:
        if p == 0.0:
            if q_lo > 0.0 or q_hi < 0.0:
                return False
            continue
        a, b = q_lo / p, q_hi / p
        if a > b:
            a, b = b, a
        t0, t1 = max(t0, a), min(t1, b)
        if t0 > t1:
            return False
    return True


def interior_cells(seg: Segment) -> set[tuple[int, int]]:
    """Every cell whose open interior the segment crosses over a positive length.

    The parameters where the segment meets a grid line split it into pieces, each inside one cell;
    a piece's midpoint names that cell. Pieces shorter than 1e-9 (rounding) are skipped, as are
    midpoints within 1e-9 of a grid line (the piece runs along a line, not through a cell)."""
    x0, y0, x1, y1 = seg
    ts = {0.0, 1.0}
    for a0, a1 in ((x0, x1), (y0, y1)):
        if a0 != a1:
            lo, hi = sorted((a0, a1))
            for k in range(math.ceil(lo), math.floor(hi) + 1):
                ts.add((k - a0) / (a1 - a0))
    ordered = sorted(t for t in ts if 0.0 <= t <= 1.0)
    out: set[tuple[int, int]] = set()
    for ta, tb in zip(ordered, ordered[1:], strict=False):
        if (tb - ta) * math.hypot(x1 - x0, y1 - y0) < 1e-9:
            continue
        tm = 0.5 * (ta + tb)
        x, y = x0 + tm * (x1 - x0), y0 + tm * (y1 - y0)
        if _near_grid(x) or _near_grid(y):
            continue
        out.add((math.floor(x), math.floor(y)))
    return out


def sampled_cells(seg: Segment, n: int = 400) -> set[tuple[int, int]]:
    """Cells of `n` points spread along the segment, leaving out points within 1e-9 of a grid line."""
    x0, y0, x1, y1 = seg
    out: set[tuple[int, int]] = set()
    for k in range(n + 1):
        t = k / n
        x, y = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
        if _near_grid(x) or _near_grid(y):
            continue
        out.add((math.floor(x), math.floor(y)))
    return out


def _near_grid(v: float) -> bool:
    return abs(v - round(v)) < 1e-9


def _cells(seg: Segment, method: int) -> list[tuple[int, int]]:
    return [(int(i), int(j)) for i, j in segment_cells(*seg, method)]


# -- exact traversal ---------------------------------------------------------------------------------

CORNER_CASES: list[Segment] = [
    (0.5, 0.5, 2.5, 2.5),
    (2.5, 2.5, 0.5, 0.5),
    (0.5, 2.5, 2.5, 0.5),
    (-0.5, -0.5, -3.5, -3.5),
    (0.0, 0.0, 3.0, 3.0),
    (0.0, 0.0, -3.0, -3.0),
    (3.0, 0.0, 0.0, 3.0),
    (1.0, 1.0, 1.0, 1.0),
    (0.0, 0.0, 0.0, 0.0),
    (-1.0, 0.5, 2.0, 0.5),
    (2.0, 0.0, -2.0, 0.0),
    (0.0, 2.0, 0.0, -2.0),
    (-0.5, -0.5, 1.5, 3.5),
    (0.999999999, 0.5, 1.000000001, 0.5),
    (-1e-12, -1e-12, 1e-12, 1e-12),
]


@settings(max_examples=250, deadline=None)
@given(segments())
@example((0.5, 0.5, 2.5, 2.5))
@example((-3.0, -2.0, 4.0, 5.0))
@example((-2.25, 7.75, 5.75, -0.25))
@example((0.0, 0.0, 0.0, 0.0))
@example((-5.0, 3.5, 12.0, 3.5))
def test_exact_chain_properties(seg: Segment) -> None:
    """The exact walk starts in the start cell, ends in the end cell, steps to a 4-neighbour each
    time, never repeats a cell and visits exactly |di| + |dj| + 1 cells."""
    check_exact_chain(seg)


def check_exact_chain(seg: Segment) -> None:
    got = _cells(seg, EXACT)
    x0, y0, x1, y1 = seg
    start = (math.floor(x0), math.floor(y0))
    end = (math.floor(x1), math.floor(y1))
    assert got[0] == start
    assert got[-1] == end
    assert len(got) == abs(end[0] - start[0]) + abs(end[1] - start[1]) + 1
    assert len(got) == cell_count(*seg, EXACT)
    assert len(set(got)) == len(got), f"a cell is visited twice: {got}"
    for (ia, ja), (ib, jb) in zip(got, got[1:], strict=False):
        assert abs(ia - ib) + abs(ja - jb) == 1, f"not 4-connected: ({ia}, {ja}) -> ({ib}, {jb})"


@settings(max_examples=250, deadline=None)
@given(segments())
@example((0.5, 0.5, 2.5, 2.5))
@example((0.5, 2.5, 2.5, 0.5))
@example((0.0, 0.0, -3.0, -3.0))
def test_exact_visits_only_touching_cells(seg: Segment) -> None:
    """Every cell the exact walk visits has a closed square that the segment touches (possibly only
    at a corner, where the walk must add one cell to stay 4-connected)."""
    check_exact_touching(seg)


def check_exact_touching(seg: Segment) -> None:
    for i, j in _cells(seg, EXACT):
        assert segment_touches_square(seg, i, j), f"cell ({i}, {j}) does not touch {seg}"


@settings(max_examples=250, deadline=None)
@given(segments())
@example((0.5, 0.5, 2.5, 2.5))
@example((-7.3, 2.1, 9.9, -4.4))
@example((0.1, 0.1, 0.1, 39.9))
def test_exact_visits_every_crossed_cell(seg: Segment) -> None:
    """Every cell whose interior the segment crosses is visited: found both from the exact pieces
    between grid-line crossings and from points sampled along the segment."""
    check_exact_crossed(seg)


def check_exact_crossed(seg: Segment) -> None:
    got = set(_cells(seg, EXACT))
    missing = (interior_cells(seg) | sampled_cells(seg)) - got
    assert not missing, f"crossed cells {sorted(missing)} not visited by {sorted(got)}"


def test_exact_corner_cases() -> None:
    """Hand-picked corner passes, grid-line runs and zero-length segments satisfy every property."""
    for seg in CORNER_CASES:
        check_exact_chain(seg)
        check_exact_touching(seg)
        check_exact_crossed(seg)


def test_exact_corner_pass_cells() -> None:
    """Through cell corners (0.5,0.5)->(2.5,2.5): the diagonal cells and one side cell per corner."""
    got = _cells((0.5, 0.5, 2.5, 2.5), EXACT)
    assert {(0, 0), (1, 1), (2, 2)} <= set(got)
    assert len(got) == 5
    side = set(got) - {(0, 0), (1, 1), (2, 2)}
    assert side <= {(0, 1), (1, 0), (1, 2), (2, 1)}


def test_exact_axis_aligned_runs() -> None:
    """A horizontal segment along y = 0.5 from x = -2.5 to 3.5 visits exactly cells -3..3 of row 0,
    and one along the grid line y = 2.0 stays in row 2 (the half-open cell [2, 3))."""
    assert _cells((-2.5, 0.5, 3.5, 0.5), EXACT) == [(i, 0) for i in range(-3, 4)]
    assert _cells((3.5, 2.0, -2.5, 2.0), EXACT) == [(i, 2) for i in range(3, -4, -1)]
    assert _cells((0.5, -0.5, 0.5, -4.5), EXACT) == [(0, j) for j in range(-1, -6, -1)]


def test_cells_generator_matches_segment_cells() -> None:
    """The compiled `cells` generator yields the same cells as `segment_cells`, for both methods."""
    rng = np.random.default_rng(3)
    for _ in range(50):
        seg = tuple(float(v) for v in rng.uniform(-20, 20, 4))
        for method in (EXACT, BRESENHAM):
            assert [(int(i), int(j)) for i, j in cells(*seg, method)] == _cells(seg, method)


# -- Bresenham ---------------------------------------------------------------------------------------


@settings(max_examples=250, deadline=None)
@given(segments())
@example((0.5, 0.5, 2.5, 2.5))
@example((-3.2, 1.7, 6.9, -2.4))
@example((0.0, 0.0, 0.0, 0.0))
def test_bresenham_properties(seg: Segment) -> None:
    """Bresenham: start cell to end cell, 8-connected, no repeats, max(|di|, |dj|) + 1 cells, one step
    along the major axis each time, and every cell within half a cell of the ideal line between the
    start and end cell indices (the classic line)."""
    got = _cells(seg, BRESENHAM)
    x0, y0, x1, y1 = seg
    i0, j0 = math.floor(x0), math.floor(y0)
    i1, j1 = math.floor(x1), math.floor(y1)
    di, dj = i1 - i0, j1 - j0
    assert got[0] == (i0, j0)
    assert got[-1] == (i1, j1)
    assert len(got) == max(abs(di), abs(dj)) + 1
    assert len(got) == cell_count(*seg, BRESENHAM)
    assert len(set(got)) == len(got)
    for (ia, ja), (ib, jb) in zip(got, got[1:], strict=False):
        assert max(abs(ia - ib), abs(ja - jb)) == 1, f"not 8-connected: ({ia}, {ja}) -> ({ib}, {jb})"
    if abs(di) >= abs(dj) and di != 0:
        for k, (i, j) in enumerate(got):
            assert i == i0 + k * (1 if di > 0 else -1)
            assert abs(j - (j0 + (i - i0) * dj / di)) <= 0.5 + 1e-12
    elif dj != 0:
        for k, (i, j) in enumerate(got):
            assert j == j0 + k * (1 if dj > 0 else -1)
            assert abs(i - (i0 + (j - j0) * di / dj)) <= 0.5 + 1e-12


# -- the per-scan trace: the union of the beams' walks --------------------------------------------------


def _planned_cells(scan: Scan, config: MapConfig, shift: int) -> list[tuple[tuple[int, int], int]]:
    """The per-scan plan's cells as global (i, j) with their kind, in the plan's order."""
    plan = plan_scan(scan, config, shift)
    local = (1 << (2 * shift)) - 1
    mask = (1 << shift) - 1
    out = []
    runs = [(c + x, 1) for c, n in zip(*plan.runs.tolist(), strict=True) for x in range(n)]
    for c, k in list(zip(plan.cell.tolist(), plan.kind.tolist(), strict=True)) + runs:
        tile, pos = c >> (2 * shift), c & local
        i = (int(plan.tiles[0, tile]) << shift) + (pos & mask)
        j = (int(plan.tiles[1, tile]) << shift) + (pos >> shift)
        out.append(((i, j), k))
    return out


def _union_of_walks(scan: Scan, config: MapConfig) -> list[tuple[tuple[int, int], int]]:
    """What per-scan semantics mean, beam by beam with `segment_cells`: every cell of every traced
    beam once, in first-visit order, a hit (2) if any return ends in it (a hit beats a miss).

    A beam's direction is computed as the engine defines it (`scan_rays`: the bearing's cosine and
    sine rotated by the heading), so that end points on cell boundaries, which these tests seek
    out, land in the same cell; `test_scan_rays_directions` checks that definition against
    cos(theta + a)."""
    res = config.resolution
    method = EXACT if config.traversal == "exact" else BRESENHAM
    ox, oy = scan.pose.x / res, scan.pose.y / res
    cos_t, sin_t = math.cos(scan.pose.theta), math.sin(scan.pose.theta)
    first: dict[tuple[int, int], int] = {}
    for a, r in zip(scan.angles.tolist(), scan.ranges.tolist(), strict=True):
        if math.isnan(r) or r < scan.range_min:
            continue
        hit = r < scan.range_max
        if not hit:
            if config.no_return_range <= 0:
                continue
            r = config.no_return_range
        cos_a, sin_a = math.cos(a), math.sin(a)
        dx, dy = cos_t * cos_a - sin_t * sin_a, sin_t * cos_a + cos_t * sin_a
        x1, y1 = ox + r / res * dx, oy + r / res * dy
        path = [(int(i), int(j)) for i, j in segment_cells(ox, oy, x1, y1, method)]
        for c in path:
            first.setdefault(c, 1)
        if hit:
            first[path[-1]] = 3
    return list(first.items())


def test_scan_rays_directions() -> None:
    """A beam's direction is its bearing's (cos, sin) rotated by the heading: within a few ulps of
    cos(theta + a) and sin(theta + a), exactly libm's cos(a) and sin(a) at heading 0, and the same
    bits whatever beam layout `scan_rays` is handed (its own, another with the same first and last
    bearings, a shorter one, none)."""
    rng = np.random.default_rng(5)
    angles = np.sort(rng.uniform(-2.3, 2.3, 60))
    ranges = rng.uniform(0.5, 20.0, 60)
    other = angles.copy()
    other[10:20] += 1e-3  # the same cache key (size, first, last), other bearings in between
    layouts = [beam_layout(angles), beam_layout(other), beam_layout(angles[:7]), np.empty((3, 0))]
    for theta in (0.0, 0.7, -2.9, math.pi):
        beams = [
            scan_rays(1.0, -2.0, theta, angles, layout, ranges, 0.0, 30.0, 0.0, 0.05) for layout in layouts
        ]
        for got in beams[1:]:
            assert np.array_equal(got[0], beams[0][0])  # rows cos, sin, ex, ey
            assert np.array_equal(got[1], beams[0][1])  # kinds
        cos, sin = beams[0][0][0], beams[0][0][1]
        assert np.max(np.abs(cos - np.cos(theta + angles))) < 1e-15
        assert np.max(np.abs(sin - np.sin(theta + angles))) < 1e-15
        if theta == 0.0:
            assert cos.tolist() == [math.cos(a) for a in angles.tolist()]
            assert sin.tolist() == [math.sin(a) for a in angles.tolist()]


def test_plans_do_not_depend_on_the_cached_beam_layouts() -> None:
    """Scans whose bearings share the layout cache's key (beam count, first and last bearing) but
    differ in between plan exactly as they do with an empty cache."""
    config = MapConfig(resolution=0.05, layers=["occupancy"])
    angles = np.linspace(-2.0, 2.0, 200)
    other = angles.copy()
    other[50:150] += 0.01
    ranges = np.linspace(2.0, 9.0, 200)
    scans = [Scan.from_angles((0.3, -1.2, 0.8), a, ranges, 0.0, 30.0) for a in (angles, other)]
    alone = []
    for scan in scans:
        update_plan._layouts.clear()
        alone.append(_planned_cells(scan, config, 8))
    update_plan._layouts.clear()
    after_each_other = [_planned_cells(scan, config, 8) for scan in scans]
    assert len(update_plan._layouts) == 1  # both scans used one cached layout
    assert alone[0] != alone[1]
    assert after_each_other == alone


def _same_cells(got: list[tuple[tuple[int, int], int]], want: list[tuple[tuple[int, int], int]]) -> bool:
    """The same cells with the same kinds, each once (per-scan updates do not depend on order)."""
    return len(got) == len(set(c for c, _ in got)) and dict(got) == dict(want)


@settings(max_examples=80, deadline=None)
@given(
    pose=st.tuples(st.floats(-30, 30), st.floats(-30, 30), st.floats(-math.pi, math.pi)),
    beams=st.lists(st.tuples(st.floats(-math.pi, math.pi), st.floats(0.0, 1200.0)), min_size=1, max_size=40),
    traversal=st.sampled_from(["exact", "bresenham"]),
    tile_size=st.sampled_from([64, 256]),
    clear=st.sampled_from([0.0, 3.0, 900.0]),
)
def test_per_scan_trace_is_the_union_of_the_walks(
    pose: tuple[float, float, float],
    beams: list[tuple[float, float]],
    traversal: str,
    tile_size: int,
    clear: float,
) -> None:
    """`trace_scan` (a dense window for compact scans, per-tile planes when the box is too large for
    one: here beams up to 1.2 km at 5 cm) yields exactly the union of the beams' own walks, each
    cell once, with hits beating misses, and no-return beams (range >= 1000 m) cleared to
    `clear` metres when that is set."""
    angles, ranges = zip(*beams, strict=True)
    scan = Scan.from_angles(pose, list(angles), list(ranges), range_min=0.02, range_max=1000.0)
    config = MapConfig(
        resolution=0.05, tile_size=tile_size, layers=["occupancy"], traversal=traversal, no_return_range=clear
    )
    assert _same_cells(
        _planned_cells(scan, config, tile_size.bit_length() - 1), _union_of_walks(scan, config)
    )


def test_per_scan_trace_of_a_very_wide_scan() -> None:
    """Two 900 m beams in opposite directions span 36,000 cells: too wide for the dense window
    (rows of 2**16 cells x 256 = 2**24 > DENSE_WINDOW_CELLS), so the per-tile planes serve; a short
    fan beside them shares cells. The result is still the union of the walks."""
    angles = [0.0, math.pi, 0.3, 0.31, 0.32, 1.9]
    ranges = [900.0, 900.0, 4.0, 4.0, 4.0, 2.5]
    scan = Scan.from_angles((0.37, -0.11, 0.2), angles, ranges, range_min=0.0, range_max=1000.0)
    config = MapConfig(resolution=0.05, layers=["occupancy"])
    got = _planned_cells(scan, config, 8)
    assert _same_cells(got, _union_of_walks(scan, config))
    assert len(got) > 36_000
    # The same box with the beams in angle order: the row trace takes it, rows all the way (no
    # dense window to hand far rows to).
    ordered = Scan.from_angles(
        (0.37, -0.11, 0.2), [0.0, 0.3, 0.31, 0.32, 1.9, math.pi], [900.0, 4.0, 4.0, 4.0, 2.5, 900.0],
        range_min=0.0, range_max=1000.0,
    )  # fmt: skip
    assert _row_trace(ordered) > 36_000
    assert _same_cells(_planned_cells(ordered, config, 8), _union_of_walks(ordered, config))


@settings(max_examples=60, deadline=None)
@given(
    pose=st.tuples(st.floats(-20, 20), st.floats(-20, 20), st.floats(-math.pi, math.pi)),
    beams=st.integers(50, 1200),
    fov=st.floats(0.5, 2 * math.pi),
    ranges=st.lists(st.floats(0.05, 12.0), min_size=4, max_size=4),
    gaps=st.sets(st.integers(0, 1199), max_size=30),
    clear=st.sampled_from([0.0, 6.0]),
    data=st.data(),
)
def test_dense_fans_trace_exactly_the_union_of_the_walks(
    pose: tuple[float, float, float],
    beams: int,
    fov: float,
    ranges: list[float],
    gaps: set[int],
    clear: float,
    data: st.DataObject,
) -> None:
    """Dense fans, which `fan_rows` traces row by row with chains of neighbouring beams and hands
    back to walks far out: the trace is still exactly the union of every beam's whole walk. Ranges
    vary smoothly with random jumps (walls, doorways); some beams are missing (NaN) or have no
    return."""
    k = np.arange(beams)
    base = np.interp(k, np.linspace(0, beams - 1, 4), ranges)
    jumps = data.draw(st.lists(st.integers(0, beams - 1), max_size=8))
    r = base.copy()
    for at in jumps:
        r[at:] *= 0.5 if at % 2 else 1.7
    r[[g for g in gaps if g < beams and g % 3 == 0]] = np.nan
    r[[g for g in gaps if g < beams and g % 3 == 1]] = np.inf
    scan = Scan.from_angles(pose, list(-fov / 2 + fov * k / beams), list(r), range_min=0.02, range_max=30.0)
    config = MapConfig(resolution=0.05, layers=["occupancy"], no_return_range=clear)
    assert _same_cells(_planned_cells(scan, config, 8), _union_of_walks(scan, config))


@settings(max_examples=60, deadline=None)
@given(
    cell=st.tuples(st.integers(-40, 40), st.integers(-40, 40)),
    offset=st.sampled_from([0.0, 1e-12, 1e-4, 0.004, 0.5, 0.996, 0.9999, 1 - 1e-12]),
    beams=st.integers(3, 700),
    fov=st.floats(0.3, 2 * math.pi),
    theta=st.sampled_from([0.0, math.pi / 2, math.pi, -math.pi / 4, 2.9]),
    ranges=st.lists(st.floats(0.05, 9.0), min_size=3, max_size=3),
    repeat=st.integers(1, 3),
)
def test_fans_from_degenerate_poses_trace_the_union_of_the_walks(
    cell: tuple[int, int],
    offset: float,
    beams: int,
    fov: float,
    theta: float,
    ranges: list[float],
    repeat: int,
) -> None:
    """The row trace's rounding guards: sensors exactly on a cell corner or within 1e-12 of a row
    line, beams exactly along the axes, and every beam repeated (equal directions) still give
    exactly the union of the walks."""
    res = 0.05
    pose = ((cell[0] + offset) * res, (cell[1] + 1 - offset) * res, theta)
    k = np.arange(beams)
    angles = np.repeat(-fov / 2 + fov * k / beams, repeat)
    r = np.repeat(np.interp(k, np.linspace(0, beams - 1, 3), ranges), repeat)
    scan = Scan.from_angles(pose, angles, r, range_min=0.0, range_max=30.0)
    config = MapConfig(resolution=res, layers=["occupancy"])
    assert _same_cells(_planned_cells(scan, config, 6), _union_of_walks(scan, config))


def _row_trace(scan: Scan) -> int:
    """`trace_fan_rows`'s cell count for a scan at 5 cm in 256-cell tiles (-1: not traced by rows),
    rows all the way (no hand-back to walks)."""
    # The scan's box, as the engine takes it.
    ox, oy, ex, ey, kinds, ti0, tj0, ti1, tj1 = ray_trace_inputs(scan, 0.0, 0.05, 8)
    ni, nj = ti1 - ti0 + 1, tj1 - tj0 + 1
    size = 1 << 20
    found, kind, planes = np.empty(size, np.int64), np.empty(size, np.uint8), np.zeros(ni * nj, np.uint8)
    run_key, run_len = np.empty(size, np.int64), np.empty(size, np.int64)
    n, r, _ = trace_fan_rows(
        ox,
        oy,
        ex,
        ey,
        kinds,
        *exact_starts(np.full(ex.size, ox), np.full(ex.size, oy), ex, ey),
        8,
        ti0,
        tj0,
        ni,
        found,
        kind,
        run_key,
        run_len,
        planes,
        np.empty((0, 3), np.int64),
    )
    return n if n < 0 else n + int(run_len[:r].sum())


def test_row_trace_takes_fans_in_angle_order_and_leaves_the_rest_to_walks() -> None:
    """Fans in angle order (either way round, wrapping past +-pi) are traced by rows; a scan whose
    beams jump back and forth in direction is not (the caller walks it), and both give the union."""
    k = np.arange(540)
    fan = Scan.from_angles((1.0, 2.0, 2.8), -2.3 + 4.6 * k / 540, np.full(540, 6.0), range_max=30.0)
    reverse = Scan.from_angles((1.0, 2.0, -3.1), 2.3 - 4.6 * k / 540, np.full(540, 6.0), range_max=30.0)
    jumbled = np.random.default_rng(1).permutation(-2.3 + 4.6 * k / 540)
    shuffled = Scan.from_angles((1.0, 2.0, 0.3), jumbled, np.full(540, 6.0), range_max=30.0)
    assert _row_trace(fan) > 0
    assert _row_trace(reverse) > 0
    assert _row_trace(shuffled) == -1
    config = MapConfig(resolution=0.05, layers=["occupancy"])
    for scan in (fan, reverse, shuffled):
        assert _same_cells(_planned_cells(scan, config, 8), _union_of_walks(scan, config))


@settings(max_examples=300, deadline=None)
@given(
    origin=st.tuples(coord, coord),
    offset=st.sampled_from([0.0, 1e-12, 0.5, 1 - 1e-12, 0.3]),
    far=st.sampled_from([1.0, 1e3, 1e6]),
    ends=st.lists(st.tuples(coord, coord), min_size=1, max_size=40),
    axis=st.sampled_from(["none", "vertical", "horizontal", "diagonal"]),
)
def test_end_row_entries_are_the_walks_entry_columns(
    origin: Point, offset: float, far: float, ends: list[Point], axis: str
) -> None:
    """`end_row_entries` (branch-free, so that it vectorises) gives, for every beam that ends above or
    below the sensor's row, the column where its exact walk enters its end row: `exit_column` at the
    crossing of the row before, as computed beam by beam. Sensors on and near cell corners, beams
    along the axes and diagonals, and end points up to 10**6 cells out."""
    from fleetmap.kernels.fan_rows import end_row_entries, exit_column
    from fleetmap.kernels.traversal import crossing, exact_start

    ox, oy = origin[0] + offset, origin[1] - offset
    ex = np.array([ox + (x - ox) * far for x, _ in ends])
    ey = np.array([oy + (y - oy) * far for _, y in ends])
    if axis == "vertical":
        ex[::2] = ox
    elif axis == "horizontal":
        ey[::2] = oy
    elif axis == "diagonal":
        ey[::2] = oy + (ex[::2] - ox)
    nb = ex.size
    kinds = np.ones(nb, dtype=np.uint8)
    kinds[1::7] = 0  # skipped beams: their state is not computed and must not be used
    j0 = math.floor(oy)
    state = [np.zeros(nb, dtype=np.int64) for _ in range(3)] + [np.zeros(nb) for _ in range(4)]
    ie, je, step_i, base_x, scale_x, base_y, scale_y = state
    for b in range(nb):
        if kinds[b]:
            _, _, ie[b], je[b], step_i[b], _, base_x[b], scale_x[b], base_y[b], scale_y[b] = exact_start(
                ox, oy, ex[b], ey[b]
            )
    got = end_row_entries(ox, ex, kinds, j0, ie, je, step_i, base_x, scale_x, base_y, scale_y)
    for b in range(nb):
        if kinds[b] and je[b] != j0:
            t = crossing(je[b] - (1 if je[b] > j0 else -1), base_y[b], scale_y[b])
            want = exit_column(math.floor(ox), ie[b], step_i[b], base_x[b], scale_x[b], t)
            assert got[b] == want, (b, ex[b], ey[b])
            # ... and it is where the walk itself is when it first reaches that row.
            if far == 1.0:
                walk = [c for c in cells(ox, oy, ex[b], ey[b], EXACT) if c[1] == je[b]]
                assert walk[0][0] == want
