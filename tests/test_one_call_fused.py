"""The one-call path's fused trace and apply (`ray_model.trace_apply_scan`, taken by
`integrate_scan.integrate_ray_scan` for occupancy-only maps when every tile of a scan's box is
stored): the far walks' cells are applied straight from the trace's window instead of being
collected and applied by `apply_cells`. It must leave the pool bit for bit as `trace_scan` +
`apply_cells` do."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_grid_map import _fleet_scans

from fleetmap.config import MapConfig
from fleetmap.datasets import load_dataset
from fleetmap.grid_map import GridMap
from fleetmap.kernels.ray_model import APPLIED, DENSE_WINDOW_CELLS, trace_apply_scan, trace_scan
from fleetmap.kernels.traversal import EXACT
from fleetmap.kernels.update import apply_cells
from fleetmap.scan import Scan
from fleetmap.update_plan import ray_trace_inputs


def _compare_kernels(scans: list[Scan], config: MapConfig) -> int:
    """Build a map of `scans` by plan and apply; before each scan whose box's tiles are all stored,
    run `trace_apply_scan` and `trace_scan` + `apply_cells` on two copies of the box's tiles and
    require the same bytes, the same count of updates and the same changed tiles. Returns how many
    scans the fused kernel applied."""
    planned = GridMap(config)
    store = planned.store
    shift = store.shift
    scratch = np.zeros(DENSE_WINDOW_CELLS, dtype=np.uint8)
    no_counts = np.zeros((0, 0, 0), dtype=np.uint32)
    applied = 0
    for k, scan in enumerate(scans):
        inputs = ray_trace_inputs(scan, config.no_return_range, config.resolution, shift)
        if inputs is not None:
            ox, oy, ex, ey, kinds, ti0, tj0, ti1, tj1 = inputs
            keys = [(ti, tj) for tj in range(tj0, tj1 + 1) for ti in range(ti0, ti1 + 1)]
            if all(key in store.slots for key in keys):
                # The box's tiles copied into a pool of their own, slot k for box tile k.
                pool = store.kernel_pools()[0][[store.slots[key] for key in keys]]
                compact = {key: slot for slot, key in enumerate(keys)}
                rays = np.vstack((np.zeros_like(ex), np.zeros_like(ex), ex, ey))
                fused, fused_changed = pool.copy(), np.zeros(len(keys), dtype=np.uint8)
                status, fused_updates, _ = trace_apply_scan(
                    ox, oy, rays, kinds, shift, ti0, tj0, ti1, tj1, scratch, np.arange(len(keys)), fused,
                    *planned._log_odds, fused_changed,
                )  # fmt: skip
                assert not scratch.any(), f"scan {k}: the scratch was left marked"
                tiles, cell, kind, runs, _ = trace_scan(
                    ox, oy, rays, kinds, EXACT, shift, ti0, tj0, ti1, tj1, scratch
                )
                slots = np.array([compact[(i, j)] for i, j in tiles.T.tolist()], dtype=np.int64)
                want, want_changed = pool.copy(), np.zeros(tiles.shape[1], dtype=np.uint8)
                want_updates = apply_cells(
                    cell, kind, runs, slots, shift, want, no_counts, no_counts, *planned._log_odds,
                    want_changed,
                )  # fmt: skip
                if status == APPLIED:
                    applied += 1
                    assert fused.tobytes() == want.tobytes(), f"scan {k}"
                    assert fused_updates == want_updates, f"scan {k}"
                    assert [keys[c] for c in np.flatnonzero(fused_changed)] == [
                        (int(tiles[0, c]), int(tiles[1, c])) for c in np.flatnonzero(want_changed)
                    ], f"scan {k}"
                else:  # declined: nothing changed
                    assert fused.tobytes() == pool.tobytes() and not fused_changed.any(), f"scan {k}"
        planned.apply(planned.plan(scan))
    return applied


@pytest.mark.parametrize(("tile_size", "share"), [(256, 0.9), (32, 0.2)])
def test_trace_apply_scan_equals_trace_and_apply_on_the_intel_log(
    datasets_dir: Path, tile_size: int, share: float
) -> None:
    """The whole Intel log, against the map it builds scan by scan; small tiles put tile edges in
    the far walks (a walk's cells then change tile within its run), and fewer scans find every tile
    of their box stored."""
    scans = list(load_dataset(datasets_dir / "intel-corrected.log.gz"))
    config = MapConfig(resolution=0.05, tile_size=tile_size, layers=["occupancy"], max_tiles=100_000)
    applied = _compare_kernels(scans, config)
    assert applied > share * len(scans)


def test_trace_apply_scan_equals_trace_and_apply_on_simulated_scans() -> None:
    """Simulated 1081-beam scans in a floor plan (hits, far returns, noise) and fans of long clearing
    beams, in tiles of 64 cells; the clearing fans' boxes are too large for the dense window and
    must be declined with nothing changed."""
    config = MapConfig(resolution=0.05, tile_size=64, layers=["occupancy"], no_return_range=25.0)
    scans = _fleet_scans(40)
    applied = _compare_kernels(scans, config)
    assert applied > len(scans) // 2


@pytest.mark.parametrize("tile_size", [256, 64])
def test_integrate_with_occupancy_alone_equals_plan_and_apply_on_the_intel_log(
    datasets_dir: Path, tile_size: int
) -> None:
    """`GridMap.integrate` with occupancy alone (where the fused kernel does most scans) gives,
    scan by scan, the result of `apply(plan(scan))`, and the same map byte for byte: tiles, their
    versions and slots, the clock and the log-odds pool."""
    scans = list(load_dataset(datasets_dir / "intel-corrected.log.gz"))
    config = MapConfig(resolution=0.05, tile_size=tile_size, layers=["occupancy"], max_tiles=100_000)
    one_call, planned = GridMap(config), GridMap(config)
    for k, scan in enumerate(scans):
        assert one_call.integrate(scan) == planned.apply(planned.plan(scan)), f"scan {k}"
    a, b = one_call.store, planned.store
    assert list(a.keys) == list(b.keys) and a.slots == b.slots and a.clock == b.clock
    n = len(a.keys)
    assert a.versions[:n].tobytes() == b.versions[:n].tobytes()
    assert a.kernel_pools()[0][:n].tobytes() == b.kernel_pools()[0][:n].tobytes()
