"""Map tiles (fleetmap.tile_render, with tile_reduce, tile_colours, png and tile_cache): the Leaflet
CRS.Simple tile convention, pixel placement at every zoom (negative cell and tile indices included),
zoomed-out aggregation that keeps walls, colours of every layer, versions / ETags, and the
rendered-tile cache.

Maps are real GridMaps fed real Scans; PNGs are decoded with Pillow. The pixel a cell should land on
is computed here from the documented convention, independently of the module's code.
"""

from __future__ import annotations

import gc
import io
import math
import threading
import warnings
from concurrent.futures import Future
from fractions import Fraction

import numpy as np
import pytest
from PIL import Image

from fleetmap import tile_cache
from fleetmap.api.routes_data import region_pixels
from fleetmap.config import MapConfig, log_odds_to_probability
from fleetmap.export import Window, map_png
from fleetmap.grid_map import REGION_LAYERS, STATE_OCCUPIED, GridMap
from fleetmap.map_entry import MapEntry
from fleetmap.scan import Scan
from fleetmap.tile_cache import TileCache
from fleetmap.tile_render import (
    EMPTY_PNG,
    MAX_ZOOM,
    MIN_ZOOM,
    TILE_PX,
    TileError,
    render_tile,
    tile_version,
    tile_window,
)

RES = 0.05


def decode(png: bytes) -> np.ndarray:
    """(256, 256, 4) uint8 RGBA."""
    img = Image.open(io.BytesIO(png))
    assert img.size == (TILE_PX, TILE_PX)
    return np.asarray(img.convert("RGBA"))


def tiles_side(z: int) -> int:
    """Cells per tile side at zoom z, by the documented convention 256 / 2**z."""
    return int(256 / 2**z)


def where(i: int, j: int, z: int) -> tuple[int, int, slice, slice]:
    """Tile (x, y) and the pixel rows / columns that show cell (i, j) at zoom z, from the convention:
    tile (z, x, y) covers i in [x*S, (x+1)*S), j in [-(y+1)*S, -y*S); the top row is the highest j."""
    s = tiles_side(z)
    x, y = math.floor(i / s), -math.floor(j / s) - 1
    col = (i - x * s) * 2**z  # pixel coordinate of the cell's low-i edge
    row = (-y * s - 1 - j) * 2**z  # of its high-j edge, counted down from the top
    if z >= 0:
        k = 2**z
        return x, y, slice(int(row), int(row) + k), slice(int(col), int(col) + k)
    return x, y, slice(math.floor(row), math.floor(row) + 1), slice(math.floor(col), math.floor(col) + 1)


def centre(i: int, j: int) -> tuple[float, float]:
    return (i + 0.5) * RES, (j + 0.5) * RES


def beam_to(i: int, j: int, cells: int = 20, times: int = 5) -> list[Scan]:
    """Scans whose one beam runs along -x through `cells` free cells and returns in cell (i, j).
    Repeated `times` so the hit is clearly occupied and the traversed cells clearly free."""
    cx, cy = centre(i, j)
    scan = Scan.from_fan((cx + cells * RES, cy, math.pi), 0.0, 0.01, [cells * RES])
    return [scan] * times


def make_map(*scans: Scan, **config: object) -> GridMap:
    gmap = GridMap(MapConfig(resolution=RES, **config))  # type: ignore[arg-type]
    for scan in scans:
        gmap.integrate(scan)
    return gmap


HIT = (-300, -10)  # a cell at negative coordinates: x in [-15, -14.95), y in [-0.5, -0.45)


@pytest.fixture(scope="module")
def hit_map() -> GridMap:
    gmap = make_map(*beam_to(*HIT))
    state = gmap.cells(np.array([centre(*HIT), centre(HIT[0] + 1, HIT[1])]))["state"]
    assert state[0] == STATE_OCCUPIED and state[1] != STATE_OCCUPIED  # the premise of the tests below
    return gmap


# -- geometry --------------------------------------------------------------------------------------------


def test_tile_window_examples() -> None:
    assert tile_window(0, 0, 0) == (0, -256, 256, 0, 1)
    assert tile_window(0, -1, -1) == (-256, 0, 0, 256, 1)
    assert tile_window(0, -2, 0) == (-512, -256, -256, 0, 1)
    assert tile_window(2, 3, -2) == (192, 64, 256, 128, 1)
    assert tile_window(4, 1, 1) == (16, -32, 32, -16, 1)
    assert tile_window(-2, -1, 0) == (-1024, -1024, 0, 0, 4)
    assert tile_window(-8, 0, -1) == (0, 0, 65536, 65536, 256)


@pytest.mark.parametrize("z", range(MIN_ZOOM, MAX_ZOOM + 1))
def test_tiles_partition_the_plane(z: int) -> None:
    """Every cell is in exactly the tile the convention names, and neighbouring tiles abut."""
    s = tiles_side(z)
    rng = np.random.default_rng(z + 100)
    for i, j in rng.integers(-300_000, 300_000, size=(50, 2)).tolist():
        x, y, _, _ = where(i, j, z)
        i0, j0, i1, j1, step = tile_window(z, x, y)
        assert i0 <= i < i1 and j0 <= j < j1
        assert i1 - i0 == j1 - j0 == s and step == max(1, 2**-z)
        assert tile_window(z, x + 1, y)[0] == i1  # east neighbour starts where this one ends
        assert tile_window(z, x, y - 1)[1] == j1  # the tile above (y - 1) starts at this one's top


