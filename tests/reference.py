"""A slow, obviously-correct pure-Python occupancy mapper to check the engine against.

It shares no code with the engine's traversal or update kernels. The map is a dict from cell to
log-odds (and two dicts of hit / miss counts). Each scan yields a set of hit cells and a set of miss
cells; a cell in both is a hit (per-scan update), or, per ray, each ray updates its cells at once.
Every update adds l_hit or l_miss to the previous value (0 for an unknown cell) and clamps.

The cells of a segment are found by column clipping instead of the engine's boundary stepping.
Precisely, the reference's cells of a segment are

* its start cell and its end cell (the cells containing the end points);
* every cell containing a point of the segment other than a grid vertex. They are found column by
  column: the part of the segment with floor(x) == i (x in [i, i + 1); x = i + 1 belongs to the next
  column, as in the half-open cell) has an interval of y values whose floors are that column's
  cells, leaving out an interval end that is a grid vertex;
* at each grid vertex V = (X, Y) the segment passes through while moving along both axes, one side
  cell. Through V the segment jumps diagonally between two cells that share only V; a 4-connected
  walk must add one of the two cells beside V. Like the engine's Amanatides-Woo walk (which steps
  y first on a tie) we add the cell with the x-index from before V and the y-index from after V
  (the start cell stands for "before" at the start, the end cell for "after" at the end).

End points are computed as the engine documents them (sensor pose plus range along the beam,
divided by the resolution), with numpy, so both start from the same floating-point numbers.

Besides the ray model with that traversal, the module has references for the map's other options:

* `bresenham_cells`, the `bresenham` traversal, for `ReferenceMap(traversal=bresenham_cells)`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np

Cell = tuple[int, int]
#: A traversal: the cells of the segment (x0, y0) -> (x1, y1), in CELL units.
Traversal = Callable[[float, float, float, float], set[Cell]]


def segment_cells(x0: float, y0: float, x1: float, y1: float) -> set[Cell]:
    """Cells of the segment (x0, y0) -> (x1, y1) in CELL units, by column clipping (see module doc)."""
    dx, dy = x1 - x0, y1 - y0
    out: set[Cell] = {(math.floor(x0), math.floor(y0)), (math.floor(x1), math.floor(y1))}
    ylo, yhi = min(y0, y1), max(y0, y1)
    if dx == 0.0:
        i = math.floor(x0)
        out.update((i, j) for j in range(math.floor(ylo), math.floor(yhi) + 1))
        return out
    slope = dy / dx
    xlo, xhi = min(x0, x1), max(x0, x1)

    def y_at(x: float) -> float:
        if x == x0:
            return y0
        if x == x1:
            return y1
        return min(max(y0 + (x - x0) * slope, ylo), yhi)

    def is_vertex(x: float, y: float) -> bool:
        return dy != 0.0 and x == math.floor(x) and y == math.floor(y)

    for i in range(math.floor(xlo), math.floor(xhi) + 1):
        xa = max(float(i), xlo)
        right_open = i + 1 <= xhi  # the piece stops short of x = i + 1, which is column i + 1's
        xb = float(i + 1) if right_open else xhi
        ya, yb = y_at(xa), y_at(xb)
        a_out = is_vertex(xa, ya)
        b_out = right_open or is_vertex(xb, yb)
        if xa == xb:  # a single point: the end point on the column's left boundary
            if not a_out:
                out.add((i, math.floor(ya)))
            continue
        (lo, lo_out), (hi, hi_out) = sorted(((ya, a_out), (yb, b_out)))
        if lo == hi:  # runs along y = lo
            out.add((i, math.floor(lo)))
            continue
        j_last = math.floor(hi)
        if hi_out and hi == j_last:
            j_last -= 1  # y reaches the integer hi only at the left-out end
        out.update((i, j) for j in range(math.floor(lo), j_last + 1))
    if dy != 0.0:
        out.update(_vertex_cells(x0, y0, x1, y1, xlo, xhi, slope))
    return out


def _vertex_cells(
    x0: float, y0: float, x1: float, y1: float, xlo: float, xhi: float, slope: float
) -> Iterable[Cell]:
    """The side cell added at every grid vertex the segment passes through (see module doc)."""
    sx = 1 if x1 > x0 else -1
    sy = 1 if y1 > y0 else -1
    for x in range(math.ceil(xlo), math.floor(xhi) + 1):
        if x == x0:
            y = y0
        elif x == x1:
            y = y1
        else:
            y = y0 + (x - x0) * slope
        if y != math.floor(y):
            continue
        at_start, at_end = (x == x0 and y == y0), (x == x1 and y == y1)
        i_before = x if (at_start or sx < 0) else x - 1
        j_after = int(y) if (at_end or sy > 0) else int(y) - 1
        yield (i_before, j_after)


def bresenham_cells(x0: float, y0: float, x1: float, y1: float) -> set[Cell]:
    """Cells of the Bresenham line from the cell of (x0, y0) to the cell of (x1, y1), CELL units.

    With (di, dj) the end cell's indices less the start cell's and n = max(|di|, |dj|), cell k
    (k = 0..n) is the point k/n of the way from the start cell's indices to the end cell's, each
    coordinate rounded to the nearest integer, a half rounded away from the start. In integers, so
    nothing is lost to rounding: the classic 8-connected line of n + 1 cells, one step along the
    major axis each time."""
    i0, j0, i1, j1 = math.floor(x0), math.floor(y0), math.floor(x1), math.floor(y1)
    di, dj = i1 - i0, j1 - j0
    n = max(abs(di), abs(dj))
    if n == 0:
        return {(i0, j0)}

    def nearest(k: int, d: int) -> int:
        """k * d / n rounded to the nearest integer, a half away from 0: floor(k|d|/n + 1/2)."""
        magnitude = (2 * k * abs(d) + n) // (2 * n)
        return magnitude if d >= 0 else -magnitude

    return {(i0 + nearest(k, di), j0 + nearest(k, dj)) for k in range(n + 1)}


class ReferenceMap:
    """Occupancy log-odds and hit / miss counts in dicts, updated by the ray sensor model; a ray's
    cells are `traversal`'s (by default `segment_cells`, the engine's `exact`)."""

    def __init__(
        self,
        resolution: float,
        l_hit: float,
        l_miss: float,
        l_min: float,
        l_max: float,
        *,
        no_return_range: float = 0.0,
        per_ray: bool = False,
        traversal: Traversal = segment_cells,
    ) -> None:
        self.resolution = resolution
        self.l_hit, self.l_miss, self.l_min, self.l_max = l_hit, l_miss, l_min, l_max
        self.no_return_range = no_return_range
        self.per_ray = per_ray
        self.traversal = traversal
        self.log_odds: dict[Cell, float] = {}
        self.hits: dict[Cell, int] = {}
        self.misses: dict[Cell, int] = {}

    def integrate(
        self,
        pose: tuple[float, float, float],
        angles: np.ndarray,
        ranges: np.ndarray,
        range_min: float,
        range_max: float,
    ) -> None:
        """One scan: returns (range_min <= r < range_max) are rays ending in a hit; no-returns
        (r >= range_max) clear `no_return_range` metres if it is > 0; everything else is ignored."""
        x, y, theta = pose
        res = self.resolution
        rays: list[tuple[float, bool]] = []  # (length in metres, ends in a hit), in beam order
        use = np.zeros(len(ranges), dtype=bool)
        lengths = np.zeros(len(ranges))
        for b, r in enumerate(ranges.tolist()):
            if r is None or math.isnan(r) or r < range_min:
                continue
            if r < range_max:
                rays.append((r, True))
            elif self.no_return_range > 0:
                rays.append((self.no_return_range, False))
            else:
                continue
            use[b] = True
            lengths[b] = rays[-1][0]
        a = theta + angles[use]
        ex = (x + lengths[use] * np.cos(a)) / res
        ey = (y + lengths[use] * np.sin(a)) / res
        ox, oy = x / res, y / res
        scan_hits: set[Cell] = set()
        scan_misses: set[Cell] = set()
        for (_, is_hit), x1, y1 in zip(rays, ex.tolist(), ey.tolist(), strict=True):
            cells = self.traversal(ox, oy, x1, y1)
            end = (math.floor(x1), math.floor(y1))
            assert end in cells
            if self.per_ray:
                for cell in cells:
                    self._update(cell, is_hit and cell == end)
            else:
                scan_misses |= cells
                if is_hit:
                    scan_hits.add(end)
        if not self.per_ray:
            for cell in scan_hits:
                self._update(cell, True)
            for cell in scan_misses - scan_hits:
                self._update(cell, False)

    def _update(self, cell: Cell, hit: bool) -> None:
        value = self.log_odds.get(cell, 0.0) + (self.l_hit if hit else self.l_miss)
        self.log_odds[cell] = min(max(value, self.l_min), self.l_max)
        counts = self.hits if hit else self.misses
        counts[cell] = counts.get(cell, 0) + 1

    def bounds(self) -> tuple[int, int, int, int]:
        """Exclusive cell bounds (i0, j0, i1, j1) of the known cells."""
        ii = [c[0] for c in self.log_odds]
        jj = [c[1] for c in self.log_odds]
        return min(ii), min(jj), max(ii) + 1, max(jj) + 1
