"""From a scan to the cell updates it implies: the pure, lock-free half of integration.

`plan_scan` runs the configured sensor model and the TSDF band tracing over a `Scan` and returns an
`UpdatePlan`: plain arrays of cells and what to do to each, plus the tiles they fall in. It reads no
map state, so the service can plan the next scan while readers hold the map; `GridMap.apply` then
writes a plan under the map's lock.
"""

from __future__ import annotations

import math
import threading
from typing import NamedTuple

import numpy as np

from fleetmap.config import MapConfig
from fleetmap.kernels.beam_model import beam_model_cells
from fleetmap.kernels.ray_model import DENSE_WINDOW_CELLS, trace_rays, trace_scan
from fleetmap.kernels.scan_geometry import (
    EXTENT_OUT_OF_RANGE,
    EXTENT_TOO_LONG,
    EXTENT_TOO_WIDE,
    beam_layout,
    beam_returns,
    scan_extent,
    scan_rays,
)
from fleetmap.kernels.traversal import BRESENHAM, EXACT
from fleetmap.kernels.tsdf import trace_tsdf
from fleetmap.kernels.update import merge_tiles, merge_tiles_in_box
from fleetmap.scan import Scan, ScanError
from fleetmap.tiles import TileLimitError

_EMPTY_I = np.empty(0, dtype=np.int64)
_EMPTY_KIND = np.empty(0, dtype=np.uint8)
_NO_LAYOUT = np.empty((3, 0))
_EMPTY_PAIRS = np.empty((2, 0), dtype=np.int64)

#: A scan whose beams span more tiles than this (its bounding box, in tiles) is refused: it would
#: be an absurd extent for one 2D scan (e.g. 10 km across at 5 cm) and its bookkeeping would be large.
MAX_SCAN_TILE_WINDOW = 1 << 20

#: At most this many cells may one scan's ray-model walks visit in all (counted before dedup, as
#: the trace allocates for them: about 13 bytes each, some 440 MB at the limit), and the beam model
#: evaluate around the sensor (about 17 bytes each). A scan past it is refused before anything is
#: allocated: within the service's input limits (16,384 beams of up to 1,000 m) one scan at 5 cm
#: walks up to 420 million cells, and 16,384 beams of 300 m held 2.8 GB for 13 s. A 1,081-beam
#: lidar at 1,000 m (27.5 million cells at 5 cm) fits; coarser maps fit proportionally longer beams.
MAX_SCAN_CELLS = 1 << 25

#: Cell indices must stay well inside int64 and exact in float64 (2**52): a scan reaching beyond
#: +-2**40 cells (55 billion km at 5 cm) is refused rather than overflowing in the kernels.
MAX_CELL_INDEX = float(2**40)

#: Each planning thread keeps one zeroed scratch for `trace_scan` (it leaves it zeroed).
_scratch = threading.local()

#: `ScanError` messages of scans the engine refuses.
OUT_OF_RANGE_MESSAGE = "the scan's pose or ranges lie beyond the map's coordinate range"
TOO_WIDE_MESSAGE = "the scan spans too large an area for one scan; check its ranges and resolution"


def too_long() -> str:
    """The `ScanError` message of a scan past `MAX_SCAN_CELLS` (the ray model's walks)."""
    return (
        f"the scan's beams cross more than {MAX_SCAN_CELLS:,} cells in all, more than one scan may; "
        "check its ranges, or use a coarser resolution for such long beams"
    )


def beam_too_wide() -> str:
    """The `ScanError` message of a beam-model scan past `MAX_SCAN_CELLS`."""
    return (
        f"the beam model would evaluate more than {MAX_SCAN_CELLS:,} cells around the sensor for this "
        "scan; check its ranges, or use a coarser resolution for such long beams"
    )


#: Beam layouts (`kernels.scan_geometry.beam_layout`) of recently seen scans, by (beams, first bearing,
#: last bearing): a fleet's robots send a few layouts again and again. A scan given another
#: layout under the same key still gets exact directions (`scan_rays` checks every bearing).
_layouts: dict[tuple[int, float, float], np.ndarray] = {}
#: At most this many layouts are kept (the cache is emptied when full).
MAX_LAYOUTS = 64


