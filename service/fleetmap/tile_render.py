"""Map tiles for web viewers: a zoom pyramid of 256 x 256 RGBA PNGs that Leaflet's `CRS.Simple`
displays as is, with versions for ETags and a thread-safe cache of rendered tiles.

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
surface (smallest |tsdf|). A pixel is unknown (transparent) only if no cell of its block is known.

Colours (RGBA; unknown is fully transparent, everything known is opaque):

- `probability`, `log_odds`: grey `255 * (1 - p)`, darker = more likely occupied (as the exported
  PNG); a known cell at p = 0.5 is mid-grey, not transparent.
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
"""

from __future__ import annotations

import itertools
import math
import struct
import threading
import time
import weakref
import zlib
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import numpy as np

from fleetmap.grid_map import LAYER_SOURCES, REGION_LAYERS, STATE_FREE, STATE_OCCUPIED, GridMap
from fleetmap.kernels.reduce import reduce_max_tiles, reduce_tsdf_tiles
from fleetmap.tiles import TileStore

if TYPE_CHECKING:
    from fleetmap.registry import MapEntry

#: Tile side in pixels.
TILE_PX = 256
#: Allowed zooms: z = 0 is one pixel per cell; MAX_ZOOM magnifies 16x, MIN_ZOOM shrinks 256x.
MIN_ZOOM, MAX_ZOOM = -8, 4
#: A hit / miss count at or above this is the top of the colour ramp (log scale below it).
COUNT_SCALE = 1000
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


# -- which storage tiles lie under a window -----------------------------------------------------------


class _KeyIndex:
    """The keys and slots of a store's tiles as arrays, for vectorised window queries over many
    storage tiles. Tiles are only ever added to a `TileStore` (`keys` grows, `slots` gains entries), so
    the index is extended with the new keys instead of rebuilt."""

    def __init__(self) -> None:
        self.count = 0
        self.ti = np.zeros(0, dtype=np.int64)
        self.tj = np.zeros(0, dtype=np.int64)
        self.slot = np.zeros(0, dtype=np.int64)


_key_indexes: weakref.WeakKeyDictionary[TileStore, _KeyIndex] = weakref.WeakKeyDictionary()
_store_tokens: weakref.WeakKeyDictionary[TileStore, int] = weakref.WeakKeyDictionary()
_token_counter = itertools.count(1)
_index_lock = threading.Lock()

#: Up to this many storage tiles in a window, probe the slot dict; beyond it, scan the key index.
_PROBE_LIMIT = 64


def _store_token(store: TileStore) -> int:
    """A number unique to this store for the process's lifetime (unlike id(), never reused), so cached
    reductions of a deleted map can never be mistaken for a new map's."""
    with _index_lock:
        token = _store_tokens.get(store)
        if token is None:
            token = _store_tokens[store] = next(_token_counter)
        return token


def _key_index(store: TileStore) -> _KeyIndex:
    with _index_lock:
        index = _key_indexes.get(store)
        if index is None:
            index = _key_indexes[store] = _KeyIndex()
        # Read the length first: TileStore.create inserts a key into `slots` before appending it to
        # `keys`, so every key in keys[:n] has its slot even while a writer is creating tiles.
        keys = store.keys
        n = len(keys)
        if n > index.count:
            new = keys[index.count : n]
            index.ti = np.concatenate([index.ti, np.fromiter((k[0] for k in new), np.int64, len(new))])
            index.tj = np.concatenate([index.tj, np.fromiter((k[1] for k in new), np.int64, len(new))])
            slots = store.slots
            index.slot = np.concatenate(
                [index.slot, np.fromiter((slots[k] for k in new), np.int64, len(new))]
            )
            index.count = n
        return index


