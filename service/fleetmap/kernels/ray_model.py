"""The ray sensor model: a return makes every cell its segment passes through a miss and its end cell
a hit; a cleared no-return beam makes every cell up to its clearing range a miss.

`trace_scan` gives a scan's per-scan updates (each cell once, a hit beating a miss) from the beams
`scan_geometry.scan_rays` computes: by rows near the sensor (`fan_rows`) and by walks elsewhere
(`beam_walks`); `trace_rays` gives every beam's cells, for per-ray updates."""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetmap.kernels.beam_walks import (
    collect_dense,
    touched_tile_index,
    walk_dense,
    walk_far,
    walk_far_apply,
    walk_planes,
)
from fleetmap.kernels.fan_rows import MIN_RUN, trace_fan_rows
from fleetmap.kernels.kinds import BEAM_HIT, BEAM_SKIP, CELL_HIT, CELL_MISS
from fleetmap.kernels.traversal import EXACT, cell_count, exact_starts, walk
from fleetmap.kernels.update import apply_cells


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


#: `trace_scan` marks cells in a dense row-major window over the scan's whole tiles when it holds
#: at most this many cells (8 MiB of scratch): steps are then a plain +-1 / +-W on one key. Larger
#: boxes (very long clearing beams) use per-tile planes for the touched tiles only, so memory stays
#: proportional to what the scan touches.
DENSE_WINDOW_CELLS = 1 << 23


