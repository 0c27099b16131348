"""Grid traversal of a segment: which cells a ray passes through.

`exact` is the Amanatides-Woo walk: every cell the segment crosses, a 4-connected chain of exactly
`|di| + |dj| + 1` cells from the start cell to the end cell. Where the segment passes exactly through
a cell corner it steps one axis at a time, so the chain stays 4-connected (the extra cell touches the
segment at that corner). `bresenham` is the classic 8-connected integer line between the start and
end cells, `max(|di|, |dj|) + 1` cells.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
from numba import njit

EXACT = 0
BRESENHAM = 1


@njit(cache=True, nogil=True, inline="always")
def cell_count(x0: float, y0: float, x1: float, y1: float, method: int) -> int:
    """Number of cells the traversal of (x0, y0) -> (x1, y1) visits, the end cell included."""
    di = abs(math.floor(x1) - math.floor(x0))
    dj = abs(math.floor(y1) - math.floor(y0))
    if method == EXACT:
        return int(di + dj + 1)
    return int(max(di, dj) + 1)


@njit(cache=True, nogil=True, inline="always")
def exact_axis(a0: float, a1: float) -> tuple[int, int, int, float, float]:
    """One axis of an exact walk from a0 to a1: `(first cell, end cell, step, base, scale)`. The
    segment parameter (0..1) at which the walk crosses the boundary after cell k is
    `crossing(k, base, scale)`.

    The crossing is computed from k alone, never accumulated step by step, so a walk resumed at any
    cell of the segment (`cell_at`) makes exactly the decisions the whole walk makes there."""
    d = a1 - a0
    if d > 0.0:
        return math.floor(a0), math.floor(a1), 1, 1.0 - a0, 1.0 / d
    if d < 0.0:
        return math.floor(a0), math.floor(a1), -1, -a0, 1.0 / d  # (k - a0) / d = (a0 - k) / |d|
    return math.floor(a0), math.floor(a1), 1, 1.0 - a0, math.inf  # never crossed: +inf


@njit(cache=True, nogil=True, inline="always")
def crossing(k: int, base: float, scale: float) -> float:
    """Segment parameter of the boundary an exact walk crosses when it leaves cell k (see
    `exact_axis`)."""
    return (k + base) * scale


@njit(cache=True, nogil=True, inline="always")
def exact_start(
    x0: float, y0: float, x1: float, y1: float
) -> tuple[int, int, int, int, int, int, float, float, float, float]:
    """State of an exact walk at its start cell: `(i, j, ie, je, step_i, step_j, base_x, scale_x,
    base_y, scale_y)`; the next vertical / horizontal boundary crossing is at segment parameter
    `crossing(i, base_x, scale_x)` / `crossing(j, base_y, scale_y)`."""
    i, ie, step_i, base_x, scale_x = exact_axis(x0, x1)
    j, je, step_j, base_y, scale_y = exact_axis(y0, y1)
    return i, j, ie, je, step_i, step_j, base_x, scale_x, base_y, scale_y


@njit(cache=True, nogil=True)
def exact_starts(
    x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """`exact_start` of every segment (x0[b], y0[b]) -> (x1[b], y1[b]): `(cells, crossings)`, rows
    `i, j, ie, je, step_i, step_j` and `base_x, scale_x, base_y, scale_y`.

    A pass of its own, with nothing but this in its loop, so that the compiler computes several
    segments' divisions and floors at once; the walks then read their state from it."""
    n = x1.size
    cells = np.empty((6, n), dtype=np.int64)
    crossings = np.empty((4, n))
    for b in range(n):
        i, j, ie, je, step_i, step_j, base_x, scale_x, base_y, scale_y = exact_start(
            x0[b], y0[b], x1[b], y1[b]
        )
        cells[0, b] = i
        cells[1, b] = j
        cells[2, b] = ie
        cells[3, b] = je
        cells[4, b] = step_i
        cells[5, b] = step_j
        crossings[0, b] = base_x
        crossings[1, b] = scale_x
        crossings[2, b] = base_y
        crossings[3, b] = scale_y
    return cells, crossings


@njit(cache=True, nogil=True, inline="always")
def cell_at(x0: float, y0: float, x1: float, y1: float, t: float) -> tuple[int, int]:
    """The cell holding the segment's point at parameter t. An exact walk resumed there (with the
    whole segment's `exact_start` bases and scales) makes the whole walk's decisions from there on."""
    return math.floor(x0 + t * (x1 - x0)), math.floor(y0 + t * (y1 - y0))


@njit(cache=True, nogil=True, inline="always")
def exact_steps_i(i: int, j: int, ie: int, je: int, t_max_x: float, t_max_y: float) -> bool:
    """Whether the exact walk's next step is along i (else along j).

    Never step past the end cell on an axis already done: the walk then ends exactly at the end
    cell after |di| + |dj| steps whatever rounding did to t_max."""
    if i == ie:
        return False
    if j == je:
        return True
    return t_max_x < t_max_y


# Not cached: numba cannot hand a cache-loaded generator to a newly compiled caller (KeyError in
# get_generator_impl). Its callers are cached and carry its code with them.
@njit(cache=False, nogil=True)
def cells(x0: float, y0: float, x1: float, y1: float, method: int) -> Iterator[tuple[int, int]]:
    """Yield the cells `(i, j)` of the traversal of (x0, y0) -> (x1, y1), start cell to end cell.

    A numba generator for kernels that are not the hottest; `beam_walks` and `tsdf` inline the same
    `exact_start` / `crossing` / `exact_steps_i` steps by hand.
    """
    if method == EXACT:
        i, j, ie, je, step_i, step_j, base_x, scale_x, base_y, scale_y = exact_start(x0, y0, x1, y1)
        yield i, j
        for _ in range(abs(ie - i) + abs(je - j)):
            if exact_steps_i(i, j, ie, je, crossing(i, base_x, scale_x), crossing(j, base_y, scale_y)):
                i += step_i
            else:
                j += step_j
            yield i, j
    else:
        i = math.floor(x0)
        j = math.floor(y0)
        ie = math.floor(x1)
        je = math.floor(y1)
        di = abs(ie - i)
        dj = -abs(je - j)
        si = 1 if i < ie else -1
        sj = 1 if j < je else -1
        err = di + dj
        yield i, j
        while i != ie or j != je:
            e2 = 2 * err
            if e2 >= dj:
                err += dj
                i += si
            if e2 <= di:
                err += di
                j += sj
            yield i, j


@njit(cache=True, nogil=True)
def walk(
    x0: float, y0: float, x1: float, y1: float, method: int, out_i: np.ndarray, out_j: np.ndarray, start: int
) -> int:
    """Write the traversal's cells into `out_i/out_j[start:]`; return how many."""
    k = start
    for i, j in cells(x0, y0, x1, y1, method):
        out_i[k] = i
        out_j[k] = j
        k += 1
    return k - start


def segment_cells(x0: float, y0: float, x1: float, y1: float, method: int = EXACT) -> np.ndarray:
    """The cells (rows of (i, j)) the traversal visits, in order; for tests and tools."""
    n = cell_count(x0, y0, x1, y1, method)
    out_i = np.empty(n, dtype=np.int64)
    out_j = np.empty(n, dtype=np.int64)
    walk(x0, y0, x1, y1, method, out_i, out_j, 0)
    return np.stack([out_i, out_j], axis=1)