# -- pixel placement ---------------------------------------------------------------------------------------


def test_hit_at_negative_cell_lands_on_its_pixel_at_z0(hit_map: GridMap) -> None:
    x, y, rows, cols = where(*HIT, 0)
    assert (x, y, rows.start, cols.start) == (-2, 0, 9, 212)  # by hand: i - (-512), (0 - 1) - j
    img = decode(render_tile(hit_map, "probability", 0, x, y))
    hit = img[9, 212]
    assert hit[3] == 255 and hit[0] < 40, hit  # opaque and dark
    free = img[9, 213]  # cell (-299, -10): traversed by the beam
    assert free[3] == 255 and free[0] > 200, free
    assert img[9, 211][3] == 0  # beyond the return: never observed
    assert img[100, 100][3] == 0 and img[10, 212][3] == 0  # elsewhere and the row below
    assert (img[..., 3] > 0).sum() == 21  # the hit and the 20 cells of the beam, nothing else


def test_hit_is_a_4x4_block_at_z2(hit_map: GridMap) -> None:
    x, y, rows, cols = where(*HIT, 2)
    assert (x, y, rows.start, cols.start) == (-5, 0, 36, 80)
    img = decode(render_tile(hit_map, "probability", 2, x, y))
    block = img[36:40, 80:84]
    assert (block[..., 3] == 255).all() and (block[..., 0] < 40).all()
    assert (img[36:40, 84:88, 0] > 200).all() and (img[36:40, 84:88, 3] == 255).all()  # free cell
    assert (img[36:40, 76:80, 3] == 0).all() and (img[32:36, 80:84, 3] == 0).all()  # unobserved


def test_zoomed_out_pixel_keeps_the_occupied_cell(hit_map: GridMap) -> None:
    """At z = -2 the pixel of cells i in [-300, -296) holds the hit and three free cells: it must be
    dark (a wall never vanishes), while a pixel of free cells only is light."""
    x, y, rows, cols = where(*HIT, -2)
    assert (x, y, rows.start, cols.start) == (-1, 0, 2, 181)
    img = decode(render_tile(hit_map, "probability", -2, x, y))
    assert img[2, 181][3] == 255 and img[2, 181][0] < 40
    assert img[2, 182][3] == 255 and img[2, 182][0] > 200  # cells -296..-293: free only
    assert img[2, 180][3] == 0  # cells -304..-301: never observed
    # The engine agrees the block is mostly free: the aggregation, not the data, makes it dark.
    states = hit_map.region("state", -300, -12, -296, -8)
    assert (states == STATE_OCCUPIED).sum() == 1


@pytest.mark.parametrize("cell", [(-300, -10), (37, 5), (-1, 0), (0, -1), (1000, -2000)])
@pytest.mark.parametrize("z", [-6, -3, -1, 0, 1, 4])
def test_hit_pixel_at_every_zoom_and_quadrant(cell: tuple[int, int], z: int) -> None:
    gmap = make_map(*beam_to(*cell, cells=6), tile_size=64)
    x, y, rows, cols = where(*cell, z)
    img = decode(render_tile(gmap, "state", z, x, y))
    assert (img[rows, cols] == (20, 20, 20, 255)).all()
    assert (img[..., 3] > 0).sum() > 0
    # Only pixels in the beam's row band are drawn.
    drawn_rows = np.flatnonzero(img[..., 3].any(axis=1))
    assert drawn_rows.min() >= rows.start and drawn_rows.max() < rows.stop


def test_unexplored_tiles_are_transparent(hit_map: GridMap) -> None:
    for z, x, y in [(0, 5, 5), (-8, 3, 3), (4, -100, 7), (0, -1, -1)]:
        for layer in REGION_LAYERS:
            png = render_tile(hit_map, layer, z, x, y)
            assert png == EMPTY_PNG
            assert (decode(png)[..., 3] == 0).all()
    # Inside an existing storage tile, away from anything observed: transparent too.
    assert hit_map.store.version((HIT[0] >> hit_map.store.shift, HIT[1] >> hit_map.store.shift))
    img = decode(render_tile(hit_map, "probability", 4, -19, 1))  # cells [-304, -288) x [-32, -16)
    assert (img[..., 3] == 0).all()


# -- aggregation against a brute-force reference -------------------------------------------------------


def reference_tile(gmap: GridMap, layer: str, z: int, x: int, y: int) -> np.ndarray:
    """The expected value grid (top row = highest j) from GridMap.region and the documented rules."""
    i0, j0, i1, j1, step = tile_window(z, x, y)
    source = {"probability": "log_odds", "state": "log_odds"}.get(layer, layer)
    region = gmap.region(source, i0, j0, i1, j1)
    n = region.shape[0] // step
    blocks = region.reshape(n, step, n, step).transpose(0, 2, 1, 3).reshape(n, n, step * step)
    if source in ("log_odds", "tsdf"):
        score = np.where(np.isnan(blocks), -np.inf, blocks if source == "log_odds" else -np.abs(blocks))
    else:
        score = blocks.astype(np.float64)
    best = np.take_along_axis(blocks, score.argmax(axis=-1)[..., None], -1)[..., 0]
    return best[::-1]


