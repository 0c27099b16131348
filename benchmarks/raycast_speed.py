"""How fast `GridMap.cast_rays` walks: 360 rays of 10 m from robot poses of the Intel map.

    .venv/bin/python benchmarks/raycast_speed.py [--dataset PATH] [--reps 7]

Builds the Intel Research Lab map at 0.05 m from its corrected log (every scan), then casts 360 rays
(one a degree) of 10 m from every 50th pose of the log, once with `unknown="stop"` and once with
"pass", each call timed on its own; prints the best of `--reps` runs over all poses as rays a
second, and the cells walked a second (the walk's length up to where each ray stopped). One call
holds the map's lock for the time shown per call. Then the same rays in one call with an origin
per ray (as a particle filter casts them), checked against the calls per pose. A quick
measurement, not a test.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from fleetmap import RAY_STATUS_NAMES, GridMap, MapConfig, load_dataset

DEFAULT_DATASET = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "intel-corrected.log.gz"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    parser.add_argument("--reps", type=int, default=7)
    args = parser.parse_args()
    if not args.dataset.is_file():  # a fresh clone has no ../shared/datasets: not a traceback
        parser.error(
            f"no dataset at {args.dataset}: this reads a CARMEN log (by default the Intel log of "
            "../shared/datasets beside the repository); give one with --dataset PATH"
        )
    dataset = load_dataset(args.dataset)
    gmap = GridMap(MapConfig(resolution=0.05))
    for scan in dataset:
        gmap.integrate(scan)
    origins = [(dataset[k].pose.x, dataset[k].pose.y) for k in range(0, len(dataset), 50)]
    angles = np.radians(np.arange(360.0))
    gmap.cast_rays(origins[0], angles, 10.0)  # compile or load the kernel
    print(f"{len(dataset)} scans, {len(gmap.store)} tiles; {len(origins)} origins x 360 rays of 10 m")
    for unknown in ("stop", "pass"):
        best = math.inf
        cells = 0
        statuses = np.zeros(3, dtype=np.int64)
        for _ in range(args.reps):
            total = 0.0
            cells = 0
            statuses[:] = 0
            for origin in origins:
                start = time.perf_counter()
                r = gmap.cast_rays(origin, angles, 10.0, unknown)  # type: ignore[arg-type]
                total += time.perf_counter() - start
                # An exact walk from cell (i0, j0) to (i, j) visits |i - i0| + |j - j0| + 1 cells.
                i0, j0 = gmap.cell_index(*origin)
                cells += int((np.abs(r.i - i0) + np.abs(r.j - j0) + 1).sum())
                statuses += np.bincount(r.status, minlength=3)
            best = min(best, total)
        calls = len(origins)
        print(
            f"unknown={unknown}: {calls * 360 / best:,.0f} rays/s, {cells / best / 1e6:.0f} M cells/s, "
            f"{best / calls * 1e6:.0f} us per call of 360 rays (best of {args.reps}); stopped: "
            + ", ".join(f"{RAY_STATUS_NAMES[k]} {int(n)}" for k, n in enumerate(statuses))
        )
        # Every pose's rays in one call, each ray with its own origin: the same answers.
        per_ray = np.repeat(np.array(origins), angles.size, axis=0)
        all_angles = np.tile(angles, len(origins))
        batched = gmap.cast_rays(per_ray, all_angles, 10.0, unknown)  # type: ignore[arg-type]
        one_by_one = [gmap.cast_rays(o, angles, 10.0, unknown) for o in origins]  # type: ignore[arg-type]
        assert np.array_equal(batched.i, np.concatenate([r.i for r in one_by_one]))
        assert np.array_equal(batched.range, np.concatenate([r.range for r in one_by_one]))
        best_one = math.inf
        for _ in range(args.reps):
            start = time.perf_counter()
            gmap.cast_rays(per_ray, all_angles, 10.0, unknown)  # type: ignore[arg-type]
            best_one = min(best_one, time.perf_counter() - start)
        print(
            f"  the same {per_ray.shape[0]} rays in one call, an origin per ray: "
            f"{per_ray.shape[0] / best_one:,.0f} rays/s ({best_one * 1e3:.2f} ms; same answers)"
        )


if __name__ == "__main__":
    main()
