"""Engine benchmark: fleetmap's integration speed beside OctoMap's, on the same scans, in one run.

Run with `make bench` (or `.venv/bin/python benchmarks/bench_engine.py [--reps N]`). See
docs/benchmarks.md for what is measured and why; in short:

* Workloads: (a) simulated 1081-beam 30 m scans from robots driving a generated floor plan,
  (a') the same lidar in a large open hall so that most beams travel far, and (b) the Intel
  Research Lab log (910 scans of 180 beams), read from `../shared/datasets` beside the repository.
* fleetmap: `GridMap.integrate` at 0.05 m, per-scan updates, occupancy layer only (the
  like-for-like comparison) and all three layers. It integrates in one compiled call when the
  scan's tiles exist, else plans and applies (creating tiles); the service's ingest plans and
  applies every scan (its figures: `make bench-service`, and "where fleetmap's time goes" below).
* OctoMap (PyPI `pyoctomap`): `OcTree.insertPointCloud` of the same beam end points (real returns
  only, z = 0) from the same sensor origin (z = 0) at the same resolution, with no range limit.
* Ray casting (Intel): on the last timed maps of both engines, 360 rays of 10 m from every pose of
  the log, fleetmap's `GridMap.cast_rays` (one call per pose) against OctoMap's `castRay` (one call
  per ray, from Python) with the same occupancy threshold and unknown handling; rays/s of both, the
  ratio, OctoMap's per-call floor, and per ray whether both stopped for the same reason in the same cell.
* A cell update is one distinct cell changed by one scan (a hit beats a miss, each cell once per
  scan): fleetmap's `IntegrationResult.cell_updates`, and for OctoMap the leaves of a fresh tree
  holding only that scan (the size of the union of its free and occupied KeySets).
* Timing: `time.perf_counter`, compilation and parsing excluded (warm-up, then a fresh map per timed
  run), everything the insertion does included, each measurement repeated and reported as best and
  median. Both engines run on one thread; the process CPU time / wall time of every run is reported
  (<= 1 means at most one core was used; well below 1 means the run waited for a busy CPU), and
  `--pin` pins the process to one CPU.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numba
import numpy as np

from fleetmap.config import LayerName, MapConfig, probability
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import RAY_STATUS_NAMES, STATE_OCCUPIED, GridMap
from fleetmap.kernels.fan_rows import trace_fan_rows
from fleetmap.kernels.raycast import RAY_MAX_RANGE, RAY_OCCUPIED, RAY_UNKNOWN
from fleetmap.kernels.traversal import exact_starts
from fleetmap.scan import Scan
from fleetmap.sim import FloorPlan, SimulatedRobot, generate_floorplan
from fleetmap.update_plan import ray_trace_inputs

try:
    import pyoctomap
except ImportError:  # pragma: no cover - reported in the output
    pyoctomap = None

REPO_ROOT = Path(__file__).resolve().parents[1]
INTEL_LOG = REPO_ROOT.parent / "shared" / "datasets" / "intel-corrected.log.gz"

#: Map resolution of both engines, metres.
RES = 0.05
#: Scans integrated into a throw-away map before timing, so that compilation and first-touch costs
#: are out of the measurement.
WARMUP_SCANS = 8
#: The issue's aims: cell updates per second on one core, and the speed-up over OctoMap.
AIM_RATE = 100e6
AIM_RATIO = 30.0
#: OctoMap's key offset: key = floor(coord / res) + 2**15 at tree depth 16.
OCTOMAP_KEY_OFFSET = 1 << 15
#: Standard deviation of simulated range noise, metres (a typical 30 m scanner is good to ~1-3 cm).
LIDAR_NOISE = 0.01

OCC_ONLY: tuple[LayerName, ...] = ("occupancy",)
ALL_LAYERS: tuple[LayerName, ...] = ("occupancy", "counts", "tsdf")


# ----------------------------------------------------------------------------------------------
# Workloads
# ----------------------------------------------------------------------------------------------


@dataclass
class Workload:
    """A named list of scans, plus the same scans as OctoMap point clouds (built before timing)."""

    name: str
    description: str
    scans: list[Scan]
    clouds: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.clouds = [scan_to_cloud(s) for s in self.scans]

    def stats(self) -> str:
        """Beams, returns and range statistics, one line."""
        ranges = np.concatenate([s.ranges for s in self.scans])
        ret = np.concatenate([s.returns_mask() for s in self.scans])
        r = ranges[ret]
        return (
            f"{len(self.scans)} scans x {self.scans[0].num_beams} beams; {ret.mean():.1%} of beams return; "
            f"return range mean {r.mean():.1f} m, median {np.median(r):.1f} m, max {r.max():.1f} m"
        )


def scan_to_cloud(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    """OctoMap's input for `scan`: the (n, 3) end points of its real returns at z = 0 and the sensor
    origin (x, y, 0). No-return, NaN and below-range_min beams are left out, as fleetmap ignores them
    (`no_return_range` 0), so `insertPointCloud` runs with no range limit."""
    hit = scan.returns_mask()
    ex, ey = scan.endpoints(np.where(hit, scan.ranges, 0.0))
    cloud = np.zeros((int(hit.sum()), 3), dtype=np.float64)
    cloud[:, 0] = ex[hit]
    cloud[:, 1] = ey[hit]
    origin = np.array([scan.pose.x, scan.pose.y, 0.0], dtype=np.float64)
    return cloud, origin


def robot_scans(plan: FloorPlan, robots: int, scans_per_robot: int, seed: int) -> list[Scan]:
    """Scans of `robots` simulated robots (1081 beams, 270 degrees, 30 m, 10 Hz, 1 m/s) driving
    `plan`, interleaved in time order as a fleet server would receive them.

    Returns carry `LIDAR_NOISE` of range noise. Without it every exact return ends exactly on a cell
    boundary of the grid-aligned walls, and which side it lands on is decided by floating-point
    rounding (fleetmap computes in float64, OctoMap in float32), a degenerate case real scans
    never produce."""
    fleet = [SimulatedRobot(plan, seed + k, noise_std=LIDAR_NOISE) for k in range(robots)]
    return [robot.tick() for _ in range(scans_per_robot) for robot in fleet]


def open_hall(width_m: float = 50.0, height_m: float = 40.0, seed: int = 3) -> FloorPlan:
    """A warehouse-like open hall: outer walls, a 7.5 m grid of 0.6 m pillars and a few pallet stacks.

    The long-range workload: from most poses most beams travel 10-30 m before they return."""
    nx, ny = round(width_m / RES), round(height_m / RES)
    occ = np.zeros((ny, nx), dtype=bool)
    wall = 3  # 0.15 m
    occ[:wall, :] = occ[-wall:, :] = True
    occ[:, :wall] = occ[:, -wall:] = True
    yy, xx = np.mgrid[0:ny, 0:nx]
    cx_, cy_ = (xx + 0.5) * RES, (yy + 0.5) * RES
    for px in np.arange(6.25, width_m - 1.0, 7.5):
        for py in np.arange(5.0, height_m - 1.0, 7.5):
            occ[(cx_ - px) ** 2 + (cy_ - py) ** 2 < 0.3**2] = True
    rng = np.random.default_rng(seed)
    for _ in range(8):
        w, h = rng.uniform(0.8, 2.4, size=2)
        x0, y0 = rng.uniform(2.0, width_m - 5.0), rng.uniform(2.0, height_m - 5.0)
        occ[round(y0 / RES) : round((y0 + h) / RES), round(x0 / RES) : round((x0 + w) / RES)] = True
    return FloorPlan(occ, RES)


def build_workloads() -> tuple[list[Workload], list[str]]:
    """The workloads, and 'skipped: ...' notes for any that could not be built."""
    notes: list[str] = []
    floor = generate_floorplan(7)
    w, h = floor.world_bounds()[2:]
    workloads = [
        Workload(
            "floorplan",
            f"generate_floorplan(7), {w:.0f} x {h:.0f} m rooms and corridors; 4 robots x 100 scans",
            robot_scans(floor, 4, 100, seed=11),
        ),
        Workload(
            "open-hall",
            "50 x 40 m open hall with pillars (long returns); 4 robots x 40 scans",
            robot_scans(open_hall(), 4, 40, seed=21),
        ),
    ]
    if INTEL_LOG.exists():
        scans = list(load_dataset(INTEL_LOG))  # parsed here, outside every timed region
        workloads.append(Workload("intel", f"{INTEL_LOG.name} (Intel Research Lab, corrected poses)", scans))
    else:
        notes.append(f"skipped: Intel dataset not found at {INTEL_LOG} (workload (b) and equivalence check)")
    return workloads, notes


# ----------------------------------------------------------------------------------------------
# Timed runs
# ----------------------------------------------------------------------------------------------


@dataclass
class Run:
    """One timed integration of a whole workload into a fresh map."""

    seconds: float
    cpu_seconds: float
    cell_updates: int
    extra: int = 0  # TSDF updates for fleetmap
    result: object = None  # the map built, kept for the equivalence check


def timed(fn: Callable[[], tuple[int, int, object]]) -> Run:
    """Time `fn` with perf_counter (and the process's CPU time beside it), GC collected before and
    paused during the measurement."""
    gc.collect()
    gc.disable()
    try:
        c0 = time.process_time()
        t0 = time.perf_counter()
        updates, extra, result = fn()
        seconds = time.perf_counter() - t0
        cpu = time.process_time() - c0
    finally:
        gc.enable()
    return Run(seconds, cpu, updates, extra, result)


def fleetmap_config(layers: Sequence[LayerName]) -> MapConfig:
    """The benchmark's fleetmap configuration: defaults (ray model, exact traversal, per-scan
    updates, octomap occupancy preset, 256-cell tiles), resolution `RES`, the given layers."""
    return MapConfig(resolution=RES, layers=list(layers))


def run_fleetmap(scans: Sequence[Scan], layers: Sequence[LayerName]) -> Run:
    """Integrate `scans` into a fresh GridMap (created outside the timed region)."""
    gmap = GridMap(fleetmap_config(layers))

    def go() -> tuple[int, int, object]:
        cells = tsdf = 0
        for scan in scans:
            r = gmap.integrate(scan)
            cells += r.cell_updates
            tsdf += r.tsdf_updates
        return cells, tsdf, gmap

    return timed(go)


def octomap_params() -> tuple[float, float, float, float]:
    """fleetmap's occupancy parameters as OctoMap probabilities (hit, miss, clamp min, clamp max)."""
    occ = fleetmap_config(OCC_ONLY).occupancy
    hit, miss, lo, hi = (probability(v) for v in (occ.l_hit, occ.l_miss, occ.l_min, occ.l_max))
    return hit, miss, lo, hi