def scattered_scans(seed: int, n: int = 12) -> list[Scan]:
    rng = np.random.default_rng(seed)
    return [
        Scan.from_fan((*rng.uniform(-12, 12, 2), rng.uniform(-3, 3)), -2.0, 0.02, rng.uniform(0.3, 9.0, 200))
        for _ in range(n)
    ]


@pytest.mark.parametrize("layer", ["probability", "hits", "tsdf", "tsdf_weight"])
def test_zoomed_out_matches_reference(layer: str) -> None:
    gmap = make_map(*scattered_scans(1), tile_size=16, max_tiles=100_000)
    for z, x, y in [(-1, -1, -1), (-2, 0, -1), (-3, -1, 0)]:
        img = decode(render_tile(gmap, layer, z, x, y))
        ref = reference_tile(gmap, layer, z, x, y)
        known = ~np.isnan(ref) if layer in ("probability", "tsdf") else ref > 0
        assert known.any()
        assert ((img[..., 3] == 255) == known).all()
        if layer == "probability":
            grey = nearest_grey(log_odds_to_probability(ref[known]))
            np.testing.assert_array_equal(img[..., 0][known], grey)
        elif layer == "tsdf":
            # Positive (in front of a surface) is red, negative blue; near 0 both are near white.
            clear = known & (np.abs(np.nan_to_num(ref)) > 0.02)
            red, blue = img[..., 0][clear].astype(int), img[..., 2][clear].astype(int)
            assert ((red > blue) == (ref[clear] > 0)).all()


def test_tile_size_does_not_change_the_picture() -> None:
    """The same scans stored in 16-cell and 256-cell storage tiles render identical tiles, also where
    one pixel spans many storage tiles (z = -6: 64 cells per pixel)."""
    scans = scattered_scans(2)
    small = make_map(*scans, tile_size=16, max_tiles=100_000)
    large = make_map(*scans, tile_size=256)
    for z, x, y in [(-6, -1, -1), (-6, 0, 0), (-4, -1, 0), (-2, 0, -1), (0, -1, -1), (3, 0, -1)]:
        for layer in ("probability", "tsdf"):
            assert render_tile(small, layer, z, x, y) == render_tile(large, layer, z, x, y), (z, x, y)


def test_tsdf_ties_across_storage_tiles_do_not_depend_on_the_tile_size() -> None:
    """A zoomed-out TSDF pixel whose nearest-surface cells tie (a value and its opposite, either side
    of a return on a cell edge) shows the one the halving keeps (`kernels.reduce`: the first of a
    pair), whether those cells share a storage tile or not. Where the pixel spanned several storage
    tiles, the tie went to whichever block NumPy wrote last: the same scans drew a red pixel with
    256-cell tiles and a blue one with 16-cell tiles. Each beam runs along an axis from a cell centre
    to the edge between storage tiles 0 and 1 (cell 16), in binary-exact metres, so the tie is exact.
    """
    res, edge = 0.125, 16
    beams = [  # (start cell centre, direction): along +x, -x, +y and -y, each in its own 32-cell block
        ((4.5, 3.5), 0.0),
        ((27.5, 35.5), math.pi),
        ((67.5, 4.5), math.pi / 2),
        ((99.5, 27.5), -math.pi / 2),
    ]
    scans = []
    for (ci, cj), theta in beams:
        reach = abs(edge - (ci if theta in (0.0, math.pi) else cj)) * res
        scans.append(Scan.from_fan((ci * res, cj * res, theta), 0.0, 0.01, [reach]))
    small, large = (
        GridMap(MapConfig(resolution=res, tile_size=size, max_tiles=1000, tsdf={"truncation": 4 * res}))
        for size in (16, 256)
    )
    for gmap in (small, large):
        for scan in scans:
            gmap.integrate(scan)
    # The premise: a cell either side of each return holds +-1/8 of the truncation exactly.
    assert small.region("tsdf", 15, 3, 17, 4).tolist() == [[0.125, -0.125]]
    assert small.region("tsdf", 15, 35, 17, 36).tolist() == [[-0.125, 0.125]]
    for z in (-5, -6, -7, -8):
        png = render_tile(large, "tsdf", z, 0, -1)
        assert decode(png)[..., 3].any()
        assert render_tile(small, "tsdf", z, 0, -1) == png, z


# -- colours -------------------------------------------------------------------------------------------------


