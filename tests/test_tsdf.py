"""Tests of the TSDF layer: band selection, the weighted running average, max_weight capping and the
sub-cell zero-crossing surface.

For a cell on a beam at distance d (its centre projected on the beam) and a measured range z:
sdf = z - d, tsdf = clamp(sdf / t, -1, 1); cells with |sdf| <= t are fused with
D <- (W*D + tsdf) / (W + 1), W <- min(W + 1, max_weight).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from fleetmap.config import STORED_CONFIG, MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan

RES = 0.25
#: The centre of cell (0, 0): a beam along +x from here passes through every cell centre of row 0,
#: and cell i's centre is at distance exactly i cells (i / 4 m).
SENSOR = (0.125, 0.125)


def tsdf_map(truncation: float = 0.5, max_weight: float = 1000.0, resolution: float = RES) -> GridMap:
    return GridMap(
        MapConfig(
            resolution=resolution,
            layers=["tsdf"],
            tsdf={"truncation": truncation, "max_weight": max_weight},
        )
    )


def along_x(m: GridMap, *ranges: float) -> None:
    """Integrate one scan per range: a single beam along +x from SENSOR."""
    for r in ranges:
        m.integrate(Scan.from_angles((*SENSOR, 0.0), [0.0], [r]))


def observed(m: GridMap, window: int = 40) -> dict[tuple[int, int], tuple[float, float]]:
    """(tsdf, weight) of every observed cell in [-window, window)^2."""
    d = m.region("tsdf", -window, -window, window, window)
    w = m.region("tsdf_weight", -window, -window, window, window)
    jj, ii = np.nonzero(w > 0)
    assert np.array_equal(np.isnan(d), w <= 0), "tsdf must be NaN exactly where the weight is 0"
    return {
        (int(i) - window, int(j) - window): (float(d[j, i]), float(w[j, i]))
        for i, j in zip(ii, jj, strict=True)
    }


def test_single_measurement_band_values() -> None:
    """z = 9 cells (2.25 m), t = 2 cells: cells 7..11 get (9 - i) / 2 = 1, 0.5, 0, -0.5, -1, each with
    weight 1 (|sdf| = t is inside the band); nothing else is observed."""
    m = tsdf_map()
    along_x(m, 2.25)
    assert observed(m) == {(7, 0): (1.0, 1.0), (8, 0): (0.5, 1.0), (9, 0): (0.0, 1.0),
                           (10, 0): (-0.5, 1.0), (11, 0): (-1.0, 1.0)}  # fmt: skip
    # The tsdf is exactly 0 at cell 9's centre: the surface is that centre, the return point.
    np.testing.assert_allclose(m.surface(0, -2, 20, 2), [[0.125 + 2.25, 0.125]], atol=1e-9)


def test_fusion_of_three_measurements_by_hand() -> None:
    """Three scans, z = 8.5, 9 and 8 cells (t = 2 cells). Per cell i the samples are (z - i) / 2 for
    |z - i| <= 2:
        z = 8.5: cells 7..10 -> 0.75, 0.25, -0.25, -0.75 (cell 6: sdf 2.5 and cell 11: -2.5, outside)
        z = 9:   cells 7..11 -> 1, 0.5, 0, -0.5, -1
        z = 8:   cells 6..10 -> 1, 0.5, 0, -0.5, -1
    so after the first two scans cells 7..10 hold (0.75+1)/2 = 0.875, 0.375, -0.125, -0.625 with
    weight 2 and cell 11 holds -1 with weight 1, and after all three
    cell 6: 1 (W 1), 7: (0.75+1+0.5)/3 = 0.75, 8: 0.25, 9: -0.25, 10: -0.75 (W 3), 11: -1 (W 1)."""
    m = tsdf_map()
    along_x(m, 2.125)
    assert observed(m) == {(7, 0): (0.75, 1.0), (8, 0): (0.25, 1.0), (9, 0): (-0.25, 1.0),
                           (10, 0): (-0.75, 1.0)}  # fmt: skip
    along_x(m, 2.25)
    assert observed(m) == {(7, 0): (0.875, 2.0), (8, 0): (0.375, 2.0), (9, 0): (-0.125, 2.0),
                           (10, 0): (-0.625, 2.0), (11, 0): (-1.0, 1.0)}  # fmt: skip
    along_x(m, 2.0)
    got = observed(m)
    expected = {(6, 0): (1.0, 1.0), (7, 0): (0.75, 3.0), (8, 0): (0.25, 3.0), (9, 0): (-0.25, 3.0),
                (10, 0): (-0.75, 3.0), (11, 0): (-1.0, 1.0)}  # fmt: skip
    assert got.keys() == expected.keys()
    for cell, (d, w) in expected.items():
        assert got[cell][0] == pytest.approx(d, abs=1e-6)
        assert got[cell][1] == w


def test_max_weight_caps_the_weight() -> None:
    """max_weight 2: cell 9 gets samples 0, 0 (z = 9) then -0.5, -0.5 (z = 8). The weight stops at 2,
    so the third sample gives (2*0 - 0.5)/3 = -1/6 and the fourth (2*(-1/6) - 0.5)/3 = -5/18, not
    the plain mean -0.25; cell 8 (samples 0.5, 0.5, 0, 0) ends at 2/9."""
    m = tsdf_map(max_weight=2.0)
    along_x(m, 2.25, 2.25)
    assert observed(m)[(9, 0)] == (0.0, 2.0)
    along_x(m, 2.0)
    assert observed(m)[(9, 0)][0] == pytest.approx(-1 / 6, abs=1e-6)
    along_x(m, 2.0)
    got = observed(m)
    assert got[(9, 0)][0] == pytest.approx(-5 / 18, abs=1e-6)
    assert got[(9, 0)][1] == 2.0
    assert got[(8, 0)][0] == pytest.approx(2 / 9, abs=1e-6)
    assert got[(6, 0)] == (1.0, 2.0)  # two samples of 1 from z = 8: weight 2


def test_a_weight_cap_that_float32_weights_round_to_zero_is_refused() -> None:
    """Weights are float32, and a weight of 0 means never observed: with max_weight 1e-50 (positive,
    so accepted) every fused cell's weight became 0, and the TSDF layer of the map never observed a
    cell, scan after scan. Refused now, naming the field; the smallest cap a float32 holds is
    accepted, and a stored map keeps its configuration."""
    stored = MapConfig.model_validate(
        {"resolution": RES, "layers": ["tsdf"], "tsdf": {"max_weight": 1e-50}}, context={STORED_CONFIG: True}
    )
    m = GridMap(stored)
    along_x(m, 2.25)
    assert m.known_bounds() is None  # what the refusal prevents
    with pytest.raises(
        ValidationError, match=r"max_weight 1e-50 is 0 as a cell's weight is stored \(float32\)"
    ):
        MapConfig.model_validate({"layers": ["tsdf"], "tsdf": {"max_weight": 1e-50}})
    tiny = tsdf_map(max_weight=float(np.nextafter(np.float32(0), np.float32(1))))
    along_x(tiny, 2.25)
    assert tiny.known_bounds() is not None


def test_a_truncation_of_no_cells_is_refused() -> None:
    """Scans divide by the truncation in cells (`truncation / resolution`): 5e-324 m at 100 m per cell
    is 0 there (the division underflows), and every scan with a return failed with "internal error:
    division by zero" (a 422 counted against the robot, a traceback in the log), on a map its
    configuration had been accepted for. Refused now, naming the field; the smallest truncation
    that is a positive number of cells at that resolution integrates."""
    with pytest.raises(ValidationError, match=r"truncation 4.94066e-324 m is 0 cells at resolution 100 m"):
        MapConfig.model_validate({"resolution": 100.0, "layers": ["tsdf"], "tsdf": {"truncation": 5e-324}})
    truncation = 5e-324
    while truncation / 100.0 == 0:
        truncation = float(np.nextafter(truncation, 1.0))
    m = tsdf_map(truncation=truncation, resolution=100.0)
    # A return exactly at the centre of cell 2 (sdf 0): the one cell a band this narrow can hold.
    m.integrate(Scan.from_angles((50.0, 50.0, 0.0), [0.0], [200.0], 0.0, 1e4))
    assert observed(m) == {(2, 0): (0.0, 1.0)}


@pytest.mark.parametrize("layers", [["tsdf"], ["occupancy", "tsdf"]])
def test_a_scan_that_changes_no_cell_changes_no_tile_version(layers: list[str]) -> None:
    """Cells at their weight cap fused with the values they hold do not change, so a scan that
    changes nothing else (the occupancy layer clamped) leaves every tile's version as it was and
    reports no changed tile, as a tile's version promises. The fusion flagged every tile it wrote,
    so a parked robot's map changed versions at every scan (with the TSDF alone, by plan and apply,
    and with the occupancy layer, in the one-call integration)."""
    m = GridMap(
        MapConfig(resolution=RES, layers=layers, tsdf={"truncation": 0.5, "max_weight": 1.0})  # type: ignore[arg-type]
    )
    scan = Scan.from_angles((*SENSOR, 0.0), [0.0, 0.3, -0.4], [2.25, 1.7, 3.1])
    for _ in range(12):  # octomap's clamp takes 5 hits and 5 misses; a weight cap of 1, one scan
        m.integrate(scan)
    versions = {key: m.store.version(key) for key in m.store.slots}
    before = observed(m)
    result = m.integrate(scan)
    assert observed(m) == before
    assert result.changed_tiles == []
    assert {key: m.store.version(key) for key in m.store.slots} == versions


def test_each_beam_is_one_sample() -> None:
    """Two identical beams in one scan are two samples (w = 1 each); no-return, NaN and below
    range_min beams add none."""
    m = tsdf_map()
    ranges = [2.25, 2.25, math.inf, math.nan, 0.01]
    m.integrate(Scan.from_angles((*SENSOR, 0.0), [0.0] * 5, ranges, range_min=0.05))
    got = observed(m)
    assert got.keys() == {(k, 0) for k in range(7, 12)}
    assert got[(9, 0)] == (0.0, 2.0)


def test_a_tsdf_only_map_ignores_its_no_return_range() -> None:
    """No-return beams add nothing to the TSDF, and a map without a cell layer clears no cells, so its
    `no_return_range` changes nothing: a scan is fused as with none. It was counted in the scan's
    extent: at 0.01 m in tiles of 16 cells, clearing 100 m (1250 tiles each way) made every scan
    with a no-return beam "span too large an area" and be refused."""
    angles = np.linspace(-3.0, 3.0, 61)
    ranges = np.where(np.arange(61) % 2 == 0, 3.0, math.inf)  # every other beam returns nothing
    scan = Scan.from_angles((0.31, -0.27, 0.4), angles, ranges)
    maps = [
        GridMap(MapConfig(resolution=0.01, tile_size=16, layers=["tsdf"], no_return_range=clear))
        for clear in (0.0, 100.0)
    ]
    for m in maps:
        assert m.integrate(scan).tsdf_updates > 0
    want, got = (observed(m, window=400) for m in maps)
    assert got == want and len(got) > 500


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-3, 3),
    y=st.floats(-3, 3),
    angle=st.floats(-math.pi, math.pi),
    z=st.floats(0.05, 4.0),
    t=st.floats(0.05, 0.6),
)
def test_oblique_beam_band(x: float, y: float, angle: float, z: float, t: float) -> None:
    """One oblique beam: every observed cell has |sdf| <= t for its centre projected on the beam and
    holds clamp(sdf / t, -1, 1); every cell the beam crosses inside the band [z - t, z + t] whose
    centre is inside the band is observed."""
    m = tsdf_map(truncation=t, resolution=0.1)
    m.integrate(Scan.from_angles((x, y, 0.0), [angle], [z]))
    res = 0.1
    c, s = math.cos(angle), math.sin(angle)

    def sdf(i: int, j: int) -> float:
        return z - (((i + 0.5) * res - x) * c + ((j + 0.5) * res - y) * s)

    got = observed(m, window=80)
    assert got, "a return must observe at least one cell"
    for (i, j), (d, w) in got.items():
        assert abs(sdf(i, j)) <= t + 1e-9
        assert d == pytest.approx(max(-1.0, min(1.0, sdf(i, j) / t)), abs=1e-5)
        assert w == 1.0
    d0, d1 = max(z - t, 0.0), z + t
    for k in range(501):
        d = d0 + (d1 - d0) * k / 500
        px, py = (x + d * c) / res, (y + d * s) / res
        if abs(px - round(px)) < 1e-6 or abs(py - round(py)) < 1e-6:
            continue
        cell = (math.floor(px), math.floor(py))
        if abs(sdf(*cell)) <= t - 1e-9:
            assert cell in got, f"cell {cell} crossed inside the band is not observed"


def _wall_scan(wall: float, ox: float, oy: float, vertical: bool, span: float = 0.4) -> Scan:
    """A fan of beams from (ox, oy) onto the straight wall x = wall (vertical) or y = wall."""
    angles = np.arange(-span, span + 1e-9, 0.005)
    toward = wall > (ox if vertical else oy)
    heading = (0.0 if toward else math.pi) if vertical else (math.pi / 2 if toward else -math.pi / 2)
    dist = abs(wall - (ox if vertical else oy))
    return Scan.from_angles((ox, oy, heading), angles, dist / np.cos(angles))


@pytest.mark.parametrize(
    ("wall", "ox", "oy", "vertical"),
    [
        (2.03, 0.01, 0.02, True),
        (-1.777, 0.3, -0.45, True),
        (1.57, -0.33, 0.02, False),
        (-2.345, -0.33, 0.02, False),
    ],
)
def test_surface_finds_straight_wall(wall: float, ox: float, oy: float, vertical: bool) -> None:
    """A fan of beams onto a straight wall (not on a cell boundary or centre): surface() returns one
    zero crossing per row (column) the wall spans, each within a quarter cell of the wall, on
    average within 5% of a cell: sub-cell accuracy from the linear interpolation."""
    res = 0.1
    m = tsdf_map(truncation=0.2, resolution=res)
    m.integrate(_wall_scan(wall, ox, oy, vertical))
    pts = m.surface(-60, -60, 60, 60)
    assert pts.shape[1] == 2
    across, along = (pts[:, 0], pts[:, 1]) if vertical else (pts[:, 1], pts[:, 0])
    err = np.abs(across - wall)
    assert err.max() < 0.25 * res
    assert err.mean() < 0.05 * res
    # The wall spans +-tan(0.4) * distance around the sensor's foot on it: one point per cell there.
    centre = oy if vertical else ox
    half = abs(wall - (ox if vertical else oy)) * math.tan(0.4)
    lo_cell, hi_cell = math.floor((centre - half) / res), math.floor((centre + half) / res)
    assert len(pts) == hi_cell - lo_cell + 1
    assert sorted(np.floor(along / res + 1e-9).astype(int).tolist()) == list(range(lo_cell, hi_cell + 1))
    # Cells are never snapped to the grid: the crossing is interpolated between cell centres.
    cells = across / res - 0.5
    assert np.all(np.abs(cells - np.round(cells)) > 1e-6)


def test_surface_interpolates_between_two_cells() -> None:
    """Along the +x beam of z = 8.7 cells (t = 2 cells) the values at cells 8 and 9 are 0.35 and -0.15:
    the zero crossing is at centre 8.5 + 0.35 / 0.5 = 9.2 cells = 2.3 m, y at the row centre."""
    m = tsdf_map()
    along_x(m, 8.7 * RES)
    pts = m.surface(-10, -10, 20, 10)
    assert pts.shape == (1, 2)
    assert pts[0] == pytest.approx([9.2 * RES, 0.5 * RES], abs=1e-6)
    assert m.surface(100, 100, 120, 120).shape == (0, 2)


@pytest.mark.parametrize("wall", [1.0, 0.97, 1.03, -1.5, 1.049])
@pytest.mark.parametrize("vertical", [True, False])
def test_windows_side_by_side_share_out_the_surface(wall: float, vertical: bool) -> None:
    """Each surface point belongs to the window it lies in: the surfaces of two windows side by side
    are, together, the surface of the window they make, each point in one of them. A wall at x = 1.0
    m (a cell edge at 0.1 m) lies between cells 9 and 10: the windows of cells 0..9 and 10..19 each
    found no crossing (one cell of each pair lay outside), though the wall lies in both, so a map read
    in windows (a big one must be: 413 past 16 Mi cells) lost every point along their seams."""
    res = 0.1
    m = tsdf_map(truncation=0.3, resolution=res)
    m.integrate(_wall_scan(wall, 0.01, 0.02, vertical))
    m.integrate(_wall_scan(wall, -0.23, -0.31, vertical))
    seam = math.floor(wall / res + 0.5)  # the cell edge nearest the wall: windows meet there

    def surface(lo: int, hi: int) -> np.ndarray:
        return m.surface(lo, -40, hi, 40) if vertical else m.surface(-40, lo, 40, hi)

    whole = surface(seam - 20, seam + 20)
    across = whole[:, 0 if vertical else 1]
    assert len(whole) > 10 and np.abs(across - wall).max() < 0.25 * res
    below, above = surface(seam - 20, seam), surface(seam, seam + 20)
    assert len(below) + len(above) == len(whole)
    both = np.concatenate([below, above])
    np.testing.assert_allclose(
        sorted(map(tuple, both.tolist())), sorted(map(tuple, whole.tolist())), atol=1e-9
    )
    # Each point is in the window it was found in: [seam - 20, seam) or [seam, seam + 20) cells.
    assert (below[:, 0 if vertical else 1] < seam * res + 1e-9).all()
    assert (above[:, 0 if vertical else 1] >= seam * res - 1e-9).all()
    # And every window's points lie in it, whatever edge it has: here one cell around the wall.
    for lo in range(seam - 2, seam + 1):
        for p in surface(lo, lo + 1):
            assert lo * res - 1e-9 <= p[0 if vertical else 1] <= (lo + 1) * res + 1e-9
