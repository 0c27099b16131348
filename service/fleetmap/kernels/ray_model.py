"""The ray sensor model: a return makes every cell its segment passes through a miss and its end cell
a hit; a cleared no-return beam makes every cell up to its clearing range a miss."""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetmap.kernels.traversal import cell_count, cells, walk

#: Per-beam kinds given to `trace_rays`.
BEAM_SKIP = 0
BEAM_HIT = 1
BEAM_CLEAR = 2

#: Per-cell update kinds produced by the sensor models. They are bit flags so that per-scan marking
#: can OR them in without a branch: a cell marked `CELL_HIT` (alone or with a miss) is a hit.
CELL_MISS = 1
CELL_HIT = 2


@njit(cache=True, nogil=True)
def trace_rays(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, beam_kind: np.ndarray, method: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells of every beam from (ox, oy) to (ex[b], ey[b]) in CELL units, in beam order.

    Returns `(ci, cj, kind)`: the cells and whether each is a miss or a hit (`CELL_MISS`,
    `CELL_HIT`). A `BEAM_HIT` beam's end cell is a hit, the rest of its cells are misses; every cell
    of a `BEAM_CLEAR` beam is a miss; `BEAM_SKIP` beams yield nothing.
    """
    total = 0
    for b in range(ex.size):
        if beam_kind[b] != BEAM_SKIP:
            total += cell_count(ox, oy, ex[b], ey[b], method)
    ci = np.empty(total, dtype=np.int64)
    cj = np.empty(total, dtype=np.int64)
    kind = np.full(total, CELL_MISS, dtype=np.uint8)
    k = 0
    for b in range(ex.size):
        if beam_kind[b] == BEAM_SKIP:
            continue
        k += walk(ox, oy, ex[b], ey[b], method, ci, cj, k)
        if beam_kind[b] == BEAM_HIT:
            kind[k - 1] = CELL_HIT
    return ci, cj, kind


#: Up to this many tiles in a scan's bounding box, `trace_rays_marks` allocates a plane for every
#: tile of the box (16 MiB at 256 x 256) and walks once; beyond it, it first walks to find the
#: touched tiles so that memory stays proportional to them.
DENSE_TILE_LIMIT = 256


@njit(cache=True, nogil=True)
def trace_rays_marks(
    ox: float,
    oy: float,
    ex: np.ndarray,
    ey: np.ndarray,
    beam_kind: np.ndarray,
    method: int,
    shift: int,
    ti0: int,
    tj0: int,
    ti1: int,
    tj1: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-scan marks: each cell any beam touches, once, as a hit if any beam ends in it.

    Returns `(tiles_i, tiles_j, planes, marks)`: tile `(tiles_i[k], tiles_j[k])` was touched and its
    marks are `marks[planes[k]]`, a `(T, T)` plane of OR-ed `CELL_MISS` / `CELL_HIT` flags indexed
    `[local_j, local_i]` (0: untouched). `[ti0, ti1] x [tj0, tj1]` must contain every beam's cells.
    """
    t = 1 << shift
    mask = t - 1
    nj = tj1 - tj0 + 1
    ni = ti1 - ti0 + 1
    if nj * ni <= DENSE_TILE_LIMIT:
        index = np.arange(nj * ni).reshape(nj, ni)
        m = nj * ni
    else:
        # A walk to find the touched tiles, so that planes exist only for those.
        index = np.full((nj, ni), -1, dtype=np.int64)
        m = 0
        for b in range(ex.size):
            if beam_kind[b] == BEAM_SKIP:
                continue
            for i, j in cells(ox, oy, ex[b], ey[b], method):
                if index[(j >> shift) - tj0, (i >> shift) - ti0] < 0:
                    index[(j >> shift) - tj0, (i >> shift) - ti0] = m
                    m += 1
    marks = np.zeros((m, t, t), dtype=np.uint8)
    touched = np.zeros(m, dtype=np.uint8)
    for b in range(ex.size):
        if beam_kind[b] == BEAM_SKIP:
            continue
        c = 0
        for i, j in cells(ox, oy, ex[b], ey[b], method):
            c = index[(j >> shift) - tj0, (i >> shift) - ti0]
            marks[c, j & mask, i & mask] |= CELL_MISS
            touched[c] = 1
        if beam_kind[b] == BEAM_HIT:
            # The end cell: the walk's last (i, j), in plane c.
            marks[c, j & mask, i & mask] |= CELL_HIT
    count = 0
    for c in range(m):
        count += touched[c]
    tiles_i = np.empty(count, dtype=np.int64)
    tiles_j = np.empty(count, dtype=np.int64)
    planes = np.empty(count, dtype=np.int64)
    k = 0
    for a in range(nj):
        for b in range(ni):
            c = index[a, b]
            if c >= 0 and touched[c]:
                tiles_i[k] = b + ti0
                tiles_j[k] = a + tj0
                planes[k] = c
                k += 1
    return tiles_i, tiles_j, planes, marks
