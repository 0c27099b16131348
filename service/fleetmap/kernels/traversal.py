"""Grid traversal of a segment: which cells a ray passes through.

`exact` is the Amanatides-Woo walk: every cell the segment crosses, a 4-connected chain of exactly
`|di| + |dj| + 1` cells from the start cell to the end cell. Where the segment passes exactly through
a cell corner it steps one axis at a time, so the chain stays 4-connected (the extra cell touches the
segment at that corner). `bresenham` is the classic 8-connected integer line between the start and
end cells, `max(|di|, |dj|) + 1` cells.
"""

from __future__ import annotations

import math

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
def exact_start(x0: float, y0: float, x1: float, y1: float):
    """State of an exact walk at its start cell: `(i, j, ie, je, step_i, step_j, t_max_x, t_max_y,
    t_delta_x, t_delta_y)`. `t_max_*` is the segment parameter (0..1) of the next vertical /
    horizontal boundary crossing, `t_delta_*` how much it grows per cell."""
    i = math.floor(x0)
    j = math.floor(y0)
    dx = x1 - x0
    dy = y1 - y0
    if dx != 0.0:
        t_max_x = ((i + 1 - x0) if dx > 0 else (x0 - i)) / abs(dx)
        t_delta_x = 1.0 / abs(dx)
    else:
        t_max_x = math.inf
        t_delta_x = math.inf
    if dy != 0.0:
        t_max_y = ((j + 1 - y0) if dy > 0 else (y0 - j)) / abs(dy)
        t_delta_y = 1.0 / abs(dy)
    else:
        t_max_y = math.inf
        t_delta_y = math.inf
    step_i = 1 if dx > 0 else -1
    step_j = 1 if dy > 0 else -1
    return i, j, math.floor(x1), math.floor(y1), step_i, step_j, t_max_x, t_max_y, t_delta_x, t_delta_y


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
def cells(x0: float, y0: float, x1: float, y1: float, method: int):  # -> Iterator[tuple[int, int]]
    """Yield the cells `(i, j)` of the traversal of (x0, y0) -> (x1, y1), start cell to end cell.

    A numba generator for kernels that are not the hottest; `trace_rays_marks` inlines the same
    `exact_start` / `exact_steps_i` steps by hand.
    """
    if method == EXACT:
        i, j, ie, je, step_i, step_j, t_max_x, t_max_y, t_delta_x, t_delta_y = exact_start(x0, y0, x1, y1)
        yield i, j
        for _ in range(abs(ie - i) + abs(je - j)):
            if exact_steps_i(i, j, ie, je, t_max_x, t_max_y):
                i += step_i
                t_max_x += t_delta_x
            else:
                j += step_j
                t_max_y += t_delta_y
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
