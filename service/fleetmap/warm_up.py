"""The engine's compiled kernels loaded (or compiled) ahead of need: `fleetmap serve` calls
`warm_up` before it serves, so that the first robot's scan does not wait for them (on a first start,
after `compile_in_child`); the Docker build calls it to fill numba's cache, and the tests before
their first timed integration."""

from __future__ import annotations

import os
import subprocess
import sys


def warm_up() -> None:
    """Integrate tiny scans into throwaway maps so the compiled kernels are loaded (or compiled)
    before the first robot's scan: its latency should not include that (loading them from numba's
    cache takes about 50 ms, compiling them 10 s).

    Both paths a scan can take: the service's ingest plans and applies (`GridMap.plan`,
    `GridMap.apply`), into new tiles and then existing ones; journal replay and library users call
    `GridMap.integrate`, whose one compiled call creates tiles itself and so never reaches the
    planning kernels. A durable service also encodes every scan for its journal (`scan_to_blob`).
    The ray caster (`GridMap.cast_rays`) and the zoomed-out tile reductions (`kernels.reduce`, one per
    dtype) are loaded too, so a first ray query or zoomed-out tile does not compile them."""
    import numpy as np

    from fleetmap.config import MapConfig
    from fleetmap.grid_map import GridMap
    from fleetmap.kernels.reduce import reduce_max_tiles, reduce_tsdf_tiles
    from fleetmap.scan import Scan
    from fleetmap.storage_format import scan_to_blob

    scan = Scan.from_fan((0.0, 0.0, 0.0), -0.5, 0.1, [1.0] * 10 + [None], 0.0, 5.0)
    scan_to_blob(scan)
    for sensor_model in ("ray", "beam"):
        config = MapConfig(sensor_model=sensor_model, tile_size=16, resolution=0.1)
        GridMap(config).integrate(scan)
        gmap = GridMap(config)
        for _ in range(2):
            gmap.apply(gmap.plan(scan))
    gmap.cast_rays((0.0, 0.0), [0.0, 1.0], 2.0)
    # The reductions alone, of each pool dtype, not a whole render (a render's faults are the
    # request's, not the start's).
    slots = np.zeros(1, dtype=np.int64)
    for dtype in (np.float32, np.uint32):
        pool = np.zeros((1, 2, 2), dtype=dtype)
        reduce_max_tiles(pool, slots, 0, 0, 2, 2, np.empty((1, 1, 1), dtype=dtype))
    tsdf = np.zeros((1, 2, 2), dtype=np.float32)
    reduce_tsdf_tiles(tsdf, tsdf, slots, 0, 0, 2, 2, np.empty((1, 1, 1), dtype=np.float32))


def compile_in_child() -> bool:
    """Compile the kernels into numba's on-disk cache in a child process (`python -m
    fleetmap.warm_up`); True if it finished. The caller's `warm_up` then loads them from the cache.

    Why: LLVM keeps what a compilation took for the life of the process (about 210 MB more resident
    memory in a service that compiled its kernels than in one that loaded them, for as long as it
    runs, however long that is). The child's memory goes with the child. The child writes the cache
    this process uses (`NUMBA_CACHE_DIR` passed on, for a cache directory chosen at run time by
    `kernels.ensure_compiled_cache_location`)."""
    import numba

    env = dict(os.environ)
    cache_dir = numba.config.CACHE_DIR  # type: ignore[attr-defined]  # set from the environment at import
    if cache_dir:
        env["NUMBA_CACHE_DIR"] = str(cache_dir)
    try:
        done = subprocess.run([sys.executable, "-m", "fleetmap.warm_up"], env=env, check=False)
    except OSError:
        return False
    return done.returncode == 0


if __name__ == "__main__":
    warm_up()
