"""The seed's TSDF worked example, run through the engine.

A robot at 0 looks along +x at an obstacle at 10 and measures it five times:
9.9494, 10.0178, 9.9733, 10.0068, 9.9676. Resolution 0.05, truncation 0.1. The example prints the
fused TSDF value (and weight) of the cells at 9.90 ... 10.10 from the robot, and as its last line
`surface <x>`, the sub-cell zero crossing.

The engine evaluates a cell at its centre, so the sensor sits half a cell behind the map origin:
cell i then has its centre exactly (i + 1) * 0.05 from the sensor, and the cells "at 9.90 ... 10.10"
are cells 197 ... 201 of row 0. Fusing by hand, every measurement is within the band of the cells at
9.95 and 10.00, so their values are the plain means of `(z - d) / t`: +0.3298 and -0.1702, and the
zero crossing between them is at 9.95 + 0.05 * 0.3298 / 0.5 = 9.98298, the mean of the five ranges,
as it must be for unclamped linear data. Cells nearer the edge of the band are updated only by the
measurements whose band reaches them (9.90: three, 10.05: four, 10.10: two).
"""

from __future__ import annotations

import argparse

from fleetmap.config import MapConfig, TsdfParams
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan

MEASUREMENTS = (9.9494, 10.0178, 9.9733, 10.0068, 9.9676)
RESOLUTION = 0.05
TRUNCATION = 0.1
DISTANCES = (9.90, 9.95, 10.00, 10.05, 10.10)


def run() -> tuple[list[tuple[float, float, float]], float]:
    """Fuse the five measurements; return `[(distance, tsdf, weight)]` and the surface distance."""
    gmap = GridMap(MapConfig(resolution=RESOLUTION, layers=["tsdf"], tsdf=TsdfParams(truncation=TRUNCATION)))
    sensor_x = -RESOLUTION / 2  # cell centres then lie at whole multiples of the resolution
    sensor_y = RESOLUTION / 2  # the beam runs along the centres of row 0
    for z in MEASUREMENTS:
        gmap.integrate(Scan.from_angles((sensor_x, sensor_y, 0.0), [0.0], [z], 0.0, 100.0))
    cells = []
    for distance in DISTANCES:
        i = round(distance / RESOLUTION) - 1
        values = gmap.cells([[(i + 0.5) * RESOLUTION, sensor_y]])
        cells.append((distance, float(values["tsdf"][0]), float(values["tsdf_weight"][0])))
    i0, i1 = round(DISTANCES[0] / RESOLUTION) - 1, round(DISTANCES[-1] / RESOLUTION)
    points = gmap.surface(i0, 0, i1, 1)
    if len(points) != 1:
        raise RuntimeError(f"expected one zero crossing, found {len(points)}")
    return cells, float(points[0, 0]) - sensor_x


def main(argv: list[str] | None = None) -> int:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    cells, surface = run()
    for distance, value, weight in cells:
        print(f"cell {distance:.2f}  tsdf {value:+.4f}  weight {weight:.0f}")
    print(f"surface {surface:.5f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