class UpdatePlan(NamedTuple):
    """Cell updates of one scan, in global cell indices. (A named tuple rather than a frozen
    dataclass: it is built once per scan, and the dataclass's `__init__` cost a microsecond.)

    Hits and misses for the occupancy and counts layers come either as per-scan updates (each cell
    once, a hit beating a miss: `cell`, `kind`, where cell n lies in tile `cell[n] >> 2*shift` of
    `tiles`, at local position `cell[n] & (T*T - 1)`; and `runs`, where run k is `runs[1, k]`
    misses on consecutive cells of one tile row from `runs[0, k]`, keyed like `cell`) or as ordered
    entries `occ_*` (per-ray updates, and the beam model). `tsdf_*` are truncated distance samples
    for the TSDF layer. `tiles` (rows: tile i, tile j) lists every tile any of them touches, the
    per-scan updates' tiles first; `occ_tile` and `tsdf_tile` give each ordered entry's tile in
    that list. (Pairs of rows share one array: each array a kernel hands back costs a fraction of
    a microsecond.) `config` is the map configuration it was planned under: its cells are laid out
    by its tile size and resolution, and made by its models, so it means nothing to another map.
    """

    cell: np.ndarray
    kind: np.ndarray
    runs: np.ndarray
    occ_i: np.ndarray
    occ_j: np.ndarray
    occ_kind: np.ndarray
    occ_tile: np.ndarray
    tsdf_i: np.ndarray
    tsdf_j: np.ndarray
    tsdf_value: np.ndarray
    tsdf_tile: np.ndarray
    tiles: np.ndarray
    config: MapConfig

    @property
    def num_tiles(self) -> int:
        return int(self.tiles.shape[1])


def plan_scan(scan: Scan, config: MapConfig, shift: int) -> UpdatePlan:
    """Every cell update `scan` implies under `config`, for tiles of `1 << shift` cells. Raises
    `ScanError` for a scan whose pose or reach lies beyond the map's index range."""
    res = config.resolution
    pose = scan.pose
    ox, oy = pose.x / res, pose.y / res
    # No-return beams are cleared in the cell layers only (the TSDF fuses returns alone): a TSDF-only
    # map's no_return_range counted in the scan's extent, and refused scans as too wide for nothing.
    clear_range = config.no_return_range if config.has_cell_layers else 0.0
    beams, extent = _scan_beams(scan, clear_range, res, shift, config)
    if extent[0] == EXTENT_OUT_OF_RANGE:
        raise ScanError(OUT_OF_RANGE_MESSAGE)
    if extent[0] == EXTENT_TOO_LONG:
        raise ScanError(too_long())
    # Every model's tiles are numbered in a table over the scan's tile box (`merge_tiles`, the trace):
    # a box past MAX_SCAN_TILE_WINDOW tiles is refused for all of them (one 1,000 km per-ray beam
    # asked for a 13 GB table).
    if extent[0] == EXTENT_TOO_WIDE and beams[6] > 0:  # beams[6]: the beams traced
        raise ScanError(TOO_WIDE_MESSAGE)
    cell = occ_i = occ_j = _EMPTY_I
    kind = occ_kind = _EMPTY_KIND
    tiles = runs = _EMPTY_PAIRS
    if config.has_cell_layers:
        if config.sensor_model == "beam":
            occ_i, occ_j, occ_kind = _beam_model(scan, config, ox, oy)
        elif config.update == "per_ray":
            occ_i, occ_j, occ_kind = _ray_model_per_ray(config, ox, oy, beams)
        else:
            tiles, cell, kind, runs = _ray_model_per_scan(scan, config, shift, beams, extent)
    tsdf_i = tsdf_j = _EMPTY_I
    tsdf_value = np.empty(0, dtype=np.float32)
    tsdf_box = _EMPTY_I  # set with the band (used only when it has cells)
    if config.has("tsdf"):
        cos, sin, z = beam_returns(beams[0], beams[1], scan.ranges, res)
        tsdf_i, tsdf_j, tsdf_value, tsdf_box = trace_tsdf(ox, oy, cos, sin, z, config.tsdf.truncation / res)
    # The ordered entries' tiles go after the per-scan tiles, each tile once.
    occ_tile = tsdf_tile = _EMPTY_I
    if occ_i.size:
        tiles, occ_tile = merge_tiles(tiles, occ_i, occ_j, shift)
    if tsdf_i.size:
        tiles, tsdf_tile = merge_tiles_in_box(tiles, tsdf_i, tsdf_j, shift, tsdf_box)
    return UpdatePlan(
        cell,
        kind,
        runs,
        occ_i,
        occ_j,
        occ_kind,
        occ_tile,
        tsdf_i,
        tsdf_j,
        tsdf_value,
        tsdf_tile,
        tiles,
        config,
    )