def test_every_layer_renders_with_plausible_colours(hit_map: GridMap) -> None:
    x, y, _, _ = where(*HIT, 0)
    hit, free, front, behind, far_free = (9, 212), (9, 213), (9, 214), (9, 211), (9, 230)
    img = {layer: decode(render_tile(hit_map, layer, 0, x, y)) for layer in REGION_LAYERS}
    for layer in ("probability", "log_odds"):
        h, f = img[layer][hit], img[layer][free]
        assert h[0] == h[1] == h[2] < 40 and h[3] == 255
        assert f[0] == f[1] == f[2] > 200 and f[3] == 255
    assert tuple(img["state"][hit]) == (20, 20, 20, 255)
    assert tuple(img["state"][free]) == (245, 245, 245, 255)
    # Counts: 5 hits on the hit cell and 5 misses on the free cells, zero elsewhere (transparent).
    assert img["hits"][hit][3] == 255 and img["hits"][free][3] == 0
    assert img["misses"][free][3] == 255 and img["misses"][hit][3] == 0
    assert (img["hits"][hit] == img["misses"][free]).all()  # same count, same colour (fixed scale)
    assert len(set(img["hits"][hit][:3].tolist())) > 1  # a colour ramp, not grey
    # TSDF: the cell in front of the return (towards the sensor) is positive -> red; the band ends
    # within truncation (0.2 m = 4 cells); unobserved -> transparent.
    assert img["tsdf"][front][0] > img["tsdf"][front][2] and img["tsdf"][front][3] == 255
    assert img["tsdf"][behind][2] > img["tsdf"][behind][0] and img["tsdf"][behind][3] == 255
    assert img["tsdf"][far_free][3] == 0 and img["tsdf_weight"][far_free][3] == 0
    assert img["tsdf_weight"][hit][3] == 255


def nearest_grey(probability: np.ndarray) -> np.ndarray:
    """The documented grey `255 (1 - p)` of each reported probability (float32, as `/cells` and the
    `probability` region give it), rounded exactly (in fractions, half to even) to an integer."""
    greys = {float(p): round(255 * (1 - Fraction(float(p)))) for p in np.unique(probability)}
    return np.vectorize(greys.__getitem__, otypes=[np.int64])(probability)


def test_grey_is_255_1_minus_p_to_the_nearest_integer_in_every_image() -> None:
    """Tiles (zoomed in and out), the exported map PNG and the region PNGs show each known cell as
    the grey nearest `255 (1 - p)` of the probability the map reports. In float32 a cell hit once
    (p = 0.699999988, 255 (1 - p) = 76.500003) drew 76 everywhere, not 77."""
    gmap = make_map(*scattered_scans(1))
    i0, j0, i1, j1, _ = tile_window(0, 0, -1)  # cells [0, 256) x [0, 256)
    probability = gmap.region("probability", i0, j0, i1, j1)[::-1]  # top row = highest j
    known = ~np.isnan(probability)
    one_hit = np.isclose(probability, 0.7)
    assert one_hit.sum() > 50  # the premise: many cells were hit once
    expected = nearest_grey(probability[known])
    assert expected[one_hit[known]].tolist() == [77] * int(one_hit.sum())
    for layer in ("probability", "log_odds"):
        img = decode(render_tile(gmap, layer, 0, 0, -1))
        assert (img[..., 3][known] == 255).all()
        np.testing.assert_array_equal(img[..., 0][known], expected)
    # Zoomed in, tile (2, 0, -4) holds cells [0, 64) x [192, 256), each a block of 4 x 4 pixels.
    corner, corner_known = probability[:64, :64], known[:64, :64]
    zoomed_in = decode(render_tile(gmap, "probability", 2, 0, -4))
    np.testing.assert_array_equal(zoomed_in[::4, ::4, 0][corner_known], nearest_grey(corner[corner_known]))
    # Zoomed out, a pixel shows its block's most occupied known cell (`reference_tile`) in that grey.
    ref = reference_tile(gmap, "probability", -1, 0, -1)
    shown = ~np.isnan(ref)
    zoomed_out = decode(render_tile(gmap, "probability", -1, 0, -1))
    np.testing.assert_array_equal(
        zoomed_out[..., 0][shown], nearest_grey(log_odds_to_probability(ref[shown]))
    )
    # The export's PNG (map.png of `fleetmap build`) and the region PNG of both layers.
    window = Window(i0, j0, i1, j1)
    exported = np.asarray(Image.open(io.BytesIO(map_png(gmap, window))))
    np.testing.assert_array_equal(exported[known], expected)
    for layer in ("probability", "log_odds"):
        pixels = region_pixels(layer, gmap.region(layer, i0, j0, i1, j1))
        np.testing.assert_array_equal(pixels[..., 0][known], expected)


def test_hit_count_colour_is_consistent_between_tiles() -> None:
    """The count ramp has a fixed scale: a cell hit 3 times looks the same in any tile, next to
    anything."""
    a = make_map(*beam_to(10, 10, times=3), *beam_to(40, 10, times=50))
    b = make_map(*beam_to(-700, 900, times=3))
    pa = decode(render_tile(a, "hits", 0, *where(10, 10, 0)[:2]))[where(10, 10, 0)[2:]]
    pb = decode(render_tile(b, "hits", 0, *where(-700, 900, 0)[:2]))[where(-700, 900, 0)[2:]]
    p50 = decode(render_tile(a, "hits", 0, *where(40, 10, 0)[:2]))[where(40, 10, 0)[2:]]
    assert (pa == pb).all() and pa[0, 0, 3] == 255
    assert not (pa == p50).all()