def new_octree() -> object:
    """An empty OcTree at `RES` with fleetmap's occupancy parameters, so both maps compute the same
    log-odds. (fleetmap's `octomap` preset clamps at 0.12 / 0.97; OctoMap's own defaults are
    0.1192 / 0.971, log-odds -2.0 / 3.5. The parameters do not change the work per update.)"""
    tree = pyoctomap.OcTree(RES)
    hit, miss, lo, hi = octomap_params()
    tree.setProbHit(hit)
    tree.setProbMiss(miss)
    tree.setClampingThresMin(lo)
    tree.setClampingThresMax(hi)
    return tree


def run_octomap(clouds: Sequence[tuple[np.ndarray, np.ndarray]], lazy: bool) -> Run:
    """Insert `clouds` into a fresh OcTree (created outside the timed region).

    lazy=True: `insertPointCloud(..., lazy_eval=True)` per scan and one `updateInnerOccupancy()` at
    the end (timed), the batch mode OctoMap documents for lazy_eval. lazy=False: the wrapper's default, whose
    Python layer runs a whole-tree `updateInnerOccupancy()` after every scan on top of the C++
    per-node inner updates.
    """
    tree = new_octree()

    def go() -> tuple[int, int, object]:
        for cloud, origin in clouds:
            tree.insertPointCloud(cloud, origin, -1.0, lazy, False)
        if lazy:
            tree.updateInnerOccupancy()
        return 0, 0, tree

    return timed(go)


