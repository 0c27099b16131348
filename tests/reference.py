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

* `bresenham_cells`, the `bresenham` traversal, for `ReferenceMap(traversal=bresenham_cells)`;
* `BeamReferenceMap`, the beam (cone) sensor model of Probabilistic Robotics' table 9.2, evaluated
  at every cell around the sensor against every beam;
* `ReferenceTsdf`, the TSDF layer: each return's truncation band walked by `segment_cells`, its
  samples fused into a float32 running average.
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


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


class BeamReferenceMap(ReferenceMap):
    """Occupancy log-odds and hit / miss counts updated by the beam (cone) inverse range sensor
    model of Probabilistic Robotics, table 9.2, evaluated by brute force.

    The beams of a scan are its returns (range_min <= r < range_max, at range z = r) and, when
    `no_return_range` > 0, its no-returns (r >= range_max), which clear up to z =
    min(no_return_range, range_max) and have no obstacle. Every cell of a square around the sensor
    holding all cells within the beams' reach is taken at its centre, at range r and bearing phi
    from the sensor (relative to its heading), and compared with every beam k (bearing phi_k):
    its beam is the one nearest in bearing, |wrap(phi - phi_k)| least (the first on a tie), so
    bearings wrap around +-pi. The cell then gets

    * no information if r > min(r_max, z_k + alpha/2) or |wrap(phi - phi_k)| > beta/2;
    * a hit if beam k has a return, z_k < r_max and |r - z_k| < alpha/2;
    * a miss if r < z_k;

    and no information otherwise. Lengths are in CELL units (cell centres at i + 0.5, the sensor at
    pose / resolution), as the engine documents its kernel; each cell is updated once a scan."""

    def __init__(
        self,
        resolution: float,
        l_hit: float,
        l_miss: float,
        l_min: float,
        l_max: float,
        *,
        alpha: float,
        beta: float,
        no_return_range: float = 0.0,
    ) -> None:
        super().__init__(resolution, l_hit, l_miss, l_min, l_max, no_return_range=no_return_range)
        self.alpha, self.beta = alpha, beta

    def integrate(
        self,
        pose: tuple[float, float, float],
        angles: np.ndarray,
        ranges: np.ndarray,
        range_min: float,
        range_max: float,
    ) -> None:
        """One scan: every cell with information gets one hit or one miss (see the class doc)."""
        res = self.resolution
        with np.errstate(invalid="ignore"):  # NaN readings are neither returns nor no-returns
            has_return = (ranges >= range_min) & (ranges < range_max)
            no_return = ranges >= range_max
        if self.no_return_range <= 0:
            no_return = np.zeros_like(no_return)
        use = has_return | no_return
        if not use.any():
            return
        z = np.where(has_return, ranges, min(self.no_return_range, range_max))[use] / res
        phi_k = angles[use]
        returned = has_return[use]
        r_max, half_alpha, half_beta = range_max / res, self.alpha / res / 2, self.beta / 2
        ox, oy, theta = pose[0] / res, pose[1] / res, pose[2]
        reach = float(np.max(np.minimum(r_max, z + half_alpha)))
        ii = np.arange(math.floor(ox - reach) - 1, math.floor(ox + reach) + 2)
        for j in range(math.floor(oy - reach) - 1, math.floor(oy + reach) + 2):
            # One row of cells at a time, each against every beam.
            dx, dy = ii + 0.5 - ox, j + 0.5 - oy
            r = np.hypot(dx, dy)
            phi = _wrap(np.arctan2(dy, dx) - theta)
            diff = np.abs(_wrap(phi[:, None] - phi_k[None, :]))
            k = np.argmin(diff, axis=1)
            d_k, z_k, ret_k = diff[np.arange(k.size), k], z[k], returned[k]
            info = (r <= np.minimum(r_max, z_k + half_alpha)) & (d_k <= half_beta)
            hit = info & ret_k & (z_k < r_max) & (np.abs(r - z_k) < half_alpha)
            miss = info & ~hit & (r < z_k)
            for i in ii[hit].tolist():
                self._update((i, j), True)
            for i in ii[miss].tolist():
                self._update((i, j), False)


class ReferenceTsdf:
    """A truncated signed distance layer in dicts: tsdf values and weights per cell.

    For each return of a scan (range_min <= r < range_max), in beam order: with lengths in CELL
    units, the sensor at s = pose / resolution, the beam's direction u = (cos a, sin a) for
    a = theta + bearing, its range z and the truncation t, the band is the segment from s +
    max(z - t, 0) u to s + (z + t) u, and its cells are `segment_cells`'. A band cell whose centre c
    projects onto the beam at d = (c - s) . u with |z - d| <= t gets the sample
    v = clamp((z - d) / t, -1, 1) (the clamp never binds given the band test; it is the definition),
    fused into the cell's weighted running average with weight 1:
    D <- (W D + v) / (W + 1), W <- min(W + 1, max_weight), both kept as float32 after each sample.
    No-returns and ignored readings add nothing."""

    def __init__(self, resolution: float, truncation: float, max_weight: float) -> None:
        self.resolution = resolution
        self.truncation = truncation
        self.max_weight = max_weight
        self.tsdf: dict[Cell, float] = {}
        self.weight: dict[Cell, float] = {}
        #: Samples fused into each cell: its weight before the cap.
        self.samples: dict[Cell, int] = {}

    def integrate(
        self,
        pose: tuple[float, float, float],
        angles: np.ndarray,
        ranges: np.ndarray,
        range_min: float,
        range_max: float,
    ) -> None:
        """Fuse one scan's returns (see the class doc)."""
        res, t = self.resolution, self.truncation / self.resolution
        ox, oy = pose[0] / res, pose[1] / res
        for a, r in zip((pose[2] + angles).tolist(), ranges.tolist(), strict=True):
            if not range_min <= r < range_max:  # also False for NaN
                continue
            c, s, z = math.cos(a), math.sin(a), r / res
            d0, d1 = max(z - t, 0.0), z + t
            for i, j in segment_cells(ox + c * d0, oy + s * d0, ox + c * d1, oy + s * d1):
                sdf = z - ((i + 0.5 - ox) * c + (j + 0.5 - oy) * s)
                if abs(sdf) <= t:
                    self._fuse((i, j), min(1.0, max(-1.0, sdf / t)))

    def _fuse(self, cell: Cell, value: float) -> None:
        w = self.weight.get(cell, 0.0)
        d = self.tsdf.get(cell, 0.0)
        self.tsdf[cell] = float(np.float32((w * d + value) / (w + 1.0)))
        self.weight[cell] = float(np.float32(min(w + 1.0, self.max_weight)))
        self.samples[cell] = self.samples.get(cell, 0) + 1

    def bounds(self) -> tuple[int, int, int, int]:
        """Exclusive cell bounds (i0, j0, i1, j1) of the observed cells."""
        ii = [c[0] for c in self.tsdf]
        jj = [c[1] for c in self.tsdf]
        return min(ii), min(jj), max(ii) + 1, max(jj) + 1