def test_weight_ramp_holds_for_the_tiniest_weight_caps() -> None:
    """`tsdf_weight` sits at `log1p(weight) / log1p(max_weight)` of the ramp for every cap a map may
    have: below ~3e-39 the float32 reciprocal of log1p(cap) was infinite, so every render warned
    (overflow, invalid multiply and cast) and a weight at a fraction of the cap took the top colour.
    Scans add 1 a time (a cap below 1 holds only 0 and the cap); other weights come with a snapshot
    upload, so they are written into the pool here as one would hold them."""
    x, y, rows, cols = where(*HIT, 0)
    hit_at = (rows.start, cols.start)
    full_at = (rows.start, cols.start + 1)  # the cell in front of the return: weight at the cap
    half: dict[float, np.ndarray] = {}
    for cap in (1e-40, 1000.0):
        gmap = make_map(*beam_to(*HIT), tsdf={"max_weight": cap})
        store = gmap.store
        slot = store.slots[(HIT[0] >> store.shift, HIT[1] >> store.shift)]
        # Half way up the ramp: log1p(weight) = log1p(cap) / 2 (5e-41 for 1e-40, 30.6 for 1000).
        cell = (slot, HIT[1] & store.mask, HIT[0] & store.mask)
        store.pools["tsdf_weight"][cell] = math.expm1(math.log1p(cap) / 2)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            img = decode(render_tile(gmap, "tsdf_weight", 0, x, y))
        assert img[full_at][3] == 255 and img[hit_at][3] == 255
        assert not (img[hit_at] == img[full_at]).all()  # half the ramp is not its top
        half[cap] = img[hit_at]
    assert (half[1e-40] == half[1000.0]).all()


# -- errors ------------------------------------------------------------------------------------------------


def test_bad_zoom_tile_and_layer_raise_tile_error(hit_map: GridMap) -> None:
    entry = MapEntry("m", hit_map, 1)
    cache = TileCache()
    for z in (MIN_ZOOM - 1, MAX_ZOOM + 1, 100, True, 1.0):
        for call in (
            lambda: render_tile(hit_map, "probability", z, 0, 0),  # noqa: B023
            lambda: tile_version(hit_map, z, 0, 0),  # noqa: B023
            lambda: cache.get_or_render(entry, "probability", z, 0, 0),  # noqa: B023
        ):
            with pytest.raises(TileError, match="zoom"):
                call()
    with pytest.raises(TileError, match="unknown layer 'nope'.*probability"):
        render_tile(hit_map, "nope", 0, 0, 0)
    with pytest.raises(TileError, match="unknown layer"):
        cache.get_or_render(entry, "nope", 0, 0, 0)
    with pytest.raises(TileError, match="outside"):
        render_tile(hit_map, "probability", 0, 2**60, 0)
    occupancy_only = make_map(layers=["occupancy"])
    for layer in ("hits", "misses", "tsdf", "tsdf_weight"):
        with pytest.raises(TileError, match="does not keep"):
            render_tile(occupancy_only, layer, 0, 0, 0)
        with pytest.raises(TileError, match="does not keep"):
            cache.get_or_render(MapEntry("o", occupancy_only, 2), layer, 0, 0, 0)
    assert issubclass(TileError, ValueError)
    assert len(cache) == 0


# -- versions and the cache -------------------------------------------------------------------------------


def test_version_changes_only_for_tiles_under_a_change() -> None:
    gmap = make_map(*beam_to(*HIT))
    here = where(*HIT, 0)[:2]
    elsewhere = where(-5000, -3000, 0)[:2]
    assert tile_version(gmap, 0, *here) > 0
    assert tile_version(gmap, 0, *elsewhere) == 0
    before = {z: tile_version(gmap, z, *where(*HIT, z)[:2]) for z in (-8, -2, 0, 4)}
    gmap.integrate(beam_to(-5000, -3000, times=1)[0])  # far away: other storage tiles
    assert tile_version(gmap, 0, *here) == before[0]
    assert tile_version(gmap, 4, *where(*HIT, 4)[:2]) == before[4]
    assert tile_version(gmap, 0, *elsewhere) > before[0]
    assert tile_version(gmap, -8, *where(*HIT, -8)[:2]) > before[-8]  # covers both places
    gmap.integrate(beam_to(HIT[0] + 5, HIT[1] + 3, times=1)[0])  # same storage tile, new cells
    assert tile_version(gmap, 0, *here) > before[0]
    assert tile_version(gmap, -2, *where(*HIT, -2)[:2]) > before[-2]


@pytest.fixture
def counted_renders(monkeypatch: pytest.MonkeyPatch) -> list[tuple]:
    """Records every real render the cache triggers (a spy around the real renderer, not a mock)."""
    calls: list[tuple] = []
    real = tile_cache.render_tile_versioned

    def spy(*args: object, **kwargs: object) -> tuple[bytes, int]:
        calls.append(args[1:5])
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(tile_cache, "render_tile_versioned", spy)
    return calls