def octomap_cell_updates(clouds: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Distinct cells OctoMap's ray casting updates per scan, counted by OctoMap itself: the leaves
    of a fresh tree holding only that scan. A z = 0 slab never fills all 8 children of a node, so
    nothing is pruned and every updated voxel is one depth-16 leaf."""
    counts = np.empty(len(clouds), dtype=np.int64)
    for k, (cloud, origin) in enumerate(clouds):
        tree = new_octree()
        tree.insertPointCloud(cloud, origin, -1.0, True, False)
        counts[k] = tree.getNumLeafNodes()
    return counts


def fleetmap_scan_updates(scans: Sequence[Scan]) -> np.ndarray:
    """fleetmap's per-scan cell updates (occupancy only, fresh map), untimed."""
    gmap = GridMap(fleetmap_config(OCC_ONLY))
    return np.array([gmap.integrate(s).cell_updates for s in scans], dtype=np.int64)


def octomap_call_floor(clouds: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    """Seconds for the same insertPointCloud calls with a 1 nm range limit: every ray ends in the
    sensor's cell, so this is the per-call and per-point cost (the wrapper's Python loop copying
    points into a C++ Pointcloud, the call, the per-point key work) without ray casting."""
    tree = new_octree()

    def go() -> tuple[int, int, object]:
        for cloud, origin in clouds:
            tree.insertPointCloud(cloud, origin, 1e-9, True, False)
        return 0, 0, None

    return timed(go).seconds


# ----------------------------------------------------------------------------------------------
# Reporting helpers
# ----------------------------------------------------------------------------------------------


@dataclass
class Measured:
    """Repeated runs of one engine setting on one workload."""

    label: str
    runs: list[Run]
    cell_updates: int

    @property
    def best(self) -> float:
        return min(r.seconds for r in self.runs)

    @property
    def median(self) -> float:
        return statistics.median(r.seconds for r in self.runs)

    @property
    def best_cpu(self) -> float:
        """Lowest process CPU time over the runs: less sensitive than wall time to a busy machine."""
        return min(r.cpu_seconds for r in self.runs)

    @property
    def cpu_wall(self) -> tuple[float, float]:
        """Lowest and highest process CPU time / wall time over the runs."""
        ratios = [r.cpu_seconds / r.seconds for r in self.runs]
        return min(ratios), max(ratios)


def fmt_rate(x: float) -> str:
    return f"{x / 1e6:8.2f}"


def machine_lines(cores: str) -> list[str]:
    """CPU, cores, load and versions."""
    model = "unknown"
    mhz = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and model == "unknown":
                model = line.split(":", 1)[1].strip()
            elif line.startswith("cpu MHz") and not mhz:
                mhz = f", {float(line.split(':', 1)[1]):.0f} MHz"
    except OSError:
        pass
    allowed = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    try:
        commit = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True, text=True, check=False, timeout=5,
        ).stdout.strip() or "?"  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        commit = "?"
    octo = metadata.version("pyoctomap") if pyoctomap is not None else "not installed"
    return [
        f"CPU: {model}{mhz}; {os.cpu_count()} logical cores on the machine, {allowed} usable by this "
        f"process; load average {load}",
        f"one core: {cores}",
        f"Python {platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, "
        f"pyoctomap {octo}, fleetmap {metadata.version('fleetmap')} (git {commit})",
    ]


def one_core(pin: int | None) -> str:
    """Pin the process to CPU `pin` if given; say how the figures are one-core figures."""
    threads = (
        "both engines run on one thread: fleetmap's numba kernels are single-threaded per scan "
        f"(njit, no parallel=True) and pyoctomap's liboctomap {octomap_openmp()}"
    )
    if pin is None:
        return f"{threads}; not pinned (--pin CPU to pin), the cpu/wall column shows the cores used"
    try:
        os.sched_setaffinity(0, {pin})
    except (AttributeError, OSError) as exc:
        return f"{threads}; could not pin to CPU {pin} ({exc})"
    return f"{threads}; process pinned to CPU {pin}"


def octomap_openmp() -> str:
    """Whether the loaded liboctomap brought an OpenMP runtime (its computeUpdate can use threads)."""
    if pyoctomap is None:
        return "is not installed"
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return "(OpenMP linkage unknown)"
    if "libgomp" in maps or "libomp" in maps:
        return "is linked with OpenMP (pinning keeps it on one core)"
    return "is not linked with OpenMP (single-threaded)"


# ----------------------------------------------------------------------------------------------
# Equivalence check (Intel)
# ----------------------------------------------------------------------------------------------


def equivalence(gmap: GridMap, tree: object, rng_seed: int = 0) -> list[str]:
    """Compare the occupancy of a fleetmap map and an OctoMap tree built from the same scans."""
    lines: list[str] = []
    xs, ys, zs, los, depths = [], [], [], [], []
    for it in tree.begin_leafs():
        x, y, z = it.getCoordinate()
        xs.append(x)
        ys.append(y)
        zs.append(z)
        depths.append(it.getDepth())
        los.append(it.current_node.getLogOdds())
    ox = np.array(xs)
    oy = np.array(ys)
    oz = np.array(zs)
    o_lo = np.array(los, dtype=np.float64)
    oi = np.floor(ox / RES).astype(np.int64)
    oj = np.floor(oy / RES).astype(np.int64)
    centred = np.allclose(ox, (oi + 0.5) * RES, atol=1e-5) and np.allclose(oy, (oj + 0.5) * RES, atol=1e-5)
    lines.append(
        f"OctoMap leaves: {len(xs)}, depths {sorted(set(depths))}, "
        f"leaf z centres {sorted({round(float(z), 6) for z in oz})}; "
        f"leaf x/y centres at (k + 0.5) * res: {centred}"
    )
    # Keys: coordToKey(x) = floor(x / res) + 2**15, so cell boundaries are at multiples of res.
    probe = [(0.0249, 0.0), (0.0251, 0.0), (-0.0001, 0.0), (0.0499, 0.0), (0.0501, 0.0), (1.2345, 0.0)]
    keys_ok = all(
        tree.coordToKey(np.array([x, y, 0.0]))[0] - OCTOMAP_KEY_OFFSET == math.floor(x / RES)
        for x, y in probe
    )
    lines.append(
        f"coordToKey(x) == floor(x / res) + 2**15 on probes either side of cell boundaries: {keys_ok} "
        "(OctoMap cell k covers [k*res, (k+1)*res), the same cells as fleetmap's)"
    )
    fb = gmap.known_bounds()
    if fb is None:
        return [*lines, "fleetmap map is empty"]
    i0, j0 = min(fb[0], int(oi.min())), min(fb[1], int(oj.min()))
    i1, j1 = max(fb[2], int(oi.max()) + 1), max(fb[3], int(oj.max()) + 1)
    f_lo = gmap.region("log_odds", i0, j0, i1, j1).astype(np.float64)
    f_known = ~np.isnan(f_lo)
    o_known = np.zeros_like(f_known)
    o_grid = np.full(f_lo.shape, np.nan)
    in_slab = np.isclose(oz, 0.5 * RES, atol=1e-6)
    o_known[oj[in_slab] - j0, oi[in_slab] - i0] = True
    o_grid[oj[in_slab] - j0, oi[in_slab] - i0] = o_lo[in_slab]
    both = f_known & o_known
    nb = int(both.sum())
    only_f = int((f_known & ~o_known).sum())
    only_o = int((o_known & ~f_known).sum())
    f_occ = f_lo[both] > 0
    o_occ = o_grid[both] > 0
    agree = float((f_occ == o_occ).mean()) if nb else float("nan")
    diff = np.abs(f_lo[both] - o_grid[both])
    states_f = gmap.classify(f_lo[both].astype(np.float32))
    states_o = gmap.classify(o_grid[both].astype(np.float32))
    lines.append(
        f"cells known to both: {nb}; only fleetmap: {only_f}; only OctoMap: {only_o}; "
        f"OctoMap leaves outside the z = 0 layer: {int((~in_slab).sum())}"
    )
    lines.append(
        f"occupied/free agreement (log-odds > 0 = occupied, OctoMap's isNodeOccupied threshold 0.5): "
        f"{agree:.4%} ({int((f_occ != o_occ).sum())} cells differ); occupied: fleetmap {int(f_occ.sum())}, "
        f"OctoMap {int(o_occ.sum())}"
    )
    lines.append(
        f"nav2 trinary state (p > 0.65 occupied, p < 0.196 free) agreement: "
        f"{(states_f == states_o).mean():.4%}; "
        f"log-odds |difference|: max {diff.max():.2e}, mean {diff.mean():.2e}"
    )
    # search() at fleetmap cell centres: z = 0.5 * res (the slab's centre) and z = 0 find the same
    # node; z = -0.5 * res (the layer below) finds nothing.
    rng = np.random.default_rng(rng_seed)
    jj, ii = np.nonzero(both)
    pick = rng.choice(ii.size, size=min(2000, ii.size), replace=False)
    found = {0.5 * RES: 0, 0.0: 0, -0.5 * RES: 0}
    same = 0
    for k in pick:
        ci, cj = int(ii[k]) + i0, int(jj[k]) + j0
        cx, cy = (ci + 0.5) * RES, (cj + 0.5) * RES
        for z in found:
            node = tree.search([cx, cy, z])
            if node is not None:
                found[z] += 1
                if z == 0.5 * RES and abs(node.getLogOdds() - f_lo[cj - j0, ci - i0]) < 1e-4:
                    same += 1
    n = len(pick)
    lines.append(
        f"search() at {n} fleetmap cell centres ((i + 0.5) * res, (j + 0.5) * res): "
        f"found {found[0.5 * RES]}/{n} at z = 0.5 * res, {found[0.0]}/{n} at z = 0, "
        f"{found[-0.5 * RES]}/{n} at z = -0.5 * res; "
        f"log-odds equal to fleetmap's (1e-4) in {same}/{n}"
    )
    return lines


# ----------------------------------------------------------------------------------------------
# Ray casting (Intel)
# ----------------------------------------------------------------------------------------------

#: The rays cast from every pose of the Intel log: 360, one a degree, of 10 m.
RAY_ANGLES = np.radians(np.arange(360.0))
RAY_RANGE = 10.0
#: z of OctoMap's ray origins: the centre of the z = 0 layer [0, res) that the scans' voxels lie in.
RAY_Z = 0.5 * RES


def ray_origins(scans: Sequence[Scan]) -> np.ndarray:
    """The rays' origins: every pose of the log, (n, 2) metres."""
    return np.array([(s.pose.x, s.pose.y) for s in scans], dtype=np.float64)


def run_fleetmap_rays(gmap: GridMap, origins: np.ndarray, unknown: str) -> Run:
    """One `GridMap.cast_rays` call of the `RAY_ANGLES` per origin; the answers kept."""

    def go() -> tuple[int, int, object]:
        out = [gmap.cast_rays(o, RAY_ANGLES, RAY_RANGE, unknown) for o in origins]
        return len(out) * RAY_ANGLES.size, 0, out

    return timed(go)


def run_octomap_rays(tree: object, origins: np.ndarray, ignore_unknown: bool, max_range: float) -> Run:
    """One `castRay(origin, direction, end, ignoreUnknownCells, maxRange)` call per ray, from Python.

    The call returns whether the ray met an occupied voxel, and only then writes that voxel's centre
    into `end`. Origins at z = `RAY_Z`, directions (cos a, sin a, 0): both built outside the timed
    region, as are the `end` arrays; each origin's 360 end points are copied out once (the answers
    kept: hit flags and centres)."""
    dirs = [np.array([math.cos(a), math.sin(a), 0.0]) for a in RAY_ANGLES]
    starts = [np.array([x, y, RAY_Z]) for x, y in origins]
    buf = np.full((RAY_ANGLES.size, 3), np.nan)
    ends = list(buf)  # row views: castRay writes into buf
    cast = tree.castRay

    def go() -> tuple[int, int, object]:
        out = []
        for start in starts:
            hits = [cast(start, d, e, ignore_unknown, max_range) for d, e in zip(dirs, ends, strict=True)]
            out.append((hits, buf.copy()))
        return len(out) * RAY_ANGLES.size, 0, out

    return timed(go)


def ray_agreement(
    gmap: GridMap,
    tree: object,
    origins: np.ndarray,
    f_out: Sequence[object],
    o_out: Sequence[object],
    stop: bool,
) -> list[str]:
    """Per ray: did both engines stop for the same reason in the same cell? With the disagreements
    classified (see docs/benchmarks.md, "Ray casting")."""
    f_status = np.stack([r.status for r in f_out])
    f_i = np.stack([r.i for r in f_out])
    f_j = np.stack([r.j for r in f_out])
    o_hit = np.array([h for h, _ in o_out], dtype=bool)
    o_end = np.stack([e for _, e in o_out])
    o_i = np.floor(np.nan_to_num(o_end[..., 0]) / RES).astype(np.int64)
    o_j = np.floor(np.nan_to_num(o_end[..., 1]) / RES).astype(np.int64)
    f_occ = f_status == RAY_OCCUPIED
    same_hit = f_occ & o_hit & (f_i == o_i) & (f_j == o_j)
    no_hit = ~f_occ & ~o_hit
    agree = same_hit | no_hit
    n = agree.size
    lines = [
        f"agreement: {int(agree.sum()):,d}/{n:,d} rays ({agree.mean():.4%}) stop for the same reason in "
        f"the same cell: occupied, same cell {int(same_hit.sum()):,d}; no occupied cell in either "
        f"{int(no_hit.sum()):,d}"
    ]
    if stop:
        # pyoctomap gives no end point for a ray that met no occupied voxel, so where fleetmap stopped
        # at an unknown cell the check is that OctoMap holds no node there either.
        p, r = np.nonzero(no_hit & (f_status == RAY_UNKNOWN))
        unknown_both = sum(
            tree.search([(f_i[a, b] + 0.5) * RES, (f_j[a, b] + 0.5) * RES, RAY_Z]) is None
            for a, b in zip(p, r, strict=True)
        )
        lines[0] += (
            f" (fleetmap: max_range {int((no_hit & (f_status == RAY_MAX_RANGE)).sum()):,d}, unknown "
            f"{p.size:,d}, of which OctoMap holds no node in that cell either: {unknown_both:,d})"
        )
    classes: dict[str, int] = {}
    examples: list[str] = []  # the first ray of each class
    for a, b in zip(*np.nonzero(~agree), strict=True):
        why = ray_disagreement(gmap, tree, origins[a], float(RAY_ANGLES[b]), stop, o_hit[a, b], o_end[a, b])
        if why not in classes:
            f_cell = (int(f_i[a, b]), int(f_j[a, b]))
            o_cell = (int(o_i[a, b]), int(o_j[a, b])) if o_hit[a, b] else None
            examples.append(
                f"pose {a}, {math.degrees(RAY_ANGLES[b]):.0f} deg: fleetmap "
                f"{RAY_STATUS_NAMES[int(f_status[a, b])]} {f_cell}, OctoMap "
                f"{'hit ' + str(o_cell) if o_cell else 'no hit'}: {why}"
            )
        classes[why] = classes.get(why, 0) + 1
    if classes:
        lines.append(
            f"rays that differ: {int((~agree).sum())}: "
            + "; ".join(f"{k}: {v}" for k, v in sorted(classes.items()))
        )
        lines += ["  e.g. " + e for e in examples]
    return lines


def ray_disagreement(
    gmap: GridMap, tree: object, origin: np.ndarray, angle: float, stop: bool, o_hit: bool, o_end: np.ndarray
) -> str:
    """Why one ray's answers differ, tested in this order:

    * 'float32 input': fleetmap, given the float32 origin and direction OctoMap computes with (its
      point3d is float), gives OctoMap's answer: the ray passes within float32 rounding of a cell
      corner, or the origin lies on a cell edge;
    * 'range edge, entered within' / 'range edge, centre within': the occupied cell one engine stops
      in is within `RAY_RANGE` by one engine's rule and not by the other's (OctoMap stops when a
      voxel centre is farther than maxRange; fleetmap counts a cell the ray enters before
      `RAY_RANGE`);
    * 'cell state': the two maps classify that cell differently;
    * 'other'."""
    unknown = "stop" if stop else "pass"
    o32 = origin.astype(np.float32).astype(np.float64)
    c32, s32 = np.float32(math.cos(angle)), np.float32(math.sin(angle))
    a32 = math.atan2(float(s32), float(c32))
    r32 = gmap.cast_rays(o32, [a32], RAY_RANGE, unknown)
    o_cell = (math.floor(o_end[0] / RES), math.floor(o_end[1] / RES)) if o_hit else (0, 0)
    f32_hit = int(r32.status[0]) == RAY_OCCUPIED
    if f32_hit == o_hit and (not o_hit or (int(r32.i[0]), int(r32.j[0])) == o_cell):
        return "float32 input"
    r = gmap.cast_rays(origin, [angle], RAY_RANGE, unknown)
    cells = []
    if int(r.status[0]) == RAY_OCCUPIED:
        cells.append((int(r.i[0]), int(r.j[0])))
    if o_hit:
        cells.append(o_cell)
    for i, j in cells:
        cx, cy = (i + 0.5) * RES, (j + 0.5) * RES
        centre_in = math.hypot(cx - origin[0], cy - origin[1]) <= RAY_RANGE
        if centre_in != (ray_entry(origin, angle, i, j) < RAY_RANGE):
            return "range edge, centre within" if centre_in else "range edge, entered within"
        node = tree.search([cx, cy, RAY_Z])
        o_occ = node is not None and tree.isNodeOccupied(node)
        f_occ = int(gmap.cells([(cx, cy)])["state"][0]) == STATE_OCCUPIED
        if o_occ != f_occ:
            return "cell state"
    return "other"


def ray_entry(origin: np.ndarray, angle: float, i: int, j: int) -> float:
    """Metres from `origin` along the ray at `angle` to where it enters cell (i, j) (slab method; the
    cell is one the ray passes through)."""
    t = 0.0
    for o, d, k in ((float(origin[0]), math.cos(angle), i), (float(origin[1]), math.sin(angle), j)):
        if d != 0.0:
            t = max(t, ((k if d > 0 else k + 1) * RES - o) / d)
    return t


def print_rays(w: Workload, gmap: GridMap, tree: object, reps: int) -> None:
    """Ray casting on the last timed Intel maps: fleetmap's `cast_rays` against OctoMap's `castRay`,
    the same rays, repetitions interleaved; OctoMap's per-call floor; whether the answers agree."""
    thresh = gmap.config.occupancy.occupied_thresh
    tree.setOccupancyThres(thresh)
    origins = ray_origins(w.scans)
    n_rays = origins.shape[0] * RAY_ANGLES.size
    print(
        f"\nray casting on Intel (the last timed maps): {RAY_ANGLES.size} rays of {RAY_RANGE:.0f} m (one a "
        f"degree) from each of the {origins.shape[0]} poses of the log = {n_rays:,d} rays; fleetmap one "
        "cast_rays call per pose, OctoMap one castRay call per ray from Python"
    )
    print(
        f"  occupied: fleetmap p > occupied_thresh {thresh}; OctoMap setOccupancyThres({thresh}), "
        f"isNodeOccupied = log-odds >= {tree.getOccupancyThresLog():.6f}; OctoMap origins at z = {RAY_Z}"
    )
    # fleetmap's unknown= and the matching ignoreUnknownCells.
    modes = [("stop", False), ("pass", True)]
    settings: list[tuple[str, Callable[[], Run]]] = []
    for unknown, ignore in modes:
        settings += [
            (f"fleetmap unknown={unknown}", lambda u=unknown: run_fleetmap_rays(gmap, origins, u)),
            (
                f"OctoMap ignoreUnknown={ignore}",
                lambda i=ignore: run_octomap_rays(tree, origins, i, RAY_RANGE),
            ),
        ]
    # Warm-up: load the ray kernel, touch castRay.
    run_fleetmap_rays(gmap, origins[:4], "stop")
    run_octomap_rays(tree, origins[:4], False, RAY_RANGE)
    runs: dict[str, list[Run]] = {label: [] for label, _ in settings}
    answers: dict[str, object] = {}
    for _ in range(reps):
        for label, fn in settings:
            run = fn()
            runs[label].append(run)
            answers[label] = run.result
            run.result = None
    floor_s = run_octomap_rays(tree, origins, False, 1e-9).seconds
    ms = {label: Measured(label, runs[label], n_rays) for label, _ in settings}
    head = (
        f"  {'engine / setting':27s} {'best s':>7s} {'median s':>8s} {'M rays/s best':>13s} "
        f"{'M rays/s med':>12s} {'us/ray best':>11s} {'xOctoMap best':>13s} {'xOctoMap med':>12s} "
        f"{'cpu/wall':>9s}"
    )
    print(head)
    print("  " + "-" * (len(head) - 2))
    for unknown, ignore in modes:
        ref = ms[f"OctoMap ignoreUnknown={ignore}"]
        for m in (ms[f"fleetmap unknown={unknown}"], ref):
            lo, hi = m.cpu_wall
            print(
                f"  {m.label:27s} {m.best:7.3f} {m.median:8.3f} {fmt_rate(n_rays / m.best):>13s} "
                f"{fmt_rate(n_rays / m.median):>12s} {m.best / n_rays * 1e6:11.3f} {ref.best / m.best:13.2f} "
                f"{ref.median / m.median:12.2f} {lo:4.2f}-{hi:4.2f}"
            )
    ref = ms["OctoMap ignoreUnknown=False"]
    print(
        f"  OctoMap per-call floor (the same castRay calls with maxRange 1 nm: the wrapper, the call and "
        f"one step, no walk): {floor_s:.3f} s = {floor_s / n_rays * 1e6:.3f} us a ray = "
        f"{floor_s / ref.best:.1%} of OctoMap's best time (ignoreUnknown=False)"
    )
    for unknown, ignore in modes:
        print(f"  agreement, unknown={unknown} / ignoreUnknown={ignore}:")
        f_out, o_out = answers[f"fleetmap unknown={unknown}"], answers[f"OctoMap ignoreUnknown={ignore}"]
        for line in ray_agreement(gmap, tree, origins, f_out, o_out, unknown == "stop"):
            print("    " + line)


# ----------------------------------------------------------------------------------------------
# Where fleetmap's time goes
# ----------------------------------------------------------------------------------------------


def traced_by_rows(scan: Scan) -> tuple[int, int, int]:
    """How the per-scan trace covers `scan`: cells of the beams' whole walks, cells written by the
    row trace (`kernels.fan_rows`) near the sensor, and cells the handed-back walks visit far out."""
    # Every workload scan traces beams, so the inputs are not None.
    ox, oy, ex, ey, kinds, ti0, tj0, ti1, tj1 = ray_trace_inputs(scan, 0.0, RES, 8)
    ni, nj = ti1 - ti0 + 1, tj1 - tj0 + 1
    traced = kinds != 0
    whole = np.abs(np.floor(ex) - math.floor(ox)) + np.abs(np.floor(ey) - math.floor(oy)) + 1
    size = int(whole[traced].sum())
    far = np.empty((ex.size, 3), dtype=np.int64)
    found, kind, planes = np.empty(size, np.int64), np.empty(size, np.uint8), np.zeros(ni * nj, np.uint8)
    run_key, run_len = np.empty(size, np.int64), np.empty(size, np.int64)
    starts, crossings = exact_starts(np.full(ex.size, ox), np.full(ex.size, oy), ex, ey)
    cells, runs, handed = trace_fan_rows(
        ox, oy, ex, ey, kinds, starts, crossings, 8, ti0, tj0, ni, found, kind, run_key, run_len, planes, far
    )
    if cells < 0:
        return size, 0, size
    rows = cells + int(run_len[:runs].sum())
    b, i, j = far[:handed, 0], far[:handed, 1], far[:handed, 2]
    walked = np.abs(np.floor(ex[b]) - i) + np.abs(np.floor(ey[b]) - j) + 1
    return size, rows, int(walked.sum())


def fleetmap_breakdown(w: Workload) -> str:
    """One untimed-for-the-table pass, occupancy only: plan vs apply time; cells of the beams' whole
    walks per distinct update, and the share of the updates the row trace writes."""
    gmap = GridMap(fleetmap_config(OCC_ONLY))
    t_plan = t_apply = 0.0
    whole = rows = walked = updates = 0
    for scan in w.scans:
        t0 = time.perf_counter()
        plan = gmap.plan(scan)
        t1 = time.perf_counter()
        res = gmap.apply(plan)
        t2 = time.perf_counter()
        t_plan += t1 - t0
        t_apply += t2 - t1
        updates += res.cell_updates
        a, b, c = traced_by_rows(scan)
        whole += a
        rows += b
        walked += c
    total = t_plan + t_apply
    return (
        f"{w.name:10s} plan (trace, dedup) {t_plan / total:5.1%}, apply (updated cells into tiles) "
        f"{t_apply / total:5.1%}; {whole / updates:4.1f} cells on the beams' whole walks per distinct "
        f"update; {rows / updates:5.1%} of the updates traced by rows, the rest by {walked / updates:4.2f} "
        f"walked cells per update"
    )


# ----------------------------------------------------------------------------------------------
# Main
# ----------------------------------------------------------------------------------------------


def verdict(best: float, median: float, aim: float) -> str:
    """'MET' if the median run meets `aim`, 'best run only' if only the best does, else 'NOT met'."""
    if median >= aim:
        return "MET"
    return "best run only" if best >= aim else "NOT met"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=3, help="timed repetitions per measurement (default 3)")
    parser.add_argument("--pin", type=int, default=None, metavar="CPU", help="pin the process to this CPU")
    args = parser.parse_args(argv)
    reps = max(1, args.reps)
    t_start = time.perf_counter()

    cores = one_core(args.pin)
    print("fleetmap engine benchmark (resolution 0.05 m, per-scan updates; times in seconds)")
    for line in machine_lines(cores):
        print("  " + line)
    if pyoctomap is None:
        print("skipped: pyoctomap is not installed; OctoMap columns, ratios and the equivalence check")
    else:
        d = pyoctomap.OcTree(RES)
        used = ", ".join(f"{v:.4f}" for v in octomap_params())
        print(
            f"  occupancy (hit, miss, clamp min, clamp max): OctoMap's defaults {d.getProbHit():.4f}, "
            f"{d.getProbMiss():.4f}, {d.getClampingThresMin():.4f}, {d.getClampingThresMax():.4f}; "
            f"both engines use fleetmap's 'octomap' preset {used}"
        )

    workloads, notes = build_workloads()
    for note in notes:
        print(note)
    print("\nworkloads (built, and the Intel log parsed, before any timing):")
    for w in workloads:
        print(f"  {w.name:10s} {w.description}\n  {'':10s} {w.stats()}")

    # Warm-up: compile / load every numba kernel and touch OctoMap's code paths on throw-away maps.
    for w in workloads:
        for layers in (OCC_ONLY, ALL_LAYERS):
            warm = GridMap(fleetmap_config(layers))
            for s in w.scans[:WARMUP_SCANS]:
                warm.integrate(s)
        if pyoctomap is not None:
            run_octomap(w.clouds[:WARMUP_SCANS], lazy=True)

    # Cell updates per scan, both counted independently.
    print("\ncell updates = distinct cells updated per scan (hit beats miss), summed over the workload:")
    print("  fleetmap: IntegrationResult.cell_updates; OctoMap: leaves of a fresh tree per scan")
    print("  (OctoMap's own count of its free + occupied KeySets; pyoctomap exposes no computeUpdate or")
    print("  computeRayKeys)")
    octo_counts: dict[str, int] = {}
    for w in workloads:
        f_counts = fleetmap_scan_updates(w.scans)
        line = f"  {w.name:10s} fleetmap {int(f_counts.sum()):>11,d}"
        if pyoctomap is not None:
            o_counts = octomap_cell_updates(w.clouds)
            octo_counts[w.name] = int(o_counts.sum())
            differ = int((o_counts != f_counts).sum())
            rel = abs(int(o_counts.sum()) - int(f_counts.sum())) / max(1, int(f_counts.sum()))
            line += (
                f"  OctoMap {int(o_counts.sum()):>11,d}  scans whose counts differ: {differ}/{len(w.scans)} "
                f"(totals differ by {rel:.4%})"
            )
        print(line)

    # Timed runs: repetitions interleaved across settings so that machine noise hits them alike.
    # The wrapper-default OctoMap row is for information only (see run_octomap) and runs once.
    settings: list[tuple[str, int, Callable[[Workload], Run]]] = [
        ("fleetmap occupancy", reps, lambda w: run_fleetmap(w.scans, OCC_ONLY)),
        ("fleetmap 3 layers", reps, lambda w: run_fleetmap(w.scans, ALL_LAYERS)),
    ]
    if pyoctomap is not None:
        settings += [
            ("OctoMap lazy+final", reps, lambda w: run_octomap(w.clouds, lazy=True)),
            ("OctoMap wrapper dflt*", 1, lambda w: run_octomap(w.clouds, lazy=False)),
        ]
    results: dict[str, list[Measured]] = {}
    kept: dict[tuple[str, str], object] = {}
    for w in workloads:
        runs: dict[str, list[Run]] = {label: [] for label, _, _ in settings}
        for rep in range(reps):
            for label, n_reps, fn in settings:
                if rep >= n_reps:
                    continue
                run = fn(w)
                runs[label].append(run)
                kept[(w.name, label)] = run.result
                run.result = None
        results[w.name] = []
        for label, _, _ in settings:
            cells = runs[label][0].cell_updates if label.startswith("fleetmap") else octo_counts[w.name]
            results[w.name].append(Measured(label, runs[label], cells))

    print(f"\nresults: {reps} timed runs each (* one run), best and median; M = 10^6; one core (see above)")
    head = (
        f"  {'workload':10s} {'engine / setting':21s} {'scans':>5s} {'cell updates':>12s} "
        f"{'best s':>7s} {'median s':>8s} {'Mcell/s best':>12s} {'Mcell/s med':>11s} "
        f"{'scans/s best':>12s} {'scans/s med':>11s} {'xOctoMap best':>13s} {'xOctoMap med':>12s} "
        f"{'cpu/wall':>9s} {'Mcell/cpu-s':>11s}"
    )
    print(head)
    print("  " + "-" * (len(head) - 2))
    for w in workloads:
        ms = results[w.name]
        ref = next((m for m in ms if m.label == "OctoMap lazy+final"), None)
        for m in ms:
            n = len(w.scans)
            ratio_b = f"{ref.best / m.best:13.2f}" if ref else f"{'-':>13s}"
            ratio_m = f"{ref.median / m.median:12.2f}" if ref else f"{'-':>12s}"
            lo, hi = m.cpu_wall
            print(
                f"  {w.name:10s} {m.label:21s} {n:5d} {m.cell_updates:12,d} {m.best:7.3f} {m.median:8.3f} "
                f"{fmt_rate(m.cell_updates / m.best):>12s} {fmt_rate(m.cell_updates / m.median):>11s} "
                f"{n / m.best:12.1f} {n / m.median:11.1f} {ratio_b} {ratio_m} {lo:4.2f}-{hi:4.2f} "
                f"{fmt_rate(m.cell_updates / m.best_cpu):>11s}"
            )
        tsdf = ms[1].runs[0].extra
        print(f"  {'':10s} (3 layers also made {tsdf:,d} TSDF band updates, not counted as cell updates)")
    print("  xOctoMap = OctoMap lazy+final time / this setting's time (same scans, same cell updates).")
    print("  cpu/wall = process CPU time / wall time over the runs: <= 1.00 means at most one core was used;")
    print("  well below 1 means the run waited for a busy CPU (a shared machine), so trust 'best' more.")
    print("  Mcell/cpu-s = cell updates per second of process CPU time (best run), for comparison only.")
    print("  * wrapper default: lazy_eval=False, for which pyoctomap also runs a whole-tree")
    print("    updateInnerOccupancy() after every scan; not the reference.")

    if pyoctomap is not None:
        print("\nOctoMap per-call floor (same calls, 1 nm range limit: point copy + call, no rays):")
        for w in workloads:
            floor_s = octomap_call_floor(w.clouds)
            ref = next(m for m in results[w.name] if m.label == "OctoMap lazy+final")
            print(f"  {w.name:10s} {floor_s:.3f} s = {floor_s / ref.best:.1%} of OctoMap's best time")

    print(f"\naims (issue): >= {AIM_RATE / 1e6:.0f} M cell updates/s, one core; >= {AIM_RATIO:.0f} x OctoMap")
    for w in workloads:
        ms = {m.label: m for m in results[w.name]}
        for label in ("fleetmap occupancy", "fleetmap 3 layers"):
            m = ms[label]
            best, med = m.cell_updates / m.best, m.cell_updates / m.median
            line = (
                f"  {w.name:10s} {label:21s} {best / 1e6:6.1f} / {med / 1e6:6.1f} M/s (best / median): "
                f"{verdict(best, med, AIM_RATE)}"
            )
            ref = ms.get("OctoMap lazy+final")
            if ref is not None:
                rb, rm = ref.best / m.best, ref.median / m.median
                line += f"; {rb:5.1f} / {rm:5.1f} x OctoMap: {verdict(rb, rm, AIM_RATIO)}"
            print(line)

    print("\nwhere fleetmap's time goes (occupancy only, one extra pass):")
    for w in workloads:
        print("  " + fleetmap_breakdown(w))

    intel = next((w for w in workloads if w.name == "intel"), None)
    if intel is None:
        print("\nskipped: equivalence check (needs the Intel dataset)")
    elif pyoctomap is None:
        print("\nskipped: equivalence check (needs pyoctomap)")
    else:
        print("\nequivalence on Intel (the last timed maps: fleetmap occupancy vs OctoMap lazy+final):")
        gmap = kept[("intel", "fleetmap occupancy")]
        tree = kept[("intel", "OctoMap lazy+final")]
        for line in equivalence(gmap, tree):
            print("  " + line)
        print(
            f"  memory: fleetmap {gmap.memory_bytes() / 2**20:.1f} MiB (allocated tile pools), "
            f"OctoMap {tree.memoryUsage() / 2**20:.1f} MiB (memoryUsage())"
        )

    if intel is not None and pyoctomap is not None:
        print_rays(intel, kept[("intel", "fleetmap occupancy")], kept[("intel", "OctoMap lazy+final")], reps)
    else:
        print("\nskipped: ray casting against OctoMap's castRay (needs the Intel dataset and pyoctomap)")

    print(f"\ntotal benchmark time {time.perf_counter() - t_start:.0f} s. Figures vary on shared machines;")
    print("compare settings within one run, not across runs.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
