"""Map tiles for web viewers: a zoom pyramid of 256 x 256 RGBA PNGs that Leaflet's `CRS.Simple`
displays as is, with versions for ETags (the thread-safe cache of rendered tiles: `tile_cache`).

Tile convention (the REST endpoint `GET /maps/{map_id}/tiles/{z}/{x}/{y}.png?layer=` serves these):

- One Leaflet map unit is one CELL, and `lng = i`, `lat = j` for cell (i, j), i.e. the cell holding
  the map point (x, y) metres is at `latLng = (y / res, x / res)` (res = the map's resolution).
- At zoom 0 one tile pixel is one cell. A tile covers `S = 256 / 2**z` cells per side: at z > 0 each
  cell is a `2**z x 2**z` block of pixels (nearest neighbour; z <= 4, so 16 cells per tile), at z < 0
  each pixel summarises `2**-z x 2**-z` cells (z >= -8, so 65536 cells per tile side).
- Tile (z, x, y) covers cells `i in [x*S, (x+1)*S)` and `j in [-(y+1)*S, -y*S)`: CRS.Simple puts
  pixel y at `-lat * 2**z`, so tile y grows downwards (south) while j grows upwards. Tile y = 0 is the
  row of tiles just below j = 0 (j in [-S, 0)), y = -1 the row from j = 0 up; tile x < 0 holds i < 0.
  Cell (i, j) is in tile `x = floor(i / S)`, `y = -floor(j / S) - 1`. The PNG's top row is the
  highest j of the tile, its left column the lowest i; cell j covers lat [j, j + 1).

What a pixel shows when it summarises several cells (z < 0), so that zooming out never hides what
matters: `probability` / `log_odds` / `state` show the MOST occupied known cell of the block (walls do
not vanish), `hits` / `misses` / `tsdf_weight` the largest value, `tsdf` the value nearest the
surface (smallest |tsdf|). A pixel is unknown (transparent) where no cell of its block is known;
for `state`, also where the block's most occupied known cell lies between the thresholds (below),
as that cell alone is: free cells beside it do not make the block free.

Colours (RGBA; unknown is fully transparent, everything known is opaque):

- `probability`, `log_odds`: grey `255 * (1 - p)` to the nearest integer, p as the map reports it
  (`export.probability_grey`), darker = more likely occupied (as the exported PNG); a known cell at
  p = 0.5 is mid-grey, not transparent.
- `state`: occupied near-black, free near-white; unknown (including known cells between the map's
  free and occupied thresholds) transparent.
- `hits`, `misses`: a viridis-like ramp of `log1p(count) / log1p(COUNT_SCALE)` (fixed, so tiles agree
  with each other and over time; counts >= COUNT_SCALE are the top colour); a zero count is
  transparent.
- `tsdf_weight`: the same ramp, scaled by `log1p(weight) / log1p(max_weight)` with the map's
  `tsdf.max_weight`; weight 0 is transparent.
- `tsdf` (normalised to [-1, 1]): diverging blue (-1, behind the surface) - white (0) - red (+1, in
  front of the surface, towards the sensor).

Versions: every storage tile (`store.tile_size` cells) has a version from a store-wide clock that
increases with every change; a web tile's version is the max over the storage tiles its window
intersects (0 if none), so any change under a tile raises it and changes elsewhere do not. A render
reads that version and the cells in the same hold of the map's lock, so a cached PNG is always
exactly the map as of its version: before or after any scan, never half-way.

Locking: the map lock is held only to read the storage tiles under the window (and their versions):
zoomed in, a copy of the cells; zoomed out, each storage tile reduced straight from its pool to its
block of pixels (`kernels.reduce`, one pass over its cells, about as long as a copy), so a render
never holds more than its blocks. Colouring and PNG encoding happen outside the lock. For zoomed-out
tiles, each storage tile's reduced block is cached by version (`ReducedCache`, owned by `TileCache`),
so only storage tiles that changed since the last render are read and reduced.

The parts, each in its module: this one holds the convention, the tile versions and the render
(`render_tile`); `tile_reduce` what a render reads under the map lock, and the zoomed-out reduction;
`tile_colours` the colours; `png` the PNG encoder; `tile_cache` the cache of rendered tiles.
"""

from __future__ import annotations

import numpy as np

from fleetmap.grid_map import LAYER_SOURCES, REGION_LAYERS, GridMap
from fleetmap.png import encode_png
from fleetmap.tile_colours import colour_index
from fleetmap.tile_reduce import ReducedCache, assemble, snapshot, storage_range, tiles_under

#: Tile side in pixels.
TILE_PX = 256
#: Allowed zooms: z = 0 is one pixel per cell; MAX_ZOOM magnifies 16x, MIN_ZOOM shrinks 256x.
MIN_ZOOM, MAX_ZOOM = -8, 4
#: Cell indices a web tile may reach; beyond this float coordinates lose whole cells and int64
#: overflows are near, so such tiles are refused rather than rendered. (Far beyond any cell a scan
#: can reach, `update_plan.MAX_CELL_INDEX`: such a tile is empty, but a valid address.)
MAX_TILE_CELL_INDEX = 2**52


class TileError(ValueError):
    """A tile request that cannot be served: bad zoom, tile index or layer. The message says why."""


# -- tile geometry ----------------------------------------------------------------------------------