def _tiles_under(store: TileStore, ti0: int, tj0: int, ti1: int, tj1: int) -> tuple[np.ndarray, ...]:
    """`(ti, tj, slot)` arrays of the existing storage tiles in `[ti0, ti1] x [tj0, tj1]` (inclusive)."""
    if (ti1 - ti0 + 1) * (tj1 - tj0 + 1) <= _PROBE_LIMIT:
        found = [
            (ti, tj, slot)
            for tj in range(tj0, tj1 + 1)
            for ti in range(ti0, ti1 + 1)
            if (slot := store.slots.get((ti, tj))) is not None
        ]
        if not found:
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty, empty
        arr = np.array(found, dtype=np.int64)
        return arr[:, 0], arr[:, 1], arr[:, 2]
    index = _key_index(store)
    inside = (index.ti >= ti0) & (index.ti <= ti1) & (index.tj >= tj0) & (index.tj <= tj1)
    return index.ti[inside], index.tj[inside], index.slot[inside]


def _storage_range(store: TileStore, i0: int, j0: int, i1: int, j1: int) -> tuple[int, int, int, int]:
    s = store.shift
    return i0 >> s, j0 >> s, (i1 - 1) >> s, (j1 - 1) >> s


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
    _, _, slots = _tiles_under(store, *_storage_range(store, i0, j0, i1, j1))
    if slots.size == 0:
        return 0
    return int(store.versions[slots].max())


def etag_for(generation: int, layer: str, z: int, x: int, y: int, version: int) -> str:
    """The (quoted) HTTP ETag of a tile: changes with the map's generation and the tile's version."""
    return f'"{generation}-{layer}-{z}-{x}-{y}-{version}"'


# -- reduction (z < 0) -------------------------------------------------------------------------------


def _score(values: np.ndarray, source: str) -> np.ndarray:
    """What the reduction maximises, as float64 (-inf = unknown), to combine values of several
    storage tiles that fall into one pixel."""
    score = values.astype(np.float64)
    if source == "tsdf":
        score = -np.abs(score)
    score[np.isnan(score)] = -np.inf
    return score


def _unknown_value(source: str) -> tuple[type[np.generic], float]:
    if source in ("hits", "misses"):
        return np.uint32, 0
    if source == "tsdf_weight":
        return np.float32, 0.0
    return np.float32, math.nan


# -- caches --------------------------------------------------------------------------------------------


