"""Beam-by-beam walks that mark each cell once in a scratch: the parts of `ray_model.trace_scan`
that the row trace (`fan_rows`) does not do. The far rests the row trace hands back are walked in a
dense window (`walk_far`); other exact scans and Bresenham lines are walked whole, in the dense
window (`walk_dense`) or, for boxes too large for it, in per-tile planes (`walk_planes`), skipping
the stretches neighbouring beams are certain to cover (`skip_spans`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.kernels.kinds import BEAM_HIT, BEAM_SKIP, CELL_HIT, CELL_MISS
from fleetmap.kernels.traversal import EXACT, cell_at, cells, crossing, exact_start, exact_steps_i
from fleetmap.kernels.update import updated_log_odds


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
def walk_dense(
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


@njit(cache=True, nogil=True, inline="always")
def _walk_far_rests(
    kinds: np.ndarray, starts: np.ndarray, crossings: np.ndarray, far: np.ndarray, shift: int, wshift: int,
    ti0: int, tj0: int, scratch: np.ndarray, found: np.ndarray, n: int,
) -> int:  # fmt: skip
    """The walks of `walk_far` and `walk_far_apply`: mark the rests' cells in the dense window,
    append each distinct cell's window key from `found[n]` and return the new count. The end cells
    of returns are marked hits after all walks, so that a later beam's miss cannot undo a hit."""
    i0 = ti0 << shift
    j0 = tj0 << shift
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
    return n


@njit(cache=True, nogil=True)
def walk_far(
    kinds: np.ndarray, starts: np.ndarray, crossings: np.ndarray, far: np.ndarray, shift: int, wshift: int,
    ti0: int, tj0: int, ni: int, scratch: np.ndarray, found: np.ndarray, kind_out: np.ndarray, n: int,
    planes: np.ndarray,
) -> int:  # fmt: skip
    """Walk the rests `trace_fan_rows` handed back (`far[h] = (beam, column, row)` of each rest's
    first cell; the beams' walk states `starts` and `crossings` from `exact_starts`) in the dense
    window, append their distinct cells from `found[n]` as plane keys with their kinds, and return
    the new count. Those rows hold no other cells of the scan."""
    start = n
    n = _walk_far_rests(kinds, starts, crossings, far, shift, wshift, ti0, tj0, scratch, found, n)
    collect_dense(found[start:], n - start, scratch, shift, wshift, ni, kind_out[start:], planes)
    return n


@njit(cache=True, nogil=True)
def walk_far_apply(
    kinds: np.ndarray, starts: np.ndarray, crossings: np.ndarray, far: np.ndarray, shift: int, wshift: int,
    ti0: int, tj0: int, ni: int, scratch: np.ndarray, found: np.ndarray, n: int, slots: np.ndarray,
    log_odds: np.ndarray, l_hit: float, l_miss: float, l_min: float, l_max: float, changed: np.ndarray,
) -> int:  # fmt: skip
    """`walk_far`, with the cells applied to the log-odds pool instead of collected for the apply:
    the same walks, then `apply_dense` over the cells they found (`found[n:]` is work space).
    Returns the number of cells updated. For the one-call path when every tile of the box exists
    (`slots[plane]` is each box tile's pool slot, planes row-major over the box)."""
    end = _walk_far_rests(kinds, starts, crossings, far, shift, wshift, ti0, tj0, scratch, found, n)
    apply_dense(
        found[n:], end - n, scratch, shift, wshift, ni, slots, log_odds, l_hit, l_miss, l_min, l_max, changed
    )
    return end - n


@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def apply_dense(
    found: np.ndarray, n: int, scratch: np.ndarray, shift: int, wshift: int, ni: int, slots: np.ndarray,
    log_odds: np.ndarray, l_hit: float, l_miss: float, l_min: float, l_max: float, changed: np.ndarray,
) -> None:  # fmt: skip
    """`collect_dense` and `update.apply_cells` in one pass, for cells whose tiles all exist: read
    and re-zero the marks of `found[:n]` (window keys, each cell once), apply each cell's hit or miss
    to the log-odds pool (`updated_log_odds`, the one rule) in the tile at `slots[plane]` (plane =
    tile row * ni + tile column in the window), and set `changed[plane]` where a stored value
    changed. What it saves: the plane keys and kinds written out and read back, the planes'
    flags and the apply's own pass."""
    # Unsigned throughout (keys, planes and pool offsets are >= 0), as in `collect_dense`.
    col_mask = np.uint64((1 << wshift) - 1)
    t_mask = np.uint64((1 << shift) - 1)
    w = np.uint64(wshift)
    t = np.uint64(shift)
    per_row = np.uint64(ni)
    flat_log_odds = log_odds.reshape(-1)
    # A walk's cells mostly stay in one tile: the slot is looked up and the change flag stored only
    # when the tile changes (a store per cell would chain every iteration to the last, see apply_cells).
    plane = np.uint64(0xFFFFFFFFFFFFFFFF)
    start = np.uint64(0)
    diff = False
    for k in range(np.uint64(n)):
        key = np.uint64(found[k])
        hit = (scratch[key] & CELL_HIT) != 0
        scratch[key] = 0
        li = key & col_mask
        lj = key >> w
        p = (lj >> t) * per_row + (li >> t)
        if p != plane:
            if diff:
                changed[plane] = 1
            diff = False
            plane = p
            start = np.uint64(slots[p]) << (t + t)
        at = start | ((lj & t_mask) << t) | (li & t_mask)
        old = flat_log_odds[at]
        new = updated_log_odds(old, hit, l_hit, l_miss, l_min, l_max)
        flat_log_odds[at] = new
        diff |= new != old  # NaN != anything: a first observation is a change
    if diff:
        changed[plane] = 1


@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def collect_dense(
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
def touched_tile_index(
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
def walk_planes(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray, method: int, shift: int,
    ti0: int, tj0: int, index: np.ndarray, scratch: np.ndarray, found: np.ndarray,
) -> int:  # fmt: skip
    """`walk_dense` for boxes too large for a window: the scratch holds one (T, T) plane per touched
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