def tile_window(z: int, x: int, y: int) -> tuple[int, int, int, int, int]:
    """The cells of tile (z, x, y): `(i0, j0, i1, j1, step)`, cells `[i0, i1) x [j0, j1)`.

    `i1 - i0 == j1 - j0 == 256 / 2**z`; `step` is the number of cells per pixel side: `2**-z` for
    z <= 0, and 1 for z > 0 (where each cell is instead `2**z` pixels wide). Raises TileError for a
    zoom outside [MIN_ZOOM, MAX_ZOOM] or a tile beyond MAX_TILE_CELL_INDEX.
    """
    _check_zoom(z)
    for name, value in (("x", x), ("y", y)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TileError(f"tile {name} must be an integer, got {value!r}")
    size = TILE_PX >> z if z >= 0 else TILE_PX << -z
    i0, j0 = x * size, -(y + 1) * size
    i1, j1 = i0 + size, j0 + size
    if max(abs(i0), abs(i1), abs(j0), abs(j1)) > MAX_TILE_CELL_INDEX:
        raise TileError(f"tile ({z}, {x}, {y}) is outside the map's cell range (|index| <= 2**52)")
    return i0, j0, i1, j1, (1 << -z) if z < 0 else 1


def _check_zoom(z: int) -> None:
    if isinstance(z, bool) or not isinstance(z, int) or not MIN_ZOOM <= z <= MAX_ZOOM:
        raise TileError(
            f"zoom {z!r} is out of range: tiles exist for z = {MIN_ZOOM}..{MAX_ZOOM} "
            "(z = 0 is one pixel per cell)"
        )


def check_layer(gmap: GridMap, layer: str) -> None:
    """Raise TileError unless `layer` is a tile layer that this map keeps."""
    if layer not in LAYER_SOURCES:
        raise TileError(f"unknown layer {layer!r}; one of {', '.join(REGION_LAYERS)}")
    needs = LAYER_SOURCES[layer][1]
    if not gmap.config.has(needs):
        raise TileError(f"layer {layer!r} needs the {needs!r} layer, which this map does not keep")


def tile_version(gmap: GridMap, z: int, x: int, y: int) -> int:
    """The version of tile (z, x, y): the max version of the storage tiles its window intersects,
    0 if there are none. Any change to a cell under the tile raises it; nothing else does.

    Cheap (a few dict probes or one vectorised scan of the tile keys) and deliberately lock-free, so
    cached tiles are served while a scan is being integrated: under the GIL each read below is atomic,
    a slot is visible only once its tile exists, and `store.versions` is read after the slots, so it
    is an array that holds them. A read racing an integration may return the version from before
    that scan (whose tiles get their new versions only at its end): the cached PNG of that version
    is the map before the scan, which is what a reader may see during integration.
    """
    i0, j0, i1, j1, _ = tile_window(z, x, y)
    store = gmap.store
    _, _, slots = tiles_under(store, *storage_range(store, i0, j0, i1, j1))
    if slots.size == 0:
        return 0
    return int(store.versions[slots].max())


def etag_for(generation: int, layer: str, z: int, x: int, y: int, version: int) -> str:
    """The (quoted) HTTP ETag of a tile: changes with the map's generation and the tile's version."""
    return f'"{generation}-{layer}-{z}-{x}-{y}-{version}"'


def render_tile(gmap: GridMap, layer: str, z: int, x: int, y: int) -> bytes:
    """Tile (z, x, y) of one layer as a 256 x 256 RGBA PNG (see the module docstring for the
    convention and colours). Unknown is transparent; a tile with nothing known is `EMPTY_PNG`.
    Raises TileError for a bad zoom, tile index or layer (including one the map does not keep)."""
    return render_tile_versioned(gmap, layer, z, x, y)[0]


def render_tile_versioned(
    gmap: GridMap, layer: str, z: int, x: int, y: int, reduced: ReducedCache | None = None
) -> tuple[bytes, int]:
    """`render_tile` plus the tile version the PNG shows exactly (read with the cells, under the
    lock). `reduced` caches reduced storage-tile blocks between renders (z < 0)."""
    i0, j0, i1, j1, cells_per_px = tile_window(z, x, y)
    check_layer(gmap, layer)
    # The stored array a pixel is computed from (`grid_map.LAYER_SOURCES`): probability and state
    # are derived from the log-odds reduced like the log_odds layer (so the three share reduced
    # blocks); tsdf is tsdf with unobserved (weight 0) cells as NaN.
    source = LAYER_SOURCES[layer][0]
    size = i1 - i0
    piece = min(gmap.store.tile_size, size)
    factor = min(cells_per_px, piece)
    snap = snapshot(gmap, source, i0, j0, size, factor, reduced)
    if not snap.blocks:
        return EMPTY_PNG, snap.version
    grid = assemble(snap, source, size // cells_per_px, piece, cells_per_px)
    idx, lut, transparent = colour_index(gmap, layer, grid)
    if not (idx != transparent).any():
        return EMPTY_PNG, snap.version
    idx = idx[::-1]  # PNG rows run from the highest j down
    if z > 0:
        k = 1 << z  # nearest neighbour: each cell becomes a k x k block
        idx = np.repeat(np.repeat(idx, k, axis=0), k, axis=1)
    return encode_png(lut[idx]), snap.version


#: The fully transparent tile: unexplored space is served as this one precomputed PNG.
EMPTY_PNG = encode_png(np.zeros((TILE_PX, TILE_PX, 4), dtype=np.uint8))
