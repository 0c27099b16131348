"""`GridMap`: one map, its configuration, its tiles, and the two things done to it: integrate and read.

Writers and readers share one lock. Integration plans a scan without the lock (`plan_scan`), then
creates the tiles it needs and applies every update inside the lock, so a reader sees each tile as it
was before or after a scan, never half-way; a scan that would pass the tile cap is refused before
anything changes. `integrate` does the same in one compiled call under the lock when the map's
configuration allows it (`kernels.integrate_scan`, which also creates the tiles the scan needs while
the pools have room, and otherwise changes nothing and leaves the scan to plan and apply): the same
result, without the plan's round trip through Python.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

# The cell-query vocabulary is defined in `cell_queries`, which loads no numba, so that the REST edge
# can import it without the engine; these names stay importable from here ("X as X" marks a re-export).
from fleetmap.cell_queries import MAX_RAY_CELLS as MAX_RAY_CELLS
from fleetmap.cell_queries import MAX_RAY_WALK as MAX_RAY_WALK
from fleetmap.cell_queries import MAX_RAYS as MAX_RAYS
from fleetmap.cell_queries import RAY_MAX_RANGE as RAY_MAX_RANGE
from fleetmap.cell_queries import RAY_OCCUPIED as RAY_OCCUPIED
from fleetmap.cell_queries import RAY_STATUS_NAMES as RAY_STATUS_NAMES
from fleetmap.cell_queries import RAY_UNKNOWN as RAY_UNKNOWN
from fleetmap.cell_queries import STATE_FREE as STATE_FREE
from fleetmap.cell_queries import STATE_NAMES as STATE_NAMES
from fleetmap.cell_queries import STATE_OCCUPIED as STATE_OCCUPIED
from fleetmap.cell_queries import STATE_UNKNOWN as STATE_UNKNOWN
from fleetmap.cell_queries import Points as Points
from fleetmap.cell_queries import UnknownCells, is_whole_number, real_number
from fleetmap.cell_queries import as_points as as_points
from fleetmap.cell_queries import cell_edge as cell_edge
from fleetmap.cell_queries import float_array as float_array
from fleetmap.config import MAX_COORDINATE, LayerName, MapConfig, is_immutable
from fleetmap.config import log_odds_to_probability as log_odds_to_probability
from fleetmap.kernels import integrate_scan
from fleetmap.kernels.raycast import cast_rays
from fleetmap.kernels.traversal import BRESENHAM, EXACT
from fleetmap.kernels.tsdf import fuse_tsdf, zero_crossings
from fleetmap.kernels.update import apply_cells, apply_entries
from fleetmap.scan import Scan, ScanError
from fleetmap.tiles import TileKey, TileStore
from fleetmap.update_plan import (
    MAX_CELL_INDEX,
    MAX_SCAN_TILE_WINDOW,
    OUT_OF_RANGE_MESSAGE,
    TOO_WIDE_MESSAGE,
    UpdatePlan,
    beam_layout_of,
    grow_trace_scratch,
    max_scan_walk,
    plan_scan,
    too_long,
    trace_scratch,
)

#: For each layer a region (or a viewer's tile) can be read as, the stored array it is read from
#: and the map layer (config `layers`) that keeps that array.
LAYER_SOURCES: dict[str, tuple[str, LayerName]] = {
    "log_odds": ("log_odds", "occupancy"),
    "probability": ("log_odds", "occupancy"),
    "state": ("log_odds", "occupancy"),
    "hits": ("hits", "counts"),
    "misses": ("misses", "counts"),
    "tsdf": ("tsdf", "tsdf"),
    "tsdf_weight": ("tsdf_weight", "tsdf"),
}

#: Layers a region can be read as: stored arrays plus the values derived from them.
REGION_LAYERS = tuple(LAYER_SOURCES)


class RayLimitError(ValueError):
    """A `cast_rays` call asked for more rays, or longer ones, than one call may walk (`MAX_RAYS`,
    `MAX_RAY_CELLS`, `MAX_RAY_WALK`)."""


class RaycastResult(NamedTuple):
    """Where each ray of `GridMap.cast_rays` stopped, one entry per angle, in order.

    `status`: uint8 codes `RAY_OCCUPIED`, `RAY_UNKNOWN`, `RAY_MAX_RANGE` (`RAY_STATUS_NAMES`).
    `range`: metres from the origin to the point where the ray enters the cell it stopped in (0 for
    the origin's own cell), `max_range` for `RAY_MAX_RANGE`. `x`, `y`: that point in the map frame.
    `i`, `j`: the cell it stopped in (for `RAY_MAX_RANGE` the last cell visited, that of the end point).
    """

    status: np.ndarray
    range: np.ndarray
    x: np.ndarray
    y: np.ndarray
    i: np.ndarray
    j: np.ndarray


class LayerUnavailableError(ValueError):
    """A read asked for a layer the map does not keep or that does not exist."""


class IntegrationResult(NamedTuple):
    """What one scan did: occupancy / count cell updates and TSDF updates applied, the tiles whose
    contents changed, and how many tiles it created. (A named tuple: a frozen dataclass took 0.36
    us to make, about 1 % of an Intel-dataset scan.)"""

    cell_updates: int
    tsdf_updates: int
    changed_tiles: list[TileKey]
    tiles_created: int


class WindowCleared(NamedTuple):
    """What `GridMap.clear_window` did: how many cells were observed (in some layer) and are unknown
    now, and the tiles that changed."""

    cells: int
    changed_tiles: list[TileKey]


class GridMap:
    """A sparse, unbounded 2D map with the layers its `MapConfig` switches on.

    `config` is a `MapConfig` (frozen, so the map shares it; of a subclass that is not, the map keeps
    a copy: changing the one given later changes no map), a dict of its fields (validated as
    `MapConfig.model_validate` does: pydantic's `ValidationError`, a ValueError, for a bad one) or
    None for the defaults. Thread-safe: writers
    and readers share `lock`.
    """

    def __init__(self, config: MapConfig | Mapping[str, Any] | None = None) -> None:
        if config is None:
            config = MapConfig()
        elif isinstance(config, Mapping):
            config = MapConfig.model_validate(config)
        elif isinstance(config, MapConfig) and not is_immutable(config):
            # A copy of its own: the map's cells were laid out by this configuration, and a
            # subclass that is not frozen can change. A MapConfig reused for a second map
            # (`cfg.resolution = 0.1; GridMap(cfg)`) re-read the first map's cells at the new
            # resolution, silently: its points fell in other cells and it lost layers. A MapConfig
            # itself is frozen all through and is shared: the deep copy took 0.2 ms a map, a
            # second of a start that restores 5,000 maps.
            config = config.model_copy(deep=True)
        elif not isinstance(config, MapConfig):
            raise TypeError(
                f"config must be a MapConfig, a dict of its fields or None, not {type(config).__name__}"
            )
        self.config = config
        self.store = TileStore(self.config.tile_size, self.config.layers, self.config.max_tiles)
        self.lock = threading.RLock()
        cfg = self.config
        #: Whether `integrate` may take the one-call path: the ray model with per-scan updates into
        #: the occupancy or counts layer (the default configuration), with or without the TSDF.
        self._in_place = cfg.traces_rays and cfg.update == "per_scan"
        #: (l_hit, l_miss, l_min, l_max), resolved once: `apply` hands them to the kernels every scan.
        self._log_odds = cfg.occupancy.resolved()
        #: The one-call kernel's arguments that are fixed for this map, in its order (a Python
        #: wrapper of a few microseconds a scan is worth trimming: about 5 % of an Intel scan).
        self._kernel_params = (
            cfg.no_return_range, cfg.resolution, cfg.tsdf.truncation, cfg.beam.alpha, MAX_CELL_INDEX,
            MAX_SCAN_TILE_WINDOW, max_scan_walk(cfg), EXACT if cfg.traversal == "exact" else BRESENHAM,
            self.store.shift,
            *self._log_odds, cfg.tsdf.max_weight, cfg.max_tiles,
        )  # fmt: skip
        #: (occupied_thresh, the smallest occupied float32 log-odds) for the ray kernel, once computed.
        self._ray_threshold: tuple[float, float] | None = None
        #: For known_bounds, per slot: the tile version its bounds are of (-1: none yet), and its
        #: observed cells' bounds in map cells (i0, j0, i1, j1), or _NO_BOUNDS for none; and the
        #: answer with the store's (clock, tiles) it is of.
        self._bounds_version = np.zeros(0, dtype=np.int64)
        self._bounds = np.zeros((0, 4), dtype=np.int64)
        self._bounds_answer: tuple[tuple[int, int], tuple[int, int, int, int] | None] = ((-1, -1), None)

    @property
    def resolution(self) -> float:
        """Metres per cell side (the configuration's)."""
        return self.config.resolution

    # -- writing ---------------------------------------------------------------------------------

    def integrate(self, scan: Scan) -> IntegrationResult:
        """Integrate one scan; raises `TileLimitError` (map unchanged) past the tile cap.

        When it can, it traces and applies in one compiled call and holds the lock for the whole
        scan. Callers that want readers and other writers to wait only for the apply (the service's
        ingest) call `plan` without the lock and then `apply`: the same result. Raises `ScanError`
        for a scan beyond the map's coordinate range, TypeError for anything but a `Scan`."""
        _check_scan(scan)
        if self._in_place:
            result = self._integrate_in_place(scan)
            if result is not None:
                return result
        return self.apply(self.plan(scan))

    def _integrate_in_place(self, scan: Scan) -> IntegrationResult | None:
        """`apply(plan(scan))` in one compiled call under the lock, creating the tiles it needs when
        the store has room; None, with nothing changed, when it has not (then plan and apply grow
        the store, or refuse the scan past the cap)."""
        store, pose = self.store, scan.pose
        layout = beam_layout_of(scan.angles)
        with self.lock:
            while True:
                status, updates, tsdf_updates, clock, tiles, extra = integrate_scan.integrate_ray_scan(
                    pose.x, pose.y, pose.theta, scan.angles, layout, scan.ranges, scan.range_min,
                    scan.range_max, *self._kernel_params, trace_scratch(store.shift), *store.index,
                    *store.kernel_pools(), store.versions, store.clock, len(store.keys),
                )  # fmt: skip
                if status != integrate_scan.NEEDS_SCRATCH:
                    break
                grow_trace_scratch(extra, store.shift, store.max_tiles)
            if status == integrate_scan.INTEGRATED:
                store.restore_clock(clock)
                changed_tiles = list(map(tuple, tiles.T.tolist()))  # (2, k) -> k (ti, tj)
                if extra:  # the last `extra` are tiles the kernel created
                    store.adopt(changed_tiles[-extra:])
                    del changed_tiles[-extra:]
                return IntegrationResult(int(updates), int(tsdf_updates), changed_tiles, int(extra))
        if status == integrate_scan.OUT_OF_RANGE:
            raise ScanError(OUT_OF_RANGE_MESSAGE)
        if status == integrate_scan.TOO_WIDE:
            raise ScanError(TOO_WIDE_MESSAGE)
        if status == integrate_scan.TOO_LONG:
            raise ScanError(too_long())
        return None  # NEEDS_TILES

    def clear_window(self, i0: int, j0: int, i1: int, j1: int) -> WindowCleared:
        """Forget the cells `[i0, i1) x [j0, j1)`: every layer back to never-observed there, as
        before any scan (octomap_server's clear of a bounding box). Tiles stay stored; the changed
        ones get new versions. Later scans observe the cells again as usual. TypeError for an index
        that is not an integer (NumPy's are taken), with the map unchanged."""
        i0, j0, i1, j1 = _cell_window(i0, j0, i1, j1)
        with self.lock:
            return WindowCleared(*self.store.clear_window(i0, j0, i1, j1))

    def plan(self, scan: Scan) -> UpdatePlan:
        """The updates `scan` implies; touches no map state, so it needs no lock."""
        _check_scan(scan)
        return plan_scan(scan, self.config, self.store.shift)

    def apply(self, plan: UpdatePlan) -> IntegrationResult:
        """Write a plan's updates, atomically with respect to readers. Creates the tiles the plan
        needs first, all or none: raises `TileLimitError` (`MemoryBudgetError` past a shared budget)
        with the map unchanged when they do not fit. `plan` must come from this map's `plan`, or that
        of a map configured alike (`MapConfig.same_map_as`): ValueError for another, map unchanged."""
        # A plan's cells are keyed by its map's tile size: one of larger tiles wrote past the ends
        # of this map's tiles (a segmentation fault), one of smaller tiles into other cells, and one
        # of another resolution or model drew another scan. Identity first: the usual case is free.
        if plan.config is not self.config and not plan.config.same_map_as(self.config):
            raise ValueError(
                "the plan was made under another map configuration than this map's: apply a plan "
                "of this map's `plan`, or of a map configured alike"
            )
        if plan.num_tiles == 0:
            return IntegrationResult(0, 0, [], 0)
        cfg, store = self.config, self.store
        keys = list(zip(*plan.tiles.tolist(), strict=True))
        changed = np.zeros(len(keys), dtype=np.uint8)
        with self.lock:
            found = [store.slots.get(k) for k in keys]
            new = [k for k, slot in zip(keys, found, strict=True) if slot is None] if None in found else []
            if new:
                store.create(new)  # all or nothing: raises before any cell is touched
                found = [store.slots[k] for k in keys]
            slots = np.array(found, dtype=np.int64)
            log_odds, hits, misses, tsdf, tsdf_weight = store.kernel_pools()
            params = self._log_odds
            updates = tsdf_updates = 0
            if plan.cell.size or plan.runs.shape[1]:
                updates += apply_cells(
                    plan.cell, plan.kind, plan.runs, slots, store.shift, log_odds, hits, misses, *params,
                    changed,
                )  # fmt: skip
            if plan.occ_i.size:
                updates += apply_entries(
                    plan.occ_i, plan.occ_j, plan.occ_kind, plan.occ_tile, slots, store.shift,
                    log_odds, hits, misses, *params, changed,
                )  # fmt: skip
            if plan.tsdf_i.size:
                tsdf_updates = fuse_tsdf(
                    plan.tsdf_i, plan.tsdf_j, plan.tsdf_value, plan.tsdf_tile, slots, store.shift,
                    tsdf, tsdf_weight, cfg.tsdf.max_weight, changed,
                )  # fmt: skip
            store.bump(slots, changed)
        return IntegrationResult(
            int(updates), int(tsdf_updates), [keys[k] for k in changed.nonzero()[0].tolist()], len(new)
        )

    # -- reading ---------------------------------------------------------------------------------

    def cell_index(self, x: float, y: float) -> tuple[int, int]:
        """The cell containing map point (x, y): `floor(x / res)`, `floor(y / res)` in double precision,
        as the integration computes it. A point on a cell edge written in decimal (0.15 at 0.05) is
        not exact in binary and may fall in either neighbouring cell. ValueError for a coordinate
        that is not finite (as `cells` refuses one: math.floor raised OverflowError for inf, and
        math.isfinite for an int past float's range)."""
        try:
            finite = math.isfinite(x) and math.isfinite(y)
        except OverflowError:  # an int past float's range: not finite as a float either
            finite = False
        if not finite:
            raise ValueError(f"a point must be finite numbers, got ({_short(x)}, {_short(y)})")
        return math.floor(x / self.resolution), math.floor(y / self.resolution)

    def region(self, layer: str, i0: int, j0: int, i1: int, j1: int) -> np.ndarray:
        """A dense copy of one layer over cells `[i0, i1) x [j0, j1)`, shape (j1-j0, i1-i0), row 0 =
        lowest y. Unknown is NaN for `log_odds`, `probability` and `tsdf`, 0 for the counts and
        `tsdf_weight`, and `STATE_UNKNOWN` for `state`. TypeError for an index that is not an
        integer (NumPy's are taken)."""
        i0, j0, i1, j1 = _cell_window(i0, j0, i1, j1)
        source = self.layer_source(layer)
        ny, nx = max(0, j1 - j0), max(0, i1 - i0)
        dtype = np.uint32 if source in ("hits", "misses") else np.float32
        # Weights and counts are 0 where unknown, as the tiles store them: filled so from the start
        # (NaN then nan_to_num held the window three times over, 2.7 GB for the 0.9 GB weights of
        # a Freiburg campus build at 2 cm).
        unknown_zero = dtype == np.uint32 or source == "tsdf_weight"
        out = np.zeros((ny, nx), dtype=dtype) if unknown_zero else np.full((ny, nx), np.nan, dtype)
        with self.lock:
            # A TSDF cell with zero weight was never observed.
            self.store.fill_window(source, i0, j0, out, "tsdf_weight" if layer == "tsdf" else None)
        if layer == "probability":
            out = log_odds_to_probability(out)
        elif layer == "state":
            out = self.classify(out)
        return out

    def classify(self, log_odds: np.ndarray) -> np.ndarray:
        """`state` codes from log-odds by the map's thresholds (`classify_probability`)."""
        return self.classify_probability(log_odds_to_probability(log_odds))

    def classify_probability(self, p: np.ndarray) -> np.ndarray:
        """`state` codes of occupancy probabilities by the map's thresholds (nav2's rule: p >
        occupied_thresh is occupied, p < free_thresh is free, otherwise and NaN (unknown) unknown).
        Compared in double precision, the thresholds as configured: `p` as given (the float32 the
        map reports) against them."""
        state = np.full(p.shape, STATE_UNKNOWN, dtype=np.uint8)
        # np.float64, not the Python float: numpy compares a float32 array with a Python float in
        # float32, which rounded the thresholds (free_thresh 0.196 to 0.19599999487), so a cell
        # reported at p 0.19599999487 was not free. The cast is per chunk of the loop, not a copy.
        occupied, free = (
            np.float64(self.config.occupancy.occupied_thresh),
            np.float64(self.config.occupancy.free_thresh),
        )
        with np.errstate(invalid="ignore"):
            state[p > occupied] = STATE_OCCUPIED
            state[p < free] = STATE_FREE
        return state

    def cells(self, points: Points) -> dict[str, np.ndarray]:
        """Every kept layer's value at each map point, one entry per point in order.

        `points`: (x, y) pairs in metres, shape (n, 2) (one pair alone is one point); ValueError for
        another shape or a non-finite coordinate. Returns numpy arrays keyed `known` (bool) and, for
        the layers the map keeps, `log_odds` (float32, NaN if unknown), `probability` (float32, 0.5
        if unknown), `state` (uint8 codes `STATE_UNKNOWN` / `STATE_FREE` / `STATE_OCCUPIED`), `hits`,
        `misses` (uint32), `tsdf` (float32, NaN if unknown) and `tsdf_weight` (float32)."""
        pts = as_points(points)
        # Clipped before the cast: a point far beyond any cell a map can hold (1e300) is unknown,
        # not an int64 overflow that numpy would turn into an arbitrary index with a warning.
        ci = np.clip(np.floor(pts[:, 0] / self.resolution), -_FAR_CELL, _FAR_CELL).astype(np.int64)
        cj = np.clip(np.floor(pts[:, 1] / self.resolution), -_FAR_CELL, _FAR_CELL).astype(np.int64)
        s, mask = self.store.shift, self.store.mask
        out: dict[str, np.ndarray] = {}
        names = [a.name for a in self.store.arrays]
        raw = {name: np.zeros(len(pts), dtype=self.store.pool(name).dtype) for name in names}
        if "log_odds" in raw:
            raw["log_odds"][:] = np.nan
        # The distinct tiles of the points (one dict probe each, under the lock), then every point's
        # cells by one gather per stored array: no Python work per point while readers and the
        # integration workers wait for the lock.
        ti, tj = ci >> s, cj >> s
        tiles, inverse = _distinct_tiles(ti, tj)
        li, lj = ci & mask, cj & mask
        with self.lock:
            tile_slots = np.array(
                [self.store.slots.get(key, -1) for key in zip(*tiles, strict=True)], dtype=np.int64
            )
            slot = tile_slots[inverse]
            inside = np.flatnonzero(slot >= 0)
            if inside.size:
                where = (slot[inside], lj[inside], li[inside])
                for name in names:
                    raw[name][inside] = self.store.pools[name][where]
        if "log_odds" in raw:
            lo = raw["log_odds"]
            out["known"] = ~np.isnan(lo)
            out["log_odds"] = lo
            out["probability"] = np.nan_to_num(log_odds_to_probability(lo), nan=0.5)
            out["state"] = self.classify(lo)
        if "hits" in raw:
            out["hits"], out["misses"] = raw["hits"], raw["misses"]
            # Not hits + misses > 0: the uint32 sum wraps (a saturated 2**32 - 1 hits and one miss
            # made 0, an observed cell "unknown"; a snapshot may hold any counts).
            out.setdefault("known", (raw["hits"] > 0) | (raw["misses"] > 0))
        if "tsdf" in raw:
            weight = raw["tsdf_weight"]
            out["tsdf"] = np.where(weight > 0, raw["tsdf"], np.nan).astype(np.float32)
            out["tsdf_weight"] = weight
            out.setdefault("known", weight > 0)
        return out

    def known_bounds(self) -> tuple[int, int, int, int] | None:
        """Cell bounds `(i0, j0, i1, j1)`, exclusive ends, of every cell any kept layer has observed;
        None if none. Each tile's bounds are kept by its version, so only the tiles changed since the
        last call are rescanned, each in a hold of the lock of its own (one scan may change a hundred
        tiles of a big map: rescanning them in one hold kept integration waiting for 5 ms); the
        tiles' bounds are then combined in one vectorised pass, and a call when nothing changed
        answers at once. `GET /maps/{id}` calls it, and every viewer asks again as the map grows: a
        loop over every tile in Python took 3.6 ms of the lock a call on a 1 km map of 6,400 tiles.
        Tiles keep their slots and cells only ever become observed, so the bounds lie between those
        before and after any scan applied meanwhile."""
        with self.lock:
            store = self.store
            n = len(store.keys)
            at = (store.clock, n)
            if self._bounds_answer[0] == at:
                return self._bounds_answer[1]
            self._grow_bounds(n)
            changed = np.flatnonzero(store.versions[:n] != self._bounds_version[:n]).tolist()
        t = store.tile_size
        for slot in changed:
            with self.lock:
                ti, tj = store.keys[slot]
                version = store.versions[slot]
                local = _local_bounds(self._observed(slot))
                if local is None:
                    self._bounds[slot] = _NO_BOUNDS
                else:
                    c0, r0, c1, r1 = local
                    self._bounds[slot] = (ti * t + c0, tj * t + r0, ti * t + c1, tj * t + r1)
                self._bounds_version[slot] = version
        with self.lock:
            answer: tuple[int, int, int, int] | None = None
            if n:
                lo = self._bounds[:n, :2].min(axis=0)
                hi = self._bounds[:n, 2:].max(axis=0)
                if lo[0] <= hi[0]:
                    answer = (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))
            # Keyed by the clock read first: a scan applied meanwhile may be in the answer or not,
            # and the next call, seeing a newer clock, looks again.
            self._bounds_answer = (at, answer)
            return answer

    def _grow_bounds(self, n: int) -> None:
        """Make the per-slot bounds arrays hold `n` slots (called under the lock)."""
        if self._bounds_version.size < n:
            grown = max(n, 2 * self._bounds_version.size)
            version = np.full(grown, -1, dtype=np.int64)
            version[: self._bounds_version.size] = self._bounds_version
            bounds = np.empty((grown, 4), dtype=np.int64)
            bounds[: self._bounds.shape[0]] = self._bounds
            self._bounds_version, self._bounds = version, bounds

    def _observed(self, slot: int) -> np.ndarray:
        """Cells of a tile that any kept layer has observed."""
        pools = self.store.pools
        seen = np.zeros((self.store.tile_size, self.store.tile_size), dtype=bool)
        if "log_odds" in pools:
            seen |= ~np.isnan(pools["log_odds"][slot])
        if "hits" in pools:
            seen |= (pools["hits"][slot] > 0) | (pools["misses"][slot] > 0)
        if "tsdf_weight" in pools:
            seen |= pools["tsdf_weight"][slot] > 0
        return seen

    def surface(self, i0: int, j0: int, i1: int, j1: int) -> np.ndarray:
        """TSDF zero-crossing points (rows of map (x, y)) that lie in the cells `[i0, i1) x [j0, j1)`:
        those between two of its cells, and those between one of them and a neighbour outside that
        fall inside (`kernels.tsdf.zero_crossings`). Windows side by side share out the surface,
        each point to the one it lies in: read only between the window's own cells, the crossings
        along the edge where two windows met were in neither, and a map read in windows lost them.
        TypeError for an index that is not an integer (NumPy's are taken)."""
        i0, j0, i1, j1 = _cell_window(i0, j0, i1, j1)
        self.layer_source("tsdf")
        nx, ny = max(0, i1 - i0), max(0, j1 - j0)
        # The window and one cell around it, where the neighbours outside lie.
        with self.lock:
            tsdf = np.zeros((ny + 2, nx + 2), dtype=np.float32)
            weight = np.zeros_like(tsdf)
            self.store.fill_window("tsdf", i0 - 1, j0 - 1, tsdf)
            self.store.fill_window("tsdf_weight", i0 - 1, j0 - 1, weight)
        xs, ys = zero_crossings(tsdf, weight, 1, 1, nx + 1, ny + 1)
        return np.stack([(xs + (i0 - 1)) * self.resolution, (ys + (j0 - 1)) * self.resolution], axis=1)

    def cast_rays(
        self,
        origin: Sequence[float] | Sequence[Sequence[float]] | np.ndarray,
        angles: float | Sequence[float] | np.ndarray,
        max_range: float,
        unknown: UnknownCells = "stop",
    ) -> RaycastResult:
        """Where rays first meet an obstacle (OctoMap's `castRay`, one call for many rays).

        Ray r starts at `origin` (x, y in metres, map frame), or at `origin[r]` when `origin` holds
        one (x, y) pair per ray (shape (n, 2) for n angles: rays from many poses in one call, as a
        particle filter casts them), and goes at map-frame angle `angles[r]` (radians; one number
        alone is one ray) for at most `max_range` metres. It visits the cells
        of the segment from the origin to the point at `max_range` in the order of the exact
        traversal (`kernels.traversal.segment_cells(..., EXACT)` in cell units), the origin's cell
        first, and stops at the first cell that is:

        - occupied by the map's own rule: p > `occupied_thresh`, the `state` of `cells`; for a map
          without the occupancy layer, the count model's p = hits / (hits + misses), as the exports
          show such a map (status `RAY_OCCUPIED`);
        - never observed (no tile, NaN log-odds, or no hit nor miss for a counts map) when
          `unknown` is "stop", as OctoMap's castRay without ignoreUnknown (status `RAY_UNKNOWN`);
          "pass" walks through unknown cells.

        A ray that stops nowhere ends at its end cell (`RAY_MAX_RANGE`); a cell the ray enters
        before `max_range` counts even when the end point lies inside it. See `RaycastResult` for
        the answer. Raises ValueError for a non-finite origin or one beyond ±1e7 m, origins whose
        number is not the number of angles, non-finite angles, a `max_range` that is not positive,
        or another `unknown`; `RayLimitError` (a ValueError) for more than `MAX_RAYS` rays, a
        `max_range` longer than `MAX_RAY_CELLS` cells, or rays x `max_range` in cells over
        `MAX_RAY_WALK`; `LayerUnavailableError` for a map that keeps neither the occupancy nor the
        counts layer, whatever the rays (it is checked first). Reads under the map's lock, from the
        tiles themselves (no copy)."""
        # The map first: rays too many or too long for the limits were refused as such (413 over
        # REST), and the caller who cut them down met this refusal, which no rays avoid, only next.
        use_counts = self._ray_source() == "counts"
        try:
            a = float_array(angles)
        except (TypeError, ValueError):
            raise ValueError(f"angles must be numbers (radians), not {angles!r}") from None
        if a.ndim > 1:
            raise ValueError(f"angles must be a number or a one-dimensional sequence; got shape {a.shape}")
        a = a.reshape(-1)
        if a.size > MAX_RAYS:
            raise RayLimitError(f"{a.size} rays is more than the limit of {MAX_RAYS} per call")
        ox, oy = _ray_origins(origin, a.size)
        if not np.isfinite(a).all():
            raise ValueError("angles must be finite numbers (radians)")
        given = max_range
        try:
            max_range = real_number(max_range)  # text ("10") is no number here either
        except OverflowError:  # an int past float's range: not finite either
            max_range = math.inf
        except TypeError:  # not a number: refused below
            max_range = math.nan
        if not (math.isfinite(max_range) and max_range > 0):
            raise ValueError(f"max_range must be a positive finite number of metres, got {given!r:.40}")
        cells = max_range / self.resolution
        if cells > MAX_RAY_CELLS:
            # Not rounded: 1000.01 m at 0.05 m was "20000 cells, more than the limit of 20000 cells",
            # and 1000.0001 m, to 6 digits, "max_range 1000 m is 20000 cells". max_range as sent, the
            # cells to 15 digits (a float's rounding left out); the limit in metres is what a caller
            # can set max_range to.
            raise RayLimitError(
                f"max_range {max_range!r} m is {cells:.15g} cells at resolution {self.resolution} m, more "
                f"than the limit of {MAX_RAY_CELLS} cells ({MAX_RAY_CELLS * self.resolution:g} m)"
            )
        if a.size * cells > MAX_RAY_WALK:
            raise RayLimitError(
                f"{a.size} rays of {cells:.0f} cells (max_range {max_range} m at resolution "
                f"{self.resolution} m) is more than the limit of {MAX_RAY_WALK} cells per call: cast "
                "fewer or shorter rays"
            )
        if unknown not in ("stop", "pass"):
            raise ValueError(f"unknown must be 'stop' or 'pass', not {unknown!r}")
        occupied_thresh = self.config.occupancy.occupied_thresh
        log_odds_occupied = math.nan if use_counts else self._log_odds_occupied()
        cos, sin = np.cos(a), np.sin(a)
        res = self.resolution
        x1 = (ox + max_range * cos) / res
        y1 = (oy + max_range * sin) / res
        n = a.size
        status = np.empty(n, dtype=np.uint8)
        t = np.empty(n, dtype=np.float64)
        ci = np.empty(n, dtype=np.int64)
        cj = np.empty(n, dtype=np.int64)
        x0 = ox / res
        y0 = oy / res
        store = self.store
        with self.lock:
            log_odds, hits, misses, _, _ = store.kernel_pools()
            cast_rays(
                x0, y0, x1, y1, unknown == "stop", use_counts, log_odds_occupied, occupied_thresh,
                *store.index, store.shift, log_odds, hits, misses, status, t, ci, cj,
            )  # fmt: skip
        distance = t * max_range
        return RaycastResult(status, distance, ox + distance * cos, oy + distance * sin, ci, cj)

    def _ray_source(self) -> str:
        """The layer rays classify cells by: `occupancy`, else `counts` (as `export.map_source`)."""
        if self.config.has("occupancy"):
            return "occupancy"
        if self.config.has("counts"):
            return "counts"
        raise LayerUnavailableError(
            "rays need the 'occupancy' or the 'counts' layer, and this map keeps neither"
        )

    def _log_odds_occupied(self) -> float:
        """The smallest float32 log-odds that `classify` calls occupied (NaN if none is), so that the
        ray kernel's `l >= threshold` is exactly `classify`'s rule (p computed in float64 and rounded
        to float32, compared with the threshold) without repeating its arithmetic: `classify` is
        monotonic in l, so a bisection over the float32 values in order finds the edge (32 probes,
        kept until the threshold changes)."""
        thresh = self.config.occupancy.occupied_thresh
        cached = self._ray_threshold
        if cached is not None and cached[0] == thresh:
            return cached[1]

        def occupied(order: int) -> bool:
            return bool(self.classify(_float32_of_order(order))[0] == STATE_OCCUPIED)

        lo, hi = _ORDER_MINUS_INF, _ORDER_PLUS_INF
        if not occupied(hi):
            edge = math.nan
        elif occupied(lo):
            edge = -math.inf
        else:
            while hi - lo > 1:  # not occupied(lo), occupied(hi)
                mid = (lo + hi) // 2
                if occupied(mid):
                    hi = mid
                else:
                    lo = mid
            edge = float(_float32_of_order(hi)[0])
        self._ray_threshold = (thresh, edge)
        return edge

    def memory_bytes(self) -> int:
        """Bytes the map's tiles hold: `TileStore.memory_bytes` (capacity, not only tiles in use)."""
        return self.store.memory_bytes()

    def layer_source(self, layer: str) -> str:
        """The stored layer that the readable layer `layer` (`REGION_LAYERS`) is made from;
        `LayerUnavailableError` if it is no such layer or the map does not keep its source."""
        if layer not in LAYER_SOURCES:
            raise LayerUnavailableError(f"unknown layer {layer!r}; one of {', '.join(REGION_LAYERS)}")
        source, needs = LAYER_SOURCES[layer]
        if not self.config.has(needs):
            raise LayerUnavailableError(
                f"layer {layer!r} needs the {needs!r} layer, which this map does not keep"
            )
        return source


def _short(value: object) -> str:
    """`repr(value)` for an error message, but a few words for an int past float's range (its repr
    is hundreds of digits, or raises ValueError past Python's limit on them)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 2**1024:
        return "an integer beyond the range of a float"
    return repr(value)


#: A cell index beyond any a map can hold (scans reach at most MAX_CELL_INDEX = 2**40 cells).
_FAR_CELL = 2.0**50


#: float32 values as ordered integers (`_float32_of_order`): -inf and +inf.
_ORDER_MINUS_INF, _ORDER_PLUS_INF = -0x7F800000, 0x7F800000


def _float32_of_order(order: int) -> np.ndarray:
    """The float32 at position `order` of the float32 values in increasing order (0 is zero, +-1 the
    smallest subnormals), as a one-element array. Non-negative floats' bit patterns count up with the
    value; a negative one's is its magnitude's with the sign bit set."""
    bits = order if order >= 0 else -(2**31) - order
    return np.array([bits], dtype=np.int32).view(np.float32)


def _ray_origins(
    origin: Sequence[float] | Sequence[Sequence[float]] | np.ndarray, rays: int
) -> tuple[np.ndarray, np.ndarray]:
    """The rays' origins as x and y arrays (one element when one origin serves every ray, else one
    per ray). ValueError unless `origin` is one (x, y) pair or `rays` of them (shape (rays, 2)),
    each two finite numbers within +-1e7 m."""
    try:
        o = float_array(origin)
    except (TypeError, ValueError):
        raise ValueError(f"origin must be an (x, y) pair of numbers or one per ray, not {origin!r}") from None
    if o.shape != (2,) and not (o.ndim == 2 and o.shape[1] == 2):
        raise ValueError(f"origin must be an (x, y) pair of numbers or one per ray; got shape {o.shape}")
    if o.ndim == 2 and o.shape[0] != 1 and o.shape[0] != rays:
        raise ValueError(f"{o.shape[0]} origins for {rays} angles: give one origin, or one per angle")
    if not (np.isfinite(o).all() and (np.abs(o) <= MAX_COORDINATE).all()):
        o = o.reshape(-1, 2)
        bad = o[np.argmin(np.isfinite(o).all(axis=1) & (np.abs(o) <= MAX_COORDINATE).all(axis=1))]
        raise ValueError(f"origin must be finite, within +-{MAX_COORDINATE:g} m; got {bad.tolist()}")
    xy = o.reshape(-1, 2).T.copy()  # rows x and y, each contiguous
    return xy[0], xy[1]


def _cell_window(i0: int, j0: int, i1: int, j1: int) -> tuple[int, int, int, int]:
    """A window's cell indices as Python ints; TypeError naming one that is no integer (a bool is
    not one). NumPy integers mixed made a float width (int64 - uint64 is a float64), and a float
    failed deep inside with a message naming nothing (`>>`, `range()`)."""
    for name, value in (("i0", i0), ("j0", j0), ("i1", i1), ("j1", j1)):
        if not is_whole_number(value):
            raise TypeError(f"{name} must be an integer cell index, got {value!r}")
    return int(i0), int(j0), int(i1), int(j1)


def _check_scan(scan: object) -> None:
    if not isinstance(scan, Scan):
        raise TypeError(
            f"expected a fleetmap Scan (Scan.from_fan, Scan.from_angles), not {type(scan).__name__}"
        )


def _distinct_tiles(ti: np.ndarray, tj: np.ndarray) -> tuple[tuple[list[int], list[int]], np.ndarray]:
    """The distinct (ti, tj) pairs as two lists, and for each input pair the index of its pair."""
    if ti.size == 0:
        return ([], []), np.zeros(0, dtype=np.int64)
    i0, j0 = int(ti.min()), int(tj.min())
    width = int(tj.max()) - j0 + 1
    if (int(ti.max()) - i0 + 1) * width < 2**62:
        # One int64 key per pair (the common case: points within a few billion tiles of each other).
        keys, inverse = np.unique((ti - i0) * width + (tj - j0), return_inverse=True)
        return ((keys // width + i0).tolist(), (keys % width + j0).tolist()), inverse.reshape(-1)
    pairs, inverse = np.unique(np.stack([ti, tj], axis=1), axis=0, return_inverse=True)
    return (pairs[:, 0].tolist(), pairs[:, 1].tolist()), inverse.reshape(-1)


#: A tile's bounds in `GridMap._bounds` when it has no observed cell: neutral for min and max.
_NO_BOUNDS = (np.iinfo(np.int64).max, np.iinfo(np.int64).max, np.iinfo(np.int64).min, np.iinfo(np.int64).min)


def _local_bounds(seen: np.ndarray) -> tuple[int, int, int, int] | None:
    """(col0, row0, col1, row1), exclusive ends, of the True cells of a tile; None if none."""
    rows = np.flatnonzero(seen.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(seen.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1