def ray_trace_inputs(
    scan: Scan, clear_range: float, res: float, shift: int
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray, int, int, int, int] | None:
    """What the per-scan trace (`kernels.ray_model.trace_scan`) takes for `scan` at `res` metres per
    cell in tiles of `1 << shift` cells, with no-return beams cleared to `clear_range` metres: the
    sensor `(ox, oy)`, end points `ex, ey` and kinds of the beams (CELL units), and the tile box
    `ti0, tj0, ti1, tj1` holding them; None when no beam is traced. (For tests and tools.)"""
    beams, (_, ti0, tj0, ti1, tj1) = _scan_beams(scan, clear_range, res, shift, None)
    rays, kinds, traced = beams[0], beams[1], beams[6]
    if traced == 0:
        return None
    return scan.pose.x / res, scan.pose.y / res, rays[2], rays[3], kinds, ti0, tj0, ti1, tj1


def _scan_beams(
    scan: Scan, clear_range: float, res: float, shift: int, config: MapConfig | None
) -> tuple[tuple, tuple]:
    """The scan's `scan_rays` and its `scan_extent` (with `config`'s TSDF and beam-model margins, or
    none). The beams' walks are bounded (`MAX_SCAN_CELLS`) when `config` traces them: the ray
    model's hits and misses (or no `config`)."""
    pose = scan.pose
    beams = scan_rays(
        pose.x, pose.y, pose.theta, scan.angles, beam_layout_of(scan.angles), scan.ranges, scan.range_min,
        scan.range_max, clear_range, res,
    )  # fmt: skip
    _, _, xmin, ymin, xmax, ymax, _, longest, walk = beams
    truncation, alpha = (config.tsdf.truncation, config.beam.alpha) if config is not None else (0.0, 0.0)
    extent = scan_extent(
        pose.x, pose.y, res, longest, clear_range, truncation, alpha, xmin, ymin, xmax, ymax,
        shift, MAX_CELL_INDEX, MAX_SCAN_TILE_WINDOW, walk, max_scan_walk(config),
    )  # fmt: skip
    return beams, extent


def max_scan_walk(config: MapConfig | None) -> float:
    """`scan_extent`'s `max_walk` for maps of `config`: `MAX_SCAN_CELLS` when the ray model traces
    hits and misses (and with no `config`), else unbounded (the beam model has its own bound, and
    the TSDF band is a few cells a return)."""
    if config is None:
        return float(MAX_SCAN_CELLS)
    return float(MAX_SCAN_CELLS) if config.traces_rays else math.inf


def beam_layout_of(angles: np.ndarray) -> np.ndarray:
    """The cached beam layout for bearings `angles` (made and kept when new)."""
    if angles.size == 0:
        return _NO_LAYOUT
    key = (angles.size, float(angles[0]), float(angles[-1]))
    layout = _layouts.get(key)
    if layout is None:
        if len(_layouts) >= MAX_LAYOUTS:
            _layouts.clear()
        layout = _layouts[key] = beam_layout(angles)
    return layout


