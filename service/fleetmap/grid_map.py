"""`GridMap`: one map, its configuration, its tiles, and the two things done to it: integrate and read.

Writers and readers share one lock. Integration plans a scan without the lock (`plan_scan`), then
creates the tiles it needs and applies every update inside the lock, so a reader sees each tile as it
was before or after a scan, never half-way; a scan that would pass the tile cap is refused before
anything changes. `integrate` does the same in one compiled call under the lock when the map's
configuration allows it and the scan needs no new tile (`kernels.integrate_scan`): the same result,
without the plan's round trip through Python.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from fleetmap.config import LayerName, MapConfig
from fleetmap.kernels import integrate_scan
from fleetmap.kernels.traversal import BRESENHAM, EXACT
from fleetmap.kernels.tsdf import fuse_tsdf, zero_crossings
from fleetmap.kernels.update import apply_cells, apply_entries
from fleetmap.scan import Scan, ScanError
from fleetmap.tiles import TileKey, TileStore
from fleetmap.update_plan import (
    MAX_CELL_INDEX,
    MAX_SCAN_TILE_WINDOW,
    OUT_OF_RANGE,
    TOO_WIDE,
    UpdatePlan,
    beam_layout_of,
    grow_trace_scratch,
    plan_scan,
    trace_scratch,
)

#: Layers a region can be read as: stored arrays plus the values derived from them.
REGION_LAYERS = ("log_odds", "probability", "state", "hits", "misses", "tsdf", "tsdf_weight")

#: Codes of the `state` layer.
STATE_UNKNOWN, STATE_FREE, STATE_OCCUPIED = 0, 1, 2
STATE_NAMES = {STATE_UNKNOWN: "unknown", STATE_FREE: "free", STATE_OCCUPIED: "occupied"}

#: The stored array each derived layer is read from, and the layer it needs.
_SOURCE: dict[str, tuple[str, LayerName]] = {
    "log_odds": ("log_odds", "occupancy"),
    "probability": ("log_odds", "occupancy"),
    "state": ("log_odds", "occupancy"),
    "hits": ("hits", "counts"),
    "misses": ("misses", "counts"),
    "tsdf": ("tsdf", "tsdf"),
    "tsdf_weight": ("tsdf_weight", "tsdf"),
}


class LayerUnavailableError(ValueError):
    """A read asked for a layer the map does not keep or that does not exist."""


def cell_edge(index: int, resolution: float) -> float:
    """The map coordinate where cell `index` begins (`index * resolution`), rounded to the nanometre
    so that exports say -20.2 rather than the product's -20.200000000000003. The rounding moves the
    edge by far less than any resolution a map may have."""
    return round(index * resolution, 9)


class IntegrationResult(NamedTuple):
    """What one scan did: cell updates applied, and the tiles whose contents changed. (A named
    tuple: a frozen dataclass took 0.36 us to make, about 1 % of an Intel-dataset scan.)"""

    cell_updates: int
    tsdf_updates: int
    changed_tiles: list[TileKey]
    tiles_created: int


class GridMap:
    """A sparse, unbounded 2D map with the layers its `MapConfig` switches on.

    `config` is a `MapConfig`, a dict of its fields (validated as `MapConfig.model_validate` does:
    pydantic's `ValidationError`, a ValueError, for a bad one) or None for the defaults. Thread-safe:
    writers and readers share `lock`.
    """

    def __init__(self, config: MapConfig | Mapping[str, Any] | None = None) -> None:
        if config is None:
            config = MapConfig()
        elif isinstance(config, Mapping):
            config = MapConfig.model_validate(config)
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
        self._in_place = (
            cfg.sensor_model == "ray" and cfg.update == "per_scan"
            and (cfg.has("occupancy") or cfg.has("counts"))
        )  # fmt: skip
        occ = cfg.occupancy
        #: The one-call kernel's arguments that are fixed for this map, in its order (a Python
        #: wrapper of a few microseconds a scan is worth trimming: about 5 % of an Intel scan).
        self._kernel_params = (
            cfg.no_return_range, cfg.resolution, cfg.tsdf.truncation, cfg.beam.alpha, MAX_CELL_INDEX,
            MAX_SCAN_TILE_WINDOW, EXACT if cfg.traversal == "exact" else BRESENHAM, self.store.shift,
            *occ.resolved(), cfg.tsdf.max_weight, cfg.max_tiles,
        )  # fmt: skip
        #: Per tile: (version, local observed bounds or None), for known_bounds.
        self._tile_bounds: dict[TileKey, tuple[int, tuple[int, int, int, int] | None]] = {}

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
                grow_trace_scratch(extra)
            if status == integrate_scan.INTEGRATED:
                store.restore_clock(clock)
                changed_tiles = list(map(tuple, tiles.T.tolist()))  # (2, k) -> k (ti, tj)
                if extra:  # the last `extra` are tiles the kernel created
                    store.adopt(changed_tiles[-extra:])
                    del changed_tiles[-extra:]
                return IntegrationResult(int(updates), int(tsdf_updates), changed_tiles, int(extra))
        if status == integrate_scan.OUT_OF_RANGE:
            raise ScanError(OUT_OF_RANGE)
        if status == integrate_scan.TOO_WIDE:
            raise ScanError(TOO_WIDE)
        return None  # NEEDS_TILES

    def plan(self, scan: Scan) -> UpdatePlan:
        """The updates `scan` implies; touches no map state, so it needs no lock."""
        _check_scan(scan)
        return plan_scan(scan, self.config, self.store.shift)

    def apply(self, plan: UpdatePlan) -> IntegrationResult:
        """Write a plan's updates, atomically with respect to readers."""
        if plan.num_tiles == 0:
            return IntegrationResult(0, 0, [], 0)
        cfg, store = self.config, self.store
        occ = cfg.occupancy
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
            params = occ.resolved()
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
        not exact in binary and may fall in either neighbouring cell."""
        return math.floor(x / self.resolution), math.floor(y / self.resolution)

    def region(self, layer: str, i0: int, j0: int, i1: int, j1: int) -> np.ndarray:
        """A dense copy of one layer over cells `[i0, i1) x [j0, j1)`, shape (j1-j0, i1-i0), row 0 =
        lowest y. Unknown is NaN for float layers, 0 for counts and `STATE_UNKNOWN` for `state`."""
        source = self._source(layer)
        ny, nx = max(0, j1 - j0), max(0, i1 - i0)
        dtype = np.uint32 if source in ("hits", "misses") else np.float32
        out = np.zeros((ny, nx), dtype=dtype) if dtype == np.uint32 else np.full((ny, nx), np.nan, dtype)
        with self.lock:
            self.store.fill_window(source, i0, j0, out)
            if layer == "tsdf":
                # A TSDF cell with zero weight was never observed.
                weight = np.zeros((ny, nx), dtype=np.float32)
                self.store.fill_window("tsdf_weight", i0, j0, weight)
        if layer == "tsdf":
            out[weight <= 0] = np.nan
        elif layer == "tsdf_weight":
            out = np.nan_to_num(out, nan=0.0)
        elif layer == "probability":
            out = log_odds_to_probability(out)
        elif layer == "state":
            out = self.classify(out)
        return out

    def classify(self, log_odds: np.ndarray) -> np.ndarray:
        """`state` codes from log-odds by the map's thresholds (`classify_probability`)."""
        return self.classify_probability(log_odds_to_probability(log_odds))

    def classify_probability(self, p: np.ndarray) -> np.ndarray:
        """`state` codes of occupancy probabilities by the map's thresholds (nav2's rule: p >
        occupied_thresh is occupied, p < free_thresh is free, otherwise and NaN (unknown) unknown)."""
        state = np.full(p.shape, STATE_UNKNOWN, dtype=np.uint8)
        with np.errstate(invalid="ignore"):
            state[p > self.config.occupancy.occupied_thresh] = STATE_OCCUPIED
            state[p < self.config.occupancy.free_thresh] = STATE_FREE
        return state

    def cells(self, points: Sequence[Sequence[float]] | np.ndarray) -> dict[str, np.ndarray]:
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
            out.setdefault("known", (raw["hits"] + raw["misses"]) > 0)
        if "tsdf" in raw:
            weight = raw["tsdf_weight"]
            out["tsdf"] = np.where(weight > 0, raw["tsdf"], np.nan).astype(np.float32)
            out["tsdf_weight"] = weight
            out.setdefault("known", weight > 0)
        return out

    def known_bounds(self) -> tuple[int, int, int, int] | None:
        """Cell bounds `(i0, j0, i1, j1)`, exclusive ends, of every cell any kept layer has observed;
        None if none. Each tile's own bounds are cached by its version, so only tiles changed since the
        last call are scanned (under the lock)."""
        lo = [math.inf, math.inf]
        hi = [-math.inf, -math.inf]
        t = self.store.tile_size
        with self.lock:
            for (ti, tj), slot in self.store.slots.items():
                version = int(self.store.versions[slot])
                cached = self._tile_bounds.get((ti, tj))
                if cached is None or cached[0] != version:
                    cached = (version, _local_bounds(self._observed(slot)))
                    self._tile_bounds[(ti, tj)] = cached
                local = cached[1]
                if local is None:
                    continue
                c0, r0, c1, r1 = local
                lo[0] = min(lo[0], ti * t + c0)
                lo[1] = min(lo[1], tj * t + r0)
                hi[0] = max(hi[0], ti * t + c1)
                hi[1] = max(hi[1], tj * t + r1)
        if lo[0] == math.inf:
            return None
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])

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
        """TSDF zero-crossing points (rows of map (x, y)) between cells in `[i0, i1) x [j0, j1)`."""
        self._source("tsdf")
        with self.lock:
            tsdf = np.zeros((max(0, j1 - j0), max(0, i1 - i0)), dtype=np.float32)
            weight = np.zeros_like(tsdf)
            self.store.fill_window("tsdf", i0, j0, tsdf)
            self.store.fill_window("tsdf_weight", i0, j0, weight)
        xs, ys = zero_crossings(tsdf, weight)
        return np.stack([(xs + i0) * self.resolution, (ys + j0) * self.resolution], axis=1)

    def memory_bytes(self) -> int:
        """Bytes the map's tiles hold: `TileStore.memory_bytes` (capacity, not only tiles in use)."""
        return self.store.memory_bytes()

    def _source(self, layer: str) -> str:
        if layer not in _SOURCE:
            raise LayerUnavailableError(f"unknown layer {layer!r}; one of {', '.join(REGION_LAYERS)}")
        source, needs = _SOURCE[layer]
        if not self.config.has(needs):
            raise LayerUnavailableError(
                f"layer {layer!r} needs the {needs!r} layer, which this map does not keep"
            )
        return source


