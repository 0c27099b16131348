"""Truncated signed distance fusion along beams, and its zero-crossing surface.

For a cell on a beam at distance d from the sensor (the cell centre projected on the beam) with
measured range z: `sdf = z - d`, `tsdf = clamp(sdf / t, -1, 1)`. Only cells with `|sdf| <= t` (the
truncation band around the return) are updated, by the weighted running average
`D <- (W*D + w*tsdf) / (W + w)`, `W <- min(W + w, max_weight)`, with w = 1 per beam.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetmap.kernels.traversal import EXACT, cell_count, crossing, exact_start, exact_steps_i


@njit(cache=True, nogil=True)
def trace_tsdf(
    ox: float, oy: float, cos: np.ndarray, sin: np.ndarray, z: np.ndarray, trunc: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Band cells of every beam and their tsdf values, in CELL units (z and trunc too).

    Beam b starts at (ox, oy), points along `(cos[b], sin[b])` (map frame) and returned at range
    `z[b]`. Returns `(ci, cj, value)`; a cell may appear once per beam that crosses it.
    """
    nb = z.size
    total = 0
    for b in range(nb):
        d0 = max(z[b] - trunc, 0.0)
        d1 = z[b] + trunc
        total += cell_count(ox + cos[b] * d0, oy + sin[b] * d0, ox + cos[b] * d1, oy + sin[b] * d1, EXACT)
    ci = np.empty(total, dtype=np.int64)
    cj = np.empty(total, dtype=np.int64)
    value = np.empty(total, dtype=np.float32)
    n = 0
    for b in range(nb):
        c = cos[b]
        s = sin[b]
        d0 = max(z[b] - trunc, 0.0)
        d1 = z[b] + trunc
        # The exact walk of the band's segment (inlined `cells`), keeping the cells whose centre
        # projects into the band.
        i, j, ie, je, step_i, step_j, base_x, scale_x, base_y, scale_y = exact_start(
            ox + c * d0, oy + s * d0, ox + c * d1, oy + s * d1
        )
        steps = abs(ie - i) + abs(je - j)
        for k in range(steps + 1):
            d = (i + 0.5 - ox) * c + (j + 0.5 - oy) * s
            sdf = z[b] - d
            if abs(sdf) <= trunc:
                ci[n] = i
                cj[n] = j
                value[n] = min(1.0, max(-1.0, sdf / trunc))
                n += 1
            if k == steps:
                break
            if exact_steps_i(i, j, ie, je, crossing(i, base_x, scale_x), crossing(j, base_y, scale_y)):
                i += step_i
            else:
                j += step_j
    return ci[:n], cj[:n], value[:n]


@njit(cache=True, nogil=True)
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
    Entry k lies in the plan's tile `tile[k]`, pool slot `slots[tile[k]]`."""
    mask = (1 << shift) - 1
    flat_tsdf = tsdf.reshape(-1)  # one flat view of each pool, indexed unsigned (no wraparound code)
    flat_weight = weight.reshape(-1)
    for k in range(ci.size):
        at = np.uint64((slots[tile[k]] << (2 * shift)) | ((cj[k] & mask) << shift) | (ci[k] & mask))
        w_old = float(flat_weight[at])
        d_old = float(flat_tsdf[at])
        flat_tsdf[at] = (w_old * d_old + value[k]) / (w_old + 1.0)
        flat_weight[at] = min(w_old + 1.0, max_weight)
        changed[tile[k]] = 1
    return ci.size


@njit(cache=True, nogil=True)
def zero_crossings(tsdf: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-cell surface points of a dense window, in window CELL coordinates (cell centres at +0.5).

    Between every pair of horizontally or vertically neighbouring observed cells (weight > 0) on
    opposite sides of zero (one value > 0, the other <= 0), the point where the linear interpolation
    of the two values is zero. `tsdf` and `weight` are (ny, nx), row = y.
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
                    xs[n] = i + 0.5 + f * di
                    ys[n] = j + 0.5 + f * dj
                    n += 1
    return xs[:n], ys[:n]
