"""Sparse tiled storage: square tiles of cells, created when first touched.

Cell (i, j) covers `[i*res, (i+1)*res) x [j*res, (j+1)*res)`; it lives in tile
`(i >> shift, j >> shift)` at local position `(i & mask, j & mask)`, which holds for negative indices
too (arithmetic shift floors). Tiles of one layer are slots of one pooled array of shape
`(capacity, tile_size, tile_size)` indexed `[slot, local_j, local_i]`: the compiled kernels get a few
plain arrays and a slot lookup instead of a dictionary of arrays. The pool doubles when full (an
amortised copy; the cap bounds it).

A `TileStore` is not thread-safe on its own: `GridMap` serialises writers and readers with its lock
(`len()` and `memory_bytes()` excepted: statistics read them without it; and `any_tile_in`, which
exports read between their tiles' reads).
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fleetmap.config import LayerName
from fleetmap.kernels.tile_index import index_has_room, index_insert, new_index
from fleetmap.kernels.update import UNKNOWN_COUNT, UNKNOWN_LOG_ODDS, UNKNOWN_TSDF, bump_versions, init_tile

if TYPE_CHECKING:
    from fleetmap.memory_budget import Charge, MemoryBudget

TileKey = tuple[int, int]
#: The pools of log_odds, hits, misses, tsdf and tsdf_weight, in the update kernels' order.
KernelPools = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class TileLimitError(RuntimeError):
    """A scan needed more tiles than the map's cap allows (or, as the subclass
    `memory_budget.MemoryBudgetError`, than a shared memory budget holds). The map was not changed."""


@dataclass(frozen=True)
class LayerArray:
    """One stored array of a layer: its name, dtype and the value of a never-observed cell."""

    name: str
    dtype: type[np.generic]
    unknown: float


#: The arrays each layer keeps per cell. Occupancy uses NaN as UNKNOWN (distinct from log-odds 0);
#: counts start at zero; a TSDF cell is unknown while its weight is zero.
LAYER_ARRAYS: dict[LayerName, tuple[LayerArray, ...]] = {
    "occupancy": (LayerArray("log_odds", np.float32, UNKNOWN_LOG_ODDS),),
    "counts": (LayerArray("hits", np.uint32, UNKNOWN_COUNT), LayerArray("misses", np.uint32, UNKNOWN_COUNT)),
    "tsdf": (
        LayerArray("tsdf", np.float32, UNKNOWN_TSDF),
        LayerArray("tsdf_weight", np.float32, UNKNOWN_TSDF),
    ),
}


def layer_arrays(layers: Iterable[LayerName]) -> tuple[LayerArray, ...]:
    """The arrays a store keeps for `layers`, in the order of its pools, `arrays` and stored tiles."""
    return tuple(a for layer in layers for a in LAYER_ARRAYS[layer])


def tile_bytes(tile_size: int, arrays: Iterable[LayerArray]) -> int:
    """Bytes one tile of `arrays` holds (every cell of each array)."""
    return tile_size * tile_size * sum(np.dtype(a.dtype).itemsize for a in arrays)


#: Bytes a tile costs beyond its cells and its version, in the structures that grow with a map's tiles
#: whatever their size: its key in `TileStore.slots` and `keys` (a tuple of two ints, its slot as an
#: int, a dict entry, a list pointer: 130-220 bytes), the kernels' index (`kernels.tile_index`: 24
#: bytes an entry, 2 to 4 entries a tile) and `GridMap`'s bounds per slot (40 bytes, up to twice over
#: as they double). tracemalloc measured 280-330 bytes a tile, up to 305 a slot of capacity (tiles of
#: 16 to 4096 cells, any layers: none of it depends on them). Uncounted, a map of 16-cell tiles held
#: 30 % more than the memory budget said it did.
SLOT_OVERHEAD = 384


def slot_bytes(tile_size: int, arrays: Iterable[LayerArray]) -> int:
    """Bytes one slot of a store's capacity holds: a tile of `arrays`, its version, and its share of
    the bookkeeping that grows with the tiles (`SLOT_OVERHEAD`). What `TileStore.memory_bytes` (and so
    the memory budget) counts a tile as."""
    return tile_bytes(tile_size, arrays) + np.dtype(np.int64).itemsize + SLOT_OVERHEAD


class TileStore:
    """Pooled per-layer tile arrays, a tile-key -> slot index, and a version per tile."""

    def __init__(self, tile_size: int, layers: Iterable[LayerName], max_tiles: int) -> None:
        if tile_size <= 0 or tile_size & (tile_size - 1):
            raise ValueError(f"tile_size must be a power of two, got {tile_size}")
        self.tile_size = tile_size
        self.shift = tile_size.bit_length() - 1
        self.mask = tile_size - 1
        self.max_tiles = max_tiles
        self.arrays = layer_arrays(layers)
        self._capacity = 0
        self.pools: dict[str, np.ndarray] = {}
        self.slots: dict[TileKey, int] = {}
        self.keys: list[TileKey] = []
        #: `slots` again, as kernels read it (`kernels.tile_index`): (keys, slots) arrays.
        self.index = new_index(0)
        self.versions = np.zeros(0, dtype=np.int64)
        self._version_clock = 0
        #: The shared budget this store's pools are charged to (`charge`), and the bytes charged, in a
        #: `Charge` that outlives the store so that its finalizer can hand them back.
        self.budget: MemoryBudget | None = None
        self.charged: Charge | None = None
        self._kernel_pools: KernelPools | None = None
        self._grow(0)

    # -- structure -------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.keys)

    def __contains__(self, key: TileKey) -> bool:
        return key in self.slots

    def pool(self, name: str) -> np.ndarray:
        """The pooled array of one stored layer array, or an empty stand-in if the layer is off.

        Kernels take every pool as an argument; a disabled layer is a (0, 0, 0) array they skip.
        """
        found = self.pools.get(name)
        if found is None:
            dtype = next(a.dtype for arrays in LAYER_ARRAYS.values() for a in arrays if a.name == name)
            return np.zeros((0, 0, 0), dtype=dtype)
        return found

    def kernel_pools(self) -> KernelPools:
        """`pool()` of log_odds, hits, misses, tsdf and tsdf_weight, as the update kernels take them
        (cached; growing the store renews them)."""
        pools = self._kernel_pools
        if pools is None:
            pools = self._kernel_pools = (
                self.pool("log_odds"), self.pool("hits"), self.pool("misses"), self.pool("tsdf"),
                self.pool("tsdf_weight"),
            )  # fmt: skip
        return pools

    def create(self, keys: list[TileKey], fill: bool = True) -> None:
        """Create tiles for `keys` (none may exist yet), all or none: past the cap, raise
        `TileLimitError` and create nothing. Their cells are never-observed, except with `fill`
        False: then they hold whatever the memory held, for a caller that writes every cell of every
        array before anyone reads them (a snapshot being restored), so that memory it never gets
        to write (a snapshot file that ends early) is never touched either."""
        if len(self.keys) + len(keys) > self.max_tiles:
            raise TileLimitError(
                f"the scan needs {len(keys)} new tile(s) but the map holds {len(self.keys)} of at most "
                f"{self.max_tiles} (max_tiles); the scan was not integrated"
            )
        needed = len(self.keys) + len(keys)
        if needed > self._capacity:
            # Empty until its first tiles, then room for just those, doubling from there: the memory
            # budget counts capacity. Four empty maps of 4096-cell tiles charged 5.4 GB and refused
            # every other map's growth; and a first growth to room for 16 tiles (21 MiB of the
            # default map) charged a map of one or two tiles 8 to 16 times what it held: 13 such
            # maps used up 256 MiB, and the 14th was refused 507 while the service held 26 tiles.
            target = 2 * self._capacity if self._capacity else needed
            self._grow(min(max(needed, target), self.max_tiles), needed)
        first = len(self.keys)
        for key in keys:
            slot = len(self.keys)
            self.slots[key] = slot
            self.keys.append(key)
            if fill:
                init_tile(slot, *self.kernel_pools())
            self.versions[slot] = self._tick()
        if not index_has_room(self.index[1], len(self.keys)):
            self.index = new_index(len(self.keys))
            keys, first = self.keys, 0
        if keys:
            pairs = np.array(keys, dtype=np.int64).reshape(-1, 2)
            index_insert(
                *self.index, np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1]), first
            )

    def adopt(self, keys: list[TileKey]) -> None:
        """Record tiles a kernel created in the next free slots, in order (see
        `kernels.integrate_scan`): it filled their arrays, gave them versions and indexed them."""
        for key in keys:
            self.slots[key] = len(self.keys)
            self.keys.append(key)

    def charge(self, budget: MemoryBudget, reserved: Charge | None = None) -> None:
        """Count this store's pools against `budget` from now on: what they hold already (even past
        the budget's limit: that memory exists), and every growth before it allocates. A growth the
        budget cannot cover stops short, at the tiles a scan needs; when even those do not fit,
        `create` raises `MemoryBudgetError` and changes nothing. The bytes go back to the budget
        when the store is freed.

        `reserved`: bytes reserved already for this store's coming tiles (an upload's reservation,
        `UploadReservation.charge`), which become its charge as they are: its growth draws on them
        before it reserves more."""
        if self.budget is not None:
            raise ValueError("this tile store is charged to a budget already")
        self.budget = budget
        self.charged = budget.reserve_anyway(self.memory_bytes(), reserved)
        weakref.finalize(self, budget.release, self.charged)

    def uncharge(self) -> None:
        """Hand the bytes this store holds back to its budget now, before the store is freed: for a
        map that is gone (deleted or replaced) and never grows again, while readers that still hold
        it (an event stream until its next poll, a download until it ends) finish, and for an
        upload's map that was not installed (`UploadReservation.release`). Loans of its bytes to
        uploads replacing it end with them (`MemoryBudget.release`). A growth after this would be
        charged again, and handed back when the store is freed."""
        if self.budget is not None and self.charged is not None:
            self.budget.release(self.charged)

    def _grow(self, capacity: int, needed: int = 0) -> None:
        """Make room for `capacity` tiles (at least `needed`, fewer when the budget runs short)."""
        if self.budget is not None and self.charged is not None:
            per_tile = self._tile_bytes()
            # Tiles charged ahead of the pools (an upload's reservation: `charge`) are drawn on first.
            ahead = min(
                capacity - self._capacity, max(0, self.charged.bytes - self.memory_bytes()) // per_tile
            )
            extra = self.budget.reserve(
                capacity - self._capacity - ahead, needed - self._capacity - ahead, per_tile, self.charged
            )
            capacity = self._capacity + ahead + extra
        t = self.tile_size
        # One array at a time, each old pool let go before the next new one is made: with the
        # cached `kernel_pools` tuple holding every old pool to the end, a growth held all the old
        # pools and all the new ones at once, twice the map's tiles (a Freiburg campus build at 2 cm
        # peaked at 4.7 GB for 2.2 GB of tiles).
        self._kernel_pools = None
        for a in self.arrays:
            new = np.empty((capacity, t, t), dtype=a.dtype)
            old = self.pools.pop(a.name, None)
            if old is not None:
                new[: len(self.keys)] = old[: len(self.keys)]
                del old
            self.pools[a.name] = new
        versions = np.zeros(capacity, dtype=np.int64)
        versions[: len(self.keys)] = self.versions[: len(self.keys)]
        self.versions = versions
        self._capacity = capacity
        self._kernel_pools = None

    # -- versions --------------------------------------------------------------------------------

    def _tick(self) -> int:
        self._version_clock += 1
        return self._version_clock

    def bump(self, slots: np.ndarray, changed: np.ndarray) -> None:
        """Give each tile `slots[k]` with `changed[k]` set a new version (`kernels.update.bump_versions`:
        a store-wide clock, so versions never repeat)."""
        self._version_clock = bump_versions(changed, slots, self.versions, self._version_clock)

    def any_tile_in(self, i0: int, j0: int, i1: int, j1: int) -> bool:
        """Whether a stored tile holds a cell of `[i0, i1) x [j0, j1)` (not empty). Reads the index
        without the map's lock: a tile created meanwhile may be missed, as a read just before it
        would have missed it (tiles are never removed)."""
        s = self.shift
        return any(
            (ti, tj) in self.slots
            for tj in range(j0 >> s, ((j1 - 1) >> s) + 1)
            for ti in range(i0 >> s, ((i1 - 1) >> s) + 1)
        )

    def version(self, key: TileKey) -> int | None:
        slot = self.slots.get(key)
        return None if slot is None else int(self.versions[slot])

    def restore_clock(self, clock: int) -> None:
        """Continue the version clock from `clock` (a store restored from disk, or versions a kernel
        handed out with `bump_versions`)."""
        self._version_clock = max(self._version_clock, int(clock))

    @property
    def clock(self) -> int:
        """The newest version handed out; it grows with every change to the store."""
        return self._version_clock

    def changed_since(self, since: int) -> np.ndarray:
        """The slots (ascending) of the tiles whose version is above `since`, a `clock` read earlier:
        every tile changed since then. The caller holds the map's lock."""
        return np.flatnonzero(self.versions[: len(self.keys)] > since)

    def clear_window(self, i0: int, j0: int, i1: int, j1: int) -> tuple[int, list[TileKey]]:
        """Make the cells `[i0, i1) x [j0, j1)` never-observed again in every array (each its
        `unknown` value, as `create` fills a tile), and give each tile where one of them was
        observed a new version. Tiles stay stored. Returns (how many of the cells were observed in
        some layer, the tiles changed, in slot order). The caller holds the map's lock.

        Only stored tiles are visited, so a window far larger than the map costs what the map does."""
        if i1 <= i0 or j1 <= j0:
            return 0, []
        s, t = self.shift, self.tile_size
        ti0, tj0, ti1, tj1 = i0 >> s, j0 >> s, (i1 - 1) >> s, (j1 - 1) >> s
        cleared, changed = 0, []
        for slot, (ti, tj) in enumerate(self.keys):
            if not (ti0 <= ti <= ti1 and tj0 <= tj <= tj1):
                continue
            rows = slice(max(j0, tj * t) - tj * t, min(j1, (tj + 1) * t) - tj * t)
            columns = slice(max(i0, ti * t) - ti * t, min(i1, (ti + 1) * t) - ti * t)
            observed = np.zeros((rows.stop - rows.start, columns.stop - columns.start), dtype=bool)
            for array in self.arrays:
                block = self.pools[array.name][slot, rows, columns]
                observed |= ~np.isnan(block) if np.isnan(array.unknown) else block != array.unknown
            count = int(np.count_nonzero(observed))
            if count == 0:
                continue
            for array in self.arrays:
                self.pools[array.name][slot, rows, columns] = array.unknown
            self.versions[slot] = self._tick()
            cleared += count
            changed.append((ti, tj))
        return cleared, changed

    # -- reads -----------------------------------------------------------------------------------

    def fill_window(
        self, name: str, i0: int, j0: int, out: np.ndarray, unobserved_by: str | None = None
    ) -> None:
        """Copy the cells `[i0, i0 + nx) x [j0, j0 + ny)` of one stored array into `out` (ny, nx).

        Cells in tiles that do not exist are left as they are in `out`, so the caller pre-fills it
        with the unknown value it wants. With `unobserved_by` (a weight array, `tsdf_weight`), the
        cells whose weight is not positive, never observed, are set to NaN instead: a tile at a time,
        so that no window of the weights is made (a whole one doubled a TSDF read's memory).
        """
        ny, nx = out.shape
        if ny == 0 or nx == 0:
            return
        s, t = self.shift, self.tile_size
        pool = self.pools[name]
        weights = None if unobserved_by is None else self.pools[unobserved_by]
        for tj in range((j0 >> s), ((j0 + ny - 1) >> s) + 1):
            for ti in range((i0 >> s), ((i0 + nx - 1) >> s) + 1):
                slot = self.slots.get((ti, tj))
                if slot is None:
                    continue
                # Overlap of this tile with the window, in global cell indices.
                gi0, gi1 = max(i0, ti * t), min(i0 + nx, (ti + 1) * t)
                gj0, gj1 = max(j0, tj * t), min(j0 + ny, (tj + 1) * t)
                cells = (slot, slice(gj0 - tj * t, gj1 - tj * t), slice(gi0 - ti * t, gi1 - ti * t))
                block = out[gj0 - j0 : gj1 - j0, gi0 - i0 : gi1 - i0]
                block[...] = pool[cells]
                if weights is not None:
                    block[weights[cells] <= 0] = np.nan

    def memory_bytes(self) -> int:
        """Bytes held by the pools, the versions and the bookkeeping of the tiles (`slot_bytes` a slot
        of allocated capacity, not only tiles in use).

        Like `len()`, it reads one int that growing replaces at once, so statistics (`/metrics`,
        `GET /maps`) read both without the map's lock: a scrape never waits for a scan or for a
        snapshot's copy of the tiles. It may lag a growth in progress by that growth."""
        return self._capacity * self._tile_bytes()

    def bytes_for(self, tiles: int) -> int:
        """Bytes `tiles` tiles take in this store's pools (what `memory_bytes` counts for them)."""
        return tiles * self._tile_bytes()

    def _tile_bytes(self) -> int:
        """Bytes one slot of capacity holds: a tile of every stored array, its version and its
        bookkeeping (`slot_bytes`)."""
        return slot_bytes(self.tile_size, self.arrays)
