"""From a scan to the cell updates it implies: the pure, lock-free half of integration.

`plan_scan` runs the configured sensor model and the TSDF band tracing over a `Scan` and returns an
`UpdatePlan`: plain arrays of cells and what to do to each, plus the tiles they fall in. It reads no
map state, so the service can plan the next scan while readers hold the map; `GridMap.apply` then
writes a plan under the map's lock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fleetmap.config import MapConfig
from fleetmap.kernels.beam_model import beam_model_cells
from fleetmap.kernels.ray_model import BEAM_CLEAR, BEAM_HIT, BEAM_SKIP, trace_rays, trace_rays_marks
from fleetmap.kernels.traversal import BRESENHAM, EXACT
from fleetmap.kernels.tsdf import trace_tsdf
from fleetmap.kernels.update import touched_tiles
from fleetmap.scan import Scan, ScanError

_EMPTY_I = np.empty(0, dtype=np.int64)
_EMPTY_KIND = np.empty(0, dtype=np.uint8)

#: A scan whose beams span more tiles than this (its bounding box, in tiles) is refused: it would
#: be an absurd extent for one 2D scan (e.g. 10 km across at 5 cm) and its bookkeeping would be large.
MAX_SCAN_TILE_WINDOW = 1 << 20


@dataclass(frozen=True)
class UpdatePlan:
    """Cell updates of one scan, in global cell indices.

    Hits and misses for the occupancy and counts layers come either as per-scan `marks` (tile
    `(marks_i[k], marks_j[k])` has the `(T, T)` plane `marks[marks_planes[k]]` of CELL_MISS /
    CELL_HIT flags: each cell updated once) or as
    ordered entries `occ_*` (per-ray updates, and the beam model). `tsdf_*` are truncated distance
    samples for the TSDF layer. `tiles_i/j` lists every tile any of them touches.
    """

    marks: np.ndarray
    marks_planes: np.ndarray
    marks_i: np.ndarray
    marks_j: np.ndarray
    occ_i: np.ndarray
    occ_j: np.ndarray
    occ_kind: np.ndarray
    tsdf_i: np.ndarray
    tsdf_j: np.ndarray
    tsdf_value: np.ndarray
    tiles_i: np.ndarray
    tiles_j: np.ndarray

    @property
    def num_tiles(self) -> int:
        return int(self.tiles_i.size)


def plan_scan(scan: Scan, config: MapConfig, shift: int) -> UpdatePlan:
    """Every cell update `scan` implies under `config`, for tiles of `1 << shift` cells."""
    res = config.resolution
    ox, oy = scan.pose.x / res, scan.pose.y / res
    t = 1 << shift
    marks = np.zeros((0, t, t), dtype=np.uint8)
    marks_planes = marks_i = marks_j = occ_i = occ_j = _EMPTY_I
    occ_kind = _EMPTY_KIND
    if config.has("occupancy") or config.has("counts"):
        if config.sensor_model == "beam":
            occ_i, occ_j, occ_kind = _beam_model(scan, config, ox, oy)
        elif config.update == "per_ray":
            occ_i, occ_j, occ_kind = _ray_model(scan, config, ox, oy, shift, per_scan=False)
        else:
            marks_i, marks_j, marks_planes, marks = _ray_model(scan, config, ox, oy, shift, per_scan=True)
    tsdf_i = tsdf_j = _EMPTY_I
    tsdf_value = np.empty(0, dtype=np.float32)
    if config.has("tsdf"):
        hit = scan.returns_mask()
        tsdf_i, tsdf_j, tsdf_value = trace_tsdf(
            ox, oy, scan.world_angles()[hit], scan.ranges[hit] / res, config.tsdf.truncation / res
        )
    # One representative cell per marked tile stands for the tile in the union.
    tiles_i, tiles_j = touched_tiles(
        np.concatenate([marks_i << shift, occ_i, tsdf_i]),
        np.concatenate([marks_j << shift, occ_j, tsdf_j]),
        shift,
    )
    return UpdatePlan(
        marks, marks_planes, marks_i, marks_j, occ_i, occ_j, occ_kind,
        tsdf_i, tsdf_j, tsdf_value, tiles_i, tiles_j,
    )  # fmt: skip


def _ray_model(scan: Scan, config: MapConfig, ox: float, oy: float, shift: int, per_scan: bool):
    """Returns trace to their end cell (a hit); no-return beams clear `no_return_range` if set.

    Per scan: `(tiles_i, tiles_j, planes, marks)`; per ray: ordered entries `(ci, cj, kind)`."""
    res = config.resolution
    ranges = scan.ranges.copy()
    kind = np.full(ranges.size, BEAM_SKIP, dtype=np.uint8)
    kind[scan.returns_mask()] = BEAM_HIT
    if config.no_return_range > 0:
        clear = scan.no_return_mask()
        kind[clear] = BEAM_CLEAR
        # Never clear past what the sensor can see (the beam model stops there too).
        ranges[clear] = min(config.no_return_range, scan.range_max)
    ex, ey = scan.endpoints(np.where(kind == BEAM_SKIP, 0.0, ranges))
    method = EXACT if config.traversal == "exact" else BRESENHAM
    ex /= res
    ey /= res
    if not per_scan:
        return trace_rays(ox, oy, ex, ey, kind, method)
    used = kind != BEAM_SKIP
    xs = np.append(ex[used], ox)
    ys = np.append(ey[used], oy)
    ti0, ti1 = math.floor(xs.min()) >> shift, math.floor(xs.max()) >> shift
    tj0, tj1 = math.floor(ys.min()) >> shift, math.floor(ys.max()) >> shift
    if (ti1 - ti0 + 1) * (tj1 - tj0 + 1) > MAX_SCAN_TILE_WINDOW:
        raise ScanError("the scan spans too large an area for one scan; check its ranges and resolution")
    return trace_rays_marks(ox, oy, ex, ey, kind, method, shift, ti0, tj0, ti1, tj1)


def _beam_model(scan: Scan, config: MapConfig, ox: float, oy: float):
    """The cone model over the cells around the sensor (see `kernels.beam_model`)."""
    res = config.resolution
    has_return = scan.returns_mask()
    no_return = scan.no_return_mask() if config.no_return_range > 0 else np.zeros_like(has_return)
    use = has_return | no_return
    # A no-return beam is free up to the clearing range, never beyond the sensor's maximum.
    r_max = scan.range_max if math.isfinite(scan.range_max) else math.inf
    z = np.where(has_return, scan.ranges, min(config.no_return_range, r_max))[use]
    phi = scan.angles[use]
    # Wrap to [-pi, pi) only where needed: wrapping an angle already in range can move it by an ulp.
    outside = (phi < -math.pi) | (phi >= math.pi)
    phi = np.where(outside, (phi + math.pi) % (2 * math.pi) - math.pi, phi)
    order = np.argsort(phi, kind="stable")
    if phi.size == 0:
        return _EMPTY_I, _EMPTY_I, _EMPTY_KIND
    return beam_model_cells(
        ox,
        oy,
        scan.pose.theta,
        np.ascontiguousarray(phi[order]),
        np.ascontiguousarray(z[order] / res),
        np.ascontiguousarray(has_return[use][order]),
        r_max / res,
        config.beam.alpha / res,
        config.beam.beta,
    )