@njit(cache=True, nogil=True, inline="always")
def _trace_rows(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray, shift: int, ti0: int, tj0: int,
    ni: int, nj: int, visits: int, far_rows: bool,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
    int, int, int,
]:  # fmt: skip
    """The row trace (`fan_rows.trace_fan_rows`) of an exact fan with its work arrays, for `trace_scan`
    and `trace_apply_scan`: `(found, kind_out, run_key, run_len, planes, far, starts, crossings, n, r,
    h)`, `n < 0` when the fan is not one the row trace takes. With `far_rows` the far rests are handed
    back in `far[:h]` for the walks (the dense window); without, the rows go all the way."""
    found = np.empty(visits, dtype=np.int64)
    kind_out = np.empty(visits, dtype=np.uint8)
    run_key = np.empty(visits // MIN_RUN + 1, dtype=np.int64)
    run_len = np.empty(visits // MIN_RUN + 1, dtype=np.int64)
    planes = np.zeros(nj * ni, dtype=np.uint8)
    far = np.empty((ex.size if far_rows else 0, 3), dtype=np.int64)
    starts, crossings = exact_starts(np.full(ex.size, ox), np.full(ex.size, oy), ex, ey)
    n, r, h = trace_fan_rows(
        ox, oy, ex, ey, kinds, starts, crossings, shift, ti0, tj0, ni, found, kind_out, run_key, run_len,
        planes, far,
    )  # fmt: skip
    return found, kind_out, run_key, run_len, planes, far, starts, crossings, n, r, h


@njit(cache=True, nogil=True)
def trace_scan(
    ox: float,
    oy: float,
    rays: np.ndarray,
    kinds: np.ndarray,
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

    Exact traversal of a fan in angle order is traced row by row near the sensor
    (`fan_rows.trace_fan_rows`) and by walks in the dense window far out (rows all the way when
    the box is too large for the window). Other exact scans (beams out of angle order, coordinates
    past `fan_rows`' limits) are walked beam by beam, skipping what neighbouring beams cover
    (`skip_spans`); Bresenham lines are walked whole. All give the union of the beams' walks.

    Input is the sensor position in CELL units and the beams' `rays` (rows 2 and 3: end points in
    CELL units) and kinds, as `scan_rays` gives them. `[ti0, ti1] x [tj0, tj1]` must hold every
    traced cell. `scratch` is a zeroed flat uint8 array; it is zeroed again on return, so one
    scratch serves every scan of a thread. When it is too small, nothing is traced and the last
    value returned is the size it needs (else 0).

    Returns `(tiles, cell, kind, runs, scratch_needed)`: tile k is `(tiles[0, k], tiles[1, k])`;
    updated cell n lies in tile `cell[n] >> 2*shift` at local position `cell[n] & (T*T - 1)`
    (= `local_j * T + local_i`) and is a `CELL_HIT` if `kind[n] & CELL_HIT`, else a miss. Run k is
    `runs[1, k]` misses on consecutive cells of one tile row from the cell `runs[0, k]` (keyed like
    `cell`; the row trace writes them). Each cell comes once, in no particular order.
    """
    ex = rays[2]
    ey = rays[3]
    plane_shift = 2 * shift
    nj = tj1 - tj0 + 1
    ni = ti1 - ti0 + 1
    visits, wshift, dense = _window(ox, oy, ex, ey, kinds, method, shift, ni, nj)
    if method == EXACT:
        # Row by row near the sensor (`fan_rows`), in row order, and the far rows by walks in the
        # dense window (when the box fits one).
        if dense and scratch.size < nj << (shift + wshift):
            return _no_trace(nj << (shift + wshift))
        found, kind_out, run_key, run_len, planes, far, starts, crossings, n, r, h = _trace_rows(
            ox, oy, ex, ey, kinds, shift, ti0, tj0, ni, nj, visits, dense
        )
        if n >= 0:
            if h:
                n = walk_far(
                    kinds, starts, crossings, far[:h], shift, wshift, ti0, tj0, ni, scratch, found, kind_out,
                    n, planes,
                )  # fmt: skip
            index = np.arange(nj * ni).reshape(nj, ni)
            return _number_tiles(
                index, planes, found[:n], kind_out[:n], run_key[:r], run_len[:r], plane_shift, ti0, tj0,
                index.size > 0,
            )  # fmt: skip
    if dense:
        needed = nj << (shift + wshift)
        index = np.arange(nj * ni).reshape(nj, ni)
    else:
        index, m = touched_tile_index(ox, oy, ex, ey, kinds, method, shift, ti0, tj0, ni, nj)
        needed = m << plane_shift
    if scratch.size < needed:
        return _no_trace(needed)  # the caller grows it
    found = np.empty(visits, dtype=np.int64)  # each cell the first time a beam reaches it
    kind_out = np.empty(visits, dtype=np.uint8)
    planes = np.zeros(index.size, dtype=np.uint8)  # which planes hold a cell
    if dense:
        n = walk_dense(ox, oy, ex, ey, kinds, method, shift, wshift, ti0, tj0, scratch, found)
        collect_dense(found, n, scratch, shift, wshift, ni, kind_out, planes)
    else:
        n = walk_planes(ox, oy, ex, ey, kinds, method, shift, ti0, tj0, index, scratch, found)
        for k in range(n):
            kind_out[k] = scratch[found[k]]
            scratch[found[k]] = 0
            planes[found[k] >> plane_shift] = 1
    none = np.empty(0, dtype=np.int64)
    return _number_tiles(index, planes, found[:n], kind_out[:n], none, none, plane_shift, ti0, tj0, dense)


@njit(cache=True, nogil=True, inline="always")
def _window(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray, method: int, shift: int, ni: int,
    nj: int,
) -> tuple[int, int, bool]:  # fmt: skip
    """The cells the beams visit in all (the work arrays' size), the dense window's row shift (rows
    of `2**wshift` cells, so that a key splits with shifts) and whether the box fits the window."""
    visits = 0
    for b in range(ex.size):
        if kinds[b] != BEAM_SKIP:
            visits += cell_count(ox, oy, ex[b], ey[b], method)
    wshift = shift
    while (1 << wshift) < (ni << shift):
        wshift += 1
    return visits, wshift, (nj << (shift + wshift)) <= DENSE_WINDOW_CELLS


#: `trace_apply_scan` statuses.
APPLIED = 0  # the scan is in the pool
NOT_APPLIED = 1  # nothing changed: the caller traces and applies (`trace_scan`, `apply_cells`)
APPLY_NEEDS_SCRATCH = 2  # nothing changed: the scratch is too small (the size it needs is returned)


@njit(cache=True, nogil=True)
def trace_apply_scan(
    ox: float, oy: float, rays: np.ndarray, kinds: np.ndarray, shift: int, ti0: int, tj0: int, ti1: int,
    tj1: int, scratch: np.ndarray, slots: np.ndarray, log_odds: np.ndarray, l_hit: float, l_miss: float,
    l_min: float, l_max: float, changed: np.ndarray,
) -> tuple[int, int, int]:  # fmt: skip
    """`trace_scan` (EXACT) followed by `update.apply_cells` on the log-odds pool alone, when every
    tile of the box `[ti0, ti1] x [tj0, tj1]` exists: `slots[a * ni + c]` is the pool slot of tile
    `(ti0 + c, tj0 + a)` (ni = ti1 - ti0 + 1), and `changed` (one flag per box tile, zeroed) gets a
    1 where a stored value changed. The pool ends as the trace and apply would leave it, bit for
    bit: the same cells, each updated once, a hit if any beam ends in it.

    The far walks' cells (most of an indoor scan's single cells) are applied straight from the
    window by `walk_far_apply`, not written out as plane keys and kinds, read back and applied by a
    pass of their own; the row trace's cells and runs go to `apply_cells` as before. With all the
    box's tiles at hand, no tile list is built and no key renumbered.

    Returns `(status, cells updated, scratch needed)`. NOT_APPLIED when the box does not fit the
    dense window or the fan is not one the row trace takes (nothing changed, scratch still zero):
    the caller takes `trace_scan`'s path, which handles those."""
    ex = rays[2]
    ey = rays[3]
    nj = tj1 - tj0 + 1
    ni = ti1 - ti0 + 1
    visits, wshift, dense = _window(ox, oy, ex, ey, kinds, EXACT, shift, ni, nj)
    if not dense:
        return NOT_APPLIED, 0, 0
    if scratch.size < nj << (shift + wshift):
        return APPLY_NEEDS_SCRATCH, 0, nj << (shift + wshift)
    # (The planes `_trace_rows` flags are not needed here: `slots` covers the whole box.)
    found, kind_out, run_key, run_len, _, far, starts, crossings, n, r, h = _trace_rows(
        ox, oy, ex, ey, kinds, shift, ti0, tj0, ni, nj, visits, True
    )
    if n < 0:
        return NOT_APPLIED, 0, 0
    updates = 0
    if h:
        updates = walk_far_apply(
            kinds, starts, crossings, far[:h], shift, wshift, ti0, tj0, ni, scratch, found, n, slots,
            log_odds, l_hit, l_miss, l_min, l_max, changed,
        )  # fmt: skip
    # The row trace's keys are plane keys numbered row-major over the box: `slots`' numbering.
    runs = np.empty((2, r), dtype=np.int64)
    runs[0] = run_key[:r]
    runs[1] = run_len[:r]
    no_counts = np.empty((0, 0, 0), dtype=np.uint32)
    if n or r:
        updates += apply_cells(
            found[:n], kind_out[:n], runs, slots, shift, log_odds, no_counts, no_counts, l_hit, l_miss, l_min,
            l_max, changed,
        )  # fmt: skip
    return APPLIED, updates, 0


@njit(cache=True, nogil=True)
def _number_tiles(
    index: np.ndarray, planes: np.ndarray, found: np.ndarray, kind_out: np.ndarray, run_key: np.ndarray,
    run_len: np.ndarray, plane_shift: int, ti0: int, tj0: int, dense: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:  # fmt: skip
    """`trace_scan`'s result from the plane keys of cells `found` and runs `run_key` (plane numbers
    from `index`, flagged in `planes` when they hold a cell): the planes that hold a cell renumbered
    0..m-1, and their tiles."""
    nj, ni = index.shape
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
    tiles = np.empty((2, m), dtype=np.int64)
    tiles[0] = tiles_i[:m]
    tiles[1] = tiles_j[:m]
    runs = np.empty((2, run_key.size), dtype=np.int64)
    runs[1] = run_len
    if dense and m == index.size:
        # The dense window numbers planes row-major over the box; when every plane holds a cell,
        # that is the final numbering and the keys need no rewrite.
        runs[0] = run_key
        return tiles, found, kind_out, runs, 0
    local = (1 << plane_shift) - 1
    for k in range(found.size):
        found[k] = (renum[found[k] >> plane_shift] << plane_shift) | (found[k] & local)
    for k in range(run_key.size):
        runs[0, k] = (renum[run_key[k] >> plane_shift] << plane_shift) | (run_key[k] & local)
    return tiles, found, kind_out, runs, 0


@njit(cache=True, nogil=True, inline="always")
def _no_trace(needed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """`trace_scan`'s result when its scratch is too small: nothing, and the size it needs."""
    return (
        np.empty((2, 0), dtype=np.int64), np.empty(0, dtype=np.int64), np.empty(0, dtype=np.uint8),
        np.empty((2, 0), dtype=np.int64), needed,
    )  # fmt: skip
