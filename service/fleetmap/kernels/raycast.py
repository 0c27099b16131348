"""Ray casting through a map's tiles: where each ray first meets an occupied (or unknown) cell.

A ray is the segment from its origin to its end point, both in cell units, walked with the exact
traversal of `traversal` (its `exact_start` / `crossing` / `exact_steps_i` steps, so the same cells
in the same order as `segment_cells(..., EXACT)`). Each cell is read from the tile pools through the
kernel tile index, with no dense copy of the map: the walk looks up a tile's slot again only when it
crosses into another tile.

A cell's class comes from the occupancy layer (log-odds: unknown when NaN, occupied at or above
`log_odds_occupied`) or, for a map without it (`use_counts`), the count model (unknown when
hits + misses is 0, occupied when `hits / (hits + misses) > occupied_thresh` in double precision).
A cell of a tile the map does not hold is unknown.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.cell_queries import RAY_MAX_RANGE, RAY_OCCUPIED, RAY_UNKNOWN
from fleetmap.kernels.tile_index import index_find
from fleetmap.kernels.traversal import crossing, exact_start, exact_steps_i

#: A cell's class as the walk sees it.
_FREE, _OCCUPIED, _UNKNOWN = 0, 1, 2


@njit(cache=True, nogil=True, inline="always")
def _cell_class(
    slot: int,
    li: int,
    lj: int,
    use_counts: bool,
    log_odds_occupied: float,
    occupied_thresh: float,
    log_odds: np.ndarray,
    hits: np.ndarray,
    misses: np.ndarray,
) -> int:
    """The class of local cell (li, lj) of pool slot `slot` (-1: no tile, so unknown)."""
    if slot < 0:
        return _UNKNOWN
    if use_counts:
        h = float(hits[slot, lj, li])
        total = h + float(misses[slot, lj, li])
        if total == 0.0:
            return _UNKNOWN
        return _OCCUPIED if h / total > occupied_thresh else _FREE
    lo = log_odds[slot, lj, li]
    if math.isnan(lo):
        return _UNKNOWN
    # A NaN threshold (no log-odds is occupied) compares False.
    return _OCCUPIED if lo >= log_odds_occupied else _FREE


@njit(cache=True, nogil=True)
def cast_rays(
    x0: np.ndarray,
    y0: np.ndarray,
    x1: np.ndarray,
    y1: np.ndarray,
    stop_at_unknown: bool,
    use_counts: bool,
    log_odds_occupied: float,
    occupied_thresh: float,
    index_keys: np.ndarray,
    index_slots: np.ndarray,
    shift: int,
    log_odds: np.ndarray,
    hits: np.ndarray,
    misses: np.ndarray,
    status: np.ndarray,
    t_stop: np.ndarray,
    stop_i: np.ndarray,
    stop_j: np.ndarray,
) -> None:
    """Walk ray r from (x0[r], y0[r]) to (x1[r], y1[r]) (cell units) and write where it stopped;
    `x0` and `y0` of one element are every ray's origin.

    A ray stops at its first cell that is occupied (`RAY_OCCUPIED`), or never observed when
    `stop_at_unknown` (`RAY_UNKNOWN`), the start cell included; else at its end cell
    (`RAY_MAX_RANGE`). `t_stop[r]` is the segment parameter (0..1) where the ray enters the cell it
    stopped in (0 for the start cell, 1 for `RAY_MAX_RANGE`), `stop_i/stop_j[r]` that cell."""
    mask = (1 << shift) - 1
    per_ray = 1 if x0.size > 1 else 0  # an origin per ray, or one for all
    for r in range(x1.size):
        ox, oy = x0[r * per_ray], y0[r * per_ray]
        i, j, ie, je, step_i, step_j, base_x, scale_x, base_y, scale_y = exact_start(ox, oy, x1[r], y1[r])
        ti = i >> shift
        tj = j >> shift
        slot = index_find(index_keys, index_slots, ti, tj)
        steps = abs(ie - i) + abs(je - j)
        t = 0.0
        k = 0
        while True:
            cls = _cell_class(
                slot, i & mask, j & mask, use_counts, log_odds_occupied, occupied_thresh,
                log_odds, hits, misses,
            )  # fmt: skip
            if cls == _OCCUPIED or (cls == _UNKNOWN and stop_at_unknown):
                status[r] = RAY_OCCUPIED if cls == _OCCUPIED else RAY_UNKNOWN
                # Rounding can put a crossing a hair outside the segment; the entry point stays on it.
                # An origin on a cell edge, walking back across it, enters at t = -0.0: answer 0.
                t_stop[r] = 0.0 if t <= 0.0 else min(t, 1.0)
                break
            if k == steps:
                status[r] = RAY_MAX_RANGE
                t_stop[r] = 1.0
                break
            t_x = crossing(i, base_x, scale_x)
            t_y = crossing(j, base_y, scale_y)
            if exact_steps_i(i, j, ie, je, t_x, t_y):
                i += step_i
                t = t_x
            else:
                j += step_j
                t = t_y
            k += 1
            if (i >> shift) != ti or (j >> shift) != tj:
                ti = i >> shift
                tj = j >> shift
                slot = index_find(index_keys, index_slots, ti, tj)
        stop_i[r] = i
        stop_j[r] = j