def test_cache_serves_unchanged_tiles_and_rerenders_changed_ones(counted_renders: list[tuple]) -> None:
    gmap = make_map(*beam_to(*HIT))
    entry = MapEntry("site", gmap, 7)
    cache = TileCache()
    x, y, _, _ = where(*HIT, 0)
    png1, etag1 = cache.get_or_render(entry, "probability", 0, x, y)
    assert etag1 == f'"7-probability-0-{x}-{y}-{tile_version(gmap, 0, x, y)}"'
    assert decode(png1)[9, 212][3] == 255
    png2, etag2 = cache.get_or_render(entry, "probability", 0, x, y)
    assert png2 == png1 and etag2 == etag1
    assert len(counted_renders) == 1
    # Another layer and another zoom are other tiles; a far tile is cached too.
    cache.get_or_render(entry, "state", 0, x, y)
    far_png, far_etag = cache.get_or_render(entry, "probability", 0, 5, 5)
    assert far_png == EMPTY_PNG and far_etag.endswith('-0"')
    assert len(counted_renders) == 3
    # A scan changing a cell under the tile: a new version, a new picture, one new render.
    gmap.integrate(beam_to(HIT[0] + 5, HIT[1] + 3, times=1)[0])
    png3, etag3 = cache.get_or_render(entry, "probability", 0, x, y)
    assert etag3 != etag1 and png3 != png1 and len(counted_renders) == 4
    assert cache.get_or_render(entry, "probability", 0, 5, 5) == (far_png, far_etag)
    assert len(counted_renders) == 4
    # The same map id re-created (new generation) never sees the old entries.
    _, etag_new = cache.get_or_render(MapEntry("site", gmap, 8), "probability", 0, x, y)
    assert etag_new.startswith('"8-') and len(counted_renders) == 5
    assert cache.hits == 2 and cache.renders == 5
    assert png3 == render_tile(gmap, "probability", 0, x, y)  # (a direct render, not the cache's)


def test_cached_answers_only_current_hits_and_never_renders(counted_renders: list[tuple]) -> None:
    """`cached` (what the HTTP route asks first, on its event loop) returns the cached tile only while
    it is the tile's current version, counts it as a hit, and never renders; it validates like
    get_or_render."""
    gmap = make_map(*beam_to(*HIT))
    entry = MapEntry("site", gmap, 7)
    cache = TileCache()
    x, y, _, _ = where(*HIT, 0)
    assert cache.cached(entry, "probability", 0, x, y) is None  # not rendered yet: no render either
    assert counted_renders == [] and cache.hits == 0
    rendered = cache.get_or_render(entry, "probability", 0, x, y)
    assert cache.cached(entry, "probability", 0, x, y) == rendered
    assert cache.cached(entry, "state", 0, x, y) is None  # another layer is another tile
    assert cache.hits == 1 and len(counted_renders) == 1
    gmap.integrate(beam_to(HIT[0] + 5, HIT[1] + 3, times=1)[0])  # the tile changes: stale
    assert cache.cached(entry, "probability", 0, x, y) is None
    assert cache.cached(MapEntry("site", gmap, 8), "probability", 0, x, y) is None  # new generation
    assert len(counted_renders) == 1
    with pytest.raises(TileError):
        cache.cached(entry, "probability", MAX_ZOOM + 1, 0, 0)
    with pytest.raises(TileError):
        cache.cached(entry, "bogus", 0, x, y)


def test_cache_is_a_bounded_lru(counted_renders: list[tuple]) -> None:
    entry = MapEntry("m", make_map(*beam_to(*HIT)), 1)
    cache = TileCache(max_entries=2)
    for x in (0, 1, 0, 2, 0, 1):
        cache.get_or_render(entry, "probability", 0, x, 0)
    # 0, 1 rendered; 0 hit; 2 evicts 1 (least recently used); 0 hit; 1 rendered again.
    assert [c[2] for c in counted_renders] == [0, 1, 2, 1]
    assert len(cache) == 2


def test_zoomed_out_cache_follows_changes() -> None:
    """Reduced storage-tile blocks are reused between renders but never when their tile changed."""
    gmap = make_map(*scattered_scans(3, n=6), tile_size=16, max_tiles=100_000)
    entry = MapEntry("m", gmap, 1)
    cache = TileCache()
    for scan in scattered_scans(4, n=3) + [None]:
        for layer, z in (("probability", -3), ("tsdf", -5), ("hits", -2)):
            for x, y in ((-1, -1), (0, 0), (-1, 0)):
                png, _ = cache.get_or_render(entry, layer, z, x, y)
                assert png == render_tile(gmap, layer, z, x, y), (layer, z, x, y)
        if scan is not None:
            gmap.integrate(scan)
    assert cache.reduced.nbytes > 0


def test_zoomed_out_blocks_of_a_deleted_map_are_dropped() -> None:
    """A deleted map's reduced blocks stayed in the cache, up to its 128 MB, until newer renders
    evicted them: memory a map no longer held. They go once the map's store is freed; a live map's
    stay."""
    kept = MapEntry("kept", make_map(*scattered_scans(3, n=6), tile_size=16, max_tiles=100_000), 1)
    gone = MapEntry("gone", make_map(*scattered_scans(5, n=6), tile_size=16, max_tiles=100_000), 2)
    cache = TileCache()
    cache.get_or_render(kept, "probability", -3, -1, -1)
    alone = cache.reduced.nbytes
    cache.get_or_render(gone, "probability", -3, -1, -1)
    assert cache.reduced.nbytes > alone > 0
    cache.drop_map("gone")  # as DELETE /maps/gone does, and the registry lets the map go
    del gone
    gc.collect()
    assert cache.reduced.nbytes == alone
    png, _ = cache.get_or_render(kept, "probability", -3, 0, 0)  # the live map's blocks still serve
    assert png == render_tile(kept.gmap, "probability", -3, 0, 0)


