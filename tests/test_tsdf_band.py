"""The TSDF band kernels against their straightforward formulation.

`trace_tsdf` walks each beam's band with the end-of-axis tests out of the loop, writes every visited
cell and keeps it only when its centre is in the band, and sizes its output from a bound on the walk's
length instead of counting; `merge_tiles_in_box` trusts the box it is given; `fuse_tsdf` looks a
tile's slot up and flags it once per run of entries. Each shortcut must give exactly what the plain
version gives: the same cells in the same order with the same float32 values, the same tile numbers,
the same pools and change flags.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetmap.config import MAX_BAND_CELLS
from fleetmap.datasets import load_dataset
from fleetmap.kernels.scan_geometry import beam_returns, scan_rays
from fleetmap.kernels.traversal import EXACT, cell_count, segment_cells
from fleetmap.kernels.tsdf import band_walk_bound, fuse_tsdf, trace_tsdf
from fleetmap.kernels.update import merge_tiles, merge_tiles_in_box
from fleetmap.update_plan import beam_layout_of

RES = 0.05


def plain_band(
    ox: float, oy: float, cos: np.ndarray, sin: np.ndarray, z: np.ndarray, trunc: float
) -> tuple[list[int], list[int], list[np.float32]]:
    """The band by its definition: every cell of the exact walk from max(z - t, 0) to z + t along
    the beam, kept when |z - (centre projected on the beam)| <= t, with clamp(sdf / t, -1, 1)."""
    ci: list[int] = []
    cj: list[int] = []
    value: list[np.float32] = []
    for c, s, zb in zip(cos.tolist(), sin.tolist(), z.tolist(), strict=True):
        d0, d1 = max(zb - trunc, 0.0), zb + trunc
        for i, j in segment_cells(ox + c * d0, oy + s * d0, ox + c * d1, oy + s * d1, EXACT).tolist():
            sdf = zb - ((i + 0.5 - ox) * c + (j + 0.5 - oy) * s)
            if abs(sdf) <= trunc:
                ci.append(i)
                cj.append(j)
                value.append(np.float32(min(1.0, max(-1.0, sdf / trunc))))
    return ci, cj, value


def assert_band_exact(
    ox: float, oy: float, cos: np.ndarray, sin: np.ndarray, z: np.ndarray, trunc: float
) -> int:
    ci, cj, value, box = trace_tsdf(ox, oy, cos, sin, z, trunc)
    want_i, want_j, want_value = plain_band(ox, oy, cos, sin, z, trunc)
    assert ci.tolist() == want_i
    assert cj.tolist() == want_j
    assert value.dtype == np.float32
    assert value.tolist() == [float(v) for v in want_value]  # bit for bit
    if ci.size:  # the box holds every cell, so merge_tiles_in_box may trust it
        assert box[0] <= ci.min() and ci.max() <= box[2]
        assert box[1] <= cj.min() and cj.max() <= box[3]
    return ci.size


def test_band_equals_its_definition_on_the_intel_log(datasets_dir: Path) -> None:
    """Every 7th scan of the Intel log, at the default truncation (4 cells), a narrow one and one
    wide one (35.5 cells)."""
    scans = list(load_dataset(datasets_dir / "intel-corrected.log.gz"))[::7]
    assert len(scans) > 100
    cells = 0
    for scan in scans:
        x, y, theta = scan.pose.x, scan.pose.y, scan.pose.theta
        layout = beam_layout_of(scan.angles)
        rays, kinds, *_ = scan_rays(
            x, y, theta, scan.angles, layout, scan.ranges, scan.range_min, scan.range_max, 0.0, RES
        )
        cos, sin, z = beam_returns(rays, kinds, scan.ranges, RES)
        for trunc in (4.0, 0.7, 35.5):
            cells += assert_band_exact(x / RES, y / RES, cos, sin, z, trunc)
    assert cells > 100_000


@settings(max_examples=150, deadline=None)
@given(
    ox=st.one_of(st.integers(-50, 50).map(float), st.floats(-1e6, 1e6)),
    oy=st.one_of(st.integers(-50, 50).map(float), st.floats(-1e6, 1e6)),
    angles=st.lists(
        st.one_of(
            st.floats(-math.pi, math.pi),
            st.sampled_from([0.0, math.pi / 4, math.pi / 2, -3 * math.pi / 4, math.pi]),  # diagonals, axes
        ),
        min_size=1,
        max_size=12,
    ),
    z=st.floats(0.0, 80.0),
    trunc=st.one_of(st.floats(0.01, 40.0), st.sampled_from([0.5, 1.0, 4.0, 32.0])),
)
def test_band_equals_its_definition_on_any_fan(
    ox: float, oy: float, angles: list[float], z: float, trunc: float
) -> None:
    """Sensors on grid vertices and far out, beams along the axes and the diagonals (where a walk
    visits the most cells for its length), returns shorter than the truncation (the band starts at
    the sensor), and narrow and wide truncations."""
    a = np.array(angles)
    ranges = np.full(a.size, z) * np.linspace(0.5, 1.0, a.size)
    assert_band_exact(ox, oy, np.cos(a), np.sin(a), ranges, trunc)


def test_band_keeps_cells_exactly_at_its_edges() -> None:
    """From a cell centre along the axes and the diagonals, returns and truncations in whole cells put
    cell centres exactly at |sdf| = t: those cells are in the band."""
    a = np.array([0.0, math.pi / 2, math.pi, -math.pi / 2, math.pi / 4])
    c, s = np.cos(a), np.sin(a)
    c[[1, 3]] = 0.0  # exactly along the axes
    s[[0, 2]] = 0.0
    for trunc in (1.0, 2.0, 4.0):
        ci, cj, value, _ = trace_tsdf(0.5, 0.5, c, s, np.full(5, 9.0), trunc)
        assert_band_exact(0.5, 0.5, c, s, np.full(5, 9.0), trunc)
        along_x = sorted(int(i) for i, j in zip(ci, cj, strict=True) if j == 0 and i > 0)
        assert along_x == list(range(9 - int(trunc), 10 + int(trunc)))
        assert {1.0, -1.0} <= set(value.tolist())


@settings(max_examples=300, deadline=None)
@given(
    x0=st.floats(-1e4, 1e4),
    y0=st.floats(-1e4, 1e4),
    angle=st.floats(-math.pi, math.pi),
    trunc=st.floats(0.0, float(MAX_BAND_CELLS)),
)
def test_band_walk_fits_the_bound(x0: float, y0: float, angle: float, trunc: float) -> None:
    """`trace_tsdf` reserves `band_walk_bound(t)` cells per beam without counting (numba does not
    check bounds, so a longer walk would write past the output): no band segment is longer."""
    c, s = math.cos(angle), math.sin(angle)
    for d0 in (0.0, 1.0 / 3.0, 1e3):
        n = cell_count(x0 + c * d0, y0 + s * d0, x0 + c * (d0 + 2 * trunc), y0 + s * (d0 + 2 * trunc), EXACT)
        assert n <= band_walk_bound(trunc)


def test_merge_in_box_equals_merge() -> None:
    """With the box `trace_tsdf` gives, the same tiles in the same order and the same tile numbers as
    `merge_tiles`, across tile boundaries and negative tiles, after tiles already in the plan."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        a = rng.uniform(-math.pi, math.pi, 40)
        ox, oy = rng.uniform(-600, 600, 2)
        ci, cj, _, box = trace_tsdf(ox, oy, np.cos(a), np.sin(a), rng.uniform(0, 500, 40), 6.0)
        before = np.array([[-3, 0, 2], [1, -1, 2]], dtype=np.int64)
        for shift in (4, 8):
            want = merge_tiles(before, ci, cj, shift)
            got = merge_tiles_in_box(before, ci, cj, shift, box)
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_fuse_flags_every_tile_it_writes() -> None:
    """Entries that come back to a tile after another one: each written tile flagged, no other, and
    the pools as the rule computed entry by entry gives them."""
    shift = 2  # 4 x 4 cells per tile
    ci = np.array([0, 1, 5, 6, 1, 2, 9], dtype=np.int64)
    cj = np.array([0, 0, 0, 0, 1, 1, 9], dtype=np.int64)
    value = np.array([0.5, -1.0, 0.25, 1.0, 0.0, 0.75, -0.5], dtype=np.float32)
    tile = np.array([0, 0, 1, 1, 0, 0, 3], dtype=np.int64)  # tile 2 of the plan gets no entry
    slots = np.array([3, 0, 1, 2], dtype=np.int64)
    tsdf = np.zeros((4, 4, 4), dtype=np.float32)  # as new tiles hold it: value 0, weight 0
    weight = np.zeros((4, 4, 4), dtype=np.float32)
    tsdf[3, 0, 0], weight[3, 0, 0] = 0.1, 2.0
    want_tsdf, want_weight = tsdf.copy(), weight.copy()
    for k in range(ci.size):
        at = (slots[tile[k]], cj[k] & 3, ci[k] & 3)
        w, d = float(want_weight[at]), float(want_tsdf[at])
        want_tsdf[at] = (w * d + float(value[k])) / (w + 1.0)
        want_weight[at] = min(w + 1.0, 1000.0)
    changed = np.zeros(4, dtype=np.uint8)
    assert fuse_tsdf(ci, cj, value, tile, slots, shift, tsdf, weight, 1000.0, changed) == ci.size
    assert changed.tolist() == [1, 1, 0, 1]
    np.testing.assert_array_equal(tsdf, want_tsdf)
    np.testing.assert_array_equal(weight, want_weight)