class ReducedCache:
    """Thread-safe LRU of reduced storage-tile blocks `key -> (version, array)`, bounded in bytes.
    A key is a tuple whose first item is the token of the store the block comes from
    (`_store_token`).

    A zoomed-out web tile spans many storage tiles; re-reducing all of them whenever any one changes
    would copy the whole window under the map lock. With this cache a render copies and reduces only
    the storage tiles whose version moved since they were last reduced. The blocks of a store go
    when the store does (`follow`): a deleted map's held up to `max_bytes` until evicted.
    """

    def __init__(self, max_bytes: int = 128 << 20) -> None:
        self.max_bytes = max_bytes
        self._items: OrderedDict[tuple[Hashable, ...], tuple[int, np.ndarray]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._followed: set[int] = set()  # tokens of the live stores whose blocks this may hold
        # Tokens of stores freed since: appended by a finalizer, which may run inside any
        # allocation (a garbage collection), this cache's own under its lock included, so it only
        # appends (atomic), and the next `put` or `nbytes` drops their blocks under the lock.
        self._freed: list[int] = []

    def follow(self, store: TileStore, token: int) -> None:
        """Drop the blocks of `store` (whose token is `token`) once the store is freed: a deleted or
        replaced map's, which no render can ask for again."""
        with self._lock:
            if token in self._followed:
                return
            self._followed.add(token)
        weakref.finalize(store, self._freed.append, token)

    def _drop_freed(self) -> None:
        """Drop the blocks of the stores freed since the last call (call under the lock)."""
        while self._freed:
            token = self._freed.pop()
            self._followed.discard(token)
            for key in [k for k in self._items if k[0] == token]:
                self._bytes -= self._items.pop(key)[1].nbytes

    def get(self, key: tuple[Hashable, ...], version: int) -> np.ndarray | None:
        with self._lock:
            item = self._items.get(key)
            if item is None or item[0] != version:
                return None
            self._items.move_to_end(key)
            return item[1]

    def get_many(self, keys: Sequence[tuple[Hashable, ...]], versions: list[int]) -> list[np.ndarray | None]:
        """`get` for many keys under one acquisition of the lock."""
        out: list[np.ndarray | None] = []
        with self._lock:
            for key, version in zip(keys, versions, strict=True):
                item = self._items.get(key)
                if item is None or item[0] != version:
                    out.append(None)
                else:
                    self._items.move_to_end(key)
                    out.append(item[1])
        return out

    def put(self, key: tuple[Hashable, ...], version: int, array: np.ndarray) -> None:
        with self._lock:
            self._drop_freed()
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old[1].nbytes
            if old is not None and old[0] > version:  # a racing render stored a newer block: keep it
                self._items[key] = old
                self._bytes += old[1].nbytes
                return
            self._items[key] = (version, array)
            self._bytes += array.nbytes
            while self._bytes > self.max_bytes and self._items:
                _, (_, evicted) = self._items.popitem(last=False)
                self._bytes -= evicted.nbytes

    @property
    def nbytes(self) -> int:
        with self._lock:
            self._drop_freed()
            return self._bytes


# -- rendering -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Snapshot:
    """What a render copied under the map lock: the version and one value block per storage tile."""

    version: int
    blocks: list[np.ndarray]  # each (b, b), [local_j, local_i], already reduced by `factor`
    pos_i: np.ndarray  # position of each block in the window, in blocks of P cells
    pos_j: np.ndarray


def _snapshot(
    gmap: GridMap, source: str, i0: int, j0: int, size: int, factor: int, reduced: ReducedCache | None
) -> _Snapshot:
    """The cells of window `[i0, i0+size)^2` that lie in existing storage tiles, as blocks of
    P = min(tile_size, size) cells reduced by `factor`, read under the map lock: with `factor` 1
    copies, else reduced from the pools there (`kernels.reduce`), so that a render holds only the
    blocks it returns, never a copy of every tile under a zoomed-out window."""
    store = gmap.store
    t = store.tile_size
    piece = min(t, size)
    whole_tiles = t <= size  # else the window lies inside one storage tile
    li0, lj0 = (0, 0) if whole_tiles else (i0 & store.mask, j0 & store.mask)
    # Only reductions are cached (a block of factor 1 is a plain copy of the store's cells).
    cache = reduced if factor > 1 else None
    token = _store_token(store) if cache is not None else 0
    if cache is not None:
        cache.follow(store, token)
    stored = ("tsdf", "tsdf_weight") if source == "tsdf" else (source,)
    with gmap.lock:
        ti, tj, slots = _tiles_under(store, *_storage_range(store, i0, j0, i0 + size, j0 + size))
        if slots.size == 0:
            return _Snapshot(0, [], ti, tj)
        versions = store.versions[slots].copy()
        blocks: list[np.ndarray | None] = [None] * slots.size
        if cache is not None:
            keys = [
                (token, source, a, b, li0, lj0, piece, factor)
                for a, b in zip(ti.tolist(), tj.tolist(), strict=True)
            ]
            blocks = cache.get_many(keys, versions.tolist())
        todo = np.array([k for k in range(slots.size) if blocks[k] is None], dtype=np.int64)
        values = np.zeros(0)
        if todo.size and factor > 1:
            # Reduced straight from the pools, a tile at a time: a copy of every tile under a
            # zoomed-out window first held a whole layer of a big map twice (kernels/reduce.py).
            side = piece // factor
            dtype, _ = _unknown_value(source)
            values = np.empty((todo.size, side, side), dtype=dtype)
            if source == "tsdf":
                reduce_tsdf_tiles(
                    store.pools["tsdf"],
                    store.pools["tsdf_weight"],
                    slots[todo],
                    li0,
                    lj0,
                    piece,
                    factor,
                    values,
                )
            else:
                reduce_max_tiles(store.pools[source], slots[todo], li0, lj0, piece, factor, values)
        elif todo.size:
            copies = {
                name: store.pools[name][slots[todo], lj0 : lj0 + piece, li0 : li0 + piece] for name in stored
            }
    # The lock is released: everything below works on copies.
    if todo.size:
        if factor == 1:
            values = copies[source]
            if source == "tsdf":
                values[copies["tsdf_weight"] <= 0] = np.nan  # a TSDF cell with zero weight is unobserved
        for n, k in enumerate(todo.tolist()):
            blocks[k] = values[n]
            if cache is not None:
                key = (token, source, int(ti[k]), int(tj[k]), li0, lj0, piece, factor)
                # A copy: a view would keep the whole stack alive and be under-counted.
                cache.put(key, int(versions[k]), values[n].copy())
    if whole_tiles:
        pos_i, pos_j = ti - (i0 >> store.shift), tj - (j0 >> store.shift)
    else:
        pos_i = pos_j = np.zeros(1, dtype=np.int64)
    # Every block is filled now: those the cache did not have are the `todo` ones, filled above.
    return _Snapshot(int(versions.max()), cast(list[np.ndarray], blocks), pos_i, pos_j)


def _assemble(snap: _Snapshot, source: str, grid_side: int, piece: int, cells_per_px: int) -> np.ndarray:
    """The (grid_side, grid_side) value grid (row 0 = lowest j) from the snapshot's blocks."""
    dtype, unknown = _unknown_value(source)
    grid = np.full((grid_side, grid_side), unknown, dtype=dtype)
    if cells_per_px <= piece:
        # Each block fills its own square of the grid: one vectorised scatter of (n, b, b) blocks.
        b = snap.blocks[0].shape[0]
        per_side = grid_side // b
        view = grid.reshape(per_side, b, per_side, b)
        view[snap.pos_j, :, snap.pos_i, :] = np.stack(snap.blocks)
        return grid
    # Several storage tiles (each reduced to one value) share a pixel: keep the best by the source's
    # score. maximum.at handles repeated pixels; the winners are then written (ties are equivalent).
    values = np.array([blk[0, 0] for blk in snap.blocks], dtype=dtype)
    px = snap.pos_i * piece // cells_per_px
    py = snap.pos_j * piece // cells_per_px
    score = _score(values, source)
    best = np.full((grid_side, grid_side), -np.inf)
    np.maximum.at(best, (py, px), score)
    win = (score == best[py, px]) & (score > -np.inf)
    grid[py[win], px[win]] = values[win]
    return grid


def _ramp_lut(anchors: list[tuple[int, int, int]]) -> np.ndarray:
    """256 RGBA entries: 0 transparent, 1..255 interpolated through `anchors`, opaque."""
    lut = np.zeros((256, 4), dtype=np.uint8)
    pos = np.linspace(0.0, 1.0, len(anchors))
    t = np.linspace(0.0, 1.0, 255)
    for c in range(3):
        lut[1:, c] = np.round(np.interp(t, pos, [a[c] for a in anchors]))
    lut[1:, 3] = 255
    return lut


#: Viridis sampled at 0, 0.1, ..., 1 (perceptually uniform, colour-blind safe).
_VIRIDIS = _ramp_lut([
    (68, 1, 84), (72, 36, 117), (65, 68, 135), (53, 95, 141), (42, 120, 142), (33, 145, 140),
    (34, 168, 132), (68, 191, 112), (122, 209, 81), (189, 223, 38), (253, 231, 37),
])  # fmt: skip
#: Blue - white - red (ColorBrewer RdBu ends).
_DIVERGING = _ramp_lut([(33, 102, 172), (247, 247, 247), (178, 24, 43)])
#: Index = round(255 * (1 - p)) -> that grey; index 256 = unknown (transparent).
_GREY = np.zeros((257, 4), dtype=np.uint8)
_GREY[:256, :3] = np.arange(256, dtype=np.uint8)[:, None]
_GREY[:256, 3] = 255
#: By state code: unknown transparent, free near-white, occupied near-black.
_STATE = np.zeros((3, 4), dtype=np.uint8)
_STATE[STATE_FREE] = (245, 245, 245, 255)
_STATE[STATE_OCCUPIED] = (20, 20, 20, 255)


def _ramp_index(values: np.ndarray, scale: float) -> np.ndarray:
    """Ramp LUT indices for non-negative values on a log scale: 0 -> 0 (transparent), else 1..255."""
    v = values.astype(np.float32)
    t = np.minimum(np.log1p(v) * np.float32(1.0 / math.log1p(scale)), 1.0)
    idx = (1.0 + np.rint(t * 254.0)).astype(np.uint8)
    idx[~(v > 0)] = 0
    return idx


def _colour_index(gmap: GridMap, layer: str, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """`(index, lut, transparent_index)`: RGBA = lut[index]."""
    if layer in ("probability", "log_odds"):
        with np.errstate(over="ignore"):
            p = 1.0 / (1.0 + np.exp(-grid))  # float32; NaN stays NaN
        idx = np.rint(255.0 * (1.0 - np.nan_to_num(p, nan=0.5))).astype(np.uint16)
        idx[np.isnan(grid)] = 256
        return idx, _GREY, 256
    if layer == "state":
        return gmap.classify(grid), _STATE, 0
    if layer in ("hits", "misses"):
        return _ramp_index(grid, COUNT_SCALE), _VIRIDIS, 0
    if layer == "tsdf_weight":
        return _ramp_index(grid, gmap.config.tsdf.max_weight), _VIRIDIS, 0
    # tsdf in [-1, 1] -> 1..255; NaN (unobserved) -> 0.
    t = (np.clip(np.nan_to_num(grid, nan=0.0), -1.0, 1.0) + 1.0) * 127.0
    idx = (1.0 + np.rint(t)).astype(np.uint8)
    idx[np.isnan(grid)] = 0
    return idx, _DIVERGING, 0


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
    snap = _snapshot(gmap, source, i0, j0, size, factor, reduced)
    if not snap.blocks:
        return EMPTY_PNG, snap.version
    grid = _assemble(snap, source, size // cells_per_px, piece, cells_per_px)
    idx, lut, transparent = _colour_index(gmap, layer, grid)
    if not (idx != transparent).any():
        return EMPTY_PNG, snap.version
    idx = idx[::-1]  # PNG rows run from the highest j down
    if z > 0:
        k = 1 << z  # nearest neighbour: each cell becomes a k x k block
        idx = np.repeat(np.repeat(idx, k, axis=0), k, axis=1)
    return encode_png(lut[idx]), snap.version


# -- PNG ------------------------------------------------------------------------------------------------


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_png(rgba: np.ndarray) -> bytes:
    """An 8-bit RGBA PNG of an (h, w, 4) uint8 array, zlib level 1 and no row filter: about twice as
    fast as Pillow at compress_level=1, and map tiles (flat areas, repeated rows) compress well."""
    h, w, _ = rgba.shape
    raw = np.zeros((h, 1 + 4 * w), dtype=np.uint8)  # column 0: filter type 0 (None) for every row
    raw[:, 1:] = rgba.reshape(h, 4 * w)
    header = struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0)  # 8 bits, colour type 6 = RGBA
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), 1))
        + _chunk(b"IEND", b"")
    )