def test_concurrent_requests_render_once_and_stay_consistent() -> None:
    gmap = make_map(*beam_to(*HIT))
    entry = MapEntry("m", gmap, 1)
    cache = TileCache()
    x, y, _, _ = where(*HIT, -1)
    results: list[tuple[bytes, str]] = []
    errors: list[BaseException] = []
    barrier = threading.Barrier(16)

    def ask() -> None:
        try:
            barrier.wait()
            for _ in range(20):
                results.append(cache.get_or_render(entry, "probability", -1, x, y))
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=ask) for _ in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert cache.renders == 1 and len(set(results)) == 1

    # Now with a writer integrating scans under the same tile while readers ask for it.
    scans = [beam_to(HIT[0] - k, HIT[1] + k % 7, cells=8, times=1)[0] for k in range(1, 60)]
    stop = threading.Event()

    def write() -> None:
        for scan in scans:
            gmap.integrate(scan)
        stop.set()

    def read() -> None:
        try:
            while not stop.is_set():
                png, etag = cache.get_or_render(entry, "probability", -1, x, y)
                assert decode(png)[..., 3].any()
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=read) for _ in range(6)] + [threading.Thread(target=write)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    png, etag = cache.get_or_render(entry, "probability", -1, x, y)
    assert etag == f'"1-probability--1-{x}-{y}-{tile_version(gmap, -1, x, y)}"'
    assert png == render_tile(gmap, "probability", -1, x, y)


def test_a_request_served_by_a_concurrent_render_counts_as_a_hit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every tile the cache serves is a hit or a render, so that `fleetmap_tile_cache_hits_total` and
    `fleetmap_tile_renders_total` add up to the tiles served: a request that waited for another
    request's render of the same tile was neither, and the hit ratio read low under load."""
    entry = MapEntry("m", make_map(*beam_to(*HIT)), 1)
    cache = TileCache()
    x, y, _, _ = where(*HIT, -1)
    rendering, release, waiting = threading.Event(), threading.Event(), threading.Event()
    real = tile_cache.render_tile_versioned

    def held_render(*args: object, **kwargs: object) -> tuple[bytes, int]:
        rendering.set()
        assert release.wait(60)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    class WatchedFuture(Future):  # type: ignore[type-arg]
        """A render's future that says when a request waits for it."""

        def result(self, timeout: float | None = None) -> object:
            waiting.set()
            return super().result(timeout)

    monkeypatch.setattr(tile_cache, "render_tile_versioned", held_render)
    monkeypatch.setattr(tile_cache, "Future", WatchedFuture)
    served: list[tuple[bytes, str]] = []

    def ask() -> None:
        served.append(cache.get_or_render(entry, "probability", -1, x, y))

    renderer = threading.Thread(target=ask)
    renderer.start()
    assert rendering.wait(60)
    waiter = threading.Thread(target=ask)
    waiter.start()
    assert waiting.wait(60)  # the second request waits for the first one's render
    release.set()
    renderer.join()
    waiter.join()
    assert len(served) == 2 and served[0] == served[1]
    assert cache.renders == 1 and cache.hits == 1


# -- zoomed-out reads of big windows ------------------------------------------------------------------


def halved(values: np.ndarray, source: str, factor: int) -> np.ndarray:
    """The reference reduction (the renderer's before `kernels.reduce`): halve a stack (n, a, a)
    `log2(factor)` times, columns then rows, each 2 x 2 block to one value by the source's rule."""
    while factor > 1:
        for axis in (2, 1):
            first = values[:, :, 0::2] if axis == 2 else values[:, 0::2, :]
            second = values[:, :, 1::2] if axis == 2 else values[:, 1::2, :]
            if source == "log_odds":
                values = np.fmax(first, second)
            elif source == "tsdf":
                values = np.where((np.abs(second) < np.abs(first)) | np.isnan(first), second, first)
            else:
                values = np.maximum(first, second)
        factor //= 2
    return values


@pytest.mark.parametrize("source", ["log_odds", "hits", "tsdf", "tsdf_weight"])
def test_reduce_kernels_match_pairwise_halving(source: str) -> None:
    """The kernels give exactly the pairwise halving's blocks, ties of the TSDF's |value| (which
    cell's sign wins) and unknown cells included, for every factor and a window inside a tile."""
    from fleetmap.kernels.reduce import reduce_max_tiles, reduce_tsdf_tiles

    rng = np.random.default_rng(7)
    n, t = 5, 64
    if source == "hits":
        pool = rng.integers(0, 4, size=(n, t, t)).astype(np.uint32)
    else:
        pool = rng.choice(np.array([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=np.float32), size=(n, t, t))
    weight = rng.choice(np.array([0.0, 1.0, 2.0], dtype=np.float32), size=(n, t, t))
    if source == "log_odds":
        pool[rng.random((n, t, t)) < 0.6] = np.nan
        pool[1] = np.nan  # a tile with nothing known
    slots = np.array([4, 0, 1, 3], dtype=np.int64)
    for li0, lj0, piece in ((0, 0, t), (16, 32, 16)):
        window = pool[slots, lj0 : lj0 + piece, li0 : li0 + piece].copy()
        if source == "tsdf":
            window[weight[slots, lj0 : lj0 + piece, li0 : li0 + piece] <= 0] = np.nan
        factor = 2
        while factor <= piece:
            out = np.empty((slots.size, piece // factor, piece // factor), dtype=pool.dtype)
            if source == "tsdf":
                reduce_tsdf_tiles(pool, weight, slots, li0, lj0, piece, factor, out)
            else:
                reduce_max_tiles(pool, slots, li0, lj0, piece, factor, out)
            expected = halved(window, source, factor)
            np.testing.assert_array_equal(out, expected, err_msg=f"{li0, lj0, piece, factor}")
            assert (np.signbit(out) == np.signbit(expected)).all()  # the tie's own cell, not its twin
            factor *= 2


def test_zoomed_out_render_holds_its_blocks_not_a_copy_of_the_window() -> None:
    """A zoomed-out tile over many storage tiles copied every one of them at once before reducing
    the copies: at z = -8 over a 1 km map of 6,400 tiles, a 2.9 GB peak for one render (7.7 s, the
    copy under the map's lock). Reduced from the pools a tile at a time, a render allocates its
    blocks and the picture: here under a fifth of the 16 MB of log-odds of the 64 tiles (about 1.5 MB)."""
    import tracemalloc

    gmap = GridMap(MapConfig(resolution=RES, layers=["occupancy"], tile_size=256))
    keys = [(i, -1 - j) for j in range(8) for i in range(8)]  # all under tile (-5, 0, 0)
    gmap.store.create(keys)
    rng = np.random.default_rng(3)
    gmap.store.pools["log_odds"][: len(keys)] = rng.normal(size=(len(keys), 256, 256)).astype(np.float32)
    layer_bytes = len(keys) * 256 * 256 * 4
    cache = TileCache()
    entry = MapEntry("big", gmap, 1)
    cache.get_or_render(entry, "probability", -6, 0, 0)  # compiled and warm before measuring
    cache.clear()
    for z in (-5, -7, -8):
        tracemalloc.start()
        try:
            png, _ = cache.get_or_render(entry, "probability", z, 0, 0)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert png != EMPTY_PNG
        assert peak < layer_bytes // 5, (z, peak)


def test_the_reduced_cache_counts_what_each_block_holds_beside_its_cells() -> None:
    """`ReducedCache` counted only its blocks' cells against its bound (128 MiB): a map of 16-cell
    tiles seen zoomed out makes blocks of one cell, 4 bytes counted for ~450 held (the block's array
    object, its key, its version, its place in the LRU), so the bound let it hold ~15 GB. Everything
    it holds, as tracemalloc sees it, stays within its bound now, whatever the blocks' size."""
    import tracemalloc

    from fleetmap.tile_reduce import ReducedCache

    for side in (1, 4, 16):
        cache = ReducedCache(1 << 20)
        gc.collect()
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            for k in range(20_000):  # keyed as `tile_reduce.snapshot` keys them
                block = np.zeros((side, side), dtype=np.float32)
                cache.put((1, "log_odds", 1000 + k, 2000 + k, 0, 0, 16, 16), 12345 + k, block)
            gc.collect()
            held = tracemalloc.get_traced_memory()[0] - before
        finally:
            tracemalloc.stop()
        assert held <= cache.max_bytes, (side, held)
        assert cache.nbytes <= cache.max_bytes


def test_tile_versions_read_while_the_map_grows_are_never_torn() -> None:
    """`tile_version` reads a big window's storage tiles lock-free (a revalidation or a cache hit, on
    the event loop) while a render in the thread pool extends the index of the store's keys, which a
    scan grew. The index's key and slot arrays were extended one after the other on one shared
    object, so a reader between two of them compared arrays of two lengths: a 500 (`operands could
    not be broadcast together`) on a zoomed-out tile of a map robots were extending."""
    import sys

    gmap = GridMap(MapConfig(resolution=RES, tile_size=16, max_tiles=200_000, layers=("occupancy",)))
    store = gmap.store
    failures: list[BaseException] = []
    done = threading.Event()

    def grow() -> None:
        try:
            for n in range(3000):
                with gmap.lock:
                    store.create([(n % 60, n // 60)])
                tile_version(gmap, -4, 0, -1)  # extends the index, as a render does
        finally:
            done.set()

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as the interpreter allows
    try:
        writer = threading.Thread(target=grow)
        writer.start()
        while not done.is_set():
            try:
                tile_version(gmap, -4, 0, -1)  # 4096 cells a side: the key index, not probes
            except Exception as exc:  # noqa: BLE001 - the failure is what the test looks for
                failures.append(exc)
                break
        writer.join()
    finally:
        sys.setswitchinterval(interval)
    assert not failures, failures
    assert tile_version(gmap, -4, 0, -1) == int(store.versions[: len(store.keys)].max())
