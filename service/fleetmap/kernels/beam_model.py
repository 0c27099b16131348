"""The beam (cone) inverse range sensor model of Probabilistic Robotics, table 9.2.

For a cell at range r and relative bearing phi from the sensor, take the beam k closest in bearing
among the beams used (a beam the scan's sensor models ignore, such as a NaN reading, is not one):
no information if `r > min(r_max, z_k + alpha/2)` or `|phi - phi_k| > beta/2`; occupied if
`z_k < r_max` and `|r - z_k| < alpha/2`; free if `r < z_k`. Cells are evaluated at their centres.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.kernels.kinds import CELL_HIT, CELL_MISS


@njit(cache=True, nogil=True, inline="always")
def _wrap(a: float) -> float:
    """Angle to [-pi, pi), as the seed computes it: `(a + pi) % 2pi - pi`."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, nogil=True, inline="always")
def _angle_diff(a: float, b: float) -> float:
    """|a - b| as an angle. Differences already within [-pi, pi] are used as they are, so that
    the model decides beam edges exactly as a plain `abs(phi - phi_k)` does."""
    d = a - b
    if d > math.pi or d < -math.pi:
        d = _wrap(d)
    return abs(d)


@njit(cache=True, nogil=True)
def beam_model_cells(
    ox: float,
    oy: float,
    theta: float,
    phi: np.ndarray,
    z: np.ndarray,
    has_return: np.ndarray,
    r_max: float,
    alpha: float,
    beta: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells with information and their kind (`CELL_HIT` occupied, `CELL_MISS` free).

    All lengths in CELL units. `phi` are the beam bearings relative to the sensor heading, wrapped to
    [-pi, pi) and sorted ascending, with `z` and `has_return` in the same order. `z[k]` is the range
    of beam k (for a beam with no return, the range it clears up to, never beyond r_max).
    """
    nb = phi.size
    reach = 0.0
    for k in range(nb):
        reach = max(reach, min(r_max, z[k] + alpha / 2.0))
    i0 = math.floor(ox - reach) - 1
    i1 = math.floor(ox + reach) + 1
    j0 = math.floor(oy - reach) - 1
    j1 = math.floor(oy + reach) + 1
    cap = (i1 - i0 + 1) * (j1 - j0 + 1)
    ci = np.empty(cap, dtype=np.int64)
    cj = np.empty(cap, dtype=np.int64)
    kind = np.empty(cap, dtype=np.uint8)
    n = 0
    for j in range(j0, j1 + 1):
        for i in range(i0, i1 + 1):
            dx = i + 0.5 - ox
            dy = j + 0.5 - oy
            r = math.sqrt(dx * dx + dy * dy)
            if r > reach:
                continue
            p = _wrap(math.atan2(dy, dx) - theta)
            # Nearest beam in bearing: binary search in the sorted bearings, then the neighbours,
            # including across the +-pi seam for scanners that see all around.
            lo = np.searchsorted(phi, p)
            best: int | np.integer = -1  # a bearing index: cand is numpy's (searchsorted)
            best_d = math.inf
            for cand in (lo - 1, lo, 0, nb - 1):
                if 0 <= cand < nb:
                    d = _angle_diff(p, phi[cand])
                    if d < best_d:
                        best_d = d
                        best = cand
            zk = z[best]
            if r > min(r_max, zk + alpha / 2.0) or best_d > beta / 2.0:
                continue
            if has_return[best] and zk < r_max and abs(r - zk) < alpha / 2.0:
                kind[n] = CELL_HIT
            elif r < zk:
                kind[n] = CELL_MISS
            else:
                continue
            ci[n] = i
            cj[n] = j
            n += 1
    return ci[:n], cj[:n], kind[:n]
