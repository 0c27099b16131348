"""From a scan's pose, bearings and ranges to its beams in CELL units, and whether the scan fits
the map: the set-up shared by every sensor model, the TSDF band, planning (`update_plan`) and the
one-call integration (`integrate_scan`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetmap.kernels.kinds import BEAM_CLEAR, BEAM_HIT, BEAM_SKIP


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
    inf) is a BEAM_CLEAR traced to `clear_range` when that is > 0 (the first `clear_range` metres
    are cleared, even past `range_max`: the map's configuration says how far), else skipped
    (BEAM_SKIP, end point at the sensor), as is one below `range_min` or NaN.

    A beam's direction is its sensor-frame direction `(cos a, sin a)` (libm's) rotated by theta:
    one cosine and sine per scan instead of one per beam. Robots send the same bearings in every
    scan, so `layout` (`beam_layout`, of this scan or another) supplies `cos a` and `sin a` for
    every beam whose bearing equals its own; others are computed here. The directions are
    therefore the same whatever layout is given, and exactly `(cos a, sin a)` when theta is 0.

    Returns `(rays, kinds, xmin, ymin, xmax, ymax, traced, longest, walk)`, `rays` holding the rows
    cos, sin, ex, ey (one array: each array handed back to Python costs a fraction of a
    microsecond), and `walk` at least the number of cells the traced beams' walks visit in all
    (`|dx| + |dy| + 3` cells a beam): what the ray model's trace allocates for, which
    `scan_extent` bounds."""
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
    walk = 0.0
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
    clear_to = clear_range
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
        walk += abs(ex[b] - ox) + abs(ey[b] - oy)  # 0 for a skipped beam
        if kinds[b] == BEAM_HIT:
            longest = max(longest, ranges[b])
    # An exact walk from cell to cell visits |di| + |dj| + 1 cells, and |di| <= |dx| + 1.
    walk += 3.0 * traced
    return rays, kinds, xmin, ymin, xmax, ymax, traced, longest, walk


#: `scan_extent` verdicts.
EXTENT_OK = 0
EXTENT_OUT_OF_RANGE = 1  # the pose or the reach lies beyond the index range
EXTENT_TOO_WIDE = 2  # the traced beams' tile box holds too many tiles
EXTENT_TOO_LONG = 3  # the traced beams' walks visit too many cells in all


@njit(cache=True, nogil=True)
def scan_extent(
    x: float, y: float, res: float, longest: float, clear_range: float, truncation: float, alpha: float,
    xmin: float, ymin: float, xmax: float, ymax: float, shift: int, max_cell_index: float, max_window: int,
    walk: float, max_walk: float,
) -> tuple[int, int, int, int, int]:  # fmt: skip
    """Whether a scan from (x, y) (metres, `res` per cell) fits the map, and its tile box: the one
    definition of both limits, for planning and for the one-call integration.

    EXTENT_OUT_OF_RANGE when the sensor plus the scan's reach (its longest return, or its clearing
    range when that is > 0 and farther, plus `truncation` and `alpha`: how far
    the TSDF band and the beam model reach past a return; metres) is not within `max_cell_index`
    cells of the origin on both axes. EXTENT_TOO_LONG when the beams' walks visit more than
    `max_walk` cells in all (`walk`, from `scan_rays`). Otherwise the tile box `ti0, tj0, ti1, tj1`
    (tiles of `1 << shift` cells) of the bounding box `xmin..ymax` (CELL units, from `scan_rays`),
    and EXTENT_TOO_WIDE when it holds more than `max_window` tiles.

    Returns `(verdict, ti0, tj0, ti1, tj1)` (the box is 0s when out of range or too long)."""
    far = longest
    if clear_range > 0:
        far = max(far, clear_range)
    reach = (far + truncation + alpha) / res
    if not (abs(x / res) + reach < max_cell_index and abs(y / res) + reach < max_cell_index):
        return EXTENT_OUT_OF_RANGE, 0, 0, 0, 0
    if walk > max_walk:
        return EXTENT_TOO_LONG, 0, 0, 0, 0
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