def _ray_model_per_scan(
    scan: Scan, config: MapConfig, shift: int, beams: tuple, extent: tuple
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ray model with per-scan semantics, in one compiled pass (`kernels.ray_model.trace_scan`);
    `beams` and `extent` are the scan's `scan_rays` and `scan_extent` for the map."""
    rays, kinds, traced = beams[0], beams[1], beams[6]
    if traced == 0:
        return _EMPTY_PAIRS, _EMPTY_I, _EMPTY_KIND, _EMPTY_PAIRS
    _, ti0, tj0, ti1, tj1 = extent  # not too wide (plan_scan refused that)
    ox, oy = scan.pose.x / config.resolution, scan.pose.y / config.resolution
    method = EXACT if config.traversal == "exact" else BRESENHAM
    while True:
        tiles, cell, kind, runs, needed = trace_scan(
            ox, oy, rays, kinds, method, shift, ti0, tj0, ti1, tj1, trace_scratch(shift)
        )
        if not needed:
            return tiles, cell, kind, runs
        grow_trace_scratch(needed, shift, config.max_tiles)


def trace_scratch(shift: int) -> np.ndarray:
    """This thread's zeroed scratch for `trace_scan` (one tile's worth to begin with)."""
    scratch = getattr(_scratch, "array", None)
    if scratch is None:
        scratch = _scratch.array = np.zeros(1 << (2 * shift), dtype=np.uint8)
    return scratch


def grow_trace_scratch(needed: int, shift: int, max_tiles: int) -> None:
    """Replace this thread's scratch with one of `needed` bytes (`trace_scan` asked for it), for a
    map of tiles of `1 << shift` cells and at most `max_tiles` tiles.

    Raises `TileLimitError`, allocating nothing, when the scratch asked for is one plane per tile the
    scan touches and those tiles are more than `max_tiles`: the map could never hold them all, so
    the scan is refused anyway, and a single long beam (100 km at 5 cm) would otherwise have this
    thread allocate, and keep for every later scan, half a gigabyte or more first."""
    # A dense window is at most DENSE_WINDOW_CELLS bytes; anything larger is per-tile planes, one
    # tile of cells per touched tile, so `needed` says exactly how many tiles the scan touches.
    if needed > DENSE_WINDOW_CELLS and needed >> (2 * shift) > max_tiles:
        raise TileLimitError(
            f"the scan touches {needed >> (2 * shift)} tiles but the map holds at most {max_tiles} "
            "(max_tiles); the scan was not integrated"
        )
    _scratch.array = np.zeros(needed, dtype=np.uint8)


def _ray_model_per_ray(
    config: MapConfig, ox: float, oy: float, beams: tuple
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ordered entries: returns trace to their end cell (a hit); no-return beams clear
    `no_return_range` metres if set. `beams` is the scan's `scan_rays`, whose end points and kinds
    the per-scan trace walks too: a beam must cross the same cells whichever update rule the map
    uses (end points computed here again as `pose + r * (cos, sin)(theta + a)` differed from
    `scan_rays`' rotated directions by an ulp, enough to pick the other side cell where a
    diagonal beam passes a cell corner, and to move an end point lying on a cell edge)."""
    rays, kinds = beams[0], beams[1]
    method = EXACT if config.traversal == "exact" else BRESENHAM
    return trace_rays(ox, oy, rays[2], rays[3], kinds, method)


def _beam_model(
    scan: Scan, config: MapConfig, ox: float, oy: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cone model over the cells around the sensor (see `kernels.beam_model`)."""
    res = config.resolution
    has_return = scan.returns_mask()
    no_return = scan.no_return_mask() if config.no_return_range > 0 else np.zeros_like(has_return)
    use = has_return | no_return
    # A no-return beam is free up to the clearing range; the model itself gives no information past
    # r_max ("none if r > min(r_max, z_k + alpha/2)"), so it clears no farther than that.
    r_max = scan.range_max if math.isfinite(scan.range_max) else math.inf
    z = np.where(has_return, scan.ranges, min(config.no_return_range, r_max))[use]
    phi = scan.angles[use]
    # Wrap to [-pi, pi) only where needed: wrapping an angle already in range can move it by an ulp.
    outside = (phi < -math.pi) | (phi >= math.pi)
    phi = np.where(outside, (phi + math.pi) % (2 * math.pi) - math.pi, phi)
    order = np.argsort(phi, kind="stable")
    if phi.size == 0:
        return _EMPTY_I, _EMPTY_I, _EMPTY_KIND
    # The kernel evaluates every cell of the square reaching `reach` cells around the sensor (and
    # one more on each side): refuse, before it allocates, a square past the scan limit.
    reach = float(np.max(np.minimum(r_max, z + config.beam.alpha / 2))) / res
    if (2 * reach + 4) ** 2 > MAX_SCAN_CELLS:
        raise ScanError(beam_too_wide())
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
