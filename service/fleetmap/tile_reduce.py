"""What a web tile's render reads from a map (see tile_render's docstring, "Locking"): the storage
tiles under the tile's window (`tiles_under`, which `tile_render.tile_version` also reads), their
cells copied (z >= 0) or reduced to one value per pixel (z < 0, `kernels.reduce`) under the map's
lock (`snapshot`), the reduced blocks cached by version between renders (`ReducedCache`), and the
blocks assembled into the tile's grid of values (`assemble`) once the lock is released. A pixel
that summarises several cells keeps the most occupied known one (walls do not vanish when zooming
out), the largest count or weight, or the TSDF value nearest the surface (of two as near, the one
the kernels' halving keeps, whether the cells share a storage tile or not)."""

from __future__ import annotations

import itertools
import math
import threading
import weakref
from collections import OrderedDict
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from fleetmap.grid_map import GridMap
from fleetmap.kernels.reduce import reduce_max_tiles, reduce_tsdf_tiles
from fleetmap.tiles import TileStore

# -- which storage tiles lie under a window ------------------------------------------------------------


@dataclass(frozen=True)
class _KeyIndex:
    """The keys and slots of a store's first `count` tiles as arrays, for vectorised window queries
    over many storage tiles. Tiles are only ever added to a `TileStore` (`keys` grows, `slots` gains
    entries), so a newer index extends the last one's arrays instead of building them anew.

    Never changed once made: readers use it without the lock while another thread makes the next
    one (a revalidation on the event loop, a render in the thread pool). Extended in place, array
    after array, a reader between two of them compared arrays of two lengths (a 500)."""

    count: int
    ti: np.ndarray
    tj: np.ndarray
    slot: np.ndarray


_NO_KEYS = _KeyIndex(0, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))


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
    """The index of `store`'s tiles as they are now: the last one made, or a new one extending it
    (kept for the next call) when tiles were added since."""
    with _index_lock:
        index = _key_indexes.get(store, _NO_KEYS)
        # Read the length first: TileStore.create inserts a key into `slots` before appending it to
        # `keys`, so every key in keys[:n] has its slot even while a writer is creating tiles.
        keys = store.keys
        n = len(keys)
        if n > index.count:
            new = keys[index.count : n]
            slots = store.slots
            index = _key_indexes[store] = _KeyIndex(
                n,
                np.concatenate([index.ti, np.fromiter((k[0] for k in new), np.int64, len(new))]),
                np.concatenate([index.tj, np.fromiter((k[1] for k in new), np.int64, len(new))]),
                np.concatenate([index.slot, np.fromiter((slots[k] for k in new), np.int64, len(new))]),
            )
        return index


def tiles_under(store: TileStore, ti0: int, tj0: int, ti1: int, tj1: int) -> tuple[np.ndarray, ...]:
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


def storage_range(store: TileStore, i0: int, j0: int, i1: int, j1: int) -> tuple[int, int, int, int]:
    s = store.shift
    return i0 >> s, j0 >> s, (i1 - 1) >> s, (j1 - 1) >> s


# -- reduction (z < 0) ---------------------------------------------------------------------------------


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


# -- the cache of reduced blocks -----------------------------------------------------------------------


#: Bytes a cached block holds beside its cells: its array object, its key (a tuple of eight), its
#: version and its place in the LRU (whose table a full cache's churn keeps at its largest);
#: tracemalloc measured 460-520. Counted with the cells: a map of 16-cell tiles seen zoomed out makes
#: blocks of one cell (4 bytes), so a bound on cells alone let 128 MiB of them hold ~15 GB.
BLOCK_OVERHEAD = 640


def _block_bytes(block: np.ndarray) -> int:
    """What `ReducedCache` counts a block as: its cells and `BLOCK_OVERHEAD`."""
    return block.nbytes + BLOCK_OVERHEAD


class ReducedCache:
    """Thread-safe LRU of reduced storage-tile blocks `key -> (version, array)`, bounded in bytes (each
    block's cells and its `BLOCK_OVERHEAD`). A key is a tuple whose first item is the token of the
    store the block comes from (`_store_token`).

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
                self._bytes -= _block_bytes(self._items.pop(key)[1])

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
                self._bytes -= _block_bytes(old[1])
            if old is not None and old[0] > version:  # a racing render stored a newer block: keep it
                self._items[key] = old
                self._bytes += _block_bytes(old[1])
                return
            self._items[key] = (version, array)
            self._bytes += _block_bytes(array)
            while self._bytes > self.max_bytes and self._items:
                _, (_, evicted) = self._items.popitem(last=False)
                self._bytes -= _block_bytes(evicted)

    @property
    def nbytes(self) -> int:
        with self._lock:
            self._drop_freed()
            return self._bytes


# -- a render's read of the map ------------------------------------------------------------------------


@dataclass(frozen=True)
class _Snapshot:
    """What a render copied under the map lock: the version and one value block per storage tile."""

    version: int
    blocks: list[np.ndarray]  # each (b, b), [local_j, local_i], already reduced by `factor`
    pos_i: np.ndarray  # position of each block in the window, in blocks of P cells
    pos_j: np.ndarray


def snapshot(
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
        ti, tj, slots = tiles_under(store, *storage_range(store, i0, j0, i0 + size, j0 + size))
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


def assemble(snap: _Snapshot, source: str, grid_side: int, piece: int, cells_per_px: int) -> np.ndarray:
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
    # score (maximum.at handles repeated pixels), and of the blocks that tie for it, the one the
    # halving would keep (`_halving_rank`): a TSDF value and its opposite tie, and NumPy writes
    # repeated indices in no set order, so the tie went to the block written last, and the same
    # scans drew a red or a blue pixel depending on the map's tile_size.
    values = np.array([blk[0, 0] for blk in snap.blocks], dtype=dtype)
    px = snap.pos_i * piece // cells_per_px
    py = snap.pos_j * piece // cells_per_px
    score = _score(values, source)
    best = np.full((grid_side, grid_side), -np.inf)
    np.maximum.at(best, (py, px), score)
    win = np.flatnonzero((score == best[py, px]) & (score > -np.inf))
    pixel = py[win] * grid_side + px[win]
    rank = _halving_rank(snap.pos_i[win], snap.pos_j[win], cells_per_px // piece)
    order = np.lexsort((rank, pixel))  # by pixel, then by rank: each pixel's first is its keeper
    _, first = np.unique(pixel[order], return_index=True)
    keep = win[order[first]]
    grid[py[keep], px[keep]] = values[keep]
    return grid


def _halving_rank(pos_i: np.ndarray, pos_j: np.ndarray, per_pixel: int) -> np.ndarray:
    """The order in which halving a pixel's `per_pixel` x `per_pixel` blocks (at positions `pos_i`,
    `pos_j` in blocks; a power of two) prefers them on a tie, lowest first. `kernels.reduce` halves
    columns, then rows, keeping the first of a pair on a tie: at every level the lower j half wins,
    then within it the lower i half, so the rank interleaves the bits of the position within the
    pixel, j before i, from the highest."""
    local_i, local_j = pos_i % per_pixel, pos_j % per_pixel
    rank = np.zeros(pos_i.shape, dtype=np.int64)
    bit = per_pixel >> 1
    while bit:
        rank = rank * 4 + ((local_j & bit) != 0) * 2 + ((local_i & bit) != 0)
        bit >>= 1
    return rank