#: A cell index beyond any a map can hold (scans reach at most MAX_CELL_INDEX = 2**40 cells).
_FAR_CELL = 2.0**50


def as_points(points: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """Map points as a float64 array of shape (n, 2); one (x, y) pair alone is one point, an empty
    sequence none. Raises ValueError for any other shape (an (n, 3) array is not read as 3n/2
    points), for values that are not numbers, and for a coordinate that is not finite."""
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"points must be (x, y) pairs of numbers: {exc}") from None
    if pts.size == 0:
        return pts.reshape(0, 2)
    if pts.shape == (2,):
        pts = pts.reshape(1, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be (x, y) pairs, an array of shape (n, 2); got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError("points must be finite numbers")
    return pts


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


def _local_bounds(seen: np.ndarray) -> tuple[int, int, int, int] | None:
    """(col0, row0, col1, row1), exclusive ends, of the True cells of a tile; None if none."""
    rows = np.flatnonzero(seen.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(seen.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def log_odds_to_probability(log_odds: np.ndarray) -> np.ndarray:
    """`p = 1 - 1/(1 + exp(l))` elementwise, NaN stays NaN; float32 out."""
    lo = np.asarray(log_odds, dtype=np.float64)
    with np.errstate(over="ignore"):
        return (1.0 - 1.0 / (1.0 + np.exp(lo))).astype(np.float32)
