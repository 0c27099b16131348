"""The ray sensor model: a return makes every cell its segment passes through a miss and its end cell
a hit; a cleared no-return beam makes every cell up to its clearing range a miss."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.kernels.traversal import EXACT, cell_count, cells, exact_start, exact_steps_i, walk

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


#: Up to this many tiles in a scan's bounding box, `trace_scan` numbers every tile of the box
#: (its scratch then needs a plane per tile: 16 MiB at 256 x 256) and walks once; beyond it, it
#: first walks to find the touched tiles so that memory stays proportional to them.
DENSE_TILE_LIMIT = 256


@njit(cache=True, nogil=True, inline="always")
def _beam(
    b: int, ranges: np.ndarray, range_min: float, range_max: float, clear_range: float
) -> tuple[int, float]:
    """Beam b's kind and the range (metres) it is traced to: a return to its range, a no-return
    beam to `clear_range` when that is > 0, anything else skipped."""
    r = ranges[b]
    if math.isnan(r) or r < range_min:
        return BEAM_SKIP, 0.0
    if r >= range_max:
        if clear_range > 0.0:
            return BEAM_CLEAR, min(clear_range, range_max)
        return BEAM_SKIP, 0.0
    return BEAM_HIT, r


@njit(cache=True, nogil=True)
def scan_extent(
    x: float, y: float, angles: np.ndarray, ranges: np.ndarray, range_min: float, range_max: float,
    clear_range: float, res: float,
) -> tuple[float, float, float, float, int]:  # fmt: skip
    """Bounding box in CELL units of every traced beam, with the sensor: (xmin, ymin, xmax, ymax,
    number of traced beams)."""
    ox = x / res
    oy = y / res
    xmin = xmax = ox
    ymin = ymax = oy
    used = 0
    for b in range(ranges.size):
        kind, r = _beam(b, ranges, range_min, range_max, clear_range)
        if kind == BEAM_SKIP:
            continue
        used += 1
        ex = ox + r / res * math.cos(angles[b])
        ey = oy + r / res * math.sin(angles[b])
        xmin = min(xmin, ex)
        xmax = max(xmax, ex)
        ymin = min(ymin, ey)
        ymax = max(ymax, ey)
    return xmin, ymin, xmax, ymax, used


@njit(cache=True, nogil=True)
def trace_scan(
    x: float,
    y: float,
    angles: np.ndarray,
    ranges: np.ndarray,
    range_min: float,
    range_max: float,
    clear_range: float,
    res: float,
    method: int,
    shift: int,
    ti0: int,
    tj0: int,
    ti1: int,
    tj1: int,
    scratch: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Per-scan updates of the ray model: every cell any beam touches, once, a hit if any beam ends
    in it (a hit beats a miss).

    Input is the sensor position (m), the beams' MAP-frame angles and ranges (m); beams are classified
    as in `_beam`. `[ti0, ti1] x [tj0, tj1]` must hold every traced cell (see `scan_extent`).
    `scratch` is a zeroed flat uint8 array; it is zeroed again on return, so one scratch serves every
    scan of a thread. It needs a (T, T) plane per tile of the box (per touched tile for boxes larger
    than DENSE_TILE_LIMIT): when it is too small, nothing is traced and the last value returned is
    the number of planes needed (else 0).

    Returns `(tiles_i, tiles_j, cell, kind, planes_needed)`: tile k is `(tiles_i[k], tiles_j[k])`;
    updated cell n lies in tile `cell[n] >> 2*shift` at local position `cell[n] & (T*T - 1)`
    (= `local_j * T + local_i`) and is a `CELL_HIT` if `kind[n] & CELL_HIT`, else a miss. Cells come
    in the order beams first reach them.
    """
    plane_shift = 2 * shift
    nj = tj1 - tj0 + 1
    ni = ti1 - ti0 + 1
    ox = x / res
    oy = y / res
    nb = ranges.size
    ex = np.empty(nb)
    ey = np.empty(nb)
    kinds = np.empty(nb, dtype=np.uint8)
    visits = 0
    for b in range(nb):
        kind, r = _beam(b, ranges, range_min, range_max, clear_range)
        kinds[b] = kind
        ex[b] = ox + r / res * math.cos(angles[b])
        ey[b] = oy + r / res * math.sin(angles[b])
        if kind != BEAM_SKIP:
            visits += cell_count(ox, oy, ex[b], ey[b], method)
    if nj * ni <= DENSE_TILE_LIMIT:
        index = np.arange(nj * ni).reshape(nj, ni)
        m = nj * ni
    else:
        # Walk once to number only the touched tiles, so the scratch stays proportional to them.
        index = np.full((nj, ni), -1, dtype=np.int64)
        m = 0
        for b in range(nb):
            if kinds[b] != BEAM_SKIP:
                for i, j in cells(ox, oy, ex[b], ey[b], method):
                    if index[(j >> shift) - tj0, (i >> shift) - ti0] < 0:
                        index[(j >> shift) - tj0, (i >> shift) - ti0] = m
                        m += 1
    if scratch.size < (m << plane_shift):
        none = np.empty(0, dtype=np.int64)
        return none, none, none, np.empty(0, dtype=np.uint8), m  # the caller grows the scratch
    found = np.empty(visits + 1, dtype=np.int64)  # each cell the first time a beam reaches it
    n = 0
    t = 1 << shift
    mask = t - 1
    for b in range(nb):
        if kinds[b] == BEAM_SKIP:
            continue
        flat = 0
        if method == EXACT:
            # The exact walk, inlined: this loop is most of the time a scan takes. The scratch key
            # moves by +-1 (a step in i) or +-T (a step in j) inside a tile and is recomputed only
            # when the walk enters another tile.
            i, j, ie, je, step_i, step_j, t_max_x, t_max_y, t_delta_x, t_delta_y = exact_start(
                ox, oy, ex[b], ey[b]
            )
            flat = _cell_key(i, j, index, ti0, tj0, shift)
            edge_i = mask if step_i > 0 else 0  # the local i after which a step leaves the tile
            edge_j = mask if step_j > 0 else 0
            for _ in range(abs(ie - i) + abs(je - j)):
                # Branch-free first-visit record: always write, advance only if the cell was unseen.
                found[n] = flat
                n += scratch[flat] == 0
                scratch[flat] |= CELL_MISS
                if exact_steps_i(i, j, ie, je, t_max_x, t_max_y):
                    if (i & mask) == edge_i:
                        i += step_i
                        flat = _cell_key(i, j, index, ti0, tj0, shift)
                    else:
                        i += step_i
                        flat += step_i
                    t_max_x += t_delta_x
                else:
                    if (j & mask) == edge_j:
                        j += step_j
                        flat = _cell_key(i, j, index, ti0, tj0, shift)
                    else:
                        j += step_j
                        flat += step_j * t
                    t_max_y += t_delta_y
            found[n] = flat
            n += scratch[flat] == 0
            scratch[flat] |= CELL_MISS
        else:
            for i, j in cells(ox, oy, ex[b], ey[b], method):
                flat = _cell_key(i, j, index, ti0, tj0, shift)
                found[n] = flat
                n += scratch[flat] == 0
                scratch[flat] |= CELL_MISS
        if kinds[b] == BEAM_HIT:
            scratch[flat] |= CELL_HIT  # the last cell walked is the end cell
    kind_out = np.empty(n, dtype=np.uint8)
    planes = np.zeros(index.size, dtype=np.int64)
    for k in range(n):
        kind_out[k] = scratch[found[k]]
        scratch[found[k]] = 0
        planes[found[k] >> plane_shift] = 1
    # Renumber the planes that hold a cell 0..m-1 and report their tiles.
    m = 0
    renum = np.full(index.size, -1, dtype=np.int64)
    tiles_i = np.empty(index.size, dtype=np.int64)
    tiles_j = np.empty(index.size, dtype=np.int64)
    for a in range(nj):
        for c in range(ni):
            p = index[a, c]
            if p >= 0 and planes[p]:
                renum[p] = m
                tiles_i[m] = c + ti0
                tiles_j[m] = a + tj0
                m += 1
    local = (1 << plane_shift) - 1
    cell = np.empty(n, dtype=np.int64)
    for k in range(n):
        cell[k] = (renum[found[k] >> plane_shift] << plane_shift) | (found[k] & local)
    return tiles_i[:m], tiles_j[:m], cell, kind_out, 0


@njit(cache=True, nogil=True, inline="always")
def _cell_key(i: int, j: int, index: np.ndarray, ti0: int, tj0: int, shift: int) -> int:
    """A cell's key in the scratch: its tile's plane number, then `local_j * T + local_i`."""
    mask = (1 << shift) - 1
    plane = index[(j >> shift) - tj0, (i >> shift) - ti0]
    return (plane << (2 * shift)) | ((j & mask) << shift) | (i & mask)
