"""A whole per-scan ray-model integration in one compiled call.

`update_plan.plan_scan` + `GridMap.apply` hand a scan's plan to Python and back: a few kernel calls,
arrays boxed for Python on the way, a dictionary probe per tile and the version bump, about 6 us a
scan whatever its size, 12 % of an Intel-dataset scan. `integrate_ray_scan` runs the same kernels
(`scan_rays`, `trace_scan`, `trace_tsdf`, `merge_tiles_in_box`, `apply_cells`, `fuse_tsdf`) back to back,
finds the tiles in `kernels.tile_index`, creates the missing ones when the pools and the index have
room (as `TileStore.create` would), and bumps the versions itself. Its result is the plan-and-apply
result bit for bit. When a tile is missing and there is no room, or the cap would be passed, it
changes nothing, and the caller plans and applies (which grows the store, or refuses the scan).

With occupancy alone, when every tile of the scan's box is already stored (looked up before
anything is traced), the trace and the apply are one pass (`ray_model.trace_apply_scan`): the far
walks' cells go from the trace's window straight into the pool, without the collection and apply
passes of their own. The same result, bit for bit; any other scan takes the path above unchanged.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetmap.kernels.ray_model import APPLIED, APPLY_NEEDS_SCRATCH, NOT_APPLIED, trace_apply_scan, trace_scan
from fleetmap.kernels.scan_geometry import (
    EXTENT_OUT_OF_RANGE,
    EXTENT_TOO_LONG,
    EXTENT_TOO_WIDE,
    beam_returns,
    scan_extent,
    scan_rays,
)
from fleetmap.kernels.tile_index import index_add, index_find, index_has_room
from fleetmap.kernels.traversal import EXACT
from fleetmap.kernels.tsdf import fuse_tsdf, trace_tsdf
from fleetmap.kernels.update import apply_cells, bump_versions, init_tile, merge_tiles_in_box

#: `integrate_ray_scan` statuses. Only INTEGRATED changed the map.
INTEGRATED = 0
NEEDS_TILES = 1  # a tile the scan touches does not exist, and the store has no room for it here
NEEDS_SCRATCH = 2  # the scratch is too small (the last value returned is the size it needs)
OUT_OF_RANGE = 3  # the pose or reach lies beyond `max_cell_index` (plan_scan's ScanError)
TOO_WIDE = 4  # the scan's tile box holds more than `max_window` tiles (plan_scan's ScanError)
TOO_LONG = 5  # the scan's beams visit more than `max_walk` cells in all (plan_scan's ScanError)


@njit(cache=True, nogil=True)
def integrate_ray_scan(
    x: float, y: float, theta: float, angles: np.ndarray, layout: np.ndarray, ranges: np.ndarray,
    range_min: float, range_max: float, clear_range: float, res: float, truncation: float, alpha: float,
    max_cell_index: float, max_window: int, max_walk: float, method: int, shift: int, l_hit: float,
    l_miss: float, l_min: float, l_max: float, max_weight: float, max_tiles: int, scratch: np.ndarray,
    index_keys: np.ndarray, index_slots: np.ndarray, log_odds: np.ndarray, hits: np.ndarray,
    misses: np.ndarray, tsdf: np.ndarray, tsdf_weight: np.ndarray, versions: np.ndarray, clock: int,
    count: int,
) -> tuple[int, int, int, int, np.ndarray, int]:  # fmt: skip
    """Integrate one scan with the ray model's per-scan updates (and the TSDF band when `tsdf` is
    not empty) into the pools, as `plan_scan` + `GridMap.apply` do with the same arguments (`alpha`
    only enters `scan_extent`, as there). Disabled layers are empty pools. The arguments come in
    three groups: the scan's, the map's parameters (fixed for a map, from `clear_range` to
    `max_tiles`, the cap on its tiles) and the map's arrays, clock and tile count (the pools have
    `versions.size` slots, the first `count` in use).

    Missing tiles are created as `TileStore.create` creates them, when `count` plus their number
    fits the pools, the cap and a half-full index: in the plan's tile order, in the next slots,
    each array at its unknown value (`update.init_tile`) and each with the next version.

    Returns `(status, cell updates, TSDF updates, version clock, tiles, extra)`: with INTEGRATED,
    the pools hold the scan, each changed tile got the next version from `clock`, the clock
    returned is the newest version, `tiles` (rows: tile i, tile j) lists the changed tiles in the
    plan's tile order and then the `extra` tiles created here in slot order (none when
    `_integrate_existing` did the scan: it runs only when every tile is stored). With NEEDS_SCRATCH,
    `extra` is the scratch size needed. With any other status nothing changed."""
    none = np.empty((2, 0), dtype=np.int64)
    rays, kinds, xmin, ymin, xmax, ymax, traced, longest, walk = scan_rays(
        x, y, theta, angles, layout, ranges, range_min, range_max, clear_range, res
    )
    # The same checks, in the same order, as plan_scan.
    verdict, ti0, tj0, ti1, tj1 = scan_extent(
        x, y, res, longest, clear_range, truncation, alpha, xmin, ymin, xmax, ymax, shift,
        max_cell_index, max_window, walk, max_walk,
    )  # fmt: skip
    if verdict == EXTENT_OUT_OF_RANGE:
        return OUT_OF_RANGE, 0, 0, clock, none, 0
    if verdict == EXTENT_TOO_LONG:
        return TOO_LONG, 0, 0, clock, none, 0
    if traced == 0:
        return INTEGRATED, 0, 0, clock, none, 0
    if verdict == EXTENT_TOO_WIDE:
        return TOO_WIDE, 0, 0, clock, none, 0
    ox = x / res
    oy = y / res
    if method == EXACT and log_odds.size and not hits.size and not tsdf.size:
        # Occupancy alone, and every tile of the box already stored: trace and apply in one pass
        # (`trace_apply_scan`), which skips the far cells' collection. Else the path below.
        status, updates, clock, out = _integrate_existing(
            ox, oy, rays, kinds, shift, ti0, tj0, ti1, tj1, scratch, index_keys, index_slots, log_odds, l_hit,
            l_miss, l_min, l_max, versions, clock,
        )  # fmt: skip
        if status == APPLY_NEEDS_SCRATCH:
            return NEEDS_SCRATCH, 0, 0, clock, none, updates
        if status == APPLIED:
            return INTEGRATED, updates, 0, clock, out, 0
    tiles, cell, kind, runs, needed = trace_scan(
        ox, oy, rays, kinds, method, shift, ti0, tj0, ti1, tj1, scratch
    )
    if needed:
        return NEEDS_SCRATCH, 0, 0, clock, none, needed
    # The TSDF band of the returns; its tiles go after the trace's, each once (as in plan_scan).
    tsdf_i = tsdf_j = tsdf_tile = np.empty(0, dtype=np.int64)
    tsdf_value = np.empty(0, dtype=np.float32)
    if tsdf.size:
        cos, sin, z = beam_returns(rays, kinds, ranges, res)
        tsdf_i, tsdf_j, tsdf_value, tsdf_box = trace_tsdf(ox, oy, cos, sin, z, truncation / res)
        if tsdf_i.size:
            tiles, tsdf_tile = merge_tiles_in_box(tiles, tsdf_i, tsdf_j, shift, tsdf_box)
    m = tiles.shape[1]
    slots = np.empty(m, dtype=np.int64)
    missing = 0
    for k in range(m):
        slots[k] = index_find(index_keys, index_slots, tiles[0, k], tiles[1, k])
        missing += slots[k] < 0
    first_new = count  # tiles in slots from here on are created below
    if missing:
        total = count + missing
        if total > max_tiles or total > versions.size or not index_has_room(index_slots, total):
            return NEEDS_TILES, 0, 0, clock, none, 0
        for k in range(m):
            if slots[k] < 0:
                slots[k] = count
                init_tile(count, log_odds, hits, misses, tsdf, tsdf_weight)
                clock += 1
                versions[count] = clock
                index_add(index_keys, index_slots, tiles[0, k], tiles[1, k], count)
                count += 1
    changed = np.zeros(m, dtype=np.uint8)
    updates = 0
    if cell.size or runs.shape[1]:
        updates = apply_cells(
            cell, kind, runs, slots, shift, log_odds, hits, misses, l_hit, l_miss, l_min, l_max, changed
        )
    tsdf_updates = 0
    if tsdf_i.size:
        tsdf_updates = fuse_tsdf(
            tsdf_i, tsdf_j, tsdf_value, tsdf_tile, slots, shift, tsdf, tsdf_weight, max_weight, changed
        )
    clock = bump_versions(changed, slots, versions, clock)
    # The changed tiles in plan order, then the created ones in slot order. (Every created tile has a
    # cell of the scan, so it is among the changed ones too.)
    n_changed = 0
    for k in range(m):
        n_changed += changed[k]
    created = count - first_new
    out = np.empty((2, n_changed + created), dtype=np.int64)
    c = 0
    for k in range(m):
        if changed[k]:
            out[0, c] = tiles[0, k]
            out[1, c] = tiles[1, k]
            c += 1
    for k in range(m):
        if slots[k] >= first_new:
            out[0, n_changed + slots[k] - first_new] = tiles[0, k]
            out[1, n_changed + slots[k] - first_new] = tiles[1, k]
    return INTEGRATED, updates, tsdf_updates, clock, out, created


@njit(cache=True, nogil=True)
def _integrate_existing(
    ox: float, oy: float, rays: np.ndarray, kinds: np.ndarray, shift: int, ti0: int, tj0: int, ti1: int,
    tj1: int, scratch: np.ndarray, index_keys: np.ndarray, index_slots: np.ndarray, log_odds: np.ndarray,
    l_hit: float, l_miss: float, l_min: float, l_max: float, versions: np.ndarray, clock: int,
) -> tuple[int, int, int, np.ndarray]:  # fmt: skip
    """`integrate_ray_scan`'s exact trace and log-odds apply through `trace_apply_scan`, when every
    tile of the scan's box `[ti0, ti1] x [tj0, tj1]` is stored. The box's slots are looked up
    before anything is traced, so that a missing tile leaves the map untouched.

    Returns `(status, cells updated or the scratch size needed, clock, changed tiles)`, status one
    of `trace_apply_scan`'s: with APPLIED the changed tiles got their versions in the box's
    row-major order, which is the plan's tile order (`trace_scan` numbers the tiles that hold a cell
    row-major over the box too), and are returned in that order. With any other status nothing
    changed."""
    none = np.empty((2, 0), dtype=np.int64)
    ni = ti1 - ti0 + 1
    nj = tj1 - tj0 + 1
    slots = np.empty(ni * nj, dtype=np.int64)
    for a in range(nj):
        for c in range(ni):
            slot = index_find(index_keys, index_slots, ti0 + c, tj0 + a)
            if slot < 0:
                return NOT_APPLIED, 0, clock, none
            slots[a * ni + c] = slot
    changed = np.zeros(ni * nj, dtype=np.uint8)
    status, updates, needed = trace_apply_scan(
        ox, oy, rays, kinds, shift, ti0, tj0, ti1, tj1, scratch, slots, log_odds, l_hit, l_miss, l_min, l_max,
        changed,
    )  # fmt: skip
    if status == APPLY_NEEDS_SCRATCH:
        return status, needed, clock, none
    if status != APPLIED:
        return status, 0, clock, none
    clock = bump_versions(changed, slots, versions, clock)
    n_changed = 0
    for k in range(changed.size):
        n_changed += changed[k]
    out = np.empty((2, n_changed), dtype=np.int64)
    c = 0
    for k in range(changed.size):
        if changed[k]:
            out[0, c] = ti0 + k % ni
            out[1, c] = tj0 + k // ni
            c += 1
    return APPLIED, updates, clock, out
