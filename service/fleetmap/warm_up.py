"""The engine's compiled kernels loaded (or compiled) ahead of need: `fleetmap serve` calls
`warm_up` before it serves, so that the first robot's scan does not wait for them (on a first start,
after `compile_in_child`); the Docker build calls it to fill numba's cache, and the tests before
their first timed integration."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from typing import NamedTuple

from fleetmap.parent_death import end_with_parent


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


#: How often `compile_in_child` looks at its stop event while the child compiles (seconds).
STOP_POLL_S = 0.2
#: How long a child told to stop (SIGTERM) has to end before it is killed (seconds).
STOP_GRACE_S = 5.0


class ChildCompile(NamedTuple):
    """What `compile_in_child` saw: whether the child compiled the kernels (exit status 0), and what
    it printed (stdout and stderr together, as one text)."""

    finished: bool
    output: str


def compile_in_child(stop: threading.Event | None = None) -> ChildCompile:
    """Compile the kernels into numba's on-disk cache in a child process (`python -m
    fleetmap.warm_up`). The caller's `warm_up` then loads them from the cache.

    Why: LLVM keeps what a compilation took for the life of the process (about 210 MB more resident
    memory in a service that compiled its kernels than in one that loaded them, for as long as it
    runs, however long that is). The child's memory goes with the child. The child writes the cache
    this process uses (`NUMBA_CACHE_DIR` passed on, for a cache directory chosen at run time by
    `kernels.ensure_compiled_cache_location`).

    When `stop` is set while the child compiles (the service got SIGTERM, but the child did not: a
    `kill` or `docker stop` signals one process, not its group), the child is terminated, and killed
    after `STOP_GRACE_S`: a stopping service does not wait out a compilation. The child's output is
    returned, not passed through, so that the caller can log it in the service's log format (a
    plain-text line in a JSON log would break a log collector)."""
    import numba

    env = dict(os.environ)
    cache_dir = numba.config.CACHE_DIR  # type: ignore[attr-defined]  # set from the environment at import
    if cache_dir:
        env["NUMBA_CACHE_DIR"] = str(cache_dir)
    command = [sys.executable, "-m", "fleetmap.warm_up", str(os.getpid())]  # (`end_with_parent`)
    try:
        # In a process group of its own: Ctrl-C in a terminal signals the whole foreground group, and
        # the child, interrupted inside numba, printed a KeyboardInterrupt traceback of some 300
        # lines, which the service then logged as the child's output (a first `make demo` stopped
        # while it compiled). The service, signalled itself, ends the child below; its death ends
        # the child too (`end_with_parent`).
        child = subprocess.Popen(
            command, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, errors="replace", process_group=0,
        )  # fmt: skip
    except OSError as exc:
        return ChildCompile(False, f"cannot run {sys.executable}: {exc}")
    while True:
        try:  # (a retried communicate loses no output)
            output, _ = child.communicate(timeout=STOP_POLL_S)
        except subprocess.TimeoutExpired:
            if stop is None or not stop.is_set():
                continue
            child.terminate()
            try:
                output, _ = child.communicate(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                child.kill()
                output, _ = child.communicate()
            return ChildCompile(False, output)
        return ChildCompile(child.returncode == 0, output)


if __name__ == "__main__":
    # `python -m fleetmap.warm_up [SERVICE_PID]`: the compile child is given the service's pid; run
    # by hand, it compiles with no parent to watch.
    if len(sys.argv) > 1:
        end_with_parent(int(sys.argv[1]))
    warm_up()
