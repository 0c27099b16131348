"""Applying per-cell updates to pooled tile arrays.

Every update names a tile of its plan's tile list (numbered 0..m-1 at planning time, see
`merge_tiles`); `slots[tile]` is that tile's pool slot and `changed[tile]` records whether a stored
value of it changed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.kernels.kinds import CELL_HIT

_U32_MAX = np.uint32(0xFFFFFFFF)

#: A never-observed cell's stored values: log-odds NaN (UNKNOWN, not 0), counts 0, TSDF value and
#: weight 0 (unknown while the weight is 0). `tiles.LAYER_ARRAYS` and `init_tile` both use these.
UNKNOWN_LOG_ODDS = np.nan
UNKNOWN_COUNT = 0
UNKNOWN_TSDF = 0.0


@njit(cache=True, nogil=True, inline="always")
def init_tile(
    slot: int, log_odds: np.ndarray, hits: np.ndarray, misses: np.ndarray, tsdf: np.ndarray,
    tsdf_weight: np.ndarray,
) -> None:  # fmt: skip
    """Set pool slot `slot` of every enabled layer (a disabled layer's pool is empty) to the values
    of a never-observed cell: the one fill for a new tile, in `TileStore.create` and in the
    one-call integration."""
    if log_odds.size:
        log_odds[slot] = UNKNOWN_LOG_ODDS
    if hits.size:
        hits[slot] = UNKNOWN_COUNT
        misses[slot] = UNKNOWN_COUNT
    if tsdf.size:
        tsdf[slot] = UNKNOWN_TSDF
        tsdf_weight[slot] = UNKNOWN_TSDF


@njit(cache=True, nogil=True)
def merge_tiles(
    tiles: np.ndarray, ci: np.ndarray, cj: np.ndarray, shift: int
) -> tuple[np.ndarray, np.ndarray]:
    """Extend the tile list `tiles` (rows: tile i, tile j) with the tiles of the cells `(ci, cj)` not
    yet in it, in the order the cells first reach them, and give each cell the number of its tile
    in the extended list. Returns `(tiles, tile of each cell)`."""
    if ci.size == 0:
        return tiles, np.empty(0, dtype=np.int64)
    i0 = i1 = ci[0]
    j0 = j1 = cj[0]
    for k in range(ci.size):  # scalars, not the box array: the compiler keeps them in registers
        i0 = min(i0, ci[k])
        j0 = min(j0, cj[k])
        i1 = max(i1, ci[k])
        j1 = max(j1, cj[k])
    return merge_tiles_in_box(tiles, ci, cj, shift, np.array([i0, j0, i1, j1]))


@njit(cache=True, nogil=True)
def merge_tiles_in_box(
    tiles: np.ndarray, ci: np.ndarray, cj: np.ndarray, shift: int, box: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """`merge_tiles` for cells known to lie in `box` (cells `i0, j0, i1, j1`, inclusive), which spares
    it a pass over them."""
    if ci.size == 0:
        return tiles, np.empty(0, dtype=np.int64)
    tiles_i = tiles[0]
    tiles_j = tiles[1]
    ti0, tj0, ti1, tj1 = box[0] >> shift, box[1] >> shift, box[2] >> shift, box[3] >> shift
    ni = ti1 - ti0 + 1
    number = np.full((tj1 - tj0 + 1) * ni, -1, dtype=np.int64)
    out_i = np.empty(tiles_i.size + ci.size, dtype=np.int64)
    out_j = np.empty(tiles_i.size + ci.size, dtype=np.int64)
    m = 0
    for k in range(tiles_i.size):
        out_i[m] = tiles_i[k]
        out_j[m] = tiles_j[k]
        if ti0 <= tiles_i[k] <= ti1 and tj0 <= tiles_j[k] <= tj1:
            number[(tiles_j[k] - tj0) * ni + tiles_i[k] - ti0] = m
        m += 1
    tile = np.empty(ci.size, dtype=np.int64)
    # Neighbouring cells (a beam's band, a ray) mostly share a tile: look up only on a change.
    last = -1
    current = 0
    for k in range(ci.size):
        at = ((cj[k] >> shift) - tj0) * ni + (ci[k] >> shift) - ti0
        if at != last:
            last = at
            current = number[at]
            if current < 0:
                current = number[at] = m
                out_i[m] = ci[k] >> shift
                out_j[m] = cj[k] >> shift
                m += 1
        tile[k] = current
    out = np.empty((2, m), dtype=np.int64)
    out[0] = out_i[:m]
    out[1] = out_j[:m]
    return out, tile


@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def bump_versions(changed: np.ndarray, slots: np.ndarray, versions: np.ndarray, clock: int) -> int:
    """Give each tile k with `changed[k]` set (pool slot `slots[k]`) the next version after `clock`,
    in tile order: the one rule for tile versions (a store-wide clock, so versions never repeat).
    Returns the newest version handed out."""
    for k in range(changed.size):
        if changed[k]:
            clock += 1
            versions[slots[k]] = clock
    return clock


@njit(cache=True, nogil=True, inline="always")
def updated_log_odds(
    old: float, hit: bool, l_hit: float, l_miss: float, l_min: float, l_max: float
) -> np.float32:
    """The log-odds update rule, the one place it is written: an unknown cell (NaN) starts at 0, a
    hit adds l_hit, a miss l_miss, and the result is clamped after every update, as OctoMap does, so a
    cell can always be changed back quickly. Returns float32, as stored."""
    lo = (0.0 if math.isnan(old) else float(old)) + (l_hit if hit else l_miss)
    return np.float32(min(max(lo, l_min), l_max))


@njit(cache=True, nogil=True, inline="always")
def _apply_one(
    slot: int,
    lj: int,
    li: int,
    hit: bool,
    log_odds: np.ndarray,
    hits: np.ndarray,
    misses: np.ndarray,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
) -> bool:
    """One hit or miss on one cell of every enabled layer; True if a stored value changed."""
    changed = False
    if log_odds.size:
        old = log_odds[slot, lj, li]
        new = updated_log_odds(old, hit, l_hit, l_miss, l_min, l_max)
        if new != old:  # NaN != anything, so a first observation always counts as a change
            log_odds[slot, lj, li] = new
            changed = True
    if hits.size:
        if hit:
            if hits[slot, lj, li] != _U32_MAX:
                hits[slot, lj, li] += 1
                changed = True
        elif misses[slot, lj, li] != _U32_MAX:
            misses[slot, lj, li] += 1
            changed = True
    return changed


@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def apply_cells(
    cell: np.ndarray,
    kind: np.ndarray,
    runs: np.ndarray,
    slots: np.ndarray,
    shift: int,
    log_odds: np.ndarray,
    hits: np.ndarray,
    misses: np.ndarray,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
    changed: np.ndarray,
) -> int:
    """Apply per-scan updates (see `ray_model.trace_scan`) to the pools; return cells updated.

    Cell n is in tile `cell[n] >> 2*shift`, which is pool slot `slots[that]`, at local position
    `cell[n] & (T*T - 1)`; run k is `runs[1, k]` misses on the consecutive cells from `runs[0, k]`
    (keyed the same way, within one tile row). `changed[tile]` is set to 1 where a stored value changed.
    Each enabled layer gets its own pass, so each inner loop is short and branch-light.
    """
    run = runs[0]
    run_len = runs[1]
    plane_shift = 2 * shift
    local_mask = (1 << plane_shift) - 1
    updates = cell.size
    for k in range(run.size):
        updates += run_len[k]
    if log_odds.size:
        # One flat view of the pool; unsigned indices (all are >= 0) spare numba's negative-index
        # wraparound code, and the store is unconditional (branch-free). Cells come in runs of one
        # tile (rows of the scan), so the change flag is kept in a register per run: or-ing it into
        # `changed` per cell made every iteration wait on the previous one's store.
        flat_log_odds = log_odds.reshape(-1)
        tile = np.uint64(0xFFFFFFFFFFFFFFFF)
        start = np.uint64(0)
        diff = False
        for n in range(cell.size):
            t = np.uint64(cell[n] >> plane_shift)
            if t != tile:
                if diff:
                    changed[tile] = 1
                diff = False
                tile = t
                start = np.uint64(slots[t] << plane_shift)
            at = start | np.uint64(cell[n] & local_mask)
            old = flat_log_odds[at]
            new = updated_log_odds(old, (kind[n] & CELL_HIT) != 0, l_hit, l_miss, l_min, l_max)
            flat_log_odds[at] = new
            diff |= new != old  # NaN != anything: a first observation is a change
        if diff:
            changed[tile] = 1
        for k in range(run.size):
            t = np.uint64(run[k] >> plane_shift)
            at = np.uint64((slots[t] << plane_shift) | (run[k] & local_mask))
            diff = False
            for x in range(np.uint64(run_len[k])):  # contiguous misses: a loop the compiler vectorises
                old = flat_log_odds[at + x]
                new = updated_log_odds(old, False, l_hit, l_miss, l_min, l_max)
                flat_log_odds[at + x] = new
                diff |= new != old
            if diff:
                changed[t] = 1
    if hits.size:
        flat_hits = hits.reshape(-1)
        flat_misses = misses.reshape(-1)
        tile = np.uint64(0xFFFFFFFFFFFFFFFF)
        start = np.uint64(0)
        for n in range(cell.size):
            t = np.uint64(cell[n] >> plane_shift)
            if t != tile:  # the tile handled once per run of its cells, as in the log-odds pass
                tile = t
                changed[t] = 1
                start = np.uint64(slots[t] << plane_shift)
            at = start | np.uint64(cell[n] & local_mask)
            if kind[n] & CELL_HIT:
                if flat_hits[at] != _U32_MAX:  # counts saturate rather than wrap
                    flat_hits[at] += 1
            elif flat_misses[at] != _U32_MAX:
                flat_misses[at] += 1
        for k in range(run.size):
            tile = np.uint64(run[k] >> plane_shift)
            at = np.uint64((slots[tile] << plane_shift) | (run[k] & local_mask))
            for x in range(np.uint64(run_len[k])):  # branch-free, so that it vectorises
                m = flat_misses[at + x]
                flat_misses[at + x] = m + np.uint32(m != _U32_MAX)
            changed[tile] = 1
    return updates


@njit(cache=True, nogil=True)
def apply_entries(
    ci: np.ndarray,
    cj: np.ndarray,
    kind: np.ndarray,
    tile: np.ndarray,
    slots: np.ndarray,
    shift: int,
    log_odds: np.ndarray,
    hits: np.ndarray,
    misses: np.ndarray,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
    changed: np.ndarray,
) -> int:
    """Apply hits and misses in order, each clamped (per-ray semantics); return updates applied.

    Entry k lies in the plan's tile `tile[k]`, which is pool slot `slots[tile[k]]`; `changed[tile]`
    is set to 1 where a stored value is not what it was before the entries. A disabled layer is
    passed as an empty array.
    """
    mask = (1 << shift) - 1
    # Without counts, which only grow, a cell may end where it began: in order, a ray may move it
    # off its clamp and the next one back (a miss, then a hit clamping at l_max). Its tile did not
    # change, and is judged by each cell's value before the entries (a new version for it was a
    # changed tile pushed to every viewer, and a new ETag). With counts, every update changes one.
    net = hits.size == 0 and log_odds.size > 0
    before = np.empty(ci.size if net else 0, dtype=np.float32)
    for k in range(before.size):
        before[k] = log_odds[slots[tile[k]], cj[k] & mask, ci[k] & mask]
    for k in range(ci.size):
        if (
            _apply_one(
                slots[tile[k]],
                cj[k] & mask,
                ci[k] & mask,
                (kind[k] & CELL_HIT) != 0,
                log_odds,
                hits,
                misses,
                l_hit,
                l_miss,
                l_min,
                l_max,
            )
            and not net
        ):
            changed[tile[k]] = 1
    for k in range(before.size):
        # An updated cell is never NaN, and NaN (unknown before) differs from every value.
        if log_odds[slots[tile[k]], cj[k] & mask, ci[k] & mask] != before[k]:
            changed[tile[k]] = 1
    return ci.size
