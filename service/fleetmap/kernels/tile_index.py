"""A tile-key -> pool-slot index that compiled kernels can read: open addressing in two arrays.

`TileStore.slots` (a dict) is the index Python code uses; this one mirrors it so that a kernel can
find a scan's tiles without a round trip to Python. `keys[h]` holds a tile's `(ti, tj)` and
`slots[h]` its pool slot, -1 where the entry is free; the table has a power-of-two size and is at
most half full, so a probe ends at a free entry after a few steps.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_MIX_I = np.uint64(0x9E3779B97F4A7C15)  # odd 64-bit constants: a multiplicative hash per coordinate
_MIX_J = np.uint64(0xC2B2AE3D27D4EB4F)


def new_index(tiles: int) -> tuple[np.ndarray, np.ndarray]:
    """An empty index with room for `tiles` tiles: `(keys, slots)`."""
    size = 16
    while size < 2 * tiles:
        size *= 2
    return np.zeros((size, 2), dtype=np.int64), np.full(size, -1, dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def _home(keys: np.ndarray, ti: int, tj: int) -> np.int64:
    """The entry where the probe for (ti, tj) starts."""
    h = np.uint64(ti) * _MIX_I ^ np.uint64(tj) * _MIX_J
    return np.int64((h ^ (h >> np.uint64(29))) & np.uint64(keys.shape[0] - 1))


@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def index_find(keys: np.ndarray, slots: np.ndarray, ti: int, tj: int) -> int:
    """The pool slot of tile (ti, tj), or -1 if the index does not hold it."""
    mask = keys.shape[0] - 1
    h = _home(keys, ti, tj)
    while slots[h] >= 0:
        if keys[h, 0] == ti and keys[h, 1] == tj:
            return slots[h]
        h = (h + 1) & mask
    return -1


@njit(cache=True, nogil=True, inline="always")
def index_has_room(slots: np.ndarray, tiles: int) -> bool:
    """Whether an index of `slots.size` entries may hold `tiles` tiles: at most half full, so that a
    probe ends at a free entry after a few steps."""
    return 2 * tiles <= slots.size


@njit(cache=True, nogil=True, inline="always")
def index_add(keys: np.ndarray, slots: np.ndarray, ti: int, tj: int, slot: int) -> None:
    """Add tile (ti, tj), not present, with pool slot `slot`. The caller keeps the table at most
    half full (`new_index`)."""
    mask = keys.shape[0] - 1
    h = _home(keys, ti, tj)
    while slots[h] >= 0:
        h = (h + 1) & mask
    keys[h, 0] = ti
    keys[h, 1] = tj
    slots[h] = slot


@njit(cache=True, nogil=True)
def index_insert(
    keys: np.ndarray, slots: np.ndarray, tiles_i: np.ndarray, tiles_j: np.ndarray, first: int
) -> None:
    """Add tiles `(tiles_i[k], tiles_j[k])`, none of them present, with slots `first + k` (see
    `index_add`)."""
    for k in range(tiles_i.size):
        index_add(keys, slots, tiles_i[k], tiles_j[k], first + k)