#: The fully transparent tile: unexplored space is served as this one precomputed PNG.
EMPTY_PNG = encode_png(np.zeros((TILE_PX, TILE_PX, 4), dtype=np.uint8))


# -- the rendered-tile cache ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Cached:
    version: int
    png: bytes
    etag: str


class TileCache:
    """Thread-safe LRU of rendered tiles keyed by (map id, generation, layer, z, x, y), each stored
    with the tile version it shows.

    `get_or_render` reads the current version first (cheap, lock-free), serves the cached PNG if it
    is that version (or newer), else renders, stores and returns it. Concurrent requests for the
    same missing tile render it once: the others wait for that render (and use it if it is at least
    the version they saw). A new map generation (a map deleted and re-created) never hits the old
    generation's entries; those age out, or `drop_map` removes them at once.
    """

    def __init__(
        self,
        max_entries: int = 4096,
        max_bytes: int = 256 << 20,
        reduced_bytes: int = 128 << 20,
        on_render: Callable[[str, int, float], None] | None = None,
    ) -> None:
        """`on_render(layer, z, seconds)` is called after each actual render (for metrics)."""
        if max_entries < 1:
            raise ValueError("max_entries must be at least 1")
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self.reduced = ReducedCache(reduced_bytes)
        self.on_render = on_render
        self.hits = 0  # requests served from the cache
        self.renders = 0  # tiles actually rendered
        self._items: OrderedDict[tuple, _Cached] = OrderedDict()
        self._bytes = 0
        self._inflight: dict[tuple, Future[_Cached]] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def cached(self, entry: MapEntry, layer: str, z: int, x: int, y: int) -> tuple[bytes, str] | None:
        """`(png_bytes, etag)` if the cache holds the tile's current version, else None: never
        renders and never waits for a render, so an event loop may call it. Raises TileError for a
        bad zoom, tile index or layer."""
        gmap = entry.gmap
        version = tile_version(gmap, z, x, y)  # validates z, x, y
        check_layer(gmap, layer)
        key = (entry.id, entry.generation, layer, z, x, y)
        with self._lock:
            hit = self._items.get(key)
            if hit is None or hit.version < version:
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return hit.png, hit.etag

    def get_or_render(self, entry: MapEntry, layer: str, z: int, x: int, y: int) -> tuple[bytes, str]:
        """`(png_bytes, etag)` of tile (z, x, y) of `layer` of the registry entry's map.
        Raises TileError for a bad zoom, tile index or layer."""
        gmap = entry.gmap
        version = tile_version(gmap, z, x, y)  # validates z, x, y
        check_layer(gmap, layer)
        key = (entry.id, entry.generation, layer, z, x, y)
        while True:
            with self._lock:
                hit = self._items.get(key)
                if hit is not None and hit.version >= version:
                    self._items.move_to_end(key)
                    self.hits += 1
                    return hit.png, hit.etag
                pending = self._inflight.get(key)
                if pending is None:
                    pending = self._inflight[key] = Future()
                    owner = True
                else:
                    owner = False
            if owner:
                return self._render(entry, layer, z, x, y, key, pending)
            done = pending.result()  # re-raises the renderer's exception
            if done.version >= version:
                return done.png, done.etag
            # That render began before the change we saw: go round (it has left _inflight by now).

    def _render(
        self, entry: MapEntry, layer: str, z: int, x: int, y: int, key: tuple, pending: Future[_Cached]
    ) -> tuple[bytes, str]:
        try:
            started = time.perf_counter()
            png, version = render_tile_versioned(entry.gmap, layer, z, x, y, self.reduced)
            seconds = time.perf_counter() - started
            done = _Cached(version, png, etag_for(entry.generation, layer, z, x, y, version))
        except BaseException as exc:
            with self._lock:
                self._inflight.pop(key, None)
            pending.set_exception(exc)
            raise
        with self._lock:
            self.renders += 1
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= len(old.png)
            keep = old if old is not None and old.version > done.version else done
            self._items[key] = keep
            self._bytes += len(keep.png)
            while len(self._items) > self.max_entries or (
                self._bytes > self.max_bytes and len(self._items) > 1
            ):
                _, evicted = self._items.popitem(last=False)
                self._bytes -= len(evicted.png)
            self._inflight.pop(key, None)
        pending.set_result(done)
        if self.on_render is not None:
            self.on_render(layer, z, seconds)
        return done.png, done.etag

    def drop_map(self, map_id: str) -> None:
        """Forget every cached tile of `map_id` (all generations), e.g. when the map is deleted."""
        with self._lock:
            for key in [k for k in self._items if k[0] == map_id]:
                self._bytes -= len(self._items.pop(key).png)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0
