"""Truncated signed distance fusion along beams, and its zero-crossing surface.

For a cell on a beam at distance d from the sensor (the cell centre projected on the beam) with
measured range z: `sdf = z - d`, `tsdf = clamp(sdf / t, -1, 1)`. Only cells with `|sdf| <= t` (the
truncation band around the return) are updated, by the weighted running average
`D <- (W*D + w*tsdf) / (W + w)`, `W <- min(W + w, max_weight)`, with w = 1 per beam.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetmap.kernels.traversal import exact_starts

#: sqrt(2): a band segment of length 2t crosses at most 2t*sqrt(2) + 3 cells (see `trace_tsdf`).
_SQRT2 = 1.4142135623730951


@njit(cache=True, nogil=True, inline="always")
def band_walk_bound(trunc: float) -> int:
    """At least the number of cells an exact walk of a segment of length 2*trunc (CELL units) visits:
    `|di| + |dj| + 1 < |dx| + |dy| + 3 <= 2*trunc*sqrt(2) + 3`, plus room for rounding."""
    return int(2.0 * _SQRT2 * trunc) + 5


@njit(cache=True, nogil=True)
def trace_tsdf(
    ox: float, oy: float, cos: np.ndarray, sin: np.ndarray, z: np.ndarray, trunc: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Band cells of every beam and their tsdf values, in CELL units (z and trunc too).

    Beam b starts at (ox, oy), points along `(cos[b], sin[b])` (map frame) and returned at range
    `z[b]`. Its band is the exact walk of its segment from `max(z - trunc, 0)` to `z + trunc`,
    keeping the cells whose centre projects into the band (`|sdf| <= trunc`). Returns
    `(ci, cj, value, box)`: the cells in beam order, each beam's in walk order (a cell may appear
    once per beam that crosses it), and a box `i0, j0, i1, j1` (inclusive) holding them all, for
    `update.merge_tiles_in_box`.

    The walk is `exact_steps_i`'s with its end-of-axis tests taken out of the loop (while both axes
    have steps left only the crossings decide, then the rest is straight), and every visited cell
    is written and kept only if it is in the band (no branch on the band test). A segment of
    length 2t visits `|di| + |dj| + 1 < 2t*sqrt(2) + 3` cells, so the output is sized from that
    bound rather than by a counting pass over the beams (about 1.1 times a count's size for returns
    beyond the truncation; a map's truncation is at most `config.MAX_BAND_CELLS` cells).
    """
    nb = z.size
    cap = nb * band_walk_bound(trunc)
    ci = np.empty(cap, dtype=np.int64)
    cj = np.empty(cap, dtype=np.int64)
    value = np.empty(cap, dtype=np.float32)
    # Every beam's band segment, then its walk start and the box, in passes of their own: they have
    # no branch that depends on the data, so the compiler does several beams at once. A band is
    # only a dozen cells, and done beam by beam inside the walk loop this set-up cost a quarter of
    # trace_tsdf's time.
    ends = np.empty((4, nb))  # the segments' x0, y0, x1, y1
    for b in range(nb):
        d0 = max(z[b] - trunc, 0.0)
        d1 = z[b] + trunc
        ends[0, b] = ox + cos[b] * d0
        ends[1, b] = oy + sin[b] * d0
        ends[2, b] = ox + cos[b] * d1
        ends[3, b] = oy + sin[b] * d1
    starts, crossings = exact_starts(ends[0], ends[1], ends[2], ends[3])
    i0 = j0 = np.iinfo(np.int64).max
    i1 = j1 = np.iinfo(np.int64).min
    for b in range(nb):
        i0 = min(i0, starts[0, b], starts[2, b])
        i1 = max(i1, starts[0, b], starts[2, b])
        j0 = min(j0, starts[1, b], starts[3, b])
        j1 = max(j1, starts[1, b], starts[3, b])
    n = 0
    for b in range(nb):
        c = cos[b]
        s = sin[b]
        zb = z[b]
        i, j, ie, je = starts[0, b], starts[1, b], starts[2, b], starts[3, b]
        step_i, step_j = starts[4, b], starts[5, b]
        base_x, scale_x, base_y, scale_y = crossings[0, b], crossings[1, b], crossings[2, b], crossings[3, b]
        left_i = abs(ie - i)
        left_j = abs(je - j)
        # The cell indices also as floats (exact), so that each crossing and centre is computed as
        # `crossing(i, ...)` and `(i + 0.5 - ox)` are, bit for bit, without a conversion per step.
        fi = float(i)
        fj = float(j)
        n = _band_cell(ci, cj, value, n, i, j, fi, fj, ox, oy, c, s, zb, trunc)
        if left_i > 0 and left_j > 0:
            t_max_x = (fi + base_x) * scale_x
            t_max_y = (fj + base_y) * scale_y
            while True:  # while both axes have steps left, only the crossings decide
                if t_max_x < t_max_y:
                    i += step_i
                    fi += step_i
                    t_max_x = (fi + base_x) * scale_x
                    n = _band_cell(ci, cj, value, n, i, j, fi, fj, ox, oy, c, s, zb, trunc)
                    left_i -= 1
                    if left_i == 0:
                        break
                else:
                    j += step_j
                    fj += step_j
                    t_max_y = (fj + base_y) * scale_y
                    n = _band_cell(ci, cj, value, n, i, j, fi, fj, ox, oy, c, s, zb, trunc)
                    left_j -= 1
                    if left_j == 0:
                        break
        for _ in range(left_i):
            i += step_i
            fi += step_i
            n = _band_cell(ci, cj, value, n, i, j, fi, fj, ox, oy, c, s, zb, trunc)
        for _ in range(left_j):
            j += step_j
            fj += step_j
            n = _band_cell(ci, cj, value, n, i, j, fi, fj, ox, oy, c, s, zb, trunc)
    box = np.array([i0, j0, i1, j1]) if nb else np.zeros(4, dtype=np.int64)
    return ci[:n], cj[:n], value[:n], box


