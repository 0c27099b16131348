"""The per-scan union of a fan of exact walks, computed row by row instead of cell by cell.

Every beam of a scan starts in the sensor's cell, and within one grid row an exact walk covers one run
of columns: from the column where it enters the row to the column where it leaves it. Both are found
in O(1) from the walk's own boundary crossings (`exit_column`), so a beam's cells in a row cost the
same whatever the row's length.

Sorted by direction, the beams that go up (or down) have runs whose ends move monotonically along a
row, and near the sensor the runs of neighbouring beams overlap or touch. A maximal group of such
beams (a *chain*) covers, in that row, exactly the span between its two end beams' runs, however
many beams it holds. So each row costs a few O(1) steps per chain plus one per beam ending in it,
and the cells come out as spans in row order, which the apply then visits sequentially in memory.

Why a chain's span is exact (all in CELL units; a row is crossed from its entry line to its exit
line, `d` = distance from the sensor to the entry line, `key` = dx/|dy| of a beam):
- A beam that passes through the row (does not end in it) touches every cell between its entry
  point `ox + d*key` and exit point `ox + (d+1)*key` on the row's lines, and no other. Sorted by key,
  both points move one way, so the runs' ends are monotonic: the chain's end beams bound its union.
- Two such beams' real intervals are at most `d*|dkey| - w` apart (`w` = the smaller |key| when
  both lean the same way, else 0). Below a gap of half a cell their cell runs overlap or touch, so
  a chain is contiguous while `d <= (0.5 + w) / |dkey|` for each neighbouring pair. Gaps only
  grow with distance, and a pair formed when a beam between them ends is farther apart, so a broken
  pair stays broken.
- Beams ending in the row are taken out of the chains first and their runs added on their own.
- Floating-point rounding could reorder the runs of beams whose crossings are within about 1e-10
  cells of each other. Pairs with `|dkey| < MIN_KEY_GAP` are therefore never chained, and a row
  whose entry line is within `NEAR_LINE` of the sensor has every beam's run computed on its own.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.kernels.kinds import BEAM_HIT, BEAM_SKIP, CELL_HIT, CELL_MISS
from fleetmap.kernels.traversal import crossing

#: Neighbouring beams closer than this in dx/|dy| are never assumed contiguous (see module doc).
MIN_KEY_GAP = 1e-7
#: A row whose entry line is nearer the sensor than this (cells) is traced beam by beam.
NEAR_LINE = 0.01
#: Largest sensor coordinate and extent (cells) the row trace takes; the rounding argument above
#: holds well inside these. Beyond them the caller walks the beams instead.
MAX_COORD = float(1 << 24)
MAX_EXTENT = float(1 << 20)
#: Shorter runs of misses in a row are written as single cells: the apply's per-run cost would
#: outweigh its per-cell saving.
MIN_RUN = 4
#: Rows are handed back to walks once the chains average fewer beams than this (see
#: `trace_fan_rows`): a row costs a few crossing computations per chain, a walk about one per cell.
CHAIN_WALK_RATIO = 8

_DE_BRUIJN = np.uint64(0x03F79D71B4CB0A89)
_DE_BRUIJN_TABLE = np.array(
    [
        0, 1, 48, 2, 57, 49, 28, 3, 61, 58, 50, 42, 38, 29, 17, 4, 62, 55, 59, 36, 53, 51, 43, 22, 45, 39, 33,
        30, 24, 18, 12, 5, 63, 47, 56, 27, 60, 41, 37, 16, 54, 35, 52, 21, 44, 32, 23, 11, 46, 26, 40, 15,
        34, 20, 31, 10, 25, 14, 19, 9, 13, 8, 7, 6,
    ],
    dtype=np.int64,
)  # fmt: skip


@njit(cache=True, nogil=True, inline="always")
def _first_not_before(k: int, step: int, base: float, scale: float, t: float) -> tuple[int, bool]:
    """The first index, going by `step`, whose crossing `(index + base) * scale` is not before t,
    from an estimate k: k - step, k or k + step, picked without a branch. Returns it and whether it
    is exact (its crossing is not before t and the one before it is), which it is whenever k was
    within one of the answer."""
    first = k - step + step * (((k - step) + base) * scale < t) + step * ((k + base) * scale < t)
    exact = ((first + base) * scale >= t) & (((first - step) + base) * scale < t)
    return first, exact


@njit(cache=True, nogil=True, inline="always")
def exit_column(i0: int, ie: int, step_i: int, base_x: float, scale_x: float, t: float) -> int:
    """The column in which an exact walk (first column `i0`, last `ie`, x crossings `crossing(i,
    base_x, scale_x)`) leaves a row whose exit boundary it crosses at segment parameter `t`: the
    first column from i0 towards ie whose own x crossing is not before t, or ie. This is where
    `exact_steps_i` stops stepping along i in that row (not a row the walk ends in)."""
    if i0 == ie or math.isinf(scale_x):
        return i0
    if math.isinf(t):
        return ie
    k = math.floor(t / scale_x - base_x)  # the real solution of (k + base_x) * scale_x = t, +-1
    first, exact = _first_not_before(k, step_i, base_x, scale_x, t)
    if exact:  # almost always; else the loops below find it
        return min(max(first, min(i0, ie)), max(i0, ie))
    if step_i > 0:
        k = min(max(k, i0), ie)
        while k > i0 and ((k - 1) + base_x) * scale_x >= t:
            k -= 1
        while k < ie and (k + base_x) * scale_x < t:
            k += 1
    else:
        k = min(max(k, ie), i0)
        while k < i0 and ((k + 1) + base_x) * scale_x >= t:
            k += 1
        while k > ie and (k + base_x) * scale_x < t:
            k -= 1
    return k


@njit(cache=True, nogil=True)
def end_row_entries(
    ox: float, ex: np.ndarray, kinds: np.ndarray, j0: int, ie: np.ndarray, je: np.ndarray, step_i: np.ndarray,
    base_x: np.ndarray, scale_x: np.ndarray, base_y: np.ndarray, scale_y: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """The column where each traced beam enters its end row, for beams that end above or below
    the sensor's row (`je != j0`; others get a meaningless value): `exit_column` at the crossing of
    the row before, as `_trace_rows` needs it for every beam that ends in a row.

    One pass over the beams with no branch per beam, which LLVM vectorises: the first column whose
    crossing is not before t is the solution of `(k + base_x) * scale_x = t` rounded, checked against
    its neighbours with the walk's own crossings. Beams whose estimate was off by more than a cell,
    if any, get `exit_column` itself in a second pass."""
    nb = ie.size
    i0 = math.floor(ox)
    entry = np.empty(nb, dtype=np.int64)
    good = np.empty(nb, dtype=np.bool_)
    for b in range(nb):
        s = step_i[b]
        lo = min(i0, ie[b])
        hi = max(i0, ie[b])
        t = _end_row_crossing(je[b], j0, base_y[b], scale_y[b])
        x = t * (ex[b] - ox) - base_x[b]
        # Not finite for a beam in the sensor's row (whose value is not used): any guess, so that
        # the conversion to an integer is defined.
        k, exact = _first_not_before(
            int(np.floor(x) if abs(x) < 4.5e15 else 0.0), s, base_x[b], scale_x[b], t
        )
        good[b] = exact | (lo == hi)
        entry[b] = min(max(k, lo), hi)
    for b in range(nb):
        if not good[b] and je[b] != j0 and kinds[b] != BEAM_SKIP:
            t = _end_row_crossing(je[b], j0, base_y[b], scale_y[b])
            entry[b] = exit_column(i0, ie[b], step_i[b], base_x[b], scale_x[b], t)
    return entry


@njit(cache=True, nogil=True, inline="always")
def _end_row_crossing(je: int, j0: int, base_y: float, scale_y: float) -> float:
    """Segment parameter at which a walk ending in row je (not the sensor's row j0) enters it."""
    return crossing(je - (1 if je > j0 else -1), base_y, scale_y)


@njit(cache=True, nogil=True, inline="always")
def _lowest_bit(word: np.uint64) -> int:
    """Index of the lowest set bit of a non-zero word."""
    low = word & (~word + np.uint64(1))
    return _DE_BRUIJN_TABLE[(low * _DE_BRUIJN) >> np.uint64(58)]


@njit(cache=True, nogil=True)
def trace_fan_rows(
    ox: float, oy: float, ex: np.ndarray, ey: np.ndarray, kinds: np.ndarray, starts: np.ndarray,
    crossings: np.ndarray, shift: int, ti0: int, tj0: int, ni: int, found: np.ndarray, kind_out: np.ndarray,
    run_key: np.ndarray, run_len: np.ndarray, planes: np.ndarray, far: np.ndarray,
) -> tuple[int, int, int]:  # fmt: skip
    """Per-scan exact-traversal updates of every traced beam (`kinds`: `kernels.kinds` codes), row by row.
    `starts` and `crossings` are the beams' walk states (`traversal.exact_starts`).

    Writes each touched cell once, as a plane key (plane = tile row * ni + tile column relative to
    tile (ti0, tj0), then `local_j * T + local_i`): runs of at least `MIN_RUN` misses on consecutive
    cells of one tile row as `run_key` (the first cell) and `run_len`, every other cell into
    `found` with its kind in `kind_out` (hit if a `BEAM_HIT` ends in it, else miss). Flags the
    planes used in `planes`. `run_key` needs room for `found.size // MIN_RUN` runs.

    Far from the sensor, where neighbouring beams no longer touch, a row costs more than walking its
    few cells. Unless `far` is empty, the rows stop there (above and below the sensor separately)
    and the beams still going on are handed back: `far[h] = (beam, column, row)` of the cell in which
    the caller walks the beam's rest. No cell of those rows is written here, so the caller only
    de-duplicates its walks among themselves.

    Returns `(cells written to found, runs written, beams handed back)`, or (-1, 0, 0) with nothing
    useful written when the fan is not ordered by direction or lies outside `MAX_COORD` /
    `MAX_EXTENT`; the caller then walks the beams.
    """
    nb = ex.size
    if not (abs(ox) < MAX_COORD and abs(oy) < MAX_COORD):
        return -1, 0, 0
    i0 = math.floor(ox)
    j0 = math.floor(oy)
    ie = starts[2]
    je = starts[3]
    step_i = starts[4]
    base_x = crossings[0]
    scale_x = crossings[1]
    base_y = crossings[2]
    scale_y = crossings[3]
    up_all = np.empty(nb, dtype=np.int64)
    down_all = np.empty(nb, dtype=np.int64)
    n_up = n_down = 0
    rows = 0  # the farthest end row from the sensor's, in rows
    for b in range(nb):
        if kinds[b] == BEAM_SKIP:
            continue
        if not (abs(ex[b] - ox) < MAX_EXTENT and abs(ey[b] - oy) < MAX_EXTENT):
            return -1, 0, 0
        rows = max(rows, abs(je[b] - j0))
        if je[b] > j0:
            up_all[n_up] = b
            n_up += 1
        elif je[b] < j0:
            down_all[n_down] = b
            n_down += 1
    up = up_all[:n_up]
    down = down_all[:n_down]
    # Each beam's key (the module doc's): dx/|dy|, where it crosses a row line per unit of distance
    # from the sensor. In a pass of its own, which the compiler does several beams at a time; the
    # beams in the sensor's row (dy may be 0) have no key and get a meaningless one.
    keys = np.empty(nb)
    for b in range(nb):
        dy = abs(ey[b] - oy)
        keys[b] = (ex[b] - ox) / (dy if dy > 0.0 else 1.0)
    up_order = _direction_order(up, keys)
    down_order = _direction_order(down, keys)
    if up_order.size != n_up or down_order.size != n_down:
        return -1, 0, 0
    entry_end = end_row_entries(ox, ex, kinds, j0, ie, je, step_i, base_x, scale_x, base_y, scale_y)
    # The sensor's row: every beam's run starts at the sensor's column, so their union is one span,
    # from the end cells of the beams ending in it and the columns where the others leave it.
    lo = hi = i0
    hit_cols = np.empty(nb, dtype=np.int64)
    nh = 0
    for b in range(nb):
        if kinds[b] != BEAM_SKIP and je[b] == j0:
            lo = min(lo, ie[b])
            hi = max(hi, ie[b])
            if kinds[b] == BEAM_HIT:
                hit_cols[nh] = ie[b]
                nh += 1
    fy = oy - j0
    for g in range(2):  # up, then down
        # A beam leaves the row at x = ox + d*key on its exit line, d from the sensor: monotonic in
        # key, so the fan's two end beams bound the others, as the end beams of a chain do (module
        # doc), with the same guards: beams within MIN_KEY_GAP of an end beam's key count as ends
        # too, and every beam does when the line is within NEAR_LINE of the sensor.
        order = up_order if g == 0 else down_order
        n = order.size
        if n == 0:
            continue
        head = tail = n  # the ends: the first `head` beams of the order and those from `tail` on
        if (1.0 - fy if g == 0 else fy) >= NEAR_LINE:
            first = keys[order[0]]
            head = 1
            while head < n and abs(keys[order[head]] - first) < MIN_KEY_GAP:
                head += 1
            last = keys[order[n - 1]]
            tail = n - 1
            while tail > head and abs(keys[order[tail - 1]] - last) < MIN_KEY_GAP:
                tail -= 1
        for q in range(head + n - tail):
            b = order[q if q < head else tail + q - head]
            col = exit_column(
                i0, ie[b], step_i[b], base_x[b], scale_x[b], crossing(j0, base_y[b], scale_y[b])
            )
            lo = min(lo, col)
            hi = max(hi, col)
    # The counts (cells, beams handed back, runs) live in an array: passed as the literal 0, an int
    # argument would make numba compile each callee twice, once for the literal.
    counts = np.zeros(3, dtype=np.int64)
    span = np.array([lo, hi], dtype=np.int64)
    if not _emit_row(
        found, kind_out, run_key, run_len, planes, counts, j0, span[:1], span[1:], 1, hit_cols, nh, shift,
        ti0, tj0, ni,
    ):  # fmt: skip
        return -1, 0, 0
    # The two halves' work arrays, allocated once for both (see `_trace_rows`).
    most = max(n_up, n_down)
    work = np.empty(3 * (rows + 2) + 15 * most + 8, dtype=np.int64)
    work_keys = np.empty(most)
    work_brk = np.empty((most + 63) >> 6, dtype=np.uint64)
    for g in range(2):  # up, then down
        # (Chosen before the call: with this many arguments, numba cannot take conditional ones.)
        order = up_order if g == 0 else down_order
        c = fy if g == 0 else 1.0 - fy  # row offset m's entry line lies m - c from the sensor
        _trace_rows(
            order, 1 - 2 * g, c, counts, keys, kinds, i0, j0, ie, je, step_i, base_x, scale_x, base_y,
            scale_y, entry_end, shift, ti0, tj0, ni, found, kind_out, run_key, run_len, planes, far, work,
            work_keys, work_brk,
        )  # fmt: skip
        if counts[0] < 0:
            return -1, 0, 0
    return counts[0], counts[2], counts[1]


@njit(cache=True, nogil=True)
def _direction_order(members: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """`members` (beam numbers, all going up or all going down) rotated so that their `keys` (dx/|dy|,
    indexed by beam) are monotonic, which they are for beams in angle order over less than a full
    turn, up to one wrap-around. Returns an empty array when no rotation makes them monotonic."""
    n = members.size
    if n <= 2:
        return members.copy()
    for sign in (1.0, -1.0):  # try non-increasing, then non-decreasing
        rises = 0
        at = 0
        for p in range(n - 1):
            if sign * (keys[members[p + 1]] - keys[members[p]]) > 0.0:
                rises += 1
                at = p + 1
        if rises == 0:
            return members.copy()
        if rises == 1 and sign * (keys[members[0]] - keys[members[n - 1]]) <= 0.0:
            out = np.empty(n, dtype=np.int64)
            for p in range(n):
                out[p] = members[(at + p) % n]
            return out
    return np.empty(0, dtype=np.int64)


# Called once per row with arrays: compiled without numba's reference counting (`_nrt=False`; it
# allocates nothing), which otherwise costs an atomic increment and decrement per array argument on
# every call, about 90 of this function's 140 ns per row.
@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def _emit_row(
    found: np.ndarray, kind_out: np.ndarray, run_key: np.ndarray, run_len: np.ndarray, planes: np.ndarray,
    counts: np.ndarray, row: int, span_lo: np.ndarray, span_hi: np.ndarray, spans: int, hit_cols: np.ndarray,
    nh: int, shift: int, ti0: int, tj0: int, ni: int,
) -> bool:  # fmt: skip
    """Write one row's cells: the first `spans` of the disjoint ascending spans `span_lo/hi` as
    misses, except the columns `hit_cols[:nh]` (end cells of returns, in any order, repeats
    allowed), which are hits. The misses, split at tile edges and around the hits, go out as runs
    when they are `MIN_RUN` cells or more, else as single cells; hits as single cells. `counts[0]`
    and `counts[2]` (cells, runs) advance. Returns False, advancing no count, if a hit lies outside
    the spans or `found` or `run_key` could overflow (none can happen for a real trace)."""
    # The hit columns sorted (a row holds only a few).
    for k in range(1, nh):
        v = hit_cols[k]
        t = k
        while t > 0 and hit_cols[t - 1] > v:
            hit_cols[t] = hit_cols[t - 1]
            t -= 1
        hit_cols[t] = v
    mask = (1 << shift) - 1
    tile_row = ((row >> shift) - tj0) * ni
    local_row = (row & mask) << shift
    n = counts[0]
    r = counts[2]
    h = 0
    for s in range(spans):
        lo = span_lo[s]
        hi = span_hi[s]
        if n + hi - lo >= found.size:
            return False
        if h < nh and hit_cols[h] < lo:
            return False  # a hit left of this span and in no earlier one
        c = lo
        while c <= hi:
            # The misses from c up to the next hit, the span's end or the tile's edge.
            tile_start = (c >> shift) << shift
            end = min(hi, tile_start + mask)
            if h < nh and hit_cols[h] <= end:
                end = hit_cols[h] - 1
            plane = tile_row + (c >> shift) - ti0
            base = ((plane << (2 * shift)) | local_row) - tile_start
            if end >= c:
                planes[plane] = 1
                if end - c + 1 >= MIN_RUN:
                    if r >= run_key.size:
                        return False
                    run_key[r] = base + c
                    run_len[r] = end - c + 1
                    r += 1
                else:
                    for x in range(c, end + 1):
                        found[n] = base + x
                        kind_out[n] = 1  # CELL_MISS
                        n += 1
            c = end + 1
            if h < nh and hit_cols[h] == c and c <= hi:
                plane = tile_row + (c >> shift) - ti0
                planes[plane] = 1
                found[n] = ((plane << (2 * shift)) | local_row) + (c & mask)
                kind_out[n] = CELL_HIT | CELL_MISS
                n += 1
                c += 1
                while h < nh and hit_cols[h] < c:  # repeats of this hit column
                    h += 1
    if h < nh:
        return False
    counts[0] = n
    counts[2] = r
    return True


@njit(cache=True, nogil=True, inline="always")
def _break_row(ka: float, kb: float, c: float, rows: int) -> int:
    """The first row offset m (distance m - c from the sensor to its entry line) at which beams with
    keys ka, kb, neighbours in a chain, may leave a gap between their runs; rows + 1 if never within
    `rows`, and 0 if they must never be chained."""
    gap = abs(ka - kb)
    if gap < MIN_KEY_GAP:
        return 0
    w = min(abs(ka), abs(kb)) if ka * kb > 0.0 else 0.0
    limit = (0.5 + w) / gap + c
    if limit >= rows:
        return rows + 1
    return math.floor(limit) + 1


# Allocates nothing (its work arrays are carved from `work`, `work_keys` and `work_brk`), so it is
# compiled without reference counting: with it, its 30 array arguments and work arrays cost about
# 80 atomic increments and decrements per call.
@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def _trace_rows(
    order: np.ndarray, step_j: int, c: float, counts: np.ndarray, keys: np.ndarray, kinds: np.ndarray,
    i0: int, j0: int, ie: np.ndarray, je: np.ndarray, step_i: np.ndarray, base_x: np.ndarray,
    scale_x: np.ndarray, base_y: np.ndarray, scale_y: np.ndarray, entry_end: np.ndarray, shift: int,
    ti0: int, tj0: int, ni: int, found: np.ndarray, kind_out: np.ndarray, run_key: np.ndarray,
    run_len: np.ndarray, planes: np.ndarray, far: np.ndarray, work: np.ndarray, work_keys: np.ndarray,
    work_brk: np.ndarray,
) -> None:  # fmt: skip
    """The rows above (step_j = 1) or below (-1) the sensor's row, crossed by the beams `order`
    (sorted by direction). Row offset m is row j0 + step_j * m, whose entry line lies m - c from the
    sensor. Appends cells and runs (`_emit_row`) and hand-backs to `far` after the `counts` (cells,
    hand-backs, runs) so far, and updates them; a cell count of -1 means the row trace gave up.
    `entry_end[b]` is the column where beam b enters its end row (`end_row_entries`), `keys[b]`
    its dx/|dy|.

    Work space, overwritten: `work` at least `3 * (rows + 2) + 15 * n + 8` integers, `work_keys` n
    floats and `work_brk` `(n + 63) // 64` words, for n = `order.size` beams whose end rows lie at
    most `rows` row offsets out."""
    h = counts[1]
    nu = order.size
    if nu == 0:
        return
    key = work_keys[:nu]
    dist = work[:nu]
    rows = 0
    for p in range(nu):
        b = order[p]
        key[p] = keys[b]
        dist[p] = abs(je[b] - j0)
        rows = max(rows, dist[p])
    # The other work arrays, one after another in `work`.
    o = nu
    ends_at, o = work[o : o + rows + 2], o + rows + 2
    fill, o = work[o : o + rows + 2], o + rows + 2
    ev_head, o = work[o : o + rows + 2], o + rows + 2
    ending, o = work[o : o + nu], o + nu
    nxt, o = work[o : o + nu], o + nu
    prv, o = work[o : o + nu], o + nu
    hit_cols, o = work[o : o + nu], o + nu
    ev_a, o = work[o : o + 2 * nu], o + 2 * nu
    ev_b, o = work[o : o + 2 * nu], o + 2 * nu
    ev_next, o = work[o : o + 2 * nu], o + 2 * nu
    span_lo, o = work[o : o + nu + 2], o + nu + 2
    span_hi, o = work[o : o + nu + 2], o + nu + 2
    tmp_lo, o = work[o : o + nu + 2], o + nu + 2
    tmp_hi = work[o : o + nu + 2]
    # Beams ending in each row offset, by a counting sort.
    ends_at[:] = 0
    for p in range(nu):
        ends_at[dist[p] + 1] += 1
    for m in range(rows + 1):
        ends_at[m + 1] += ends_at[m]
    for m in range(rows + 2):
        fill[m] = ends_at[m]
    for p in range(nu):
        m = dist[p]
        ending[fill[m]] = p
        fill[m] += 1
    # The beams still going on, as a linked list in direction order; brk has bit p set when the
    # chain breaks between p and the next beam still going on.
    for p in range(nu):
        nxt[p] = p + 1
        prv[p] = p - 1
    nxt[nu - 1] = -1
    head = 0
    tail = nu - 1
    words = (nu + 63) >> 6
    brk = work_brk[:words]
    brk[:] = 0
    # Pending breaks: pair (ev_a, ev_b) breaks at row offset m; a per-row linked list, checked when due
    # (the pair may no longer be neighbours by then).
    ev_head[:] = -1
    events = 0
    for p in range(nu - 1):
        m = _break_row(key[p], key[p + 1], c, rows)
        if m <= 1:
            brk[p >> 6] |= np.uint64(1) << np.uint64(p & 63)
        elif m <= rows:
            ev_a[events] = p
            ev_b[events] = p + 1
            ev_next[events] = ev_head[m]
            ev_head[m] = events
            events += 1
    descending = key[0] >= key[nu - 1]  # the runs' columns fall along `order`
    going = nu
    handing_back = False
    for m in range(1, rows + 1):
        row = j0 + step_j * m
        if handing_back:
            # Walk the rest: every beam still going on, from the cell where it enters this row.
            p = head
            while p >= 0:
                b = order[p]
                far[h, 0] = b
                far[h, 1] = exit_column(
                    i0, ie[b], step_i[b], base_x[b], scale_x[b], crossing(row - step_j, base_y[b], scale_y[b])
                )
                far[h, 2] = row
                h += 1
                p = nxt[p]
            break
        # Beams ending in this row: their own runs, then out of the chains.
        ended = ends_at[m + 1] - ends_at[m]
        own = 0  # their runs so far, each joined to the one before when they touch (no branch)
        for q in range(ended):
            p = ending[ends_at[m] + q]
            b = order[p]
            entry = entry_end[b]  # where b enters this row, its end row
            lo = min(entry, ie[b])
            hi = max(entry, ie[b])
            touch = (own > 0) & (lo <= span_hi[own - 1] + 1) & (hi + 1 >= span_lo[own - 1])
            at = own - touch
            span_lo[at] = min(span_lo[at], lo) if touch else lo
            span_hi[at] = max(span_hi[at], hi) if touch else hi
            own += 1 - touch
            going -= 1
            a = prv[p]
            z = nxt[p]
            brk[p >> 6] &= ~(np.uint64(1) << np.uint64(p & 63))
            if a >= 0:
                nxt[a] = z
            else:
                head = z
            if z >= 0:
                prv[z] = a
            else:
                tail = a
            if a >= 0:
                bit = np.uint64(1) << np.uint64(a & 63)
                brk[a >> 6] &= ~bit
                # (When z ends in this row too, it is taken out later in this loop, and a is paired
                # with the beam after it then.)
                if z >= 0 and dist[z] != m:
                    mb = _break_row(key[a], key[z], c, rows)
                    if mb <= m:
                        brk[a >> 6] |= bit
                    elif mb <= rows:
                        ev_a[events] = a
                        ev_b[events] = z
                        ev_next[events] = ev_head[mb]
                        ev_head[mb] = events
                        events += 1
        e = ev_head[m]
        while e >= 0:
            a = ev_a[e]
            if nxt[a] == ev_b[e] and prv[ev_b[e]] == a:  # still neighbours, both going on
                brk[a >> 6] |= np.uint64(1) << np.uint64(a & 63)
            e = ev_next[e]
        # The chains of beams going on: each covers the span between its end beams' runs.
        spans = own
        if head >= 0:
            if m - c < NEAR_LINE:
                p = head
                while p >= 0:
                    b = order[p]
                    span_lo[spans], span_hi[spans] = _row_run(
                        i0, ie[b], step_i[b], base_x[b], scale_x[b], base_y[b], scale_y[b], row, step_j
                    )
                    spans += 1
                    p = nxt[p]
            else:
                first = head
                w = 0
                word = brk[0]
                while True:
                    # The next chain: from `first` to the next break, or to the tail.
                    while word == 0 and w + 1 < words:
                        w += 1
                        word = brk[w]
                    if word:
                        last = (w << 6) + _lowest_bit(word)
                        word &= word - np.uint64(1)
                    else:
                        last = tail
                    b = order[first]
                    lo, hi = _row_run(
                        i0, ie[b], step_i[b], base_x[b], scale_x[b], base_y[b], scale_y[b], row, step_j
                    )
                    if last != first:
                        b = order[last]
                        lo2, hi2 = _row_run(
                            i0, ie[b], step_i[b], base_x[b], scale_x[b], base_y[b], scale_y[b], row, step_j
                        )
                        lo = min(lo, lo2)
                        hi = max(hi, hi2)
                    span_lo[spans] = lo
                    span_hi[spans] = hi
                    spans += 1
                    if last == tail:
                        break
                    first = nxt[last]
        if far.shape[0] and (spans - own) * CHAIN_WALK_RATIO > going:
            handing_back = True  # from the next row on, most chains are single beams
        merged = _union(span_lo, span_hi, own, spans, descending, tmp_lo, tmp_hi)
        # Hits: the end cells of returns ending in this row, in ascending columns but for rounding
        # (`ending` lists them in direction order; reversed when the columns fall), so that
        # `_emit_row`'s insertion sort costs one pass. A wall along the row ends dozens of beams in
        # it, and in reverse order the sort was quadratic (42 shifts per floor-plan row, now 2).
        nh = 0
        first_end = ends_at[m]
        last_end = ends_at[m + 1] - 1
        for q in range(first_end, last_end + 1):
            b = order[ending[last_end - (q - first_end) if descending else q]]
            # Written always, kept if a return ending in a column not just kept: beams ending in
            # one cell come together, and `_emit_row` would skip each repeat one by one.
            hit_cols[nh] = ie[b]
            nh += (kinds[b] == BEAM_HIT) & ((nh == 0) or (hit_cols[nh - 1] != ie[b]))
        if not _emit_row(
            found, kind_out, run_key, run_len, planes, counts, row, span_lo, span_hi, merged, hit_cols, nh,
            shift, ti0, tj0, ni,
        ):  # fmt: skip
            counts[0] = -1  # cannot happen (a walk covers its end cell, the union is at most every walk)
            return
    counts[1] = h


# Once per row with arrays, allocates nothing: no reference counting (see `_emit_row`).
@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def _union(
    span_lo: np.ndarray, span_hi: np.ndarray, ended: int, spans: int, descending: bool, tmp_lo: np.ndarray,
    tmp_hi: np.ndarray,
) -> int:  # fmt: skip
    """Replace the row's spans by their union as disjoint spans in ascending order; returns how many.

    The spans come as two runs, each in direction order: `[0, ended)` of the beams ending in the row
    (neighbours' runs that touch already joined) and `[ended, spans)` of the chains; `descending`
    says their columns fall. The runs are merged, then an insertion pass puts right whatever
    rounding or joining left out of order (it costs nothing on sorted input), then touching spans
    are joined."""
    a, a_end, b, b_end, d = 0, ended, ended, spans, 1
    if descending:
        a, a_end, b, b_end, d = ended - 1, -1, spans - 1, ended - 1, -1
    for k in range(spans):
        if b == b_end or (a != a_end and span_lo[a] <= span_lo[b]):
            tmp_lo[k] = span_lo[a]
            tmp_hi[k] = span_hi[a]
            a += d
        else:
            tmp_lo[k] = span_lo[b]
            tmp_hi[k] = span_hi[b]
            b += d
    for k in range(1, spans):
        lo_k, hi_k = tmp_lo[k], tmp_hi[k]
        t = k
        while t > 0 and tmp_lo[t - 1] > lo_k:
            tmp_lo[t] = tmp_lo[t - 1]
            tmp_hi[t] = tmp_hi[t - 1]
            t -= 1
        tmp_lo[t] = lo_k
        tmp_hi[t] = hi_k
    merged = 0
    for k in range(spans):
        if merged and tmp_lo[k] <= span_hi[merged - 1] + 1:
            span_hi[merged - 1] = max(span_hi[merged - 1], tmp_hi[k])
        else:
            span_lo[merged] = tmp_lo[k]
            span_hi[merged] = tmp_hi[k]
            merged += 1
    return merged


@njit(cache=True, nogil=True, inline="always")
def _row_run(
    i0: int, ie: int, step_i: int, base_x: float, scale_x: float, base_y: float, scale_y: float, row: int,
    step_j: int,
) -> tuple[int, int]:  # fmt: skip
    """A beam's run `(lo, hi)` of columns in `row`, a row it passes through (does not end in).

    Scalars only: numba reference-counts every array handed to a helper, atomically, which in
    these per-row loops cost more than the arithmetic."""
    entry = exit_column(i0, ie, step_i, base_x, scale_x, crossing(row - step_j, base_y, scale_y))
    leave = exit_column(i0, ie, step_i, base_x, scale_x, crossing(row, base_y, scale_y))
    return min(entry, leave), max(entry, leave)
