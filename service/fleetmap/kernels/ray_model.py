"""The ray sensor model: a return makes every cell its segment passes through a miss and its end cell
a hit; a cleared no-return beam makes every cell up to its clearing range a miss."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.kernels.fan_rows import MIN_RUN, trace_fan_rows
from fleetmap.kernels.traversal import (
    EXACT,
    cell_at,
    cell_count,
    cells,
    crossing,
    exact_start,
    exact_starts,
    exact_steps_i,
    walk,
)

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


#: `trace_scan` marks cells in a dense row-major window over the scan's whole tiles when it holds
#: at most this many cells (8 MiB of scratch): steps are then a plain +-1 / +-W on one key. Larger
#: boxes (very long clearing beams) use per-tile planes for the touched tiles only, so memory stays
#: proportional to what the scan touches.
DENSE_WINDOW_CELLS = 1 << 23


@njit(cache=True, nogil=True)
def beam_layout(angles: np.ndarray) -> np.ndarray:
    """A beam layout for `scan_rays`: rows `angles` (sensor-frame bearings), their cosines and their
    sines (libm's)."""
    layout = np.empty((3, angles.size))
    for b in range(angles.size):
        layout[0, b] = angles[b]
        layout[1, b] = math.cos(angles[b])
        layout[2, b] = math.sin(angles[b])
    return layout


@njit(cache=True, nogil=True)
def scan_rays(
    x: float, y: float, theta: float, angles: np.ndarray, layout: np.ndarray, ranges: np.ndarray,
    range_min: float, range_max: float, clear_range: float, res: float,
) -> tuple:  # fmt: skip
    """One pass over a scan's beams (sensor at (x, y, theta), bearings `angles`, metres), for every
    sensor model: each beam's map-frame direction, kind and end point in CELL units
    (`res` metres per cell); the bounding box of the traced beams' end points with the sensor; how
    many beams are traced; and the longest usable return (`range_min <= r < range_max`, metres; 0
    if none).

    A usable return is a BEAM_HIT traced to its range. A beam at or past `range_max` (no return,
    inf) is a BEAM_CLEAR traced to `min(clear_range, range_max)` when `clear_range > 0`, else
    skipped (BEAM_SKIP, end point at the sensor), as is one below `range_min` or NaN.

    A beam's direction is its sensor-frame direction `(cos a, sin a)` (libm's) rotated by theta:
    one cosine and sine per scan instead of one per beam. Robots send the same bearings in every
    scan, so `layout` (`beam_layout`, of this scan or another) supplies `cos a` and `sin a` for
    every beam whose bearing equals its own; others are computed here. The directions are
    therefore the same whatever layout is given, and exactly `(cos a, sin a)` when theta is 0.

    Returns `(rays, kinds, xmin, ymin, xmax, ymax, traced, longest)`, `rays` holding the rows cos,
    sin, ex, ey (one array: each array handed back to Python costs a fraction of a microsecond)."""
    ox = x / res
    oy = y / res
    nb = ranges.size
    rays = np.empty((4, nb))
    cos = rays[0]
    sin = rays[1]
    ex = rays[2]
    ey = rays[3]
    kinds = np.empty(nb, dtype=np.uint8)
    xmin = xmax = ox
    ymin = ymax = oy
    traced = 0
    longest = 0.0
    cos_t = math.cos(theta)
    sin_t = math.sin(theta)
    known = min(nb, layout.shape[1])
    # The directions, then the kinds and end points, in loops with no branch on the data, so that
    # the compiler does several beams at once (the layout's cosines and sines are checked beam by
    # beam only when some bearing differs); then the box and counts, a scalar reduction. In one
    # loop with branches they cost the floor plan's 1081-beam scans 2.5 us more.
    same = known == nb
    for b in range(known):
        same &= layout[0, b] == angles[b]
    for b in range(nb):
        if same or (b < known and layout[0, b] == angles[b]):
            cos_a = layout[1, b]
            sin_a = layout[2, b]
        else:
            cos_a = math.cos(angles[b])
            sin_a = math.sin(angles[b])
        cos[b] = cos_t * cos_a - sin_t * sin_a
        sin[b] = sin_t * cos_a + cos_t * sin_a
    clear_to = min(clear_range, range_max)
    clears = clear_range > 0.0
    for b in range(nb):
        # Selects, no branch: NaN fails every comparison, so it is skipped.
        r = ranges[b]
        hit = (r >= range_min) & (r < range_max)
        clear = (r >= range_min) & (r >= range_max) & clears
        kinds[b] = BEAM_HIT if hit else (BEAM_CLEAR if clear else BEAM_SKIP)
        r = r if hit else (clear_to if clear else 0.0)
        ex[b] = ox + r / res * cos[b]
        ey[b] = oy + r / res * sin[b]
    for b in range(nb):
        # A skipped beam's end point is the sensor, which the box holds anyway.
        xmin = min(xmin, ex[b])
        xmax = max(xmax, ex[b])
        ymin = min(ymin, ey[b])
        ymax = max(ymax, ey[b])
        traced += kinds[b] != BEAM_SKIP
        if kinds[b] == BEAM_HIT:
            longest = max(longest, ranges[b])
    return rays, kinds, xmin, ymin, xmax, ymax, traced, longest


#: `scan_extent` verdicts.
EXTENT_OK = 0
EXTENT_OUT_OF_RANGE = 1  # the pose or the reach lies beyond the index range
EXTENT_TOO_WIDE = 2  # the traced beams' tile box holds too many tiles


@njit(cache=True, nogil=True)
def scan_extent(
    x: float, y: float, res: float, longest: float, clear_range: float, range_max: float, truncation: float,
    alpha: float, xmin: float, ymin: float, xmax: float, ymax: float, shift: int, max_cell_index: float,
    max_window: int,
) -> tuple[int, int, int, int, int]:  # fmt: skip
    """Whether a scan from (x, y) (metres, `res` per cell) fits the map, and its tile box: the one
    definition of both limits, for planning and for the one-call integration.

    EXTENT_OUT_OF_RANGE when the sensor plus the scan's reach (its longest return, or its clearing
    range when that is > 0 and farther, at most `range_max`, plus `truncation` and `alpha`: how far
    the TSDF band and the beam model reach past a return; metres) is not within `max_cell_index`
    cells of the origin on both axes. Otherwise the tile box `ti0, tj0, ti1, tj1` (tiles
    of `1 << shift` cells) of the bounding box `xmin..ymax` (CELL units, from `scan_rays`), and
    EXTENT_TOO_WIDE when it holds more than `max_window` tiles.

    Returns `(verdict, ti0, tj0, ti1, tj1)` (the box is 0s when out of range)."""
    far = longest
    if clear_range > 0:
        far = max(far, min(clear_range, range_max))
    reach = (far + truncation + alpha) / res
    if not (abs(x / res) + reach < max_cell_index and abs(y / res) + reach < max_cell_index):
        return EXTENT_OUT_OF_RANGE, 0, 0, 0, 0
    ti0 = math.floor(xmin) >> shift
    tj0 = math.floor(ymin) >> shift
    ti1 = math.floor(xmax) >> shift
    tj1 = math.floor(ymax) >> shift
    ni = ti1 - ti0 + 1
    nj = tj1 - tj0 + 1
    if ni > max_window or nj > max_window or ni * nj > max_window:  # each side first: no overflow
        return EXTENT_TOO_WIDE, ti0, tj0, ti1, tj1
    return EXTENT_OK, ti0, tj0, ti1, tj1


@njit(cache=True, nogil=True)
def beam_returns(rays: np.ndarray, kinds: np.ndarray, ranges: np.ndarray, res: float) -> tuple:
    """The returns of a scan, for the TSDF band: the directions (cos, sin) and ranges in CELL units
    of its `BEAM_HIT` beams, from `scan_rays`' `rays` and `kinds`."""
    n = 0
    for b in range(kinds.size):
        n += kinds[b] == BEAM_HIT
    cos = np.empty(n)
    sin = np.empty(n)
    z = np.empty(n)
    q = 0
    for b in range(kinds.size):
        if kinds[b] == BEAM_HIT:
            cos[q] = rays[0, b]
            sin[q] = rays[1, b]
            z[q] = ranges[b] / res
            q += 1
    return cos, sin, z


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
    visits = 0
    for b in range(ex.size):
        if kinds[b] != BEAM_SKIP:
            visits += cell_count(ox, oy, ex[b], ey[b], method)
    wshift = shift  # the dense window's rows are 2**wshift cells, so a key splits with shifts
    while (1 << wshift) < (ni << shift):
        wshift += 1
    dense = (nj << (shift + wshift)) <= DENSE_WINDOW_CELLS
    if method == EXACT:
        # Row by row near the sensor (`fan_rows`), in row order, and the far rows by walks in the
        # dense window (when the box fits one).
        if dense and scratch.size < nj << (shift + wshift):
            return _no_trace(nj << (shift + wshift))
        found = np.empty(visits, dtype=np.int64)
        kind_out = np.empty(visits, dtype=np.uint8)
        run_key = np.empty(visits // MIN_RUN + 1, dtype=np.int64)
        run_len = np.empty(visits // MIN_RUN + 1, dtype=np.int64)
        planes = np.zeros(nj * ni, dtype=np.uint8)
        far = np.empty((ex.size if dense else 0, 3), dtype=np.int64)
        starts, crossings = exact_starts(np.full(ex.size, ox), np.full(ex.size, oy), ex, ey)
        n, r, h = trace_fan_rows(
            ox, oy, ex, ey, kinds, starts, crossings, shift, ti0, tj0, ni, found, kind_out, run_key, run_len,
            planes, far,
        )  # fmt: skip
        if n >= 0:
            if h:
                n = _walk_far(
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
        index, m = _touched_tile_index(ox, oy, ex, ey, kinds, method, shift, ti0, tj0, ni, nj)
        needed = m << plane_shift
    if scratch.size < needed:
        return _no_trace(needed)  # the caller grows it
    found = np.empty(visits, dtype=np.int64)  # each cell the first time a beam reaches it
    kind_out = np.empty(visits, dtype=np.uint8)
    planes = np.zeros(index.size, dtype=np.uint8)  # which planes hold a cell
    if dense:
        n = _walk_dense(ox, oy, ex, ey, kinds, method, shift, wshift, ti0, tj0, scratch, found)
        _collect_dense(found, n, scratch, shift, wshift, ni, kind_out, planes)
    else:
        n = _walk_planes(ox, oy, ex, ey, kinds, method, shift, ti0, tj0, index, scratch, found)
        for k in range(n):
            kind_out[k] = scratch[found[k]]
            scratch[found[k]] = 0
            planes[found[k] >> plane_shift] = 1
    none = np.empty(0, dtype=np.int64)
    return _number_tiles(index, planes, found[:n], kind_out[:n], none, none, plane_shift, ti0, tj0, dense)


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


@njit(cache=True, nogil=True, inline="always")
def _record(found: np.ndarray, scratch: np.ndarray, n: int, key: int) -> int:
    """Mark `key` visited as a miss and append it to `found` if it was unseen; returns the new count.
    Branch-free: always write, advance only for a first visit. The unsigned casts only spare
    numba's negative-index wraparound code in the hottest loop (keys and counts are >= 0)."""
    u = np.uint64(key)
    found[np.uint64(n)] = key
    n += scratch[u] == 0
    scratch[u] = CELL_MISS
    return n


#: Distance (cells) from the sensor that every beam walks itself before any skip (see `skip_spans`).
WALK_NEAR = 2.0
#: Skip only gaps worth a restart (cells).
MIN_SKIP = 4.0


@njit(cache=True, nogil=True)
def skip_spans(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each beam, a stretch of its exact walk that other beams are certain to cover: the walk may
    leave out the cells after segment parameter `stop[b]` and before the cell at `resume[b]`
    (`resume[b] == 0`: walk it all). Per-scan updates are then unchanged: the union of the walks
    is the same set of cells.

    Why: beams form a hierarchy by index. Beam b (b > 0) has level k = lowest set bit of b; its
    neighbours b - 2**k and b + 2**k have higher levels. A cell C that b's segment touches, lying
    wholly within distance S of the sensor, has at least half a cell of its extent across b's line
    on one side (the width of a unit square across any line is >= 1). A neighbour on that side at
    angle g from b is offset by at most S*sin(g) within that distance, so when
    `S*sin(g) <= 0.45*cos(g)` its line passes through C's interior with a margin, and when the
    neighbour's segment is longer than S + 2 cells its segment does (C's contact with b beyond
    WALK_NEAR keeps the crossing ahead of the sensor). So C is crossed by a neighbour, which records
    it, or, if that neighbour skipped it too, by the same argument one level up; base beams walk
    everything. Each beam still walks its first WALK_NEAR cells and its last 2 cells itself.
    Neighbours must lie on opposite sides of b (monotonic angles) and be traced; otherwise the
    beam is walked whole. Everything is in CELL units; the parameter t runs 0..1 along a segment.
    """
    nb = ex.size
    stop = np.zeros(nb)
    resume = np.zeros(nb)
    length = np.empty(nb)
    for b in range(nb):
        length[b] = math.sqrt((ex[b] - ox) ** 2 + (ey[b] - oy) ** 2)
    for b in range(1, nb):
        step = b & -b  # 2**level
        lo = b - step
        hi = b + step
        if hi >= nb or kinds[b] == BEAM_SKIP or kinds[lo] == BEAM_SKIP or kinds[hi] == BEAM_SKIP:
            continue
        ux = ex[b] - ox
        uy = ey[b] - oy
        # The neighbours must lie on opposite sides of b, ahead of the sensor.
        cross_lo = (ex[lo] - ox) * uy - (ey[lo] - oy) * ux
        cross_hi = (ex[hi] - ox) * uy - (ey[hi] - oy) * ux
        dot_lo = (ex[lo] - ox) * ux + (ey[lo] - oy) * uy
        dot_hi = (ex[hi] - ox) * ux + (ey[hi] - oy) * uy
        if not (cross_lo * cross_hi < 0.0 and dot_lo > 0.0 and dot_hi > 0.0):
            continue
        # S * sin(g) <= 0.45 * cos(g) for both, i.e. S <= 0.45 * dot / |cross|; both neighbours
        # longer than S + 2; the beam's own last 2 cells always walked.
        safe = min(length[b], length[lo], length[hi]) - 2.0
        safe = min(safe, 0.45 * dot_lo / abs(cross_lo), 0.45 * dot_hi / abs(cross_hi))
        # Cells skipped are touched before `resume` and reach at most sqrt(2) cells further.
        end_skip = safe - 1.5
        if end_skip - WALK_NEAR >= MIN_SKIP:
            stop[b] = WALK_NEAR / length[b]
            resume[b] = end_skip / length[b]
    return stop, resume


@njit(cache=True, nogil=True, inline="always")
def _walk_rest(
    found: np.ndarray, scratch: np.ndarray, n: int, i: int, j: int, ie: int, je: int, step_i: int,
    step_j: int, base_x: float, scale_x: float, base_y: float, scale_y: float, i0: int, j0: int,
    wshift: int,
) -> tuple[int, int]:  # fmt: skip
    """Record an exact walk from cell (i, j) to its end cell (ie, je) in the dense window (rows of
    `2**wshift` cells, cell (0, 0) = (i0, j0)); returns (count, the end cell's key).

    `exact_steps_i` with its end-of-axis tests moved out of the loop: while both axes have steps
    left only the crossings decide; then the rest is a straight run."""
    key = ((j - j0) << wshift) + (i - i0)
    left_i = abs(ie - i)
    left_j = abs(je - j)
    move_j = step_j << wshift
    if left_i > 0 and left_j > 0:
        # The cell indices as floats (exact: integers far below 2**53), so each crossing is
        # `crossing(i, ...)` bit for bit without an int-to-float conversion per step.
        fi = float(i)
        fj = float(j)
        t_max_x = (fi + base_x) * scale_x
        t_max_y = (fj + base_y) * scale_y
        while True:
            n = _record(found, scratch, n, key)
            if t_max_x < t_max_y:
                fi += step_i
                key += step_i
                t_max_x = (fi + base_x) * scale_x
                left_i -= 1
                if left_i == 0:
                    break
            else:
                fj += step_j
                key += move_j
                t_max_y = (fj + base_y) * scale_y
                left_j -= 1
                if left_j == 0:
                    break
    move = step_i if left_i > 0 else move_j
    for _ in range(left_i + left_j):
        n = _record(found, scratch, n, key)
        key += move
    return _record(found, scratch, n, key), key


@njit(cache=True, nogil=True)
def _walk_dense(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray, method: int, shift: int,
    wshift: int, ti0: int, tj0: int, scratch: np.ndarray, found: np.ndarray,
) -> int:  # fmt: skip
    """Walk every traced beam, marking cells in a row-major window of rows `2**wshift` cells whose
    cell (0, 0) is the first cell of tile (ti0, tj0); returns the number of distinct cells, whose
    window keys are in `found[:n]`. End cells of returns become hits.

    Exact walks leave out the stretches `skip_spans` proves other beams cover, which indoors is most
    of each walk: near the sensor dozens of beams cross every cell."""
    i0 = ti0 << shift
    j0 = tj0 << shift
    ends = np.empty(ex.size, dtype=np.int64)
    hits = 0
    n = 0
    if method == EXACT:
        stop, resume = skip_spans(ox, oy, ex, ey, kinds)
    for b in range(ex.size):
        if kinds[b] == BEAM_SKIP:
            continue
        key = 0
        if method == EXACT:
            i, j, ie, je, step_i, step_j, base_x, scale_x, base_y, scale_y = exact_start(ox, oy, ex[b], ey[b])
            if resume[b] > 0.0:
                # The first cells, up to the crossing past parameter stop[b] (the steps of
                # `exact_steps_i`), then the rest of the walk from the cell at resume[b].
                key = ((j - j0) << wshift) + (i - i0)
                n = _record(found, scratch, n, key)
                while True:
                    t_max_x = crossing(i, base_x, scale_x)
                    t_max_y = crossing(j, base_y, scale_y)
                    if exact_steps_i(i, j, ie, je, t_max_x, t_max_y):
                        if t_max_x >= stop[b]:
                            break
                        i += step_i
                        key += step_i
                    else:
                        if j == je or t_max_y >= stop[b]:
                            break
                        j += step_j
                        key += step_j << wshift
                    n = _record(found, scratch, n, key)
                i, j = cell_at(ox, oy, ex[b], ey[b], resume[b])
            n, key = _walk_rest(
                found,
                scratch,
                n,
                i,
                j,
                ie,
                je,
                step_i,
                step_j,
                base_x,
                scale_x,
                base_y,
                scale_y,
                i0,
                j0,
                wshift,
            )
        else:
            for i, j in cells(ox, oy, ex[b], ey[b], method):
                key = ((j - j0) << wshift) + (i - i0)
                n = _record(found, scratch, n, key)
        if kinds[b] == BEAM_HIT:
            ends[hits] = key  # the last cell walked is the end cell
            hits += 1
    for k in range(hits):  # after all walks, so a later beam's miss cannot undo a hit
        scratch[ends[k]] = CELL_MISS | CELL_HIT
    return n


@njit(cache=True, nogil=True)
def _walk_far(
    kinds: np.ndarray, starts: np.ndarray, crossings: np.ndarray, far: np.ndarray, shift: int, wshift: int,
    ti0: int, tj0: int, ni: int, scratch: np.ndarray, found: np.ndarray, kind_out: np.ndarray, n: int,
    planes: np.ndarray,
) -> int:  # fmt: skip
    """Walk the rests `trace_fan_rows` handed back (`far[h] = (beam, column, row)` of each rest's
    first cell; the beams' walk states `starts` and `crossings` from `exact_starts`) in the dense
    window, append their distinct cells from `found[n]` as plane keys with their kinds, and return
    the new count. Those rows hold no other cells of the scan."""
    i0 = ti0 << shift
    j0 = tj0 << shift
    start = n
    hit_keys = np.empty(far.shape[0], dtype=np.int64)
    hits = 0
    for q in range(far.shape[0]):
        b = far[q, 0]
        n, key = _walk_rest(
            found, scratch, n, far[q, 1], far[q, 2], starts[2, b], starts[3, b], starts[4, b], starts[5, b],
            crossings[0, b], crossings[1, b], crossings[2, b], crossings[3, b], i0, j0, wshift,
        )  # fmt: skip
        if kinds[b] == BEAM_HIT:
            hit_keys[hits] = key
            hits += 1
    for k in range(hits):
        scratch[hit_keys[k]] = CELL_MISS | CELL_HIT
    _collect_dense(found[start:], n - start, scratch, shift, wshift, ni, kind_out[start:], planes)
    return n


@njit(cache=True, nogil=True, _nrt=False)
def _collect_dense(
    found: np.ndarray, n: int, scratch: np.ndarray, shift: int, wshift: int, ni: int, kind_out: np.ndarray,
    planes: np.ndarray,
) -> None:  # fmt: skip
    """Read and re-zero the marks of `found[:n]` (window keys) into `kind_out`, turn the keys into
    plane keys (plane = tile row * ni + tile column in the window, then `local_j * T + local_i`), and
    flag in `planes` the planes that hold a cell."""
    # Unsigned throughout (keys and planes are >= 0): numba's negative-index wraparound code would
    # cost each of the four indexings below two instructions.
    col_mask = np.uint64((1 << wshift) - 1)
    t_mask = np.uint64((1 << shift) - 1)
    w = np.uint64(wshift)
    t = np.uint64(shift)
    per_row = np.uint64(ni)
    for k in range(np.uint64(n)):
        key = np.uint64(found[k])
        kind_out[k] = scratch[key]
        scratch[key] = 0
        li = key & col_mask
        lj = key >> w
        plane = (lj >> t) * per_row + (li >> t)
        planes[plane] = 1
        found[k] = np.int64((((plane << t) | (lj & t_mask)) << t) | (li & t_mask))


@njit(cache=True, nogil=True)
def _touched_tile_index(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray, method: int, shift: int,
    ti0: int, tj0: int, ni: int, nj: int,
) -> tuple[np.ndarray, int]:  # fmt: skip
    """Number the tiles of the box that any beam touches 0..m-1 (others -1), for large boxes."""
    index = np.full((nj, ni), -1, dtype=np.int64)
    m = 0
    for b in range(ex.size):
        if kinds[b] != BEAM_SKIP:
            for i, j in cells(ox, oy, ex[b], ey[b], method):
                if index[(j >> shift) - tj0, (i >> shift) - ti0] < 0:
                    index[(j >> shift) - tj0, (i >> shift) - ti0] = m
                    m += 1
    return index, m


@njit(cache=True, nogil=True)
def _walk_planes(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray, method: int, shift: int,
    ti0: int, tj0: int, index: np.ndarray, scratch: np.ndarray, found: np.ndarray,
) -> int:  # fmt: skip
    """`_walk_dense` for boxes too large for a window: the scratch holds one (T, T) plane per touched
    tile (numbered by `index`), and the keys in `found[:n]` are plane keys."""
    t = 1 << shift
    mask = t - 1
    ends = np.empty(ex.size, dtype=np.int64)
    hits = 0
    n = 0
    for b in range(ex.size):
        if kinds[b] == BEAM_SKIP:
            continue
        key = 0
        if method == EXACT:
            # Inside a tile the key moves by +-1 (a step in i) or +-T (a step in j); it is recomputed
            # from the index only when the walk enters another tile.
            i, j, ie, je, step_i, step_j, base_x, scale_x, base_y, scale_y = exact_start(ox, oy, ex[b], ey[b])
            key = _cell_key(i, j, index, ti0, tj0, shift)
            edge_i = mask if step_i > 0 else 0  # the local i after which a step leaves the tile
            edge_j = mask if step_j > 0 else 0
            for _ in range(abs(ie - i) + abs(je - j)):
                n = _record(found, scratch, n, key)
                if exact_steps_i(i, j, ie, je, crossing(i, base_x, scale_x), crossing(j, base_y, scale_y)):
                    if (i & mask) == edge_i:
                        i += step_i
                        key = _cell_key(i, j, index, ti0, tj0, shift)
                    else:
                        i += step_i
                        key += step_i
                else:
                    if (j & mask) == edge_j:
                        j += step_j
                        key = _cell_key(i, j, index, ti0, tj0, shift)
                    else:
                        j += step_j
                        key += step_j * t
            n = _record(found, scratch, n, key)
        else:
            for i, j in cells(ox, oy, ex[b], ey[b], method):
                key = _cell_key(i, j, index, ti0, tj0, shift)
                n = _record(found, scratch, n, key)
        if kinds[b] == BEAM_HIT:
            ends[hits] = key
            hits += 1
    for k in range(hits):
        scratch[ends[k]] = CELL_MISS | CELL_HIT
    return n


@njit(cache=True, nogil=True, inline="always")
def _cell_key(i: int, j: int, index: np.ndarray, ti0: int, tj0: int, shift: int) -> int:
    """A cell's key in the plane scratch: its tile's plane number, then `local_j * T + local_i`."""
    mask = (1 << shift) - 1
    plane = index[(j >> shift) - tj0, (i >> shift) - ti0]
    return (plane << (2 * shift)) | ((j & mask) << shift) | (i & mask)