@njit(cache=True, nogil=True, inline="always")
def _band_cell(
    ci: np.ndarray, cj: np.ndarray, value: np.ndarray, n: int, i: int, j: int, fi: float, fj: float,
    ox: float, oy: float, c: float, s: float, z: float, trunc: float,
) -> int:  # fmt: skip
    """Write cell (i, j) (also given as floats) and its tsdf value at position n, and return n + 1 if
    its centre projects into the band, else n (the next cell overwrites it)."""
    sdf = z - ((fi + 0.5 - ox) * c + (fj + 0.5 - oy) * s)
    u = np.uint64(n)  # unsigned: no negative-index wraparound code
    ci[u] = i
    cj[u] = j
    value[u] = min(1.0, max(-1.0, sdf / trunc))
    return n + (abs(sdf) <= trunc)


@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # _nrt is not in numba's stubs
def fuse_tsdf(
    ci: np.ndarray,
    cj: np.ndarray,
    value: np.ndarray,
    tile: np.ndarray,
    slots: np.ndarray,
    shift: int,
    tsdf: np.ndarray,
    weight: np.ndarray,
    max_weight: float,
    changed: np.ndarray,
) -> int:
    """Fuse each (cell, value) into the tsdf / weight pools, in order; return the updates made.
    Entry k lies in the plan's tile `tile[k]`, pool slot `slots[tile[k]]`; `changed[tile]` is set
    to 1 where a stored value changed (a cell at its weight cap fused with the value it holds does
    not change, and its tile keeps its version, as a clamped log-odds cell's does)."""
    mask = (1 << shift) - 1
    plane_shift = 2 * shift
    flat_tsdf = tsdf.reshape(-1)  # one flat view of each pool, indexed unsigned (no wraparound code)
    flat_weight = weight.reshape(-1)
    # Entries come beam by beam, so runs of them share a tile: its slot is looked up and its change
    # flag kept in a register per run (a store per entry made every iteration wait on the previous
    # one's).
    last = -1
    start = 0
    diff = False
    for k in range(ci.size):
        if tile[k] != last:
            if diff:
                changed[last] = 1
            diff = False
            last = tile[k]
            start = slots[last] << plane_shift
        at = np.uint64(start | ((cj[k] & mask) << shift) | (ci[k] & mask))
        w_old = flat_weight[at]
        d_old = flat_tsdf[at]
        d_new = np.float32((float(w_old) * float(d_old) + value[k]) / (float(w_old) + 1.0))
        w_new = np.float32(min(float(w_old) + 1.0, max_weight))
        flat_tsdf[at] = d_new
        flat_weight[at] = w_new
        diff |= (d_new != d_old) | (w_new != w_old)
    if diff:
        changed[last] = 1
    return ci.size


@njit(cache=True, nogil=True)
def zero_crossings(
    tsdf: np.ndarray, weight: np.ndarray, i0: int, j0: int, i1: int, j1: int
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-cell surface points of a dense window that lie in its cells `[i0, i1) x [j0, j1)`, in
    window CELL coordinates (cell centres at +0.5).

    Between every pair of horizontally or vertically neighbouring observed cells (weight > 0) on
    opposite sides of zero (one value > 0, the other <= 0), the point where the linear interpolation
    of the two values is zero: a fraction `f` of the way from the first cell's centre to the
    second's, so in the first cell for f < 0.5 and in the second from f = 0.5 (its edge) on. Only
    the points whose cell lies in `[i0, i1) x [j0, j1)` are kept. A window holding those cells and
    one more around them finds the crossings between them and their neighbours outside, and windows
    side by side then share out a surface, each point to the one it lies in: decided by `f`, which
    is the same in every window, not by the point's coordinates, rounded differently in each.
    `tsdf` and `weight` are (ny, nx), row = y.
    """
    ny, nx = tsdf.shape
    xs = np.empty(2 * ny * nx, dtype=np.float64)
    ys = np.empty(2 * ny * nx, dtype=np.float64)
    n = 0
    for j in range(ny):
        for i in range(nx):
            if weight[j, i] <= 0:
                continue
            a = float(tsdf[j, i])
            for dj, di in ((0, 1), (1, 0)):
                jj = j + dj
                ii = i + di
                if jj >= ny or ii >= nx or weight[jj, ii] <= 0:
                    continue
                b = float(tsdf[jj, ii])
                if (a > 0) != (b > 0):
                    f = a / (a - b)
                    second = f >= 0.5
                    ci = ii if second else i
                    cj = jj if second else j
                    if i0 <= ci < i1 and j0 <= cj < j1:
                        xs[n] = i + 0.5 + f * di
                        ys[n] = j + 0.5 + f * dj
                        n += 1
    return xs[:n], ys[:n]
