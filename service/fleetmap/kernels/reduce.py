"""Zoomed-out tile blocks: reduce storage tiles straight from their pools, one tile at a time.

A zoomed-out web tile (`tile_render`, z < 0) shows each storage tile as a block of
`piece / factor` pixels per side. Copying the storage tiles first and reducing the copies costs a copy
of every tile under the window at once: at z = -8 a web tile spans 256 x 256 storage tiles, so a
map of 6,400 tiles had its whole layer (1.7 GB of log-odds) copied, and reduced through halving
temporaries, for one render (a 2.9 GB peak). These kernels read each tile from its pool and write only
the reduced block, through a scratch of a quarter tile, so a render holds what it returns.

The result is exactly that of halving the block `log2(factor)` times, columns then rows (the order
of the NumPy halving these replaced), which matters for the TSDF's ties: `reduce_max_tiles` keeps the largest
value of each block, a NaN only where every cell is NaN (NumPy's `fmax`; counts and weights hold no
NaN), and `reduce_tsdf_tiles` the value nearest the surface (smallest |tsdf|) among observed cells
(weight above 0), the first of a pair on a tie.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _fmax(first, second):  # type: ignore[no-untyped-def]
    """NumPy's `fmax` of two scalars: NaN only if both are."""
    if first != first:
        return second
    if second != second:
        return first
    return first if first >= second else second


@njit(cache=True, nogil=True, inline="always")
def _nearest(first, second):  # type: ignore[no-untyped-def]
    """The TSDF value nearer the surface, `first` on a tie; an unobserved (NaN) `first` loses."""
    if first != first or abs(second) < abs(first):
        return second
    return first


@njit(cache=True, nogil=True)
def reduce_max_tiles(
    pool: np.ndarray, slots: np.ndarray, li0: int, lj0: int, piece: int, factor: int, out: np.ndarray
) -> None:
    """For each k, `out[k]` = the `piece` x `piece` cells of tile `slots[k]` from local (li0, lj0),
    each `factor` x `factor` block reduced to its largest value (`fmax`). `factor` >= 2, a power of
    two dividing `piece`; `out` is (n, piece / factor, piece / factor) of the pool's dtype."""
    half = piece // 2
    side = piece // factor
    scratch = np.empty((half, half), dtype=out.dtype)
    for k in range(slots.size):
        s = slots[k]
        for r in range(half):
            j = lj0 + 2 * r
            for c in range(half):
                i = li0 + 2 * c
                low = _fmax(pool[s, j, i], pool[s, j, i + 1])
                high = _fmax(pool[s, j + 1, i], pool[s, j + 1, i + 1])
                scratch[r, c] = _fmax(low, high)
        m = half
        while m > side:
            m //= 2
            # In place: cell (r, c) is written after every read of it (those of (r // 2, c // 2)).
            for r in range(m):
                for c in range(m):
                    low = _fmax(scratch[2 * r, 2 * c], scratch[2 * r, 2 * c + 1])
                    high = _fmax(scratch[2 * r + 1, 2 * c], scratch[2 * r + 1, 2 * c + 1])
                    scratch[r, c] = _fmax(low, high)
        out[k, :, :] = scratch[:side, :side]


@njit(cache=True, nogil=True, inline="always")
def _tsdf_at(tsdf: np.ndarray, weight: np.ndarray, s: int, j: int, i: int) -> np.float32:
    """The TSDF value of one cell, NaN where its weight says it was never observed."""
    return tsdf[s, j, i] if not weight[s, j, i] <= 0 else np.float32(np.nan)


@njit(cache=True, nogil=True)
def reduce_tsdf_tiles(
    tsdf: np.ndarray,
    weight: np.ndarray,
    slots: np.ndarray,
    li0: int,
    lj0: int,
    piece: int,
    factor: int,
    out: np.ndarray,
) -> None:
    """`reduce_max_tiles` for the TSDF: each block reduced to the observed value nearest the surface
    (NaN if no cell of it was observed). `out` is float32."""
    half = piece // 2
    side = piece // factor
    scratch = np.empty((half, half), dtype=np.float32)
    for k in range(slots.size):
        s = slots[k]
        for r in range(half):
            j = lj0 + 2 * r
            for c in range(half):
                i = li0 + 2 * c
                low = _nearest(_tsdf_at(tsdf, weight, s, j, i), _tsdf_at(tsdf, weight, s, j, i + 1))
                high = _nearest(_tsdf_at(tsdf, weight, s, j + 1, i), _tsdf_at(tsdf, weight, s, j + 1, i + 1))
                scratch[r, c] = _nearest(low, high)
        m = half
        while m > side:
            m //= 2
            for r in range(m):
                for c in range(m):
                    low = _nearest(scratch[2 * r, 2 * c], scratch[2 * r, 2 * c + 1])
                    high = _nearest(scratch[2 * r + 1, 2 * c], scratch[2 * r + 1, 2 * c + 1])
                    scratch[r, c] = _nearest(low, high)
        out[k, :, :] = scratch[:side, :side]
